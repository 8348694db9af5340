"""Hostile input: every way a user (or a damaged file) can feed jaxci garbage, held to one contract.

The contract each case asserts:

- the exit code is 2 for any bad input a user can fix, 0 only when the input is actually fine, never 1
  ("internal error" is reserved for our own bugs);
- on exit 2, stderr is exactly ONE line starting ``jaxci: error:`` and no traceback (nor on exit 0);
- no file appears, changes or disappears in the working folder (names and bytes are compared before and after)
  except an output the command was asked to write and succeeded in writing;
- a file that was read with exit 0 was read as what it holds (node and cell counts of the file, JSON without
  NaN / Infinity).

The CLI runs in-process (`jaxci.cli.main`, stdout/stderr through capsys) in a fresh working folder; only the
cases that would exhaust memory or never return when the contract is broken (`TOO_LARGE`) run `jaxci.cli.main`
in one child process under an 8 GiB address-space limit and a timeout.

Hypothesis corrupts small valid meshes written in every format (jaxci's own writers, ASCII variants written by
meshio, an ANSYS NLIST/ELIST listing, the Mesquite and peer meshes of ../shared): truncations that cut data,
byte flips, and numbers replaced by huge, negative, NaN/inf, out-of-range, duplicate or wrong values, each with
the exit code it must give. The default run keeps a few examples per case (seconds); the ``deep`` marker has
the same cases with many more examples and is deselected by default (``addopts`` in pyproject.toml). Run it with::

    python3 -m pytest tests/test_hostile.py -m deep          # the deep set only
    python3 -m pytest tests/test_hostile.py -m "deep or not deep"   # everything
"""

from __future__ import annotations

import functools
import json
import os
import re
import resource
import signal
import tempfile
import time
from pathlib import Path

import meshio
import numpy as np
import pytest
from helpers import MESQUITE, PEERS
from hostile_kit import assert_ok, assert_refused, changes, cli_in, inside, run_in, run_in_child, snapshot
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

import jaxci
from jaxci.cli import main
from jaxci.errors import JaxciError

# ----------------------------------------------------------------------------------------------- settings

FAST = 10  # examples per parametrised hypothesis case in the default run
DEEP = 250  # ... in the deep run
_COMMON = dict(
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],  # no shrinking: the case note says what was done
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

# ----------------------------------------------------------------------------------------------- helpers


def assert_ok_or_refused(rc, out, err, what=""):
    assert rc in (0, 2), f"{what}: rc {rc} (1 is an internal error), stderr {err[-1500:]!r}"
    if rc == 2:
        assert_refused(rc, out, err, what=what)
    else:
        assert_ok(rc, out, err, what)


def strict_json(text: str, what=""):
    """The JSON object `text` holds; NaN / Infinity (not JSON) fail."""

    def bad(token):
        raise AssertionError(f"{what}: quality --json printed {token}: {text[:500]!r}")

    return json.loads(text, parse_constant=bad)


def assert_counts(d: dict, n_nodes: int, n_cells: int, what=""):
    other = d.get("other_cells") or {}
    got = (d["n_nodes"], d["n_elements"] + sum(other.values()))
    assert got == (n_nodes, n_cells), (
        f"{what}: read as {d['n_nodes']} nodes, {d['n_elements']} hexahedra + {other}; the file holds "
        f"{n_nodes} nodes and {n_cells} cells")


def expect_quality(capsys, folder, path, expect: str, n_nodes: int, n_cells: int, what: str):
    """`jaxci quality PATH --json` in `folder`: ``expect`` is "refuse" (2), "accept" (0) or "any" (0 or 2)."""
    rc, out, err = run_in(capsys, folder, "quality", path, "--json")
    if expect == "refuse":
        assert_refused(rc, out, err, what=what)
        return
    if expect == "accept":
        assert_ok(rc, out, err, what)
    else:
        assert_ok_or_refused(rc, out, err, what)
    if rc == 0:
        assert_counts(strict_json(out, what), n_nodes, n_cells, what)


def points_of(path) -> np.ndarray:
    return np.asarray(meshio.read(str(path)).points, dtype=np.float64)


def write_hexes(path, points, hexes, **kw):
    """Write a hexahedral mesh with meshio directly (no jaxci validation between the test and the file)."""
    meshio.write(str(path), meshio.Mesh(np.asarray(points, float), [("hexahedron", np.asarray(hexes))]), **kw)


# ----------------------------------------------------------------------------------------------- base files

BOX = jaxci.box(2, 2, 2)
N_NODES, N_CELLS = BOX.n_nodes, BOX.n_hexes  # 27, 8
PTS = np.asarray(BOX.points, dtype=np.float64)
HEX = np.asarray(BOX.hexes, dtype=np.int64)


def listing_text(points, hexes, node_ids=None, elem_ids=None) -> str:
    """An ANSYS NLIST + ELIST listing (the layout of tests/fixtures/ansys/block_combined.txt)."""
    node_ids = np.arange(1, len(points) + 1) if node_ids is None else node_ids
    elem_ids = np.arange(1, len(hexes) + 1) if elem_ids is None else elem_ids
    page = [" *** ANSYS - ENGINEERING ANALYSIS SYSTEM  RELEASE 2020 R2          20.2     ***",
            " ANSYS Mechanical Enterprise                       ",
            " 00000000  VERSION=WINDOWS x64   10:31:01  JUN 14, 2021 CP=      0.813", "", " hostile box", ""]
    lines = ["", " LIST ALL SELECTED NODES.   DSYS=      0", "  SORT TABLE ON  NODE  NODE  NODE", "", *page,
             "    NODE        X             Y             Z           THXY     THYZ     THZX", ""]
    lines += [f"{int(i):9d}   {x:.10f}       {y:.10f}       {z:.10f}          0.00     0.00     0.00"
              for i, (x, y, z) in zip(node_ids, points, strict=True)]
    lines += ["", "", " LIST ALL SELECTED ELEMENTS.  (LIST NODES)", "", *page,
              "    ELEM MAT TYP REL ESY SEC        NODES", ""]
    for e, h in zip(elem_ids, hexes, strict=True):
        lines.append(f"{int(e):8d}   1   1   1   0   1 " + "".join(f" {int(node_ids[n]):5d}" for n in h))
    return "\n".join(lines) + "\n"


def cdb_text(points, hexes, node_ids=None, elem_ids=None, width=9) -> str:
    """An APDL NBLOCK/EBLOCK file with integer fields `width` wide (the Fortran format lines say so)."""
    node_ids = np.arange(1, len(points) + 1) if node_ids is None else node_ids
    elem_ids = np.arange(1, len(hexes) + 1) if elem_ids is None else elem_ids
    w = width
    lines = ["/PREP7", "ET,1,185", f"NBLOCK,6,SOLID,{int(max(node_ids))},{len(points)}", f"(3i{w},6e21.13e3)"]
    lines += [f"{int(i):{w}d}{0:{w}d}{0:{w}d}" + "".join(f"{v:21.13E}" for v in p)
              for i, p in zip(node_ids, points, strict=True)]
    lines += ["-1", f"EBLOCK,19,SOLID,{int(max(elem_ids))},{len(hexes)}", f"(19i{w})"]
    for e, h in zip(elem_ids, hexes, strict=True):
        fields = [1, 1, 1, 1, 0, 0, 0, 0, 8, 0, int(e), *(int(node_ids[n]) for n in h)]
        lines.append("".join(f"{v:{w}d}" for v in fields))
    lines += ["-1", "FINISH"]
    return "\n".join(lines) + "\n"


@functools.cache
def base_files() -> dict[str, tuple[str, dict[str, bytes]]]:
    """format key -> (file to read, {file name: bytes}) of the 2x2x2 box, each written once per session."""
    from jaxci.io import write_mesh

    out = {}
    with tempfile.TemporaryDirectory() as d, inside(d):
        mm = meshio.Mesh(PTS, [("hexahedron", HEX)])
        jobs = {
            "vtk": ("a.vtk", lambda: write_mesh(BOX, "a.vtk")),
            "vtk-binary": ("a.vtk", lambda: meshio.write("a.vtk", mm, binary=True)),
            "vtu": ("a.vtu", lambda: write_mesh(BOX, "a.vtu")),
            "vtu-ascii": ("a.vtu", lambda: meshio.write("a.vtu", mm, binary=False)),
            "gmsh41": ("a.msh", lambda: write_mesh(BOX, "a.msh")),
            "gmsh22": ("a.msh", lambda: write_mesh(BOX, "a.msh", file_format="gmsh22")),
            "gmsh41-ascii": ("a.msh", lambda: meshio.write("a.msh", mm, file_format="gmsh", binary=False)),
            "gmsh22-ascii": ("a.msh", lambda: meshio.write("a.msh", mm, file_format="gmsh22", binary=False)),
            "abaqus": ("a.inp", lambda: write_mesh(BOX, "a.inp")),
            "cdb": ("a.cdb", lambda: write_mesh(BOX, "a.cdb")),
            "mac": ("a.mac", lambda: write_mesh(BOX, "a.mac")),
            "lis": ("a.lis", lambda: Path("a.lis").write_text(listing_text(PTS, HEX))),
        }
        try:
            import h5py  # noqa: F401

            jobs["xdmf"] = ("a.xdmf", lambda: write_mesh(BOX, "a.xdmf"))
        except ImportError:
            pass
        for key, (name, write) in jobs.items():
            sub = Path(d) / key
            sub.mkdir()
            with inside(sub):
                write()
            out[key] = (name, {p.name: p.read_bytes() for p in sorted(sub.iterdir())})
    return out


ALL_FORMATS = ["vtk", "vtk-binary", "vtu", "vtu-ascii", "gmsh41", "gmsh22", "gmsh41-ascii", "gmsh22-ascii",
               "abaqus", "cdb", "mac", "lis", "xdmf"]


def base(fmt):
    files = base_files()
    if fmt not in files:
        pytest.skip(f"{fmt}: needs h5py")
    return files[fmt]


# ----------------------------------------------------------------------------------------------- token scanners
# A token: (start, end, role, text, width) in the text of a file; width is the field width of fixed-width
# formats (the replacement is right-justified to it), else None. Roles and what replacing one must give:
#   count  a header or row count                 -> any other value: refused
#   coord  a coordinate                          -> NaN/inf refused; 1e300 read or refused; a finite value read
#   conn   a node reference of a cell            -> out of range refused; another node read or refused
#   ctype  a cell type / element type            -> a type with another node count or unknown: refused
#   nid    a node id (its definition)            -> duplicate, huge, 0, negative: refused (cells lose their node)
#   eid    an element id                         -> duplicate, huge (>= 1e19), 0, negative: refused
#   other  anything else numeric                 -> read (consistently) or refused

_WORD = re.compile(r"\S+")
_FIELD = re.compile(r"[^,\s]+")


def _lines(text):
    pos = 0
    for line in text.splitlines(keepends=True):
        yield pos, line.rstrip("\r\n")
        pos += len(line)


def _tok(start, m, role, width=None):
    return (start + m.start(), start + m.end(), role, m.group(), width)


def scan_vtk(text):
    words = [(m.start(), m.end(), m.group()) for m in _WORD.finditer(text)]
    w = [x[2] for x in words]

    def t(i, role):
        return (*words[i][:2], role, words[i][2], None)

    out = []
    p = w.index("POINTS")
    n = int(w[p + 1])
    out += [t(p + 1, "count")] + [t(i, "coord") for i in range(p + 3, p + 3 + 3 * n)]
    c = w.index("CELLS")
    m = int(w[c + 1])
    out += [t(c + 1, "count"), t(c + 2, "count")]
    if "OFFSETS" in w:  # version 5.1: OFFSETS type, m+1 offsets, CONNECTIVITY type, the node indices
        o = w.index("OFFSETS")
        out += [t(i, "count") for i in range(o + 2, o + 3 + m)]
        k = w.index("CONNECTIVITY")
        out += [t(i, "conn") for i in range(k + 2, w.index("CELL_TYPES"))]
    else:
        k = c + 3
        for _ in range(m):
            size = int(w[k])
            out += [t(k, "count")] + [t(i, "conn") for i in range(k + 1, k + 1 + size)]
            k += 1 + size
    ct = w.index("CELL_TYPES")
    out += [t(ct + 1, "count")] + [t(i, "ctype") for i in range(ct + 2, ct + 2 + m)]
    return out


def scan_vtu(text):
    out = []
    for attr in ("NumberOfPoints", "NumberOfCells", "NumberOfComponents"):
        out += [_tok(0, m, "count") for m in re.finditer(rf'(?<={attr}=")\d+', text)]
    roles = {"Points": "coord", "connectivity": "conn", "offsets": "count", "types": "ctype"}
    for m in re.finditer(r'<DataArray[^>]*Name="(\w+)"[^>]*>(.*?)</DataArray>', text, re.S):
        role = roles.get(m.group(1), "other")
        out += [_tok(m.start(2), w, role) for w in _WORD.finditer(m.group(2))]
    return out


def scan_gmsh41(text):
    lines = list(_lines(text))
    s = [ln for _, ln in lines]
    out = []

    def row(i, roles):
        start, line = lines[i]
        ws = list(_WORD.finditer(line))
        assert len(ws) == len(roles), (i, line, roles)
        return [_tok(start, w, r) for w, r in zip(ws, roles, strict=True) if r]

    i = s.index("$Nodes")
    out += row(i + 1, ["count", "count", "other", "other"])
    nb = int(s[i + 2].split()[3])
    out += row(i + 2, ["other", "other", "other", "count"])
    for k in range(nb):
        out += row(i + 3 + k, ["nid"])
    for k in range(nb):
        out += row(i + 3 + nb + k, ["coord"] * 3)
    i = s.index("$Elements")
    out += row(i + 1, ["count", "count", "other", "other"])
    ne = int(s[i + 2].split()[3])
    out += row(i + 2, ["other", "other", "ctype", "count"])
    for k in range(ne):
        out += row(i + 3 + k, ["eid"] + ["conn"] * 8)
    return out


def scan_gmsh22(text):
    lines = list(_lines(text))
    s = [ln for _, ln in lines]
    out = []

    def words(i):
        return list(_WORD.finditer(lines[i][1]))

    i = s.index("$Nodes")
    out += [_tok(lines[i + 1][0], words(i + 1)[0], "count")]
    for k in range(int(s[i + 1])):
        ws = words(i + 2 + k)
        out += [_tok(lines[i + 2 + k][0], w, r) for w, r in zip(ws, ["nid", "coord", "coord", "coord"], strict=True)]
    i = s.index("$Elements")
    out += [_tok(lines[i + 1][0], words(i + 1)[0], "count")]
    for k in range(int(s[i + 1])):
        ws = words(i + 2 + k)
        ntags = int(ws[2].group())
        roles = ["eid", "ctype", "count"] + ["other"] * ntags + ["conn"] * 8
        out += [_tok(lines[i + 2 + k][0], w, r) for w, r in zip(ws, roles, strict=True)]
    return out


def scan_abaqus(text):
    out, section = [], None
    for start, line in _lines(text):
        if line.startswith("*"):
            up = line.upper()
            section = "node" if up.startswith("*NODE") else "elem" if up.startswith("*ELEMENT") else None
            if section == "elem":
                m = re.search(r"(?i)(?<=TYPE=)\w+", line)
                out.append((start + m.start(), start + m.end(), "ctype", m.group(), None))
            continue
        ws = list(_FIELD.finditer(line))
        if section == "node" and ws:
            out += [_tok(start, w, r) for w, r in zip(ws, ["nid", "coord", "coord", "coord"], strict=True)]
        elif section == "elem" and ws:
            out += [_tok(start, w, "eid" if k == 0 else "conn") for k, w in enumerate(ws)]
    return out


_EROLES = ["other", "ctype"] + ["other"] * 6 + ["count", "other", "eid"] + ["conn"] * 8


def scan_apdl(text):
    out, block, widths = [], None, None
    lines = list(_lines(text))
    k = 0
    while k < len(lines):
        start, line = lines[k]
        k += 1
        head = line.split(",", 1)[0].strip().upper()
        if head == "ET":
            ws = list(_FIELD.finditer(line))
            out += [_tok(start, ws[1], "other"), _tok(start, ws[2], "ctype")]
        elif head in ("NBLOCK", "EBLOCK"):
            ws = list(_FIELD.finditer(line))
            out += [_tok(start, ws[1], "other"), _tok(start, ws[3], "other"), _tok(start, ws[4], "count")]
            fmt = lines[k][1]
            k += 1
            widths = []
            for n, _, width in re.findall(r"(\d*)([ie])(\d+)", fmt.lower()):
                widths += [int(width)] * int(n or 1)
            block = head
            while k < len(lines) and lines[k][1].strip() != "-1" and not lines[k][1].upper().startswith("N,"):
                start, row = lines[k]
                k += 1
                pos, fields = 0, []
                while pos < len(row):
                    fields.append((pos, min(pos + widths[len(fields)], len(row))))
                    pos += widths[len(fields) - 1]
                roles = ["nid", "other", "other", "coord", "coord", "coord"] if block == "NBLOCK" else _EROLES
                out += [(start + a, start + b, r, row[a:b], b - a) for (a, b), r in zip(fields, roles, strict=False)]
    return out


def scan_listing(text):
    out = []
    for start, line in _lines(text):
        ws = list(_WORD.finditer(line))
        if not ws or any(not re.fullmatch(r"[-+0-9.eE]+", w.group()) for w in ws):
            continue
        if len(ws) == 7:
            out += [_tok(start, w, r) for w, r in zip(ws, ["nid"] + ["coord"] * 3 + ["other"] * 3, strict=True)]
        elif len(ws) == 14:
            out += [_tok(start, w, r) for w, r in zip(ws, ["eid"] + ["other"] * 5 + ["conn"] * 8, strict=True)]
    return out


def scan_xdmf(text):
    out = []
    for m in re.finditer(r'Dimensions="(\d+) (\d+)"', text):
        out += [(m.start(g), m.end(g), "count", m.group(g), None) for g in (1, 2)]
    for attr in ("NumberOfElements", "NodesPerElement"):
        out += [_tok(0, m, "count") for m in re.finditer(rf'(?<={attr}=")\d+', text)]
    out += [_tok(0, m, "ctype") for m in re.finditer(r'(?<=TopologyType=")\w+', text)]
    return out


SCANNERS = {"vtk": scan_vtk, "vtu-ascii": scan_vtu, "gmsh41-ascii": scan_gmsh41, "gmsh22-ascii": scan_gmsh22,
            "abaqus": scan_abaqus, "cdb": scan_apdl, "mac": scan_apdl, "lis": scan_listing, "xdmf": scan_xdmf}
#: 0-based node references (VTK, VTU) or 1-based ids (the others): (first, last) valid reference.
CONN_RANGE = {"vtk": (0, N_NODES - 1), "vtu-ascii": (0, N_NODES - 1)}
#: cell type replacements that cannot be read as the file's 8-node cells (never VTK 11 = voxel, Gmsh 5 = hex)
BAD_CTYPES = {
    "vtk": ["10", "13", "14", "9", "1", "0", "-1", "999", "25", "29", "100000000000000000000"],
    "gmsh": ["4", "6", "7", "3", "1", "15", "17", "12", "0", "999"],
    "abaqus": ["C3D4", "C3D6", "C3D20", "C3D10", "S4R", "B31", "FOO"],
    "apdl-et": ["187", "285", "1", "999", "SOLID187", "0"],
    "apdl-type": ["2", "0", "-1", "99"],
    "xdmf": ["Tetrahedron", "Wedge", "Pyramid", "Quadrilateral", "Polyvertex", "Hexahedron_20", "Bogus"],
}


TOKEN_CASES = [(fmt, role) for fmt in SCANNERS
               for role in ("count", "coord", "conn", "ctype", "nid", "eid", "other")
               if role in {"vtk": "count coord conn ctype",
                           "vtu-ascii": "count coord conn ctype",
                           "gmsh41-ascii": "count coord conn ctype nid eid other",
                           "gmsh22-ascii": "count coord conn ctype nid eid other",
                           "abaqus": "coord conn ctype nid eid",
                           "cdb": "count coord conn ctype nid eid other",
                           "mac": "count coord conn ctype nid eid other",
                           "lis": "coord conn nid eid other",
                           "xdmf": "count ctype"}[fmt].split()]


def replacements(fmt, tok, all_toks, draw) -> list[tuple[str, str]]:
    """(replacement text, expectation) options for token `tok` of a file of format `fmt`."""
    _, _, role, text, _ = tok
    if role == "count":
        v = int(text)
        vals = [v + d for d in (-3, -2, -1, 1, 2, 3)] + [0, -1, 10**9, 10**20]
        return [(str(x), "refuse") for x in dict.fromkeys(vals) if x != v]
    if role == "coord":
        v = float(text.replace("D", "E"))
        x = draw(st.floats(-5, 5, allow_nan=False))
        return [("nan", "refuse"), ("NaN", "refuse"), ("inf", "refuse"), ("-inf", "refuse"),
                ("1e300", "any"), ("-1e300", "any"), (f"{-v:.6g}", "accept"), (f"{x:.6g}", "accept"),
                ("1e-300", "accept")]
    if role == "conn":
        lo, hi = CONN_RANGE.get(fmt, (1, N_NODES))
        bad = [hi + 1, hi + 2, hi + 100, lo - 1, -1, 2**31, 2**63, 10**19, 10**20]
        other = draw(st.integers(lo, hi).filter(lambda n: str(n) != text))
        return [(str(b), "refuse") for b in dict.fromkeys(bad)] + [(str(other), "any")]
    if role == "ctype":
        if fmt in ("vtk", "vtu-ascii"):
            pool = BAD_CTYPES["vtk"]
        elif fmt.startswith("gmsh"):
            pool = BAD_CTYPES["gmsh"]
        elif fmt in ("cdb", "mac"):
            pool = BAD_CTYPES["apdl-type"] if text.strip().isdigit() and tok[4] else BAD_CTYPES["apdl-et"]
        else:
            pool = BAD_CTYPES[fmt]
        return [(p, "refuse") for p in pool if p != text.strip()]
    if role in ("nid", "eid"):
        ids = [t[3].strip() for t in all_toks if t[2] == role and t[3].strip() != text.strip()]
        dup = draw(st.sampled_from(ids))
        return [(dup, "refuse"), ("0", "refuse"), ("-1", "refuse"), ("10000000000000000000", "refuse"),
                ("100000000000000000000", "refuse")]
    return [(x, "any") for x in ("0", "1", "2", "7", "-1", "1000", "1.5", "nan", "100000000000000000000")]


def apply(text: str, tok, new: str) -> str:
    start, end, _, old, width = tok
    if width:
        new = new.rjust(width)
    return text[:start] + new + text[end:]


# ----------------------------------------------------------------------------------------------- truncation zones


def truncation_zones(fmt, name, data: bytes) -> list[tuple[int, int]]:
    """Inclusive ranges of lengths to cut `data` (file `name` of format `fmt`) to, each of which cuts mesh data
    (or the end marker of a format that requires one), so that reading what is left must fail."""
    if name.endswith(".h5"):
        return [(0, len(data) - 1)]
    if fmt == "vtk":
        return [(0, max(t[0] for t in scan_vtk(data.decode()) if t[2] == "ctype"))]
    if fmt == "vtk-binary":
        i = data.index(b"CELL_TYPES")
        j = data.index(b"\n", i) + 1
        return [(0, j + 4 * N_CELLS - 1)]
    if fmt.startswith("vtu"):
        return [(0, data.index(b"</VTKFile>"))]
    if fmt.startswith("gmsh"):
        return [(0, data.index(b"$EndElements") + len(b"$EndElements") - 1)]
    if fmt == "xdmf":
        return [(0, data.index(b"</Xdmf>"))]
    text = data.decode()
    if fmt in ("cdb", "mac"):  # up to the first digit of the last node of the last EBLOCK row
        last = max((t for t in scan_apdl(text) if t[2] == "conn"), key=lambda t: t[0])
        return [(0, last[0] + len(last[3]) - len(last[3].lstrip()))]
    if fmt in ("abaqus", "lis"):  # no counts: cut before the first element, or inside an element row
        rows = {}
        for t in (scan_abaqus if fmt == "abaqus" else scan_listing)(text):
            if t[2] in ("eid", "conn", "other"):
                rows.setdefault(text.rfind("\n", 0, t[0]) + 1, []).append(t)
        elem_rows = {k: v for k, v in rows.items() if any(t[2] == "eid" for t in v)}
        first = min(elem_rows)
        zones = [(0, min(t[0] for t in elem_rows[first]))]
        for toks in elem_rows.values():
            starts = sorted(t[0] for t in toks)
            zones.append((starts[0] + 1, starts[-1]))
        return zones
    raise AssertionError(fmt)


# ----------------------------------------------------------------------------------------------- the base files


@pytest.mark.parametrize("fmt", ALL_FORMATS)
def test_base_files_are_read(capsys, tmp_path, fmt):
    """Control: every uncorrupted file reads with exit 0 as 27 nodes and 8 hexahedra."""
    name, files = base(fmt)
    for n, data in files.items():
        (tmp_path / n).write_bytes(data)
    expect_quality(capsys, tmp_path, name, "accept", N_NODES, N_CELLS, f"{fmt} {name}")


@pytest.mark.parametrize("fmt", list(SCANNERS))
def test_token_scanners_see_the_whole_mesh(fmt):
    """Control: the scanners find every coordinate and node reference of the base files."""
    name, files = base(fmt)
    toks = SCANNERS[fmt](files[name].decode())
    n = {r: sum(t[2] == r for t in toks) for r in ("coord", "conn", "nid", "eid")}
    if fmt != "xdmf":
        assert (n["coord"], n["conn"]) == (3 * N_NODES, 8 * N_CELLS), n
    if fmt not in ("vtk", "vtu-ascii", "xdmf"):
        assert (n["nid"], n["eid"]) == (N_NODES, N_CELLS), n


# ----------------------------------------------------------------------------------------- hypothesis: corruptions


def _truncation(capsys, tmp_path, fmt, data):
    name, files = base(fmt)
    target = data.draw(st.sampled_from(sorted(files)), label="file")
    zones = truncation_zones(fmt, target, files[target])
    lo, hi = data.draw(st.sampled_from(zones), label="zone")
    cut = data.draw(st.integers(lo, hi), label="length")
    with tempfile.TemporaryDirectory(dir=tmp_path) as d:
        for n, b in files.items():
            Path(d, n).write_bytes(b[:cut] if n == target else b)
        tail = files[target][max(0, cut - 40):cut]
        what = f"{fmt}: {target} cut to {cut} of {len(files[target])} bytes (...{tail!r})"
        expect_quality(capsys, d, name, "refuse", N_NODES, N_CELLS, what)


def _flips(capsys, tmp_path, fmt, data):
    name, files = base(fmt)
    target = data.draw(st.sampled_from(sorted(files)), label="file")
    b = bytearray(files[target])
    flips = data.draw(st.lists(st.tuples(st.integers(0, len(b) - 1), st.integers(1, 255)), min_size=1,
                               max_size=3), label="flips")
    for pos, mask in flips:
        b[pos] ^= mask
    with tempfile.TemporaryDirectory(dir=tmp_path) as d:
        for n, raw in files.items():
            Path(d, n).write_bytes(bytes(b) if n == target else raw)
        what = f"{fmt}: {target} with bytes flipped {[(p, hex(m)) for p, m in flips]}"
        expect_quality(capsys, d, name, "any", N_NODES, N_CELLS, what)


def _token(capsys, tmp_path, fmt, role, data):
    name, files = base(fmt)
    text = files[name].decode()
    toks = SCANNERS[fmt](text)
    tok = data.draw(st.sampled_from([t for t in toks if t[2] == role]), label="token")
    new, expect = data.draw(st.sampled_from(replacements(fmt, tok, toks, data.draw)), label="replacement")
    with tempfile.TemporaryDirectory(dir=tmp_path) as d:
        for n, raw in files.items():
            Path(d, n).write_bytes(apply(text, tok, new).encode() if n == name else raw)
        line = text.count("\n", 0, tok[0]) + 1
        what = f"{fmt}: {role} {tok[3].strip()!r} at line {line} replaced by {new!r} (must {expect})"
        expect_quality(capsys, d, name, expect, N_NODES, N_CELLS, what)


@pytest.mark.parametrize("fmt", ALL_FORMATS)
@settings(max_examples=FAST, **_COMMON)
@given(data=st.data())
def test_truncated_file_refused(capsys, tmp_path, fmt, data):
    _truncation(capsys, tmp_path, fmt, data)


@pytest.mark.deep
@pytest.mark.parametrize("fmt", ALL_FORMATS)
@settings(max_examples=DEEP, **_COMMON)
@given(data=st.data())
def test_truncated_file_refused_deep(capsys, tmp_path, fmt, data):
    _truncation(capsys, tmp_path, fmt, data)


@pytest.mark.parametrize("fmt", ALL_FORMATS)
@settings(max_examples=FAST, **_COMMON)
@given(data=st.data())
def test_flipped_bytes_read_consistently_or_refused(capsys, tmp_path, fmt, data):
    _flips(capsys, tmp_path, fmt, data)


@pytest.mark.deep
@pytest.mark.parametrize("fmt", ALL_FORMATS)
@settings(max_examples=DEEP, **_COMMON)
@given(data=st.data())
def test_flipped_bytes_read_consistently_or_refused_deep(capsys, tmp_path, fmt, data):
    _flips(capsys, tmp_path, fmt, data)


@pytest.mark.parametrize(("fmt", "role"), TOKEN_CASES)
@settings(max_examples=FAST, **_COMMON)
@given(data=st.data())
def test_replaced_number(capsys, tmp_path, fmt, role, data):
    _token(capsys, tmp_path, fmt, role, data)


@pytest.mark.deep
@pytest.mark.parametrize(("fmt", "role"), TOKEN_CASES)
@settings(max_examples=DEEP // 3, **_COMMON)
@given(data=st.data())
def test_replaced_number_deep(capsys, tmp_path, fmt, role, data):
    _token(capsys, tmp_path, fmt, role, data)


REAL_VTK = [MESQUITE / n for n in ("single_hex.vtk", "hexes_4by2by2.vtk", "hex_5_tangled.vtk",
                                    "large_box_hex_1000.vtk", "1000hex-block-internal-bias.vtk", "pave3.e.vtk")]
REAL_VTK += [PEERS / "cube9_pert.vtk"]


def _real(capsys, tmp_path, path, data, mode):
    raw = path.read_bytes()
    toks = scan_vtk(raw.decode())
    words = raw.decode().split()
    n_nodes, n_cells = int(words[words.index("POINTS") + 1]), int(words[words.index("CELLS") + 1])
    if mode == "cut":
        cut = data.draw(st.integers(0, max(t[0] for t in toks if t[2] == "ctype")), label="length")
        bad, what = raw[:cut], f"{path.name} cut to {cut} of {len(raw)} bytes"
    else:
        b = bytearray(raw)
        flips = data.draw(st.lists(st.tuples(st.integers(0, len(b) - 1), st.integers(1, 255)), min_size=1,
                                   max_size=3), label="flips")
        for pos, mask in flips:
            b[pos] ^= mask
        bad, what = bytes(b), f"{path.name} with bytes flipped {[(p, hex(m)) for p, m in flips]}"
    with tempfile.TemporaryDirectory(dir=tmp_path) as d:
        Path(d, "real.vtk").write_bytes(bad)
        expect_quality(capsys, d, "real.vtk", "refuse" if mode == "cut" else "any", n_nodes, n_cells, what)


@pytest.mark.shared
@pytest.mark.parametrize("mode", ["cut", "flip"])
@pytest.mark.parametrize("path", REAL_VTK, ids=lambda p: p.name)
@settings(max_examples=4, **_COMMON)
@given(data=st.data())
def test_real_mesh_corrupted(capsys, tmp_path, path, mode, data):
    _real(capsys, tmp_path, path, data, mode)


@pytest.mark.shared
@pytest.mark.deep
@pytest.mark.parametrize("mode", ["cut", "flip"])
@pytest.mark.parametrize("path", REAL_VTK, ids=lambda p: p.name)
@settings(max_examples=DEEP // 2, **_COMMON)
@given(data=st.data())
def test_real_mesh_corrupted_deep(capsys, tmp_path, path, mode, data):
    _real(capsys, tmp_path, path, data, mode)


# ----------------------------------------------------------------------------------------------- reported file cases


def vtk_text(points, hexes, n_cells=None, n_types=None, types=None) -> str:
    """A legacy ASCII VTK file written by hand; the CELLS / CELL_TYPES headers may announce other counts."""
    types = [12] * len(hexes) if types is None else types
    lines = ["# vtk DataFile Version 4.2", "hostile", "ASCII", "DATASET UNSTRUCTURED_GRID",
             f"POINTS {len(points)} double"] + [" ".join(repr(float(v)) for v in p) for p in points]
    n = len(hexes) if n_cells is None else n_cells
    lines += [f"CELLS {n} {9 * n}"] + ["8 " + " ".join(map(str, h)) for h in hexes]
    lines += [f"CELL_TYPES {len(types) if n_types is None else n_types}"] + [str(t) for t in types]
    return "\n".join(lines) + "\n"


def test_vtk_hand_written_control(capsys, tmp_path):
    (tmp_path / "ok.vtk").write_text(vtk_text(PTS, HEX))
    expect_quality(capsys, tmp_path, "ok.vtk", "accept", N_NODES, N_CELLS, "hand-written VTK")


def test_vtk_cell_types_cut_short(capsys, tmp_path):
    """Reported: CELL_TYPES announcing 8 cells with fewer present was smoothed as a smaller mesh (rc 0)."""
    (tmp_path / "short.vtk").write_text(vtk_text(PTS, HEX, types=[12] * 5, n_types=8))
    expect_quality(capsys, tmp_path, "short.vtk", "refuse", N_NODES, N_CELLS, "CELL_TYPES 8 with 5 types")
    rc, out, err = run_in(capsys, tmp_path, "smooth", "short.vtk", "out.vtk", "--method", "laplace")
    assert_refused(rc, out, err, what="smooth of CELL_TYPES 8 with 5 types")


def test_vtk_cells_fewer_than_announced(capsys, tmp_path):
    (tmp_path / "few.vtk").write_text(vtk_text(PTS, HEX[:7], n_cells=8, n_types=8))
    expect_quality(capsys, tmp_path, "few.vtk", "refuse", N_NODES, N_CELLS, "CELLS 8 and CELL_TYPES 8, 7 present")


def test_vtk_points_fewer_than_announced(capsys, tmp_path):
    text = vtk_text(PTS, HEX).replace(f"POINTS {N_NODES} double", f"POINTS {N_NODES + 1} double")
    (tmp_path / "few.vtk").write_text(text)
    expect_quality(capsys, tmp_path, "few.vtk", "refuse", N_NODES, N_CELLS, "POINTS 28 with 27 points")


def test_abaqus_node_defined_twice(capsys, tmp_path):
    text = base("abaqus")[1]["a.inp"].decode()
    text = text.replace("*ELEMENT", "5, 9.0, 9.0, 9.0\n*ELEMENT", 1)
    (tmp_path / "twice.inp").write_text(text)
    expect_quality(capsys, tmp_path, "twice.inp", "refuse", N_NODES, N_CELLS, "Abaqus node 5 defined twice")


def test_abaqus_element_defined_twice(capsys, tmp_path):
    text = base("abaqus")[1]["a.inp"].decode().rstrip("\n") + "\n3,1,2,5,4,10,11,14,13\n"
    (tmp_path / "twice.inp").write_text(text)
    expect_quality(capsys, tmp_path, "twice.inp", "refuse", N_NODES, N_CELLS + 1, "Abaqus element 3 twice")


@pytest.mark.parametrize("kind", ["lis", "cdb"])
@pytest.mark.parametrize("base_id", [10**19, 10**20, 2**63, 2**64 + 5], ids=["1e19", "1e20", "2^63", "2^64+5"])
def test_ansys_ids_beyond_int64(capsys, tmp_path, kind, base_id):
    """ANSYS listing / CDB node and element ids of 1e19-1e20: refused with exit 2 (not an overflow, rc 1)."""
    ids_n, ids_e = base_id + np.arange(N_NODES, dtype=object), base_id + np.arange(N_CELLS, dtype=object)
    text = listing_text(PTS, HEX, ids_n, ids_e) if kind == "lis" else cdb_text(PTS, HEX, ids_n, ids_e, width=24)
    (tmp_path / f"big.{kind}").write_text(text)
    expect_quality(capsys, tmp_path, f"big.{kind}", "refuse", N_NODES, N_CELLS, f"{kind} ids from {base_id}")


@pytest.mark.parametrize("kind", ["lis", "cdb"])
def test_ansys_ids_large_but_valid(capsys, tmp_path, kind):
    """Control for the test above: the same files with ids from 2^31 (wide fields) are read."""
    big = 2**31
    ids_n, ids_e = big + np.arange(N_NODES, dtype=object), big + np.arange(N_CELLS, dtype=object)
    text = listing_text(PTS, HEX, ids_n, ids_e) if kind == "lis" else cdb_text(PTS, HEX, ids_n, ids_e, width=24)
    (tmp_path / f"big.{kind}").write_text(text)
    expect_quality(capsys, tmp_path, f"big.{kind}", "accept", N_NODES, N_CELLS, f"{kind} ids from 2^31")


@pytest.mark.parametrize("kind", ["lis", "cdb"])
def test_ansys_ids_above_2_53(capsys, tmp_path, kind):
    """Distinct ids between 2^53 and 2^63 (int64, not float64): read as distinct, or refused without calling
    them duplicates."""
    big = 2**62
    ids_n, ids_e = big + np.arange(N_NODES, dtype=object), big + np.arange(N_CELLS, dtype=object)
    text = listing_text(PTS, HEX, ids_n, ids_e) if kind == "lis" else cdb_text(PTS, HEX, ids_n, ids_e, width=24)
    (tmp_path / f"big.{kind}").write_text(text)
    rc, out, err = run_in(capsys, tmp_path, "quality", f"big.{kind}", "--json")
    assert_ok_or_refused(rc, out, err, f"{kind} ids from 2^62")
    if rc == 0:
        assert_counts(strict_json(out), N_NODES, N_CELLS, f"{kind} ids from 2^62")
    else:
        assert not re.search(r"twice|duplicate", err, re.I), f"distinct ids called duplicates: {err!r}"


@pytest.mark.parametrize("name", ["meshdir", "meshdir.vtk", "meshdir.cdb"])
@pytest.mark.parametrize("command", ["quality", "smooth", "classify"])
def test_folder_as_input(capsys, tmp_path, name, command):
    (tmp_path / name).mkdir()
    argv = [command, name] + ([] if command == "quality" else ["out.vtu"])
    rc, out, err = run_in(capsys, tmp_path, *argv)
    assert_refused(rc, out, err, what=f"{command} on folder {name}")
    assert "folder" in err or "directory" in err, f"the message should say {name} is a folder: {err!r}"


def test_disk_full_simulated_by_file_size_limit(capsys, tmp_path):
    """A write that fails half-way (RLIMIT_FSIZE: the kernel refuses bytes past 1 KiB, as a full disk would):
    exit 2, one line, and no partial file or temporary folder left behind."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    before = snapshot(tmp_path)
    try:
        with inside(tmp_path):
            capsys.readouterr()
            resource.setrlimit(resource.RLIMIT_FSIZE, (1024, hard))
            try:
                rc = main(["generate", "box", "out.vtk", "--n", "3"])
            finally:
                resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
            out, err = capsys.readouterr()
    finally:
        signal.signal(signal.SIGXFSZ, old)
    assert_refused(rc, out, err, what="generate onto a full disk")
    assert changes(before, snapshot(tmp_path)) == []


# ----------------------------------------------------------------------------------------------- extreme geometry


def _quality_of_scaled_box(capsys, tmp_path, scale):
    write_hexes(tmp_path / "in.vtk", PTS * scale, HEX)
    rc, out, err = run_in(capsys, tmp_path, "quality", "in.vtk", "--json")
    assert_ok_or_refused(rc, out, err, f"quality of a box scaled by {scale:g}")
    if rc == 0:
        d = strict_json(out, f"box scaled by {scale:g}")
        assert d["inverted_elements"] == 0 and d["inverted_corners"] == 0, d
        assert d["max_condition"] == pytest.approx(1.0, abs=1e-9), d
        assert d["min_scaled_jacobian"] == pytest.approx(1.0, abs=1e-9), d


def _smooth_of_scaled_box(capsys, tmp_path, scale):
    write_hexes(tmp_path / "in.vtk", PTS * scale, HEX)
    rc, out, err = run_in(capsys, tmp_path, "smooth", "in.vtk", "out.vtk", "--method", "laplace",
                          outputs=["out.vtk"])
    assert_ok_or_refused(rc, out, err, f"smooth of a box scaled by {scale:g}")
    if rc == 0:
        p = points_of(tmp_path / "out.vtk")
        assert np.isfinite(p).all()
        np.testing.assert_allclose(p / scale, PTS, atol=1e-6)  # a perfect box stays a perfect box


def test_box_scaled_1e300_quality(capsys, tmp_path):
    _quality_of_scaled_box(capsys, tmp_path, 1e300)


def test_box_scaled_1e_minus_300_quality(capsys, tmp_path):
    _quality_of_scaled_box(capsys, tmp_path, 1e-300)


def test_box_scaled_1e300_smooth(capsys, tmp_path):
    _smooth_of_scaled_box(capsys, tmp_path, 1e300)


def test_box_scaled_1e_minus_300_smooth(capsys, tmp_path):
    _smooth_of_scaled_box(capsys, tmp_path, 1e-300)


def test_one_node_at_1e300(capsys, tmp_path):
    p = PTS.copy()
    p[13] = (1e300, 0.5, 0.5)  # the centre node of the 2x2x2 box
    write_hexes(tmp_path / "in.vtk", p, HEX)
    rc, out, err = run_in(capsys, tmp_path, "quality", "in.vtk", "--json")
    assert_ok_or_refused(rc, out, err, "quality with one node at 1e300")
    if rc == 0:
        assert_counts(strict_json(out, "one node at 1e300"), N_NODES, N_CELLS)
    rc, out, err = run_in(capsys, tmp_path, "smooth", "in.vtk", "out.vtk", "--method", "laplace",
                          outputs=["out.vtk"])
    assert_ok_or_refused(rc, out, err, "smooth with one node at 1e300")
    if rc == 0:
        assert np.isfinite(points_of(tmp_path / "out.vtk")).all()


def test_flat_mesh_refused_quickly(capsys, tmp_path):
    p = PTS.copy()
    p[:, 2] = 0.0  # every node on the plane z = 0
    write_hexes(tmp_path / "flat.vtk", p, HEX)
    t0 = time.perf_counter()
    rc, out, err = run_in(capsys, tmp_path, "smooth", "flat.vtk", "out.vtk", "--method", "laplace")
    assert_refused(rc, out, err, what="smooth of a flat mesh")
    assert time.perf_counter() - t0 < 30
    rc, out, err = run_in(capsys, tmp_path, "quality", "flat.vtk", "--json")
    assert_ok_or_refused(rc, out, err, "quality of a flat mesh")
    if rc == 0:
        strict_json(out, "flat mesh")


def test_coincident_duplicate_nodes_stay_coincident(capsys, tmp_path):
    """Two blocks side by side, the interface nodes written twice (one copy per block): after smoothing each pair
    is still exactly coincident (or the command refuses, or says it found coincident nodes)."""
    nx, ny, nz = 4, 3, 3
    grid = np.asarray(jaxci.box(nx, ny, nz).points)
    pert = np.asarray(jaxci.perturb_box(nx, ny, nz, amplitude=0.3, seed=3, which="interior").points)
    hexes = np.asarray(jaxci.box(nx, ny, nz).hexes)
    left = grid[hexes].mean(axis=1)[:, 0] < 0.5
    ln, rn = np.unique(hexes[left]), np.unique(hexes[~left])
    points = np.concatenate([pert[ln], pert[rn]])
    lmap, rmap = {n: k for k, n in enumerate(ln)}, {n: len(ln) + k for k, n in enumerate(rn)}
    new = np.array([[(lmap if is_left else rmap)[n] for n in h] for h, is_left in zip(hexes, left, strict=True)])
    pairs = np.array([(lmap[n], rmap[n]) for n in np.intersect1d(ln, rn)])
    assert len(pairs) == (ny + 1) * (nz + 1)
    write_hexes(tmp_path / "two.vtk", points, new)
    rc, out, err = run_in(capsys, tmp_path, "smooth", "two.vtk", "out.vtk", "--method", "laplace",
                          outputs=["out.vtk"])
    assert_ok_or_refused(rc, out, err, "smooth of two blocks with duplicated interface nodes")
    if rc == 0:
        p = points_of(tmp_path / "out.vtk")
        apart = np.abs(p[pairs[:, 0]] - p[pairs[:, 1]]).max(axis=1)
        said = re.search(r"coincident|duplicate", out + err, re.I)
        assert said or (apart == 0).all(), (
            f"{int((apart > 0).sum())} of {len(pairs)} coincident node pairs were pulled apart (up to "
            f"{apart.max():.3g}) and nothing was said")


# ----------------------------------------------------------------------------------------------- method parameters


@pytest.fixture
def work(tmp_path, monkeypatch):
    """A working folder holding in.vtk (a perturbed 2x2x2 box) and p3.vtk (a perturbed 3x3x3 box)."""
    write_hexes(tmp_path / "in.vtk", jaxci.perturb_box(2, amplitude=0.2, seed=0).points, HEX)
    p3 = jaxci.perturb_box(3, amplitude=0.3, seed=0)
    write_hexes(tmp_path / "p3.vtk", p3.points, p3.hexes)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _param(capsys, work, *argv, mentions=()):
    rc, out, err = run_in(capsys, work, "smooth", "in.vtk", "out.vtk", *argv)
    assert_refused(rc, out, err, *mentions, what=" ".join(argv))
    return err


def test_param_cohort_abc(capsys, work):
    _param(capsys, work, "--param", "cohort=abc", mentions=["cohort"])


def test_param_presmooth_abc_lbfgs(capsys, work):
    _param(capsys, work, "--method", "lbfgs", "--param", "presmooth=abc", mentions=["presmooth"])


def test_param_cohort_nan(capsys, work):
    _param(capsys, work, "--param", "cohort=nan", mentions=["cohort"])


def test_param_init_width_abc(capsys, work):
    err = _param(capsys, work, "--param", "init_width=abc", mentions=["init_width"])
    assert "not supported" not in err, err


@pytest.mark.parametrize("item", ["cohort", "=3", "cohort=", "nosuchparam=3", "max_sweeps=-1", "max_sweeps=1.5",
                                  "max_sweeps=1e400", "cohort=[1,2]", "cohort={}"])
def test_param_malformed(capsys, work, item):
    _param(capsys, work, "--param", item)


# ----------------------------------------------------------------------------------------------- seeds


def _smoothed(capsys, work, seed, out):
    return run_in(capsys, work, "smooth", "p3.vtk", out, "--method", "ci", "--seed", seed, "--param",
                  "max_sweeps=3", "--json", outputs=[out])


def _seed_case(capsys, work, seed):
    rc, out, err = _smoothed(capsys, work, "0", "s0.vtk")
    assert_ok(rc, out, err, "seed 0")
    rc, out, err = _smoothed(capsys, work, seed, "sx.vtk")
    assert_ok_or_refused(rc, out, err, f"--seed {seed}")
    if rc == 0:
        assert not np.array_equal(points_of(work / "s0.vtk"), points_of(work / "sx.vtk")), (
            f"--seed {seed} gave the result of --seed 0")


def test_seed_control_seed_1_differs_from_seed_0(capsys, work):
    rc, out, err = _smoothed(capsys, work, "0", "s0.vtk")
    assert_ok(rc, out, err)
    rc, out, err = _smoothed(capsys, work, "1", "s1.vtk")
    assert_ok(rc, out, err)
    assert not np.array_equal(points_of(work / "s0.vtk"), points_of(work / "s1.vtk"))


def test_seed_99999999999999999999999(capsys, work):
    _seed_case(capsys, work, "99999999999999999999999")


def test_seed_9223372036854775808(capsys, work):
    _seed_case(capsys, work, "9223372036854775808")


def test_seed_4294967296(capsys, work):
    _seed_case(capsys, work, "4294967296")


@pytest.mark.parametrize("seed", ["1.5", "abc", ""])
def test_seed_not_a_seed(capsys, work, seed):
    rc, out, err = run_in(capsys, work, "smooth", "in.vtk", "out.vtk", "--seed", seed)
    assert_refused(rc, out, err, what=f"--seed {seed!r}")


# ----------------------------------------------------------------------------------------------- configs (YAML)

TINY = """\
mesh:
  generate: {box: [1, 1, 1], amplitude: 0.1}
methods:
  - {method: laplace}
seeds: [0]
figures: false
write_meshes: false
"""


def _config_refused(capsys, folder, text, *argv, mentions=()):
    if isinstance(text, bytes):
        (folder / "cfg.yaml").write_bytes(text)
    else:
        (folder / "cfg.yaml").write_text(text)
    rc, out, err = run_in(capsys, folder, "run", "cfg.yaml", *(argv or ("--out", "res")))
    assert_refused(rc, out, err, *mentions, what=f"run of {text[:80]!r} {argv}")


TOO_LARGE = {  # argv, config text (None: no config)
    "config-box-1000^3": (["run", "cfg.yaml", "--out", "res"], TINY.replace("[1, 1, 1]", "[1000, 1000, 1000]")),
    "config-box-1e9x1x1": (["run", "cfg.yaml", "--out", "res"], TINY.replace("[1, 1, 1]", "[1000000000, 1, 1]")),
    "config-runs-1e12": (["run", "cfg.yaml", "--out", "res"], TINY.replace("seeds: [0]", "runs: 1000000000000")),
    "config-attempts-1e12": (["run", "cfg.yaml", "--out", "res"], TINY.replace(
        "{method: laplace}", "{method: ci-global, params: {attempts: 1000000000000}}")),
    "run-seeds-1e12": (["run", "cfg.yaml", "--out", "res", "--seeds", "1000000000000"], TINY),
    "smooth-attempts-1e12-ci-global": (["smooth", "in.vtk", "out.vtk", "--method", "ci-global", "--param",
                                        "attempts=1000000000000"], None),
    "generate-n-100000": (["generate", "box", "out.vtk", "--n", "100000"], None),
    "generate-1e9x1x1": (["generate", "box", "out.vtk", "--nx", "1000000000", "--n", "1"], None),
}




@pytest.fixture(scope="module")
def too_large(tmp_path_factory):
    """Every `TOO_LARGE` case, run by `jaxci.cli.main` in ONE child process (one JAX import) under 8 GiB of
    address space and a timeout, each in its own folder: case -> (result or None, folder, snapshot before)."""
    root = tmp_path_factory.mktemp("too_large")
    jobs, before = [], {}
    for case, (argv, text) in TOO_LARGE.items():
        folder = root / re.sub(r"\W", "_", case)
        folder.mkdir()
        if text is not None:
            (folder / "cfg.yaml").write_text(text)
        write_hexes(folder / "in.vtk", jaxci.perturb_box(2, amplitude=0.2, seed=0).points, HEX)
        before[case] = snapshot(folder)
        jobs.append((case, str(folder), argv))

    results, err = run_in_child(jobs, timeout=240)
    return {case: (results.get(case), Path(folder), before[case], err[-2000:]) for case, folder, _ in jobs}


@pytest.mark.parametrize("case", list(TOO_LARGE))
def test_too_large_refused_up_front(too_large, case):
    """Sizes and counts no machine gets through (a 1000^3 or 10^9 x 1 x 1 box, 10^12 runs or CI attempts):
    refused with exit 2 before anything is built, in seconds, nothing written. Run in a child process (the
    `too_large` fixture) so that a broken check fails the test instead of exhausting the machine or hanging."""
    r, folder, before, child_err = too_large[case]
    assert r is not None, f"{case}: did not finish (hung, or killed the child process): {child_err!r}"
    assert r["rc"] == 2, f"{case}: rc {r['rc']}, stderr {r['err']!r}"
    assert_refused(r["rc"], r["out"], r["err"], what=case)
    assert r["secs"] < 60, f"{case}: took {r['secs']:.0f} s"
    assert changes(before, snapshot(folder)) == []


YAML_CASES = {
    "syntax-error": "mesh: [unclosed\nmethods: {\n",
    "unknown-key": TINY + "colour: red\n",
    "unknown-nested-key": TINY.replace("amplitude: 0.1", "amplitude: 0.1, colour: red"),
    "wrong-type-methods": TINY.replace("  - {method: laplace}", "  laplace"),
    "wrong-type-seeds": TINY.replace("seeds: [0]", "seeds: abc"),
    "wrong-type-box": TINY.replace("[1, 1, 1]", "abc"),
    "float-box": TINY.replace("[1, 1, 1]", "[1.5, 1, 1]"),
    "negative-box": TINY.replace("[1, 1, 1]", "[-1, 1, 1]"),
    "nan-amplitude": TINY.replace("amplitude: 0.1", "amplitude: .nan"),
    "duplicate-keys": TINY + "seeds: [1]\n",
    "duplicate-nested-keys": TINY.replace("{method: laplace}", "{method: laplace, method: cg}"),
    "empty-file": "",
    "only-a-comment": "# nothing\n",
    "a-list": "- mesh\n- methods\n",
    "a-string": "hello\n",
    "not-utf8": b"mesh: \xff\xfe\x00\x01\n",
    "unknown-method": TINY.replace("laplace", "nosuch"),
    "bad-param": TINY.replace("{method: laplace}", "{method: ci, params: {cohort: abc}}"),
    "missing-mesh-file": TINY.replace("generate: {box: [1, 1, 1], amplitude: 0.1}", "file: nosuch.vtk"),
}


@pytest.mark.parametrize("case", list(YAML_CASES))
def test_bad_config(capsys, tmp_path, case):
    _config_refused(capsys, tmp_path, YAML_CASES[case])


def test_config_is_a_folder(capsys, tmp_path):
    (tmp_path / "cfg.yaml").mkdir()
    rc, out, err = run_in(capsys, tmp_path, "run", "cfg.yaml", "--out", "res")
    assert_refused(rc, out, err, what="config that is a folder")


def test_config_missing(capsys, tmp_path):
    rc, out, err = run_in(capsys, tmp_path, "run", "nosuch.yaml", "--out", "res")
    assert_refused(rc, out, err, "nosuch.yaml", what="missing config")


@pytest.mark.parametrize("seeds", ["0", "-1", "abc", "1.5"])
def test_run_bad_seeds_option(capsys, tmp_path, seeds):
    (tmp_path / "cfg.yaml").write_text(TINY)
    rc, out, err = run_in(capsys, tmp_path, "run", "cfg.yaml", "--out", "res", "--seeds", seeds)
    assert_refused(rc, out, err, what=f"--seeds {seeds}")


# ----------------------------------------------------------------------------------------------- outputs: never over
# the input, never over an existing file without --force, never over a folder of the user's


def test_run_force_replaces_its_own_results(capsys, tmp_path):
    """Control for the refusals below: the tiny config runs, and --force replaces a results folder it wrote."""
    (tmp_path / "cfg.yaml").write_text(TINY)
    rc, out, err = cli_in(capsys, tmp_path, "run", "cfg.yaml", "--out", "res", "--quiet")
    assert_ok(rc, out, err, "run")
    rc, out, err = cli_in(capsys, tmp_path, "run", "cfg.yaml", "--out", "res", "--quiet", "--force")
    assert_ok(rc, out, err, "run --force over its own results")
    assert (tmp_path / "res" / "summary.json").exists()


def test_run_out_dot_force_refused(capsys, tmp_path):
    """Reported: ``run cfg.yaml --out . --force`` deleted cfg.yaml and the user's notes."""
    (tmp_path / "cfg.yaml").write_text(TINY)
    (tmp_path / "notes.txt").write_text("my notes\n")
    rc, out, err = run_in(capsys, tmp_path, "run", "cfg.yaml", "--out", ".", "--force")
    assert_refused(rc, out, err, what="run --out . --force")


def test_run_output_dot_in_config_force_refused(capsys, tmp_path):
    (tmp_path / "cfg.yaml").write_text(TINY + "output: .\n")
    (tmp_path / "notes.txt").write_text("my notes\n")
    rc, out, err = run_in(capsys, tmp_path, "run", "cfg.yaml", "--force")
    assert_refused(rc, out, err, what="run with output: . and --force")


def test_run_out_foreign_folder_force_refused(capsys, tmp_path):
    (tmp_path / "cfg.yaml").write_text(TINY)
    (tmp_path / "foreign" / "sub").mkdir(parents=True)
    (tmp_path / "foreign" / "thesis.tex").write_text("\\chapter{One}\n")
    (tmp_path / "foreign" / "sub" / "data.csv").write_text("1,2\n")
    rc, out, err = run_in(capsys, tmp_path, "run", "cfg.yaml", "--out", "foreign", "--force")
    assert_refused(rc, out, err, what="run --out foreign --force")


@pytest.mark.parametrize("target", ["cfg.yaml", "notes.txt", ".."])
def test_run_out_onto_file_or_parent_refused(capsys, tmp_path, target):
    work = tmp_path / "w"
    work.mkdir()
    (work / "cfg.yaml").write_text(TINY)
    (work / "notes.txt").write_text("my notes\n")
    rc, out, err = run_in(capsys, tmp_path, "run", "w/cfg.yaml", "--out", f"w/{target}", "--force")
    assert_refused(rc, out, err, what=f"run --out {target} --force")


def test_smooth_onto_existing_output_without_force(capsys, work):
    (work / "out.vtk").write_text("keep me\n")
    rc, out, err = run_in(capsys, work, "smooth", "in.vtk", "out.vtk", "--method", "laplace")
    assert_refused(rc, out, err, "out.vtk", what="smooth onto an existing file")


def test_smooth_force_overwrites_output(capsys, work):
    (work / "out.vtk").write_text("replace me\n")
    rc, out, err = run_in(capsys, work, "smooth", "in.vtk", "out.vtk", "--method", "laplace", "--force",
                          outputs=["out.vtk"])
    assert_ok(rc, out, err, "smooth --force")
    assert (work / "out.vtk").read_text() != "replace me\n"


SAME_FILE = ["in.vtk", "./in.vtk", "sub/../in.vtk", "ABSOLUTE", "link.vtk", "hard.vtk"]


def _spell(work, spelling):
    (work / "sub").mkdir(exist_ok=True)
    if spelling == "ABSOLUTE":
        return str(work / "in.vtk")
    if spelling == "link.vtk" and not (work / "link.vtk").exists():
        (work / "link.vtk").symlink_to("in.vtk")
    if spelling == "hard.vtk" and not (work / "hard.vtk").exists():
        os.link(work / "in.vtk", work / "hard.vtk")
    return spelling


@pytest.mark.parametrize("force", [False, True], ids=["noforce", "force"])
@pytest.mark.parametrize("spelling", SAME_FILE)
@pytest.mark.parametrize("command", ["smooth", "classify"])
def test_output_is_input(capsys, work, command, spelling, force):
    target = _spell(work, spelling)
    argv = [command, "in.vtk", target] + (["--method", "laplace"] if command == "smooth" else [])
    rc, out, err = run_in(capsys, work, *argv, *(["--force"] if force else []))
    assert_refused(rc, out, err, what=" ".join(argv) + (" --force" if force else ""))


def test_classify_part_inp_onto_itself(capsys, tmp_path):
    """Reported: ``classify part.inp part.inp`` overwrote its own input."""
    (tmp_path / "part.inp").write_bytes(base("abaqus")[1]["a.inp"])
    rc, out, err = run_in(capsys, tmp_path, "classify", "part.inp", "part.inp")
    assert_refused(rc, out, err, what="classify part.inp part.inp")


def test_classify_onto_existing_output_without_force(capsys, work):
    (work / "out.vtu").write_text("keep me\n")
    rc, out, err = run_in(capsys, work, "classify", "in.vtk", "out.vtu")
    assert_refused(rc, out, err, "out.vtu", what="classify onto an existing file")


def test_classify_force_overwrites_output(capsys, work):
    (work / "out.vtu").write_text("replace me\n")
    rc, out, err = run_in(capsys, work, "classify", "in.vtk", "out.vtu", "--force", outputs=["out.vtu"])
    assert_ok(rc, out, err, "classify --force")


def test_generate_onto_existing_file_without_force(capsys, tmp_path):
    (tmp_path / "out.vtk").write_text("keep me\n")
    rc, out, err = run_in(capsys, tmp_path, "generate", "box", "out.vtk", "--n", "2")
    assert_refused(rc, out, err, "out.vtk", what="generate onto an existing file")


def test_generate_force_overwrites_output(capsys, tmp_path):
    (tmp_path / "out.vtk").write_text("replace me\n")
    rc, out, err = run_in(capsys, tmp_path, "generate", "box", "out.vtk", "--n", "2", "--force",
                          outputs=["out.vtk"])
    assert_ok(rc, out, err, "generate --force")


@pytest.mark.parametrize("force", [False, True], ids=["noforce", "force"])
@pytest.mark.parametrize("command", ["generate", "smooth", "classify"])
def test_output_onto_a_folder(capsys, work, command, force):
    (work / "outdir.vtk").mkdir()
    (work / "outdir.vtk" / "keep.txt").write_text("mine\n")
    argv = {"generate": ["generate", "box", "outdir.vtk", "--n", "2"],
            "smooth": ["smooth", "in.vtk", "outdir.vtk", "--method", "laplace"],
            "classify": ["classify", "in.vtk", "outdir.vtk"]}[command]
    rc, out, err = run_in(capsys, work, *argv, *(["--force"] if force else []))
    assert_refused(rc, out, err, what=" ".join(argv))


# ----------------------------------------------------------------------------------------------- Python API


def _api_error(call, what):
    try:
        result = call()
    except JaxciError:
        return None
    except BaseException as e:  # noqa: BLE001 - the point: which exception escapes
        pytest.fail(f"{what}: raised {type(e).__name__}: {e} (not a jaxci.errors.JaxciError)")
    return result


def test_api_smooth_ndarray(work):
    r = _api_error(lambda: jaxci.smooth(np.zeros((8, 3)), "laplace"), "jaxci.smooth(ndarray)")
    assert r is None, "jaxci.smooth(ndarray) returned instead of raising a JaxciError"


def test_api_smooth_meshio_mesh(work):
    m = meshio.read("in.vtk")
    r = _api_error(lambda: jaxci.smooth(m, "laplace"), "jaxci.smooth(meshio.Mesh)")
    assert r is None or isinstance(r, jaxci.SmoothResult)


def test_api_smooth_path(work):
    r = _api_error(lambda: jaxci.smooth("in.vtk", "laplace"), "jaxci.smooth('in.vtk')")
    assert r is None or isinstance(r, jaxci.SmoothResult)


@pytest.mark.parametrize("seed", [1.5, "a", None, float("nan")], ids=repr)
def test_api_seed_not_an_integer(work, seed):
    mesh = jaxci.perturb_box(3, amplitude=0.3, seed=0)
    r = _api_error(lambda: jaxci.smooth(mesh, "ci", seed=seed, max_sweeps=2), f"jaxci.smooth(seed={seed!r})")
    assert r is None, f"jaxci.smooth(seed={seed!r}) returned instead of raising a JaxciError"


@pytest.mark.parametrize("kw", [{"method": "nosuch"}, {"dtype": "float16"}, {"feature_angle": float("nan")},
                                {"feature_angle": -5}, {"untangle": "maybe"}, {"cohort": "abc"},
                                {"fixed_nodes": [10**6]}, {"fixed_nodes": [-1]}, {"fixed_sets": ["nosuch"]}],
                         ids=lambda kw: ",".join(f"{k}={v}" for k, v in kw.items()))
def test_api_smooth_bad_arguments(work, kw):
    mesh = jaxci.perturb_box(2, amplitude=0.2, seed=0)
    kw = {"method": "ci", **kw}
    r = _api_error(lambda: jaxci.smooth(mesh, **kw), f"jaxci.smooth({kw})")
    assert r is None, f"jaxci.smooth({kw}) returned instead of raising a JaxciError"


def test_api_write_mesh_ndarray(work):
    from jaxci.io import write_mesh

    before = snapshot(work)
    r = _api_error(lambda: write_mesh(np.zeros((8, 3)), "x.vtk"), "write_mesh(ndarray)")
    assert r is None, "write_mesh(ndarray) did not raise"
    assert changes(before, snapshot(work)) == []


@pytest.mark.parametrize("arg", [np.zeros((8, 3)), 42, None, ["in.vtk", "in.vtk", "in.vtk"]], ids=repr)
def test_api_read_mesh_not_a_path(work, arg):
    from jaxci.io import read_mesh

    r = _api_error(lambda: read_mesh(arg), f"read_mesh({type(arg).__name__})")
    assert r is None


# ----------------------------------------------------------------------------------------------- CLI arguments


def test_cli_unknown_method(capsys, work):
    rc, out, err = run_in(capsys, work, "smooth", "in.vtk", "out.vtk", "--method", "nosuch")
    assert_refused(rc, out, err, "nosuch", what="--method nosuch")


def test_cli_unknown_command(capsys, work):
    rc, out, err = run_in(capsys, work, "frobnicate", "in.vtk")
    assert_refused(rc, out, err, what="unknown command")


def test_cli_missing_argument(capsys, work):
    rc, out, err = run_in(capsys, work, "smooth", "in.vtk")
    assert_refused(rc, out, err, what="smooth without an output")


@pytest.mark.parametrize("angle", ["-5", "abc", "nan", "inf", "200", "1e400"])
@pytest.mark.parametrize("command", ["quality", "smooth", "classify"])
def test_cli_bad_feature_angle(capsys, work, command, angle):
    argv = {"quality": ["quality", "in.vtk"], "smooth": ["smooth", "in.vtk", "out.vtk", "--method", "laplace"],
            "classify": ["classify", "in.vtk", "out.vtu"]}[command]
    rc, out, err = run_in(capsys, work, *argv, f"--feature-angle={angle}")
    assert_refused(rc, out, err, what=f"{command} --feature-angle {angle}")


def test_cli_dtype_float16(capsys, work):
    rc, out, err = run_in(capsys, work, "smooth", "in.vtk", "out.vtk", "--dtype", "float16")
    assert_refused(rc, out, err, "float16", what="--dtype float16")


@pytest.mark.parametrize("command", ["quality", "smooth", "classify"])
def test_cli_missing_input(capsys, work, command):
    argv = [command, "missing.vtk"] + ([] if command == "quality" else ["out.vtu"])
    rc, out, err = run_in(capsys, work, *argv)
    assert_refused(rc, out, err, "missing.vtk", what=f"{command} missing.vtk")


@pytest.mark.parametrize("case", ["quality-input", "smooth-input", "smooth-output", "classify-output",
                                  "generate-output", "no-extension"])
def test_cli_unknown_extension(capsys, work, case):
    (work / "in.xyz").write_bytes((work / "in.vtk").read_bytes())
    (work / "noext").write_bytes((work / "in.vtk").read_bytes())
    argv = {"quality-input": ["quality", "in.xyz"], "smooth-input": ["smooth", "in.xyz", "out.vtk"],
            "smooth-output": ["smooth", "in.vtk", "out.xyz", "--method", "laplace"],
            "classify-output": ["classify", "in.vtk", "out.xyz"], "generate-output": ["generate", "box", "out.xyz"],
            "no-extension": ["quality", "noext"]}[case]
    rc, out, err = run_in(capsys, work, *argv)
    assert_refused(rc, out, err, what=" ".join(argv))


@pytest.mark.parametrize("args", [["--n", "0"], ["--n", "-2"], ["--n", "abc"], ["--nx", "0"],
                                  ["--amplitude", "nan"], ["--amplitude", "-1"], ["--size", "0", "1", "1"],
                                  ["--size", "nan", "1", "1"], ["--size", "inf", "1", "1"]], ids=" ".join)
def test_cli_generate_bad_arguments(capsys, tmp_path, args):
    rc, out, err = run_in(capsys, tmp_path, "generate", "box", "out.vtk", *args)
    assert_refused(rc, out, err, what="generate " + " ".join(args))


@pytest.mark.parametrize("seed", ["99999999999999999999999", "9223372036854775808", "4294967296"])
def test_cli_generate_seed_out_of_range(capsys, tmp_path, seed):
    rc, out, err = run_in(capsys, tmp_path, "generate", "box", "s0.vtk", "--n", "2", "--amplitude", "0.3",
                          outputs=["s0.vtk"])
    assert_ok(rc, out, err)
    rc, out, err = run_in(capsys, tmp_path, "generate", "box", "sx.vtk", "--n", "2", "--amplitude", "0.3",
                          "--seed", seed, outputs=["sx.vtk"])
    assert_ok_or_refused(rc, out, err, f"generate --seed {seed}")
    if rc == 0:
        assert not np.array_equal(points_of(tmp_path / "s0.vtk"), points_of(tmp_path / "sx.vtk"))
