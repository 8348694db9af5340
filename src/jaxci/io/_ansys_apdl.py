"""Write a mesh as an ANSYS APDL input file (NBLOCK / EBLOCK), and read that subset back.

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

One ``ET,<typ>,SOLID185`` per TYP seen (element type names are not kept: jaxci only holds 8-node bricks and
their degenerate forms). EBLOCK rows hold MAT TYPE REAL SECNUM ESYS, birth/death 0, solid ref 0, shape 0, node
count 8, 0, the element number and the node numbers I..P; wedges, pyramids and tetrahedra are written as the
degenerate bricks they were read from (see `jaxci.io._ansys`). Node and element numbers are kept; elements are
grouped by cell type. Coordinates keep 14 significant digits (``E21.13``). Other cell types, data and sets are
left out with a warning.

`read_apdl` reads exactly this subset with one parser: each NBLOCK and EBLOCK in SOLID format, its fields cut
by the Fortran format line that follows it, trailing zero coordinates omitted, 20-node bricks continued on a
second line (corners kept), block row counts checked. Other commands (``/PREP7``, ``ET``, ``*SET``, ``FINISH``,
comments) are skipped. That is also the mesh of an ANSYS ``CDWRITE`` archive (``.cdb``): the reader and the
writer agree with the ``mapdl-archive`` package on its example archives (``tests/test_ansys.py``).
"""

from __future__ import annotations

import os
import re
import warnings

import numpy as np

from ..errors import MeshReadError, MeshWriteError
from ..mesh import HexMesh
from ._ansys import ATTRIBUTES, Bricks, from_hexmesh, to_hexmesh
from ._ansys_listing import read_text_lines
from ._meshio import LossyWriteWarning, file_cells

_FORMAT_ITEM = re.compile(r"(\d*)([IEFGD])(\d+)(?:\.\d+)?(?:E\d+)?", re.IGNORECASE)
_NBLOCK_FORMAT = "(3i9,6e21.13e3)"
_EBLOCK_FORMAT = "(19i9)"
_EBLOCK_FIXED = 11  # MAT TYPE REAL SECNUM ESYS birth/death solid-ref shape node-count 0 element-number


def _fortran_widths(line: str, where: str) -> list[tuple[bool, int]]:
    """(is_integer, width) of every field of a Fortran format line such as ``(3i9,6e21.13e3)``."""
    body = line.strip()
    if not (body.startswith("(") and body.endswith(")")):
        raise MeshReadError(f"{where}: expected a Fortran format line such as {_NBLOCK_FORMAT}, got {body!r}")
    fields = []
    for item in body[1:-1].split(","):
        m = _FORMAT_ITEM.fullmatch(item.strip())
        if m is None:
            raise MeshReadError(f"{where}: cannot read the format item {item.strip()!r} of {body}")
        fields += [(m.group(2).upper() == "I", int(m.group(3)))] * int(m.group(1) or 1)
    return fields


def _cut(line: str, fields: list[tuple[bool, int]], where: str) -> list[float | int]:
    """The values of a fixed-width row; fields past the end of the line are absent."""
    line = line.rstrip()
    out, pos = [], 0
    for is_int, width in fields:
        if pos >= len(line):
            break
        chunk = line[pos : pos + width].strip()
        pos += width
        try:
            out.append(int(chunk) if is_int else float(chunk.replace("D", "E").replace("d", "e")))
        except ValueError:
            kind = "an integer" if is_int else "a number"
            raise MeshReadError(f"{where}: field {len(out) + 1} {chunk!r} is not {kind}") from None
    if pos < len(line):
        raise MeshReadError(f"{where}: row is longer than its format allows ({len(fields)} fields)")
    return out


def _block_header(line: str, lineno: int, path: str) -> tuple[str, int | None]:
    parts = [p.strip() for p in line.split(",")]
    name = parts[0].upper()
    if len(parts) < 3 or parts[2].upper() != "SOLID":
        raise MeshReadError(f"{path}, line {lineno}: only the SOLID format of {name} is supported, got {line!r}")
    count = None
    if len(parts) > 4 and parts[4]:
        try:
            count = int(parts[4])
        except ValueError:
            raise MeshReadError(f"{path}, line {lineno}: {name} count {parts[4]!r} is not an integer") from None
    return name, count


def read_apdl(path: str | os.PathLike) -> HexMesh:
    """Read the NBLOCK / EBLOCK mesh of an APDL input file (as written by `write_apdl`, or an ANSYS CDB).

    **Arguments:** `path` the file.

    **Returns:** a `HexMesh` as from `jaxci.io.read_ansys_listing` (ids, ``ansys:*`` cell data, degenerate
    bricks as wedge/pyramid/tetra blocks).
    """
    path = os.fspath(path)
    lines = read_text_lines(path, "APDL file")
    nodes, node_src, elems, elem_src = [], [], [], []
    n_midside, i = 0, 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        name = line.split(",", 1)[0].strip().upper()
        if name not in ("NBLOCK", "EBLOCK"):
            continue  # /PREP7, ET, FINISH, comments, other commands
        start = i
        name, count = _block_header(line, start, path)
        if i >= len(lines):
            raise MeshReadError(f"{path}, line {start}: file ends after {name} (truncated?)")
        fields = _fortran_widths(lines[i], f"{path}, line {i + 1}")
        i += 1
        found = 0
        while True:
            if i >= len(lines):
                raise MeshReadError(f"{path}: file ends inside the {name} of line {start} (truncated?)")
            row, lineno = lines[i], i + 1
            i += 1
            if row.strip() == "-1" or row.strip().upper().startswith("N,"):
                break
            where = f"{path}, line {lineno}"
            values = _cut(row, fields, where)
            if name == "NBLOCK":
                if len(values) < 3:
                    raise MeshReadError(f"{where}: NBLOCK row has {len(values)} fields, expected at least 3")
                xyz = (values[3:6] + [0.0, 0.0, 0.0])[:3]  # ANSYS omits trailing zero coordinates
                nodes.append((values[0], *xyz))
                node_src.append((0, lineno))
            else:
                n_nodes = values[8] if len(values) > 8 else -1
                if n_nodes not in (8, 20) or len(values) != _EBLOCK_FIXED + 8:
                    raise MeshReadError(
                        f"{where}: EBLOCK row has {len(values)} fields and node count {n_nodes}; expected "
                        f"{_EBLOCK_FIXED + 8} fields for an 8- or 20-node solid brick"
                    )
                if n_nodes == 20:  # midside nodes continue on the next line: skip them, keep the corners
                    if i >= len(lines) or len(_cut(lines[i], fields, f"{path}, line {i + 1}")) != 12:
                        raise MeshReadError(f"{where}: 20-node element {values[10]} lacks its midside node line")
                    i += 1
                    n_midside += 1
                elems.append(values)
                elem_src.append((0, lineno))
            found += 1
        if count is not None and found != count:
            raise MeshReadError(f"{path}, line {start}: {name} announces {count} rows but holds {found}")
    if not nodes:
        raise MeshReadError(f"{path}: no NBLOCK (nodes) found; not an APDL mesh file")
    if not elems:
        raise MeshReadError(f"{path}: no EBLOCK (elements) found; the file has {len(nodes)} nodes only")
    e = np.array(elems, dtype=np.int64)
    nd = np.array(nodes, dtype=np.float64)
    bricks = Bricks(
        node_ids=nd[:, 0].astype(np.int64),
        points=nd[:, 1:],
        elem_ids=e[:, 10],
        attrs=e[:, [0, 1, 2, 4, 3]],  # EBLOCK order MAT TYPE REAL SECNUM ESYS -> MAT TYP REL ESY SEC
        corners=e[:, _EBLOCK_FIXED:],
        files=(path,),
        node_src=np.array(node_src, dtype=np.int64),
        elem_src=np.array(elem_src, dtype=np.int64),
        n_midside=n_midside,
    )
    return to_hexmesh(bricks, path, "NBLOCK")


def _e21(x: float) -> str:
    """Fortran E21.13E3: `` 7.5000000000000E-001``."""
    mantissa, exponent = f"{x:.13E}".split("E")
    return f"{mantissa}E{int(exponent):+04d}".rjust(21)


def write_apdl(mesh: HexMesh, path: str | os.PathLike) -> None:
    """Write `mesh` as an APDL input file that re-creates it with its node and element numbers.

    **Arguments:**

    - `mesh`: the mesh; hexahedron, wedge, pyramid and tetra blocks are written (as 8-node bricks).
    - `path`: the file to write (`jaxci.io.write_mesh` passes a temporary name and moves it into place).

    **Returns:** nothing. Issues a `LossyWriteWarning` listing the cells, data and sets it leaves out.
    """
    path = os.fspath(path)
    b, dropped = from_hexmesh(mesh, file_cells(mesh), path)
    if len(b.elem_ids) == 0:
        raise MeshWriteError(f"{path}: the mesh has no cells that ANSYS bricks can hold")
    lost = [f"cells {', '.join(dropped)}"] if dropped else []
    other = sorted(set(mesh.cell_data) - set(ATTRIBUTES)) + sorted(mesh.point_data)
    if other:
        lost.append(f"point/cell data {other}")
    if mesh.point_sets or mesh.cell_sets:
        lost.append(f"sets {sorted(mesh.point_sets) + sorted(mesh.cell_sets)}")
    if mesh.field_data:
        lost.append(f"field data {sorted(mesh.field_data)}")
    if lost:
        warnings.warn(f"{os.path.basename(path)}: APDL drops {'; '.join(lost)}", LossyWriteWarning, stacklevel=3)

    out = [f"/COM, jaxci mesh: {len(b.node_ids)} nodes, {len(b.elem_ids)} elements", "/PREP7"]
    out += [f"ET,{t},SOLID185" for t in np.unique(b.attrs[:, 1])]
    out += [f"NBLOCK,6,SOLID,{b.node_ids.max():10d},{len(b.node_ids):10d}", _NBLOCK_FORMAT]
    out += [
        f"{nid:9d}{0:9d}{0:9d}{_e21(x)}{_e21(y)}{_e21(z)}"
        for nid, (x, y, z) in zip(b.node_ids.tolist(), b.points.tolist(), strict=True)
    ]
    out += ["N,R5.3,LOC,       -1,", f"EBLOCK,19,SOLID,{b.elem_ids.max():10d},{len(b.elem_ids):10d}", _EBLOCK_FORMAT]
    mat, typ, rel, esy, sec = b.attrs.T
    fixed = np.stack([mat, typ, rel, sec, esy] + [np.zeros_like(mat)] * 3 + [np.full_like(mat, 8), 0 * mat], axis=1)
    rows = np.concatenate([fixed, b.elem_ids[:, None], b.corners], axis=1)
    out += ["".join(f"{v:9d}" for v in row) for row in rows.tolist()]
    out += [f"{-1:9d}", "FINISH", ""]
    try:
        with open(path, "w", encoding="ascii") as f:
            f.write("\n".join(out))
    except OSError as exc:
        raise MeshWriteError(f"{path}: cannot write ({exc.strerror})") from exc
