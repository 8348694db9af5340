"""Write a mesh as an ANSYS APDL input file (NBLOCK / EBLOCK); `jaxci.io._ansys_apdl` reads it back.

`write_apdl` writes, for the extensions ``.mac``, ``.apdl``, ``.ans`` and ``.cdb``:

```
/COM, jaxci mesh: 27 nodes, 8 elements
/PREP7
ET,1,SOLID185
NBLOCK,6,SOLID,        27,        27
(3i9,6e21.13e3)
        1        0        0 0.0000000000000E+000 0.0000000000000E+000 0.0000000000000E+000
...
N,R5.3,LOC,       -1,
EBLOCK,19,SOLID,         8,         8
(19i9)
        1        1        1        1        0        0        0        0        8        0        1 ... (8 nodes)
...
       -1
FINISH
```

- ``ET,<itype>,<routine>`` per element type: the file's own ``ET`` records when the mesh came from an APDL file or
  CDB archive (``ansys:et`` field data; in a ``.cdb`` as numbers, ``ET,1,186``, as ANSYS ``CDWRITE`` does and
  mapdl-archive reads; elsewhere as names, ``ET,1,SOLID186``, or the number when jaxci has no name), and its
  ``KEYOPT,<itype>,<knum>,<value>`` records (``ansys:keyopt``); for other meshes SOLID185 per TYP seen (SOLID186
  for a TYP whose elements have midside nodes).
- NBLOCK rows: node number, 0, 0 and X Y Z in ``E21.13`` (14 significant digits), and the rotation angles THXY
  THYZ THZX when the mesh has them (``ansys:angles`` point data).
- EBLOCK rows: MAT TYPE REAL SECNUM ESYS, birth/death, solid ref, shape (``ansys:birth``, ``ansys:solid``,
  ``ansys:shape``, else 0), the node count, 0, the element number and the nodes: 8 (I..P) for an 8-node type;
  20 for a 20-node type (SOLID186: I..P then the midside nodes Q..B on a second line, 0 where an edge has none);
  4 or 10 for a tetrahedron type (SOLID285, SOLID187: I J K L then M..R). Wedges, pyramids and tetrahedra of a
  brick type are written as the degenerate bricks they were read from (see `jaxci.io._ansys`). Node and element
  numbers are kept; elements are grouped by cell type.
- ``CMBLOCK,<name>,NODE|ELEM,<n>`` per point / cell set (ANSYS components, numbers in ``8i10`` with ranges as
  ANSYS writes them), for sets whose names ANSYS accepts (a letter, then up to 31 letters, digits or ``_``).
  Other cell types, data and sets are left out with a `LossyWriteWarning`.
- Integer fields are ANSYS's ``i9`` (``i10`` in CMBLOCK) while the numbers fit with a blank between them, and
  wider for larger ids: ``(3i11,6e21.13e3)``, ``(19i11)``, ``(8i12)`` for 10-digit ids, and so on up to int64;
  the format lines say so, and jaxci and mapdl-archive (int32 ids) read them back.

**In place.** A mesh read from an APDL file or CDB archive carries the file's text (field data ``ansys:deck``).
When the mesh still has the file's nodes, ids, cells, element attributes, element types, key options, nodal angles
and components (only its coordinates changed, as after smoothing), `write_apdl` writes that text again with only the
coordinate fields of the moved nodes' NBLOCK rows rewritten, in the block's own format (``e21.13e3``, ``e20.13``,
...): materials, loads, ``*SET`` parameters and every other command are kept byte for byte. Otherwise the file is
written afresh as above, with a `LossyWriteWarning` naming the commands that are lost; every warning comes before
the file is written.
"""

from __future__ import annotations

import os
import re
import warnings

import numpy as np

from ..errors import MeshWriteError
from ..mesh import CellBlock, HexMesh
from ._ansys import (
    ATTRIBUTES,
    BRICK8,
    BRICK20,
    ELEMENT_NAMES,
    EXTRA_ATTRIBUTES,
    TET4,
    TET10,
    Bricks,
    from_hexmesh,
    has_midside,
    to_hexmesh,
)
from ._ansys_apdl import CMBLOCK_FORMAT, COMPONENT_NAME, EBLOCK_FORMAT, NBLOCK_FORMAT, DeckReader
from ._deck import model_difference
from ._losses import SOURCE_FIELDS, deck_losses
from ._meshio import file_cells, write_text


def _e21(x: float) -> str:
    """Fortran E21.13E3: `` 7.5000000000000E-001``."""
    mantissa, exponent = f"{x:.13E}".split("E")
    return f"{mantissa}E{int(exponent):+04d}".rjust(21)


def _compress(ids: np.ndarray) -> list[int]:
    """Sorted numbers as CMBLOCK items: a run i, i+1, ..., j becomes i, -j (the inverse of `expand_ranges`)."""
    ids = np.unique(np.asarray(ids, np.int64))
    if not len(ids):
        return []
    breaks = np.flatnonzero(np.diff(ids) != 1)
    starts, ends = ids[np.r_[0, breaks + 1]], ids[np.r_[breaks, len(ids) - 1]]
    out: list[int] = []
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        out += [a] if a == b else [a, -b]
    return out


def int_width(largest: int, least: int) -> int:
    """Width of the integer fields that hold numbers up to `largest` in magnitude: `least` (ANSYS's own width),
    or one more than the digits of `largest` (and its sign) when those do not fit, so fields stay apart."""
    digits = len(str(int(largest)))
    return least if digits < least else digits + 1


def _cmblock(name: str, kind: str, ids: np.ndarray) -> list[str]:
    items = _compress(ids)
    w = int_width(max((abs(v) for v in items), default=0) * 10, 10)  # room for the '-' of a range end
    out = [f"CMBLOCK,{name},{kind},{len(items):8d}", CMBLOCK_FORMAT if w == 10 else f"(8i{w})"]
    out += ["".join(f"{v:{w}d}" for v in items[i : i + 8]) for i in range(0, len(items), 8)]
    return out


def _element_rows(b: Bricks, path: str, w: int) -> list[str]:
    """EBLOCK rows (one or two lines per element) of the bricks `b`, node counts by each TYPE's routine, in
    integer fields of width `w`."""
    routine = dict(b.etypes.tolist())
    typ = b.attrs[:, 1]
    own_mid = has_midside(b)
    mat, _, rel, esy, sec = b.attrs.T
    extra = b.extra if b.extra is not None else np.zeros((len(typ), 3), np.int64)
    out = []
    for k in range(len(typ)):
        r = routine[int(typ[k])]
        corners, mid = b.corners[k], b.midside[k]
        tet = corners[2] == corners[3] and (corners[4:] == corners[4]).all() and len(set(corners.tolist())) == 4
        if r in TET4 or r in TET10:
            if not tet:
                shape = "hexahedron" if len(set(corners.tolist())) == 8 else "wedge or pyramid"
                raise MeshWriteError(f"{path}: element {b.elem_ids[k]} has TYPE {typ[k]} = {ELEMENT_NAMES[r]}, a "
                                     f"tetrahedron type, but is a {shape}")
            nodes = [corners[0], corners[1], corners[2], corners[4]]
            if own_mid[k] and r in TET10:
                nodes += [mid[0], mid[1], mid[3], mid[8], mid[9], mid[10]]
        elif r in BRICK20:
            nodes = corners.tolist() + mid.tolist()
        elif r in BRICK8:
            nodes = corners.tolist()
        else:
            raise MeshWriteError(f"{path}: element {b.elem_ids[k]} has TYPE {typ[k]} = "
                                 f"{ELEMENT_NAMES.get(r, f'element type {r}')}, which is not a 3-D solid jaxci writes")
        if own_mid[k] and len(nodes) <= 8:
            raise MeshWriteError(f"{path}: element {b.elem_ids[k]} has midside nodes, but its TYPE {typ[k]} is "
                                 f"{ELEMENT_NAMES.get(r, r)}, a linear element; give it a quadratic type (SOLID186)")
        head = [mat[k], typ[k], rel[k], sec[k], esy[k], *extra[k], len(nodes), 0, b.elem_ids[k]]
        vals = [int(v) for v in head + nodes[:8]]
        out.append("".join(f"{v:{w}d}" for v in vals))
        if len(nodes) > 8:
            out.append("".join(f"{int(v):{w}d}" for v in nodes[8:]))
    return out


def write_apdl(mesh: HexMesh, path: str | os.PathLike) -> None:
    """Write `mesh` as an APDL input file that re-creates it with its node and element numbers.

    **Arguments:**

    - `mesh`: the mesh; hexahedron, wedge, pyramid and tetra blocks are written (with their midside nodes),
      with the element types, key options and components it was read with (module docstring).
    - `path`: the file to write (`jaxci.io.write_mesh` passes a temporary name and moves it into place).

    **Returns:** nothing. Issues a `LossyWriteWarning` listing the cells, data and sets it leaves out; raises
    `MeshWriteError` for a mesh ANSYS cannot hold as such (midside nodes in a linear element type, a brick of a
    tetrahedron type, duplicate ids).
    """
    path = os.fspath(path)
    lost, text = [], None
    deck = mesh.field_data.get("ansys:deck")
    if isinstance(deck, str):
        reason, text = _in_place(mesh, deck)
        if text is None:
            lost += [f"{what} ({reason}, so the file cannot be rewritten in place)"
                     for fmt, what in deck_losses(mesh, "apdl") if fmt == "apdl"]
    other = sorted(set(mesh.cell_data) - set(ATTRIBUTES) - set(EXTRA_ATTRIBUTES))
    other += sorted(set(mesh.point_data) - {"ansys:angles"})
    if other:
        lost.append(f"point/cell data {other}")
    field = sorted(set(mesh.field_data) - {"ansys:et", "ansys:keyopt", *SOURCE_FIELDS})
    if field:
        lost.append(f"field data {field}")
    if text is None:
        fresh, more = _fresh(mesh, path)
        lost = more + lost + [what for fmt, what in deck_losses(mesh, "apdl") if fmt != "apdl"]
    write_text(path, fresh if text is None else text, "APDL", lost)


def _fresh(mesh: HexMesh, path: str) -> tuple[str, list[str]]:
    """The text of an APDL file written afresh, and what it leaves out."""
    b, dropped = from_hexmesh(mesh, file_cells(mesh), path)
    if len(b.elem_ids) == 0:
        raise MeshWriteError(f"{path}: the mesh has no cells that ANSYS bricks can hold")
    lost = [f"cells {', '.join(dropped)}"] if dropped else []
    bad_names = sorted(n for n in (*mesh.point_sets, *mesh.cell_sets) if not COMPONENT_NAME.fullmatch(n))
    if bad_names:
        lost.append(f"sets {bad_names} (not valid ANSYS component names)")

    out = [f"/COM, jaxci mesh: {len(b.node_ids)} nodes, {len(b.elem_ids)} elements", "/PREP7"]
    numeric = path.lower().endswith(".cdb")  # CDWRITE's form (what mapdl-archive reads); names elsewhere
    out += [f"ET,{t},{r if numeric else ELEMENT_NAMES.get(r, r)}" for t, r in b.etypes.tolist()]
    if b.keyopts is not None:
        out += [f"KEYOPT,{t},{k},{v}" for t, k, v in np.asarray(b.keyopts, np.int64).reshape(-1, 3).tolist()]
    wn = int_width(b.node_ids.max(), 9)  # ANSYS's i9, wider for node numbers of 9 digits or more
    out += [f"NBLOCK,6,SOLID,{b.node_ids.max():10d},{len(b.node_ids):10d}",
            NBLOCK_FORMAT if wn == 9 else NBLOCK_FORMAT.replace("3i9", f"3i{wn}")]
    if b.angles is not None and (b.angles != 0).any():
        out += [
            f"{nid:{wn}d}{0:{wn}d}{0:{wn}d}" + "".join(_e21(v) for v in (*xyz, *ang))
            for nid, xyz, ang in zip(b.node_ids.tolist(), b.points.tolist(), b.angles.tolist(), strict=True)
        ]
    else:
        out += [
            f"{nid:{wn}d}{0:{wn}d}{0:{wn}d}{_e21(x)}{_e21(y)}{_e21(z)}"
            for nid, (x, y, z) in zip(b.node_ids.tolist(), b.points.tolist(), strict=True)
        ]
    largest = max(int(np.abs(a).max(initial=0)) for a in (b.node_ids, b.elem_ids, b.attrs, b.extra))
    we = int_width(largest, 9)
    out += ["N,R5.3,LOC,       -1,", f"EBLOCK,19,SOLID,{b.elem_ids.max():10d},{len(b.elem_ids):10d}",
            EBLOCK_FORMAT if we == 9 else f"(19i{we})"]
    out += _element_rows(b, path, we)
    out += [f"{-1:{we}d}"]
    node_ids = b.node_ids
    for name, idx in mesh.point_sets.items():
        if COMPONENT_NAME.fullmatch(name):
            out += _cmblock(name, "NODE", node_ids[np.asarray(idx, np.int64)])
    if mesh.cell_sets:
        ids_of = [blk.ids for blk in _element_blocks_with_ids(mesh, b)]
        for name, per_block in mesh.cell_sets.items():
            if COMPONENT_NAME.fullmatch(name):
                ids = [ids_of[i][np.asarray(rows, np.int64)] for i, rows in enumerate(per_block)
                       if ids_of[i] is not None and rows is not None]
                out += _cmblock(name, "ELEM", np.concatenate(ids) if ids else np.zeros(0, np.int64))
    out += ["FINISH", ""]
    return "\n".join(out), lost


def _element_blocks_with_ids(mesh: HexMesh, b: Bricks) -> list[CellBlock]:
    """Each cell block with the element numbers the file gives it (None for blocks the file leaves out)."""
    out, start = [], 0
    for blk in mesh.cells:
        if blk.type in ("hexahedron", "wedge", "pyramid", "tetra"):
            out.append(CellBlock(blk.type, blk.data, b.elem_ids[start : start + len(blk.data)]))
            start += len(blk.data)
        else:
            out.append(CellBlock(blk.type, blk.data, None))
    return out


# ---------------------------------------------------------------------------------------------------- in place
_REAL_ITEM = re.compile(r"(\d*)([EDGF])(\d+)\.(\d+)(?:E(\d+))?", re.IGNORECASE)


class _Unfit(Exception):
    """A coordinate does not fit its NBLOCK field."""


def _fortran_real(v: float, letter: str, w: int, d: int, e: int) -> str:
    """`v` in the Fortran edit descriptor ``Ew.dEe`` (ANSYS's form: one digit before the point) or ``Fw.d``."""
    if letter == "F":
        s = f"{v:{w}.{d}f}"
    else:
        mantissa, exponent = f"{v:.{d}E}".split("E")
        s = f"{mantissa}E{int(exponent):+0{e + 1}d}".rjust(w)
    if len(s) > w:
        raise _Unfit(f"{v!r} does not fit the field {letter}{w}.{d}")
    return s


def _nblock_row(line: str, fmt_line: str, fields: list, xyz: list[float]) -> str:
    """An NBLOCK row (with its line ending) with new coordinates; fields whose value did not change keep their text."""
    body = line.rstrip("\r\n")
    end = line[len(body):]
    n_int = 0
    while n_int < len(fields) and fields[n_int][0]:
        n_int += 1
    items = [m for m in (_REAL_ITEM.fullmatch(t.strip()) for t in fmt_line.strip("() ").split(",")) if m]
    if n_int < 3 or not items or len(fields) < n_int + 3:
        raise _Unfit(f"NBLOCK format {fmt_line} is not 3 integers and 3 or more reals")
    letter, d = items[0].group(2).upper(), int(items[0].group(4))
    e = int(items[0].group(5) or 2)
    start = sum(w for _, w in fields[:n_int])
    out = body[:start].ljust(start)
    pos = start
    for k in range(3):
        w = fields[n_int + k][1]
        chunk = body[pos : pos + w]
        old = float(chunk.replace("D", "E").replace("d", "e")) if chunk.strip() else 0.0
        out += chunk.ljust(w) if old == xyz[k] else _fortran_real(xyz[k], letter, w, d, e)
        pos += w
    return (out + body[pos:]).rstrip() + end


def _in_place(mesh: HexMesh, text: str) -> tuple[str | None, str | None]:
    """(None, the file's text with the mesh's node coordinates) when `mesh` is the file's mesh with moved nodes,
    else (what differs, None)."""
    label = f"the text of {mesh.source or 'the mesh'}"
    reader = DeckReader(label, text.splitlines())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader.run()
        ref = to_hexmesh(reader.bricks(), label, "NBLOCK")
    reason = model_difference(mesh, ref, cell_data=ATTRIBUTES + EXTRA_ATTRIBUTES, point_data=("ansys:angles",),
                              field_data=("ansys:et", "ansys:keyopt"))
    if reason is not None:
        return reason, None
    lines = text.splitlines(keepends=True)
    moved = np.flatnonzero((mesh.points != ref.points).any(axis=1))
    for k in moved.tolist():
        i = reader.node_src[k][1] - 1
        fmt_line, fields = reader.nblock_formats[reader.node_format[k]]
        try:
            lines[i] = _nblock_row(lines[i], fmt_line, fields, mesh.points[k].tolist())
        except _Unfit as exc:
            return f"node {int(ref.node_ids[k])}: {exc}", None
    return None, "".join(lines)
