"""Write a mesh as an LS-DYNA keyword deck; `jaxci.io._lsdyna` reads it back.

**In place.** A mesh read from a keyword deck carries the deck's text (field data ``lsdyna:deck``, its
``*INCLUDE`` files inlined). When the mesh still has the deck's nodes, element ids, solids and part ids (only the
coordinates changed, as after smoothing), `write_lsdyna` writes the deck again with only the coordinate fields of
the ``*NODE`` lines that moved rewritten, each in its own columns (16 characters, 20 in the long format; free-format
fields as wide) as the text that reads back nearest to the new value; a value its field cannot hold closely enough
is refused with a `MeshWriteError` naming the node (`jaxci.io._fields.REL_TOLERANCE`). Every other keyword, line
and comment is kept byte for byte.

**Afresh**, for any other mesh: ``*KEYWORD``, ``*NODE`` (standard 8/16/16/16 columns), ``*ELEMENT_SOLID`` (one line
per element: id, part, 8 nodes; wedges, pyramids and tetrahedra in LS-DYNA's degenerate forms), ``*ELEMENT_SHELL``
for quadrilaterals and triangles, ``*END``, with the mesh's ids (8 digits at most) and the part ids of the cell
data ``lsdyna:pid`` (else the block number). Midside nodes (`jaxci.io.write_mesh` warns), sets, other data and
the keywords of a source deck that could not be written in place are left out with a `LossyWriteWarning`, issued
before the file is written.
"""

from __future__ import annotations

import os

import numpy as np

from ..mesh import HexMesh
from ._fields import block_pids, fresh_coordinates, numbered_blocks
from ._losses import deck_text
from ._lsdyna import DEGENERATE, parse_deck
from ._meshio import write_text
from ._patran import file_block

_MAX_ID = 99_999_999  # 8-character integer fields


def _eight(cell: str, row: list[int]) -> list[int]:
    """The 8 node fields of a solid: a brick's nodes, or LS-DYNA's degenerate form of another solid."""
    if cell == "hexahedron":
        return row
    out = [0] * 8
    for k, p in enumerate(DEGENERATE[cell]):
        out[p] = row[k]
    if cell == "tetra":
        out[4:] = [out[3]] * 4
    elif cell == "pyramid":
        out[5:] = [out[4]] * 3
    else:  # wedge: N5 N5 N6 N6
        out[5], out[7] = out[4], out[6]
    return out


def _fresh(mesh: HexMesh, path: str) -> tuple[str, list[str]]:
    lost = []
    node_ids = np.arange(1, mesh.n_nodes + 1) if mesh.node_ids is None else np.asarray(mesh.node_ids, np.int64)
    solids, shells = [], []
    for k, blk in enumerate(mesh.cells):
        cell, data, _, more = file_block(blk, k, mesh.hex_mirrored)  # midside nodes: write_mesh warns
        lost += more
        pids = block_pids(mesh, "lsdyna:pid", k, len(data))
        ids = None if blk.ids is None else np.asarray(blk.ids, np.int64)
        if cell in ("hexahedron", "wedge", "pyramid", "tetra"):
            solids.append((cell, ids, data, pids))
        elif cell in ("quad", "triangle"):
            shells.append((cell, ids, data, pids))
        else:
            lost.append(f"{len(data)} {blk.type} cells (not a solid or shell)")
    numbered, all_ids = numbered_blocks(solids + shells, node_ids, path, "LS-DYNA", "node", _MAX_ID,
                                        "the 8-character fields")
    xyz = fresh_coordinates(mesh, node_ids, path, "node", nastran=False)
    out = ["*KEYWORD", f"$ jaxci mesh: {mesh.n_nodes} nodes, {len(all_ids)} elements", "*NODE"]
    out += [f"{nid:>8}" + "".join(f"{t:>16}" for t in texts) for nid, texts in zip(node_ids.tolist(), xyz,
                                                                                     strict=True)]
    for keyword, kinds in (("*ELEMENT_SOLID", ("hexahedron", "wedge", "pyramid", "tetra")),
                           ("*ELEMENT_SHELL", ("quad", "triangle"))):
        blocks = [b for b in numbered if b[0] in kinds]
        if not blocks:
            continue
        out.append(keyword)
        for cell, ids, data, pids in blocks:
            for eid, row, pid in zip(ids.tolist(), node_ids[data].tolist(), pids.tolist(), strict=True):
                nodes = _eight(cell, row) if keyword == "*ELEMENT_SOLID" else row + row[-1:] * (4 - len(row))
                out.append(f"{eid:>8}{pid:>8}" + "".join(f"{v:>8}" for v in nodes))
    out.append("*END")
    return "\n".join(out) + "\n", lost


def write_lsdyna(mesh: HexMesh, path: str | os.PathLike) -> None:
    """Write `mesh` as an LS-DYNA keyword deck: its source deck with new coordinates when it has one, else afresh
    (module docstring).

    **Arguments:** `mesh` the mesh; `path` the file (`jaxci.io.write_mesh` passes a temporary name).

    **Returns:** nothing. Issues one `LossyWriteWarning` (before writing) listing what the deck leaves out; raises
    `MeshWriteError` for ids the deck cannot hold or a coordinate its field cannot hold. `OSError` propagates.
    """
    path = os.fspath(path)
    text, lost = deck_text(mesh, path, "lsdyna", _fresh, parse_deck, "node", nastran=False)
    write_text(path, text, "lsdyna", lost, "surrogateescape")
