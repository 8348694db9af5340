"""Numbers in the fields of card-image decks (Nastran bulk data, LS-DYNA keyword files): parsing them (`parse_real`,
which the Abaqus and ANSYS listing readers use too), writing a coordinate back into the field it came from, and
checking that the field is wide enough.

Both formats hold a node's coordinates either in fixed columns (8, 10, 16 or 20 characters) or in free format
(fields separated by commas). A deck written back in place (`rewrite_coordinates`) keeps every line byte for byte
except the coordinate fields of the nodes that moved: each new value is written in its field's width, as the text
that reads back nearest to it (`format_real`). A value the width cannot hold closely enough (more than
`REL_TOLERANCE` times the shortest edge at its node away, `node_scale`) is refused with a `MeshWriteError` naming
the node, never silently rounded.
"""

from __future__ import annotations

import re

import numpy as np

from ..cells import EDGES
from ..errors import MeshReadError, MeshWriteError
from ..mesh import HexMesh
from ._deck import element_ids, model_difference, refuse_bad_ids, reread_deck

#: A rewritten coordinate may differ from the smoothed one by at most this fraction of the shortest edge at its node.
REL_TOLERANCE = 1e-3
#: A Nastran real: mantissa, then an exponent with E/D or just a sign ("1.5-3" is 1.5e-3).
_NASTRAN_REAL = re.compile(r"([+-]?(?:\d+\.?\d*|\.\d+))(?:[EeDd]([+-]?\d+)|([+-]\d+))?")


def parse_real(token: str, where: str, what: str, nastran: bool = False) -> float:
    """A finite float from a field (blank is 0; Fortran ``D`` exponents; with `nastran`, implicit exponents such as
    ``1.5-3``), or a `MeshReadError` at `where`."""
    tok = token.strip()
    if not tok:
        return 0.0
    m = _NASTRAN_REAL.fullmatch(tok) if nastran else None
    try:
        if m:
            value = float(f"{m.group(1)}e{m.group(2) or m.group(3) or 0}")
        else:
            value = float(tok.replace("D", "E").replace("d", "e"))
    except (ValueError, OverflowError):
        raise MeshReadError(f"{where}: {what} {tok!r} is not a number") from None
    if not np.isfinite(value):
        raise MeshReadError(f"{where}: {what} is {tok!r}; coordinates must be finite numbers")
    return value


def _candidates(value: float, width: int, nastran: bool):
    text = repr(value)
    yield text
    for p in range(min(width, 17), -1, -1):
        fixed = f"{value:.{p}f}"
        if "." in fixed:
            fixed = fixed.rstrip("0")
        fixed = fixed if "." in fixed else fixed + "."
        yield fixed
        if fixed.lstrip("-").startswith("0.") and fixed.lstrip("-0."):
            yield fixed.replace("0.", ".", 1)  # ".3333333": one more digit than "0.333333"
        mant, exp = f"{value:.{p}e}".split("e")
        if "." in mant:
            mant = mant.rstrip("0")
        elif nastran:
            mant += "."
        e = int(exp)
        yield f"{mant}{'+' if e >= 0 else '-'}{abs(e)}" if nastran else f"{mant}e{e}"


def format_real(value: float, width: int, nastran: bool = False) -> tuple[str, float]:
    """The text of at most `width` characters that reads back nearest to `value`, and the error it leaves.

    With `nastran` the text always has a decimal point (Nastran's mark of a real) and exponents are written
    Nastran's short way (``1.234-5``); otherwise as ``1.234e-5``. Shorter texts win ties.
    """
    value = float(value)
    best, err = None, np.inf
    for text in _candidates(value, width, nastran):
        if nastran and "." not in text and "e" in text:
            continue
        if len(text) > width:
            continue
        back = parse_real(text, "", "", nastran=nastran)
        e = abs(back - value)
        if e < err or (e == err and best is not None and len(text) < len(best)):
            best, err = text, e
        if e == 0:
            break
    if best is None:  # pragma: no cover - a width below 2 never occurs in these formats
        raise ValueError(f"no text of {width} characters holds {value}")
    return best, err


def node_scale(points: np.ndarray, cells) -> np.ndarray:
    """The length of the shortest edge at each node over the cells (``inf`` for a node in none), shape
    ``(n_nodes,)``: what a rewritten coordinate's error is measured against."""
    scale = np.full(len(points), np.inf)
    for b in cells:
        data = np.asarray(b.data, np.int64)
        if not len(data):
            continue
        pairs = EDGES[b.type] if b.type in EDGES else np.array([(k, (k + 1) % data.shape[1])
                                                                 for k in range(data.shape[1])])
        if data.shape[1] < 2:
            continue
        a, c = data[:, pairs[:, 0]].ravel(), data[:, pairs[:, 1]].ravel()
        length = np.linalg.norm(points[a] - points[c], axis=1)
        np.minimum.at(scale, a, length)
        np.minimum.at(scale, c, length)
    scale[scale == 0] = np.inf
    return scale


def replace_field(line: str, field: tuple, text: str) -> str:
    """`line` with one field replaced by `text`: ``("fixed", start, width)`` (columns, 0-based; the text keeps the
    old one's side of the field, right-justified unless the old text began at the field's start) or ``("free",
    index)`` (the index-th comma-separated field; its surrounding blanks kept)."""
    body = line.rstrip("\r\n")
    end = line[len(body) :]
    if field[0] == "fixed":
        _, start, width = field
        body = body.expandtabs(8)  # columns count with tabs at 8-column stops
        old = body[start : start + width].ljust(width)
        left = bool(old.strip()) and not old[0].isspace()
        new = text.ljust(width) if left else text.rjust(width)
        tail = body[start + width :]
        if not tail:
            new = new.rstrip()
        return body[:start].ljust(start) + new + tail + end
    parts = body.split(",")
    old = parts[field[1]]
    lead = old[: len(old) - len(old.lstrip())]
    trail = old[len(old.rstrip()) :] if old.strip() else ""
    parts[field[1]] = lead + text + trail
    return ",".join(parts) + end


def rewrite_coordinates(lines: list[str], old: np.ndarray, new: np.ndarray, fields: list, scale: np.ndarray,
                        label, nastran: bool) -> None:
    """Write the coordinates of the nodes that moved (`new` differs from `old`) into `lines` (in place).

    **Arguments:** `fields[k]` the three ``(line index, field, width)`` of node k's x, y, z (field as in
    `replace_field`); `scale` the `node_scale`; `label(k)` the node's name in a message; `nastran` the
    number style. Raises `MeshWriteError` when a width cannot hold a value to `REL_TOLERANCE` of the scale.
    """
    moved = np.flatnonzero((new != old).any(axis=1) | (np.signbit(new) != np.signbit(old)).any(axis=1))
    for k in moved.tolist():
        for c in range(3):
            v, o = float(new[k, c]), float(old[k, c])
            if v == o and np.signbit(v) == np.signbit(o):
                continue
            i, field, width = fields[k][c]
            text, err = format_real(v, width, nastran)
            if err > REL_TOLERANCE * scale[k]:
                raise MeshWriteError(
                    f"{label(k)}: its new {'xyz'[c]} coordinate {v!r} cannot be written in its {width}-"
                    f"character field closer than {err:.3g} ({text}), more than {REL_TOLERANCE:g} of its shortest "
                    f"edge ({scale[k]:.3g}); write the deck in a wider field format, or write another format")
            lines[i] = replace_field(lines[i], field, text)


def rewrite_deck(mesh: HexMesh, text: str, path: str, parse_deck, pid_key: str, what: str, nastran: bool
                 ) -> tuple[str | None, str | None]:
    """``(None, the deck text with the mesh's coordinates)`` when `mesh` is the mesh of the deck `text` (read by
    ``parse_deck``: Nastran's or LS-DYNA's) with moved nodes, else ``(what differs, None)``: the in-place write
    both deck writers share. `pid_key` the deck's property-id cell data, `what` its node entity (``"GRID"``,
    ``"node"``) for messages, `nastran` its field rules (`rewrite_coordinates`)."""
    lines, deck, ref = reread_deck(mesh, text, parse_deck)
    reason = model_difference(mesh, ref, cell_data=(pid_key,))
    if reason is not None:
        return reason, None
    ids = ref.node_ids

    def name(k: int) -> str:
        return f"{path}: {what} {int(ids[k])} (line {deck.origin[deck.node_line[k]][1]} of the deck)"

    rewrite_coordinates(lines, ref.points, mesh.points, deck.node_spots, node_scale(mesh.points, mesh.cells), name,
                        nastran=nastran)
    return None, "".join(lines)


def numbered_blocks(blocks: list, node_ids: np.ndarray, path: str, deck: str, node: str, maximum: int,
                    fields: str) -> tuple[list, np.ndarray]:
    """A deck's element blocks ``(cell or card, ids or None, rows, property ids)`` with every element numbered
    (blocks without ids continue from the largest id given) and all element ids; `MeshWriteError` where a node or
    element id is used twice (`deck` names the format, `node` its nodes) or lies outside ``1..maximum`` (`fields`
    names the fields that cannot hold it)."""
    numbered = [(cell, ids, rows, pids) for (cell, _, rows, pids), ids in
                zip(blocks, element_ids([b[1] for b in blocks], [len(b[2]) for b in blocks]), strict=True)]
    all_ids = np.concatenate([b[1] for b in numbered]) if numbered else np.zeros(0, np.int64)
    refuse_bad_ids(path, ((node_ids, node), (all_ids, "element")), deck, maximum, f"of {fields}")
    return numbered, all_ids


def block_pids(mesh: HexMesh, key: str, k: int, n: int) -> np.ndarray:
    """The property (part) ids of the `n` cells of block `k` of a deck written afresh: the cell data `key` where
    it fits the blocks, else the block number ``k + 1``."""
    data = mesh.cell_data.get(key)
    if data is not None and len(data) == len(mesh.cells) and len(data[k]) == n:
        return np.asarray(data[k], np.int64)
    return np.full(n, k + 1)


def fresh_coordinates(mesh: HexMesh, node_ids: np.ndarray, path: str, node: str, nastran: bool) -> list[list[str]]:
    """The x, y, z texts (16 characters at most, `format_real` with `nastran`) of each node of a deck written
    afresh; a `MeshWriteError` naming the node (`node` the format's word, its id from `node_ids`) where 16
    characters cannot hold a coordinate to `REL_TOLERANCE` of its `node_scale`."""
    scale = node_scale(mesh.points, mesh.cells)
    out = []
    for k, (nid, xyz) in enumerate(zip(node_ids.tolist(), mesh.points.tolist(), strict=True)):
        texts = []
        for c, v in enumerate(xyz):
            text, err = format_real(v, 16, nastran=nastran)
            if err > REL_TOLERANCE * scale[k]:
                raise MeshWriteError(f"{path}: {node} {nid}: its {'xyz'[c]} coordinate {v!r} cannot be written in 16 "
                                     f"characters closer than {err:.3g}")
            texts.append(text)
        out.append(texts)
    return out
