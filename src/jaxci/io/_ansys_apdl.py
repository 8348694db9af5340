"""Read ANSYS APDL input files (NBLOCK / EBLOCK) and CDB archives: the subset `jaxci.io._ansys_apdl_write` writes.

`read_apdl` reads the mesh of an APDL input file (as `write_apdl` writes it) or of an ANSYS ``CDWRITE`` archive
(``.cdb``) with one parser: each NBLOCK and EBLOCK in SOLID format, fields cut by the Fortran format line that
follows it, trailing zero coordinates omitted, an element's nodes continued on following lines, block row counts
checked; ``ET`` (and ``ETBLOCK``) and ``KEYOPT`` records; ``CMBLOCK`` node and element components (as point and cell
sets). Elements must be 3-D solids of a type jaxci knows (`jaxci.io._ansys.BRICK8`, ``BRICK20``, ``TET4``,
``TET10``); an element of another type, or of a TYPE no ``ET`` defines, is refused naming the file, line and
element. Other commands (materials, loads, ``*SET`` parameters, ...) are not modelled (counted in `HexMesh.notes`);
the whole text of the file is kept as the field data ``ansys:deck``, and `jaxci.io._ansys_apdl_write.write_apdl`
writes it back with only the coordinates of the NBLOCK rows changed. Node and element numbers must be positive and
unique and fit int64, coordinates finite; anything else is a `MeshReadError` naming the file and line. The reader
and the writer agree with the ``mapdl-archive`` package on its example archives (``tests/test_ansys.py``,
``tests/test_cdb.py``, ``tests/test_roundtrip.py``).
"""

from __future__ import annotations

import os
import re

import numpy as np

from ..errors import MeshReadError
from ..mesh import HexMesh
from ._ansys import (
    BRICK8,
    BRICK20,
    ELEMENT_NAMES,
    TET4,
    TET10,
    Bricks,
    expand_ranges,
    to_hexmesh,
)
from ._deck import MAX_ID, read_text

_FORMAT_ITEM = re.compile(r"(\d*)([IEFGD])(\d+)(?:\.\d+)?(?:E\d+)?", re.IGNORECASE)
NBLOCK_FORMAT = "(3i9,6e21.13e3)"
EBLOCK_FORMAT = "(19i9)"
_EBLOCK_FIXED = 11  # MAT TYPE REAL SECNUM ESYS birth/death solid-ref shape node-count 0 element-number
_NODE_COUNTS = (4, 8, 10, 20)
CMBLOCK_FORMAT = "(8i10)"
#: Commands that carry no model data worth a note (session control, the block terminator of CDWRITE).
_HARMLESS = {"FINISH", "NUMOFF", "DOF", "TYPE", "MAT", "REAL", "ESYS", "SECNUM", "CSYS", "ANTYPE"}
#: ANSYS component names: a letter, then letters, digits and underscores, 32 characters at most.
COMPONENT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,31}")


def _fortran_widths(line: str, where: str) -> list[tuple[bool, int]]:
    """(is_integer, width) of every field of a Fortran format line such as ``(3i9,6e21.13e3)``."""
    body = line.strip()
    if not (body.startswith("(") and body.endswith(")")):
        raise MeshReadError(f"{where}: expected a Fortran format line such as {NBLOCK_FORMAT}, got {body!r}")
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
            value = int(chunk) if is_int else float(chunk.replace("D", "E").replace("d", "e"))
        except ValueError:
            kind = "an integer" if is_int else "a number"
            raise MeshReadError(f"{where}: field {len(out) + 1} {chunk!r} is not {kind}") from None
        if is_int and abs(value) > MAX_ID:
            raise MeshReadError(f"{where}: field {len(out) + 1} {chunk!r} is too large (jaxci reads numbers up to "
                                f"{MAX_ID})")
        out.append(value)
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


class DeckReader:
    """One pass over the lines of an APDL file, collecting blocks and records with their line numbers."""

    def __init__(self, path: str, lines: list[str]) -> None:
        self.path, self.lines = path, lines
        self.i = 0
        self.nodes, self.node_src, self.angles = [], [], []
        self.node_format: list[int] = []  # index into nblock_formats of each node's row
        self.nblock_formats: list[tuple[str, list]] = []  # (format line, fields) of each NBLOCK
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
                self.etblock()
            elif name in ("KEYOPT", "KEYOP"):
                self.keyopt(raw)
            elif name == "CMBLOCK":
                self.cmblock(raw)
            elif name.startswith("/INP"):  # the file it names is not read: its mesh is not part of this one
                self.skipped["/INPUT (not followed)"] = self.skipped.get("/INPUT (not followed)", 0) + 1
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

    def etblock(self) -> None:
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
            self.components.append((name, "NODE" if kind == "NODE" else "ELEM", expand_ranges(items),
                                    self.where(start)))
        else:
            self.skipped[f"CMBLOCK {kind}"] = self.skipped.get(f"CMBLOCK {kind}", 0) + 1

    # ----------------------------------------------------------------- NBLOCK / EBLOCK
    def block(self, raw: str) -> None:
        start = self.i
        name, count = _block_header(raw, start, self.path)
        line, lineno = self.next_line(name, start)
        fields = _fortran_widths(line, self.where(lineno))
        if name == "NBLOCK":
            self.nblock_formats.append((line.strip(), fields))
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
        if values[0] < 1:
            raise MeshReadError(f"{where}: node number {values[0]} is not positive (ids start at 1)")
        xyz = (values[3:6] + [0.0, 0.0, 0.0])[:3]  # ANSYS omits trailing zero coordinates
        if not np.isfinite(values[3:9]).all():
            raise MeshReadError(f"{where}: node {values[0]} has a non-finite coordinate or angle "
                                f"({', '.join(map(str, values[3:9]))})")
        self.nodes.append((values[0], *xyz))
        self.angles.append((values[6:9] + [0.0, 0.0, 0.0])[:3])
        self.node_src.append((0, lineno))
        self.node_format.append(len(self.nblock_formats) - 1)

    def elem_row(self, values: list, fields, where: str, lineno: int, start: int) -> None:
        n_nodes = values[8] if len(values) > 8 else -1
        if n_nodes not in _NODE_COUNTS or len(values) != _EBLOCK_FIXED + min(n_nodes, 8):
            raise MeshReadError(
                f"{where}: EBLOCK row has {len(values)} fields and node count {n_nodes}; expected "
                f"{_EBLOCK_FIXED} fields and 4, 8, 10 or 20 nodes (a 3-D solid in SOLID format)"
            )
        if values[10] < 1:
            raise MeshReadError(f"{where}: element number {values[10]} is not positive (ids start at 1)")
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
        nd = np.array([n[1:] for n in self.nodes], dtype=np.float64).reshape(-1, 3)
        ang = np.array(self.angles, dtype=np.float64)
        extra = fixed[:, 5:8]
        return Bricks(
            node_ids=np.array([n[0] for n in self.nodes], dtype=np.int64),  # not through float64: ids above 2^53
            points=nd,
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
    path = os.fspath(path)
    text = read_text(path, "APDL file")
    reader = DeckReader(path, text.splitlines())
    reader.run()
    notes = []
    if reader.skipped:
        top = sorted(reader.skipped.items(), key=lambda kv: -kv[1])
        listed = ", ".join(f"{k} x{v}" if v > 1 else k for k, v in top[:8]) + (", ..." if len(top) > 8 else "")
        notes.append(f"{sum(reader.skipped.values())} other APDL commands not modelled ({listed}); kept in the "
                     f"file's text, and written back when the mesh is written as APDL with only its node "
                     f"coordinates changed")
    return to_hexmesh(reader.bricks(), reader.path, "NBLOCK", notes=notes, extra_field_data={"ansys:deck": text})


def other_commands(text: str) -> list[str]:
    """The APDL commands of a file's text that jaxci does not model (``MPDATA x3``, ...), most frequent first."""
    reader = DeckReader("(text)", text.splitlines())
    try:
        reader.run()
    except MeshReadError:
        return ["(unreadable)"]
    top = sorted(reader.skipped.items(), key=lambda kv: -kv[1])
    return [f"{k} x{v}" if v > 1 else k for k, v in top]
