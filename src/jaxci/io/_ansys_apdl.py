"""Write a mesh as an ANSYS APDL input file (NBLOCK / EBLOCK), and read that subset of APDL and CDB archives.

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

`read_apdl` reads the mesh of such a file or of an ANSYS ``CDWRITE`` archive (``.cdb``) with one parser: each
NBLOCK and EBLOCK in SOLID format, fields cut by the Fortran format line that follows it, trailing zero
coordinates omitted, an element's nodes continued on following lines, block row counts checked; ``ET`` (and
``ETBLOCK``) and ``KEYOPT`` records; ``CMBLOCK`` node and element components (as point and cell sets). Elements
must be 3-D solids of a type jaxci knows (`jaxci.io._ansys.BRICK8`, ``BRICK20``, ``TET4``, ``TET10``); an
element of another type, or of a TYPE no ``ET`` defines, is refused naming the file, line and element. Other
commands (materials, loads, ``*SET`` parameters, ...) are skipped and counted in `HexMesh.notes`: the written file
holds the mesh, element types and components only. The reader and the writer agree with the ``mapdl-archive``
package on its example archives (``tests/test_ansys.py``, ``tests/test_cdb.py``).
"""

from __future__ import annotations

import os
import re
import warnings

import numpy as np

from ..errors import MeshReadError, MeshWriteError
from ..mesh import CellBlock, HexMesh, mirrored_block
from ._ansys import (
    ATTRIBUTES,
    BRICK8,
    BRICK20,
    ELEMENT_NAMES,
    EXTRA_ATTRIBUTES,
    TET4,
    TET10,
    Bricks,
    _expand,
    _has_midside,
    from_hexmesh,
    to_hexmesh,
)
from ._ansys_listing import read_text_lines
from ._meshio import LossyWriteWarning

_FORMAT_ITEM = re.compile(r"(\d*)([IEFGD])(\d+)(?:\.\d+)?(?:E\d+)?", re.IGNORECASE)
_NBLOCK_FORMAT = "(3i9,6e21.13e3)"
_EBLOCK_FORMAT = "(19i9)"
_EBLOCK_FIXED = 11  # MAT TYPE REAL SECNUM ESYS birth/death solid-ref shape node-count 0 element-number
_NODE_COUNTS = (4, 8, 10, 20)
_CMBLOCK_FORMAT = "(8i10)"
#: Commands that carry no model data worth a note (session control, the block terminator of CDWRITE).
_HARMLESS = {"FINISH", "NUMOFF", "DOF", "TYPE", "MAT", "REAL", "ESYS", "SECNUM", "CSYS", "ANTYPE"}
#: ANSYS component names: a letter, then letters, digits and underscores, 32 characters at most.
_COMPONENT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,31}")


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


class _Reader:
    """One pass over the lines of an APDL file, collecting blocks and records with their line numbers."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.lines = read_text_lines(path, "APDL file")
        self.i = 0
        self.nodes, self.node_src, self.angles = [], [], []
        self.elems, self.elem_src = [], []  # (fixed 11 fields, node list)
        self.etypes, self.keyopts, self.components = {}, [], []
        self.skipped: dict[str, int] = {}

    def where(self, lineno: int) -> str:
        return f"{self.path}, line {lineno}"

    def next_line(self, what: str, start: int) -> tuple[str, int]:
        if self.i >= len(self.lines):
            raise MeshReadError(f"{self.path}: file ends inside the {what} of line {start} (truncated?)")
        self.i += 1
        return self.lines[self.i - 1], self.i

    def run(self) -> None:
        while self.i < len(self.lines):
            raw = self.lines[self.i].split("!", 1)[0].strip()
            self.i += 1
            name = raw.split(",", 1)[0].strip().upper()
            if name in ("NBLOCK", "EBLOCK"):
                self.block(raw)
            elif name == "ET":
                self.et(raw)
            elif name == "ETBLOCK":
                self.etblock(raw)
            elif name in ("KEYOPT", "KEYOP"):
                self.keyopt(raw)
            elif name == "CMBLOCK":
                self.cmblock(raw)
            elif name and not name.startswith(("/", "*", "C***")) and "=" not in name and name not in _HARMLESS:
                self.skipped[name] = self.skipped.get(name, 0) + 1

    # ----------------------------------------------------------------- element types
    def _int(self, tok: str, lineno: int, what: str) -> int:
        try:
            return int(float(tok))
        except ValueError:
            raise MeshReadError(f"{self.where(lineno)}: {what} {tok.strip()!r} is not a number") from None

    def et(self, raw: str) -> None:
        lineno = self.i
        parts = [p.strip() for p in raw.split(",")]
        if len(parts) < 3 or not parts[1] or not parts[2]:
            raise MeshReadError(f"{self.where(lineno)}: ET record {raw!r} lacks the type number or element name")
        itype = self._int(parts[1], lineno, "element type number")
        m = re.fullmatch(r"[A-Za-z]*(\d+)", parts[2])
        if m is None:
            raise MeshReadError(f"{self.where(lineno)}: ET record {raw!r}: cannot read the element name {parts[2]!r}")
        self.etypes[itype] = (int(m.group(1)), lineno)
        for k, tok in enumerate(parts[3:9], 1):  # KOP1..KOP6
            if tok and self._int(tok, lineno, f"KEYOPT({k})"):
                self.keyopts.append((itype, k, self._int(tok, lineno, f"KEYOPT({k})")))

    def etblock(self, raw: str) -> None:
        start = self.i
        self.next_line("ETBLOCK", start)  # format line
        while True:
            row, lineno = self.next_line("ETBLOCK", start)
            toks = row.split()
            if toks == ["-1"]:
                break
            vals = [self._int(t, lineno, "ETBLOCK field") for t in toks]
            if len(vals) < 2:
                raise MeshReadError(f"{self.where(lineno)}: ETBLOCK row {row.strip()!r} has fewer than 2 fields")
            self.etypes[vals[0]] = (vals[1], lineno)
            self.keyopts += [(vals[0], k, v) for k, v in enumerate(vals[2:20], 1) if v]

    def keyopt(self, raw: str) -> None:
        lineno = self.i
        parts = [p.strip() for p in raw.split(",")]
        if len(parts) < 4:
            raise MeshReadError(f"{self.where(lineno)}: KEYOPT record {raw!r} needs ITYPE, KNUM and VALUE")
        self.keyopts.append(tuple(self._int(p, lineno, "KEYOPT field") for p in parts[1:4]))

    # ----------------------------------------------------------------- components
    def cmblock(self, raw: str) -> None:
        start = self.i
        parts = [p.strip() for p in raw.split(",")]
        if len(parts) < 4:
            raise MeshReadError(f"{self.where(start)}: CMBLOCK record {raw!r} needs a name, a type and a count")
        name, kind = parts[1], parts[2].upper()
        count = self._int(parts[3], start, "CMBLOCK count")
        line, lineno = self.next_line("CMBLOCK", start)
        fields = _fortran_widths(line, self.where(lineno))
        items: list[int] = []
        while len(items) < count:
            row, lineno = self.next_line("CMBLOCK", start)
            items += _cut(row, fields, self.where(lineno))
        if len(items) != count:
            raise MeshReadError(f"{self.where(start)}: CMBLOCK {name} announces {count} items but holds "
                                f"{len(items)}")
        if kind in ("NODE", "ELEM", "ELEMENT"):
            self.components.append((name, "NODE" if kind == "NODE" else "ELEM", _expand(items),
                                    self.where(start)))
        else:
            self.skipped[f"CMBLOCK {kind}"] = self.skipped.get(f"CMBLOCK {kind}", 0) + 1

    # ----------------------------------------------------------------- NBLOCK / EBLOCK
    def block(self, raw: str) -> None:
        start = self.i
        name, count = _block_header(raw, start, self.path)
        line, lineno = self.next_line(name, start)
        fields = _fortran_widths(line, self.where(lineno))
        found = 0
        while True:
            row, lineno = self.next_line(name, start)
            if row.strip() == "-1" or row.strip().upper().startswith("N,"):
                break
            where = self.where(lineno)
            values = _cut(row, fields, where)
            if name == "NBLOCK":
                self.node_row(values, where, lineno)
            else:
                self.elem_row(values, fields, where, lineno, start)
            found += 1
        if count is not None and found != count:
            raise MeshReadError(f"{self.where(start)}: {name} announces {count} rows but holds {found}")

    def node_row(self, values: list, where: str, lineno: int) -> None:
        if len(values) < 3:
            raise MeshReadError(f"{where}: NBLOCK row has {len(values)} fields, expected at least 3")
        if any(isinstance(v, float) for v in values[:3]):
            raise MeshReadError(f"{where}: NBLOCK row does not start with 3 integers (node number, 0, 0)")
        xyz = (values[3:6] + [0.0, 0.0, 0.0])[:3]  # ANSYS omits trailing zero coordinates
        self.nodes.append((values[0], *xyz))
        self.angles.append((values[6:9] + [0.0, 0.0, 0.0])[:3])
        self.node_src.append((0, lineno))

    def elem_row(self, values: list, fields, where: str, lineno: int, start: int) -> None:
        n_nodes = values[8] if len(values) > 8 else -1
        if n_nodes not in _NODE_COUNTS or len(values) != _EBLOCK_FIXED + min(n_nodes, 8):
            raise MeshReadError(
                f"{where}: EBLOCK row has {len(values)} fields and node count {n_nodes}; expected "
                f"{_EBLOCK_FIXED} fields and 4, 8, 10 or 20 nodes (a 3-D solid in SOLID format)"
            )
        nodes = values[_EBLOCK_FIXED:]
        while len(nodes) < n_nodes:  # the nodes continue on the next line(s)
            if self.i >= len(self.lines):
                raise MeshReadError(f"{where}: {n_nodes}-node element {values[10]} lacks its continuation line "
                                    f"(truncated?)")
            row, cont = self.next_line("EBLOCK", start)
            more = _cut(row, fields, self.where(cont))
            if not more or len(nodes) + len(more) > n_nodes:
                raise MeshReadError(f"{self.where(cont)}: {n_nodes}-node element {values[10]} continues with "
                                    f"{len(more)} nodes; expected {n_nodes - len(nodes)}")
            nodes += more
        self.elems.append((values[:_EBLOCK_FIXED], nodes))
        self.elem_src.append((0, lineno))

    # ----------------------------------------------------------------- to Bricks
    def bricks(self) -> Bricks:
        path = self.path
        if not self.nodes:
            raise MeshReadError(f"{path}: no NBLOCK (nodes) found; not an APDL mesh file")
        if not self.elems:
            raise MeshReadError(f"{path}: no EBLOCK (elements) found; the file has {len(self.nodes)} nodes only")
        fixed = np.array([f for f, _ in self.elems], dtype=np.int64)
        corners = np.zeros((len(self.elems), 8), np.int64)
        midside = np.zeros((len(self.elems), 12), np.int64)
        n_mid = n_tet10 = 0
        for k, ((f, nodes), (_, lineno)) in enumerate(zip(self.elems, self.elem_src, strict=True)):
            family = self.family(f, len(nodes), lineno)
            if family == "tet":  # I J K L [M N O P Q R] -> brick I J K K L L L L, Q R K O L L L L P Q R R
                i, j, kk, ll = nodes[:4]
                corners[k] = (i, j, kk, kk, ll, ll, ll, ll)
                if len(nodes) == 10:
                    m = nodes[4:]
                    midside[k] = (m[0], m[1], kk, m[2], ll, ll, ll, ll, m[3], m[4], m[5], m[5])
            else:
                corners[k] = nodes[:8]
                if len(nodes) == 20:
                    midside[k] = nodes[8:]
            n_mid += len(nodes) == 20
            n_tet10 += len(nodes) == 10
        nd = np.array(self.nodes, dtype=np.float64)
        ang = np.array(self.angles, dtype=np.float64)
        extra = fixed[:, 5:8]
        return Bricks(
            node_ids=nd[:, 0].astype(np.int64),
            points=nd[:, 1:],
            elem_ids=fixed[:, 10],
            attrs=fixed[:, [0, 1, 2, 4, 3]],  # EBLOCK order MAT TYPE REAL SECNUM ESYS -> MAT TYP REL ESY SEC
            corners=corners,
            files=(path,),
            node_src=np.array(self.node_src, dtype=np.int64),
            elem_src=np.array(self.elem_src, dtype=np.int64),
            n_midside=n_mid,
            n_tet10=n_tet10,
            midside=midside if (midside != 0).any() else None,
            angles=ang if (ang != 0).any() else None,
            extra=extra if (extra != 0).any() else None,
            etypes=np.array([[t, r] for t, (r, _) in sorted(self.etypes.items())], np.int64).reshape(-1, 2)
            if self.etypes else None,
            keyopts=np.array(self.keyopts, np.int64).reshape(-1, 3) if self.keyopts else None,
            components=tuple(self.components),
        )

    def family(self, fixed: list, n: int, lineno: int) -> str:
        """"brick" or "tet" for an element with `n` nodes listed, checked against its type's ET record."""
        typ, eid = int(fixed[1]), int(fixed[10])
        where = self.where(lineno)
        if not self.etypes:  # no ET records (a hand-written file): the node count decides
            return "tet" if n in (4, 10) else "brick"
        if typ not in self.etypes:
            raise MeshReadError(f"{where}: element {eid} has TYPE {typ}, which no ET record of the file defines "
                                f"(types defined: {', '.join(map(str, sorted(self.etypes)))})")
        routine, et_line = self.etypes[typ]
        label = ELEMENT_NAMES.get(routine, f"element type {routine}")
        for family, table, counts in (("brick", BRICK8, (8,)), ("brick", BRICK20, (8, 20)), ("tet", TET4, (4,)),
                                      ("tet", TET10, (4, 10))):
            if routine in table:
                if n not in counts:
                    raise MeshReadError(
                        f"{where}: element {eid} lists {n} nodes, but its TYPE {typ} is {label} "
                        f"(ET at line {et_line}), which has {' or '.join(map(str, counts))}"
                    )
                return family
        known = ", ".join(ELEMENT_NAMES[r] for r in (*BRICK8, *BRICK20, *TET4, *TET10))
        raise MeshReadError(
            f"{where}: element {eid} has TYPE {typ} = {label} (ET at line {et_line}), an element type jaxci "
            f"cannot read; jaxci reads the 3-D solids {known}"
        )


def read_apdl(path: str | os.PathLike) -> HexMesh:
    """Read the mesh of an APDL input file (as written by `write_apdl`) or of an ANSYS CDB archive.

    **Arguments:** `path` the file.

    **Returns:** a `HexMesh` as from `jaxci.io.read_ansys_listing` (ids, ``ansys:*`` cell data, degenerate
    bricks as wedge/pyramid/tetra blocks, midside nodes of 20-node bricks and 10-node tetrahedra), with the
    ``ET``/``KEYOPT`` records as field data ``ansys:et`` (rows ``[itype, routine]``) and ``ansys:keyopt`` (rows
    ``[itype, knum, value]``), nodal rotation angles as point data ``ansys:angles``, and the CMBLOCK node and
    element components as point and cell sets. Raises `MeshReadError` naming the file and line for a bad or
    truncated block, a node no NBLOCK defines, an element type jaxci cannot read.
    """
    reader = _Reader(os.fspath(path))
    reader.run()
    notes = []
    if reader.skipped:
        top = sorted(reader.skipped.items(), key=lambda kv: -kv[1])
        listed = ", ".join(f"{k} x{v}" if v > 1 else k for k, v in top[:8]) + (", ..." if len(top) > 8 else "")
        notes.append(f"{sum(reader.skipped.values())} other APDL commands skipped ({listed}); a file jaxci writes "
                     f"holds the mesh, element types and components only")
    return to_hexmesh(reader.bricks(), reader.path, "NBLOCK", notes=notes)


def _e21(x: float) -> str:
    """Fortran E21.13E3: `` 7.5000000000000E-001``."""
    mantissa, exponent = f"{x:.13E}".split("E")
    return f"{mantissa}E{int(exponent):+04d}".rjust(21)


def _file_cells(mesh: HexMesh) -> list[CellBlock]:
    """The cell blocks as the file holds them: hexahedra (and their midside nodes) mirrored back when
    `HexMesh.hex_mirrored`."""
    if not mesh.hex_mirrored:
        return list(mesh.cells)
    return [mirrored_block(b) if b.type == "hexahedron" else b for b in mesh.cells]


def _compress(ids: np.ndarray) -> list[int]:
    """Sorted numbers as CMBLOCK items: a run i, i+1, ..., j becomes i, -j (the inverse of `_expand`)."""
    ids = np.unique(np.asarray(ids, np.int64))
    if not len(ids):
        return []
    breaks = np.flatnonzero(np.diff(ids) != 1)
    starts, ends = ids[np.r_[0, breaks + 1]], ids[np.r_[breaks, len(ids) - 1]]
    out: list[int] = []
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        out += [a] if a == b else [a, -b]
    return out


def _cmblock(name: str, kind: str, ids: np.ndarray) -> list[str]:
    items = _compress(ids)
    out = [f"CMBLOCK,{name},{kind},{len(items):8d}", _CMBLOCK_FORMAT]
    out += ["".join(f"{v:10d}" for v in items[i : i + 8]) for i in range(0, len(items), 8)]
    return out


def _element_rows(b: Bricks, path: str) -> list[str]:
    """EBLOCK rows (one or two lines per element) of the bricks `b`, node counts by each TYPE's routine."""
    routine = dict(b.etypes.tolist())
    typ = b.attrs[:, 1]
    own_mid = _has_midside(b)
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
        out.append("".join(f"{v:9d}" for v in vals))
        if len(nodes) > 8:
            out.append("".join(f"{int(v):9d}" for v in nodes[8:]))
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
    b, dropped = from_hexmesh(mesh, _file_cells(mesh), path)
    if len(b.elem_ids) == 0:
        raise MeshWriteError(f"{path}: the mesh has no cells that ANSYS bricks can hold")
    lost = [f"cells {', '.join(dropped)}"] if dropped else []
    other = sorted(set(mesh.cell_data) - set(ATTRIBUTES) - set(EXTRA_ATTRIBUTES))
    other += sorted(set(mesh.point_data) - {"ansys:angles"})
    if other:
        lost.append(f"point/cell data {other}")
    bad_names = sorted(n for n in (*mesh.point_sets, *mesh.cell_sets) if not _COMPONENT_NAME.fullmatch(n))
    if bad_names:
        lost.append(f"sets {bad_names} (not valid ANSYS component names)")
    field = sorted(set(mesh.field_data) - {"ansys:et", "ansys:keyopt"})
    if field:
        lost.append(f"field data {field}")
    if lost:
        warnings.warn(f"{os.path.basename(path)}: APDL drops {'; '.join(lost)}", LossyWriteWarning, stacklevel=3)

    out = [f"/COM, jaxci mesh: {len(b.node_ids)} nodes, {len(b.elem_ids)} elements", "/PREP7"]
    numeric = path.lower().endswith(".cdb")  # CDWRITE's form (what mapdl-archive reads); names elsewhere
    out += [f"ET,{t},{r if numeric else ELEMENT_NAMES.get(r, r)}" for t, r in b.etypes.tolist()]
    if b.keyopts is not None:
        out += [f"KEYOPT,{t},{k},{v}" for t, k, v in np.asarray(b.keyopts, np.int64).reshape(-1, 3).tolist()]
    out += [f"NBLOCK,6,SOLID,{b.node_ids.max():10d},{len(b.node_ids):10d}", _NBLOCK_FORMAT]
    if b.angles is not None and (b.angles != 0).any():
        out += [
            f"{nid:9d}{0:9d}{0:9d}" + "".join(_e21(v) for v in (*xyz, *ang))
            for nid, xyz, ang in zip(b.node_ids.tolist(), b.points.tolist(), b.angles.tolist(), strict=True)
        ]
    else:
        out += [
            f"{nid:9d}{0:9d}{0:9d}{_e21(x)}{_e21(y)}{_e21(z)}"
            for nid, (x, y, z) in zip(b.node_ids.tolist(), b.points.tolist(), strict=True)
        ]
    out += ["N,R5.3,LOC,       -1,", f"EBLOCK,19,SOLID,{b.elem_ids.max():10d},{len(b.elem_ids):10d}", _EBLOCK_FORMAT]
    out += _element_rows(b, path)
    out += [f"{-1:9d}"]
    node_ids = b.node_ids
    for name, idx in mesh.point_sets.items():
        if _COMPONENT_NAME.fullmatch(name):
            out += _cmblock(name, "NODE", node_ids[np.asarray(idx, np.int64)])
    if mesh.cell_sets:
        ids_of = [blk.ids for blk in _element_blocks_with_ids(mesh, b)]
        for name, per_block in mesh.cell_sets.items():
            if _COMPONENT_NAME.fullmatch(name):
                ids = [ids_of[i][np.asarray(rows, np.int64)] for i, rows in enumerate(per_block)
                       if ids_of[i] is not None and rows is not None]
                out += _cmblock(name, "ELEM", np.concatenate(ids) if ids else np.zeros(0, np.int64))
    out += ["FINISH", ""]
    try:
        with open(path, "w", encoding="ascii") as f:
            f.write("\n".join(out))
    except OSError as exc:
        raise MeshWriteError(f"{path}: cannot write ({exc.strerror})") from exc


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
