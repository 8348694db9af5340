"""Hostile input at the edges, in the default suite: names the file system cannot hold, files that are not regular
files (a FIFO would make a reader wait forever), standard output closed or full, sizes a few lines of a file imply
(10^12 set members, a CMBLOCK range of 10^9, a Gmsh node tag of 2^63 - 1), and values beyond what the readers
underneath take (legacy VTK cells beyond int32). Each must end quickly with the contract of `tests/test_hostile.py`:
exit 2 and one line naming what is really wrong (or exit 0 with the right mesh), nothing written, never an internal
error, a hang or a memory error. The cases that would hang or exhaust memory when broken run in one child process
(`hostile_kit.run_in_child`), so that a regression fails the test instead of stopping the suite."""

from __future__ import annotations

import os
import subprocess
import sys
import weakref
from pathlib import Path

import numpy as np
import pytest
from hostile_kit import assert_ok, assert_refused, changes, run_in, run_in_child, snapshot

import jaxci
from jaxci.io import read_mesh, write_mesh

BOX = jaxci.box(2, 2, 2)  # 27 nodes, 8 hexahedra
LINUX = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="FIFOs, /dev/full, /proc")

#: One hexahedron in Gmsh 4.1 and 2.2 ASCII, the last node's tag (and the element's reference to it) as {tag}.
GMSH41 = """$MeshFormat
4.1 0 8
$EndMeshFormat
$Nodes
1 8 1 {tag}
3 0 0 8
1
2
3
4
5
6
7
{tag}
0 0 0
1 0 0
1 1 0
0 1 0
0 0 1
1 0 1
1 1 1
0 1 1
$EndNodes
$Elements
1 1 1 1
3 0 5 1
1 1 2 3 4 5 6 7 {tag}
$EndElements
"""
GMSH22 = """$MeshFormat
2.2 0 8
$EndMeshFormat
$Nodes
8
1 0 0 0
2 1 0 0
3 1 1 0
4 0 1 0
5 0 0 1
6 1 0 1
7 1 1 1
{tag} 0 1 1
$EndNodes
$Elements
1
1 5 2 0 0 1 2 3 4 5 6 7 {tag}
$EndElements
"""


def _deck(folder: Path, extra: str = "") -> Path:
    """The box as an Abaqus deck with `extra` lines at its end."""
    write_mesh(BOX, folder / "box.inp")
    (folder / "box.inp").write_text((folder / "box.inp").read_text() + extra)
    return folder / "box.inp"


def _cdb(folder: Path, first: int, last: int, kind: str = "NODE") -> Path:
    """The box as a CDB archive with a CMBLOCK component of the numbers first..last (one range)."""
    write_mesh(BOX, folder / "box.cdb")
    lines = (folder / "box.cdb").read_text().splitlines()
    cut = next((i for i, ln in enumerate(lines) if ln.strip().upper() == "FINISH"), len(lines))
    block = [f"CMBLOCK,BIG,{kind},       2", "(8i12)", f"{first:12d}{-last:12d}"]
    (folder / "box.cdb").write_text("\n".join(lines[:cut] + block + lines[cut:]) + "\n")
    return folder / "box.cdb"


# ----------------------------------------------------------------------------------------------- in a child process
def _fifo(path: Path) -> None:
    os.mkfifo(path)


def _setup_cases(root: Path) -> list[tuple[str, Path, list[str]]]:
    """The child-process cases: (case, folder, argv), each folder set up."""
    cases = []

    def case(name, argv, setup):
        folder = root / name
        folder.mkdir()
        setup(folder)
        cases.append((name, folder, argv))

    case("fifo-mesh-quality", ["quality", "in.vtk"], lambda f: _fifo(f / "in.vtk"))
    case("fifo-mesh-smooth", ["smooth", "in.vtk", "out.vtk"], lambda f: _fifo(f / "in.vtk"))
    case("fifo-mesh-classify", ["classify", "in.inp", "out.vtu"], lambda f: _fifo(f / "in.inp"))
    case("char-device-mesh", ["quality", "zero.vtk"], lambda f: (f / "zero.vtk").symlink_to("/dev/zero"))
    case("fifo-include", ["quality", "main.inp"], lambda f: (
        _fifo(f / "nodes.inp"), (f / "main.inp").write_text("*HEADING\n*INCLUDE, INPUT=nodes.inp\n")))
    case("fifo-config", ["run", "cfg.yaml", "--out", "res"], lambda f: _fifo(f / "cfg.yaml"))
    case("fifo-config-mesh", ["run", "cfg.yaml", "--out", "res"], lambda f: (
        _fifo(f / "m.vtk"), (f / "cfg.yaml").write_text("mesh: {file: m.vtk}\nmethods: [{method: laplace}]\n")))

    def xdmf_fifo(f):
        write_mesh(BOX, f / "x.xdmf")
        os.unlink(f / "x.h5")
        _fifo(f / "x.h5")

    case("fifo-xdmf-data", ["quality", "x.xdmf"], xdmf_fifo)
    case("nset-generate-1e12", ["quality", "box.inp"],
         lambda f: _deck(f, "*NSET, NSET=ALL, GENERATE\n1, 1000000000000\n"))
    case("elset-generate-1e12", ["quality", "box.inp"],
         lambda f: _deck(f, "*ELSET, ELSET=ALL, GENERATE\n1, 1000000000000, 1\n"))
    case("cmblock-node-1e9", ["quality", "box.cdb"], lambda f: _cdb(f, 1, 10**9))
    case("cmblock-node-3e7", ["quality", "box.cdb"], lambda f: _cdb(f, 1, 3 * 10**7))
    case("cmblock-elem-1e9", ["quality", "box.cdb"], lambda f: _cdb(f, 1, 10**9, "ELEM"))
    case("gmsh41-tag-2^63-1", ["quality", "g.msh"], lambda f: (f / "g.msh").write_text(GMSH41.format(tag=2**63 - 1)))
    case("gmsh22-tag-1e9", ["quality", "g.msh"], lambda f: (f / "g.msh").write_text(GMSH22.format(tag=10**9)))
    return cases


#: case -> (expected exit code, words the stderr line must hold)
EXPECT = {
    "fifo-mesh-quality": (2, ["in.vtk", "FIFO", "not a regular file"]),
    "fifo-mesh-smooth": (2, ["in.vtk", "FIFO"]),
    "fifo-mesh-classify": (2, ["in.inp", "FIFO"]),
    "char-device-mesh": (2, ["zero.vtk", "character device"]),
    "fifo-include": (2, ["main.inp, line 2", "nodes.inp", "FIFO"]),
    "fifo-config": (2, ["cfg.yaml", "FIFO"]),
    "fifo-config-mesh": (2, ["m.vtk"]),
    "fifo-xdmf-data": (2, ["x.xdmf", "x.h5", "FIFO"]),
    "nset-generate-1e12": (2, ["box.inp, line", "GENERATE", "node 28", "no *NODE defines"]),
    "elset-generate-1e12": (2, ["box.inp, line", "GENERATE", "element 9", "no *ELEMENT defines"]),
    "cmblock-node-1e9": (0, []),
    "cmblock-node-3e7": (0, []),
    "cmblock-elem-1e9": (0, []),
    "gmsh41-tag-2^63-1": (2, ["g.msh", "node tag 9223372036854775807", "renumber"]),
    "gmsh22-tag-1e9": (2, ["g.msh", "node tag 1000000000", "3.73 GiB", "renumber"]),
}


@pytest.fixture(scope="module")
def edge_runs(tmp_path_factory):
    if not sys.platform.startswith("linux"):
        pytest.skip("FIFOs and /dev/zero")
    root = tmp_path_factory.mktemp("edges")
    cases = _setup_cases(root)
    before = {name: snapshot(folder) for name, folder, _ in cases}
    results, err = run_in_child(cases, timeout=180)
    return {name: (results.get(name), folder, before[name], err[-2000:]) for name, folder, _ in cases}


@pytest.mark.parametrize("case", list(EXPECT))
def test_edge_case_ends_at_once(edge_runs, case):
    """A FIFO, a device, 10^12 set members, a huge Gmsh tag: refused (or read, for the CMBLOCK ranges, whose numbers
    that exist are kept) within seconds, without waiting, allocating what the numbers imply, or an internal error."""
    r, folder, before, child_err = edge_runs[case]
    assert r is not None, f"{case}: did not finish (hung, or killed the child process): {child_err!r}"
    rc, words = EXPECT[case]
    if rc == 2:
        assert_refused(r["rc"], r["out"], r["err"], *words, what=case)
    else:
        assert_ok(r["rc"], r["out"], r["err"], case)
        assert "component BIG lists" in r["out"] and "left out" in r["out"], r["out"]
    assert r["secs"] < 30, f"{case}: took {r['secs']:.0f} s"
    assert changes(before, snapshot(folder)) == []


def test_generate_ranges_resolved_against_the_ids(tmp_path):
    """GENERATE lines within the mesh read as the ids they list (with a step), and a CMBLOCK range keeps the
    numbers that exist."""
    m = read_mesh(_deck(tmp_path, "*NSET, NSET=ODD, GENERATE\n1, 27, 2\n*ELSET, ELSET=E, GENERATE\n2, 8, 3\n"))
    np.testing.assert_array_equal(np.asarray(m.node_ids)[m.point_sets["ODD"]], np.arange(1, 28, 2))
    assert [np.asarray(b.ids)[rows].tolist() for b, rows in zip(m.cells, m.cell_sets["E"], strict=True)] == [[2, 5, 8]]
    c = read_mesh(_cdb(tmp_path, 3, 1000))  # small here: the huge ranges run in the child process above
    np.testing.assert_array_equal(np.sort(np.asarray(c.node_ids)[c.point_sets["BIG"]]), np.arange(3, 28))
    assert any("lists 973 node numbers that the file does not define (first 28)" in n for n in c.notes)


# ----------------------------------------------------------------------------------------------- in-process
@pytest.fixture
def work(tmp_path, monkeypatch):
    write_mesh(BOX, tmp_path / "in.vtk")
    monkeypatch.chdir(tmp_path)
    return tmp_path


LONG = "m" * 300


@pytest.mark.parametrize("argv", [
    ["quality", LONG + ".vtk"], ["smooth", LONG + ".vtk", "out.vtk"], ["classify", LONG + ".vtk", "out.vtu"],
    ["smooth", "in.vtk", LONG + ".vtk"], ["classify", "in.vtk", LONG + ".vtu"], ["generate", "box", LONG + ".vtk"],
    ["run", LONG + ".yaml"], ["smooth", "in.vtk", f"{LONG}/out.vtk"],
], ids=["quality-in", "smooth-in", "classify-in", "smooth-out", "classify-out", "generate-out", "run-config",
        "folder-name"])
def test_name_too_long(capsys, work, argv):
    """ENAMETOOLONG (a name over 255 bytes) is said in words, not an internal error."""
    rc, out, err = run_in(capsys, work, *argv)
    assert_refused(rc, out, err, "too long", what=" ".join(a[:20] for a in argv))


@pytest.mark.parametrize(("line", "value", "words"), [
    (10, "99999999999999999999", "node index 99999999999999999999 in cell 0"),
    (10, str(2**63 - 1), f"node index {2**63 - 1} in cell 0"),
    (10, str(2**32), f"node index {2**32} in cell 0"),
    (10, str(2**32 + 1), f"node index {2**32 + 1} in cell 0"),  # meshio would read it as node 1: a valid mesh
    (10, str(-(2**32) - 1), f"node index {-(2**32) - 1} in cell 0"),
    (8, str(2**32 + 8), f"gives cell 0 {2**32 + 8} nodes"),  # ... as 8
], ids=["1e20", "2^63-1", "2^32", "2^32+1", "-2^32-1", "count-2^32+8"])
def test_vtk_cell_value_beyond_int32(capsys, tmp_path, line, value, words):
    """meshio reads legacy VTK cells as 32-bit integers: a larger value read as -1 ("node index -1") or wrapped
    around, silently, to another node. It is named as written in the file."""
    write_mesh(jaxci.box(1, 1, 1), tmp_path / "one.vtk")
    lines = (tmp_path / "one.vtk").read_text().splitlines()
    assert lines[6].startswith("CELLS") and lines[line - 1].strip().lstrip("-").isdigit()
    lines[line - 1] = value
    (tmp_path / "h.vtk").write_text("\n".join(lines) + "\n")
    rc, out, err = run_in(capsys, tmp_path, "quality", "h.vtk")
    assert_refused(rc, out, err, "h.vtk", words, "32-bit", what=value)
    assert "-1" not in err.replace(value, "")


@pytest.mark.parametrize(("target", "words"), [
    (".", ["*INCLUDE file .", "is a folder"]),
    ("sub", ["*INCLUDE file sub", "is a folder"]),
    ("/dev/null", ["*INCLUDE file /dev/null", "character device"]),
    ("nowhere.inp", ["*INCLUDE file nowhere.inp not found"]),
])
def test_include_that_is_not_a_file(capsys, tmp_path, target, words):
    """``*INCLUDE, INPUT=.`` or ``=/dev/null`` exist: the message says what they are, not "not found"."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "main.inp").write_text(f"*HEADING\n*INCLUDE, INPUT={target}\n")
    rc, out, err = run_in(capsys, tmp_path, "quality", "main.inp")
    assert_refused(rc, out, err, "main.inp, line 2", *words, what=target)
    if target != "nowhere.inp":
        assert "not found" not in err


def test_interrupt_raised_in_the_unraisable_hook_is_not_lost(monkeypatch):
    """The guard's signal handler can run inside a weakref callback, where Python ignores exceptions and hands
    them to ``sys.unraisablehook``; the guard's hook must raise the interrupt at the next event OUTSIDE itself
    (raised inside, Python printed "Exception ignored in sys.unraisablehook ... _Interrupt" and lost it)."""
    import sys as _sys

    from jaxci.cli import _interrupt

    g = _interrupt.Guard()
    monkeypatch.setattr(_sys, "unraisablehook", g._unraisable)

    class Thing:
        pass

    def callback(_):
        raise _interrupt._Interrupt

    thing = Thing()
    ref = weakref.ref(thing, callback)
    caught = False
    try:
        del thing  # the callback's interrupt goes to the hook
        for _ in range(3):
            len("next events")
            (lambda: None)()
    except KeyboardInterrupt:
        caught = True
    finally:
        _sys.setprofile(None)
    assert ref() is None and caught


# ----------------------------------------------------------------------------------------------- standard output
def _jaxci(args, cwd, stdout):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-m", "jaxci", *args], cwd=cwd, env=env, stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=120)


@LINUX
def test_stdout_full(tmp_path):
    """``> /dev/full``: exit 2, one line saying standard output could not be written; a file the command wrote
    first is complete."""
    with open("/dev/full", "w") as full:
        p = _jaxci(["generate", "box", "--n", "2", "out.vtk"], tmp_path, full)
    assert_refused(p.returncode, "", p.stderr, "standard output", "no space left", what="generate > /dev/full")
    assert read_mesh(tmp_path / "out.vtk").n_hexes == 8
    with open("/dev/full", "w") as full:
        p = _jaxci(["quality", "out.vtk"], tmp_path, full)
    assert_refused(p.returncode, "", p.stderr, "standard output", what="quality > /dev/full")


@LINUX
@pytest.mark.parametrize("args", [["quality", "in.vtk"], ["--help"], ["quality", "in.vtk", "--json"]],
                         ids=" ".join)
def test_stdout_closed_pipe(tmp_path, args):
    """Standard output a pipe whose reader has gone (as after ``| head -c 1``, made certain here by closing the
    read end first): exit 141 (128 + SIGPIPE) without a word, as other commands end."""
    write_mesh(BOX, tmp_path / "in.vtk")
    before = snapshot(tmp_path)
    r, w = os.pipe()
    os.close(r)
    try:
        p = _jaxci(args, tmp_path, w)
    finally:
        os.close(w)
    assert p.returncode == 141 and p.stderr == "", (p.returncode, p.stderr)
    assert changes(before, snapshot(tmp_path)) == []
