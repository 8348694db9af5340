"""Write a mesh as an Abaqus input deck (``.inp``); `jaxci.io._abaqus` reads it back.

**In place.** A mesh read from an Abaqus deck carries the deck's text (field data ``abaqus:deck``). When the mesh
still has the deck's nodes, node ids, cells, element ids, element types and sets (only the coordinates changed, as
after smoothing), `write_abaqus` writes the deck again with only the coordinate fields of its ``*NODE`` lines
rewritten: every other line (``*MATERIAL``, ``*SOLID SECTION``, ``*STEP``, ``*BOUNDARY``, comments, ...) is kept
byte for byte, and so is a node line whose coordinates did not change. New coordinates are written as Python's
shortest round-trip form of the float64 (``0.30000000000000004``), so they read back exactly.

**Afresh**, for any other mesh:

```
*HEADING
jaxci mesh: 27 nodes, 8 elements
*NODE
1, 0.0, 0.0, 0.0
...
*ELEMENT, TYPE=C3D8
1, 1, 2, 5, 4, 10, 11, 14, 13
...
*NSET, NSET=corner
1, 3
*ELSET, ELSET=top
1, 4, 6
```

with the mesh's node and element ids (else 1..n, and elements numbered on from the largest id), one ``*ELEMENT``
per cell block with the block's Abaqus type name (``abaqus:element_types``, when it fits the block) or `DEFAULT_NAMES`
(``C3D8``; ``C3D20`` / ``C3D15`` / ``C3D10`` for cells with midside nodes, `jaxci.mesh.CellBlock.midside`), at most
16 numbers per line, and the node and element sets. Point and cell data, field data, cells Abaqus cannot hold and
the keyword blocks of a source deck that could not be written in place are left out with a `LossyWriteWarning`,
issued before the file is written.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ..mesh import HexMesh
from ._abaqus import DEFAULT_NAMES, element_family, parse_deck, split_line
from ._deck import model_difference, refuse_bad_ids, reread_deck
from ._losses import data_losses, deck_losses
from ._meshio import file_cells, write_text

#: Set names written as they are; others are written in double quotes (Abaqus's form for labels with spaces).
_PLAIN_LABEL = re.compile(r"[A-Za-z][A-Za-z0-9_.\-]{0,79}")
_QUOTABLE_LABEL = re.compile(r'[^",\r\n=*]{1,80}')
_PER_LINE = 16


def _rows(values: list[int]) -> str:
    """Numbers as Abaqus data lines of at most 16 entries, continued lines ending with a comma."""
    return ",\n".join(", ".join(map(str, values[i : i + _PER_LINE])) for i in range(0, len(values), _PER_LINE))


def _coordinate_line(line: str, xyz) -> str:
    """A ``*NODE`` data line with new coordinates; fields whose value did not change keep their text."""
    body, end = split_line(line)
    parts = body.split(",")
    for k, v in enumerate(xyz):
        j = k + 1
        tok = parts[j] if j < len(parts) else ""
        old = float(tok.replace("D", "E").replace("d", "e")) if tok.strip() else 0.0
        if old == v and (tok.strip() or np.signbit(v) == np.signbit(old)):
            continue
        while len(parts) <= j:
            parts.append(" 0.")
        lead = tok[: len(tok) - len(tok.lstrip())] if tok.strip() else " "
        parts[j] = lead + repr(float(v))
    return ",".join(parts) + end


def _in_place(mesh: HexMesh, text: str) -> tuple[str | None, str | None, dict[int, str]]:
    """(None, the deck with the mesh's coordinates, ...) when `mesh` is the deck's mesh with moved nodes, else
    (what differs, None, ...); last the Abaqus element type of every element id of the deck."""
    lines, deck, ref = reread_deck(mesh, text, parse_deck)
    id_types = {i: b.name for b in deck.blocks for i in b.ids}
    reason = model_difference(mesh, ref, field_data=("abaqus:element_types",))
    if reason is not None:
        return reason, None, id_types
    old = ref.points
    moved = np.flatnonzero((mesh.points != old).any(axis=1) | (np.signbit(mesh.points) != np.signbit(old)).any(axis=1))
    for k in moved.tolist():
        i = deck.node_line[k]
        lines[i] = _coordinate_line(lines[i], mesh.points[k].tolist())
    return None, "".join(lines), id_types


def _block_name(blk, names, k: int, quadratic: bool, id_types: dict[int, str]) -> str | None:
    """The Abaqus type name of cell block `k`: its own (``abaqus:element_types``, else the one the source deck gives
    all its element ids) when that fits the block, else the default."""
    own = None
    if names is not None:
        own = str(names[k])
    elif blk.ids is not None and id_types:
        found = {id_types.get(int(i)) for i in np.asarray(blk.ids).tolist()}
        own = found.pop() if len(found) == 1 else None
    if own is not None:
        fam = element_family(own)
        if fam is not None and fam[0] == blk.type and (fam[2] > fam[1]) == quadratic:
            return own.upper()
    return DEFAULT_NAMES.get((blk.type, quadratic))


def _label(name: str) -> str | None:
    if _PLAIN_LABEL.fullmatch(name):
        return name
    if _QUOTABLE_LABEL.fullmatch(name) and name.strip() == name:
        return f'"{name}"'
    return None


def _fresh(mesh: HexMesh, path: str, id_types: dict[int, str]) -> tuple[str, list[str]]:
    """The text of a deck written afresh, and what it leaves out; `id_types` the Abaqus element type of each element
    id of the mesh's source deck (if any)."""
    lost = []
    node_ids = np.arange(1, mesh.n_nodes + 1) if mesh.node_ids is None else np.asarray(mesh.node_ids, np.int64)
    cells = file_cells(mesh)
    known = [np.asarray(b.ids, np.int64) for b in cells if b.ids is not None and len(b.ids)]
    next_id = int(max((ids.max() for ids in known), default=0)) + 1
    names = mesh.field_data.get("abaqus:element_types")
    names = tuple(names) if isinstance(names, tuple | list) and len(names) == len(cells) else None
    blocks = []  # (cell block index, type name, element ids, node index rows)
    for k, blk in enumerate(cells):
        data = np.asarray(blk.data, np.int64)
        mid = None if blk.midside is None else np.asarray(blk.midside, np.int64)
        name = _block_name(blk, names, k, mid is not None, id_types)
        if mid is not None and (name is None or (mid < 0).any()):
            why = "lack midside nodes on some edges" if (mid < 0).any() else "have no quadratic Abaqus type"
            lost.append(f"the midside nodes of the {len(data)} {blk.type} cells of block {k}, which {why} "
                        f"(written as linear cells)")
            mid, name = None, _block_name(blk, names, k, False, id_types)
        if name is None:
            lost.append(f"{len(data)} {blk.type} cells (no Abaqus element type)")
            continue
        if blk.ids is None:
            ids = np.arange(next_id, next_id + len(data))
            next_id += len(data)
        else:
            ids = np.asarray(blk.ids, np.int64)
        blocks.append((k, name, ids, data if mid is None else np.concatenate([data, mid], axis=1)))
    all_ids = np.concatenate([b[2] for b in blocks]) if blocks else np.zeros(0, np.int64)
    refuse_bad_ids(path, ((node_ids, "node"), (all_ids, "element")), "Abaqus")

    out = ["*HEADING", f"jaxci mesh: {mesh.n_nodes} nodes, {len(all_ids)} elements", "*NODE"]
    out += [f"{i}, {x!r}, {y!r}, {z!r}" for i, (x, y, z) in zip(node_ids.tolist(), mesh.points.tolist(), strict=True)]
    ids_of = {}
    for k, name, ids, rows in blocks:
        ids_of[k] = ids
        out.append(f"*ELEMENT, TYPE={name}")
        for eid, row in zip(ids.tolist(), node_ids[rows].tolist(), strict=True):
            out.append(_rows([eid, *row]))
    bad = []
    for name, idx in mesh.point_sets.items():
        if (lab := _label(name)) is None:
            bad.append(name)
            continue
        out.append(f"*NSET, NSET={lab}")
        ids = np.unique(node_ids[np.asarray(idx, np.int64)]).tolist()
        if ids:
            out.append(_rows(ids))
    for name, per_block in mesh.cell_sets.items():
        if (lab := _label(name)) is None:
            bad.append(name)
            continue
        ids = [ids_of[k][np.asarray(rows, np.int64)] for k, rows in enumerate(per_block)
               if k in ids_of and rows is not None and len(rows)]
        out.append(f"*ELSET, ELSET={lab}")
        if ids:
            out.append(_rows(np.unique(np.concatenate(ids)).tolist()))
    if bad:
        lost.append(f"sets {sorted(bad)} (names Abaqus cannot hold)")
    return "\n".join(out) + "\n", lost


def write_abaqus(mesh: HexMesh, path: str | os.PathLike) -> None:
    """Write `mesh` as an Abaqus deck: its source deck with new coordinates when it has one, else afresh.

    **Arguments:**

    - `mesh`: the mesh (module docstring for what is kept).
    - `path`: the file to write (`jaxci.io.write_mesh` passes a temporary name and moves it into place).

    **Returns:** nothing. Issues one `LossyWriteWarning` (before writing) listing what the deck leaves out; raises
    `MeshWriteError` for duplicate or non-positive ids. `OSError` from writing propagates.
    """
    path = os.fspath(path)
    lost = []
    text, id_types = None, {}
    deck = mesh.field_data.get("abaqus:deck")
    if isinstance(deck, str):
        reason, text, id_types = _in_place(mesh, deck)
        if text is None:
            lost += [f"{what} ({reason}, so the deck cannot be rewritten in place)"
                     for fmt, what in deck_losses(mesh, "abaqus") if fmt == "abaqus"]
    if text is None:
        text, more = _fresh(mesh, path, id_types)
        lost += more
        lost += [what for fmt, what in deck_losses(mesh, "abaqus") if fmt != "abaqus"]
    lost += data_losses(mesh)
    write_text(path, text, "abaqus", lost, "surrogateescape")
