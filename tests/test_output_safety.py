"""Never lose or silently change a user's data: outputs refused over inputs, foreign folders and existing files
(without --force), earlier results replaced only by a complete run, and SIGINT / SIGTERM acted on within
seconds with the finished work kept and no temporary file left. Every case checks the exit code, one line on
stderr without a traceback, and that nothing but the files asked for appeared, changed or disappeared."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import QUICK_EXPERIMENT as QUICK
from helpers import complete_results, interrupted_on_call

import jaxci
from jaxci.cli import main
from jaxci.experiments.results import MARKER, foreign_entries

BOX = jaxci.box(2, 2, 2)
#: QUICK's first run, then a long one (local CI on a perturbed 24^3 box: 10 s or more on 2 cores).
LONG = """\
mesh:
  - generate: {case: cube27}
  - name: big
    generate: {box: [24, 24, 24], amplitude: 0.3}
methods:
  - name: CI local
    method: ci
    params: {max_sweeps: 200}
figures: false
"""
FIRST_MESH = "meshes/cube27_ci-local_seed0.vtu"


def snapshot(folder: Path) -> dict:
    """Every entry under `folder` (hidden ones too): folders as "dir", files as (bytes, mtime)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        out[rel] = "dir" if p.is_dir() and not p.is_symlink() else (p.read_bytes(), p.lstat().st_mtime_ns)
    return out


def changes(before: dict, after: dict) -> set[str]:
    return {k for k in before.keys() | after.keys() if before.get(k) != after.get(k)}


def one_line(err: str, text: str = "") -> None:
    assert "Traceback" not in err and err.count("\n") == 1 and err.startswith("jaxci: "), err
    assert text in err, err


def cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def earlier(tmp_path_factory):
    """A complete results folder of QUICK (`jaxci run`), to copy as the earlier results of a test."""
    return complete_results(tmp_path_factory)


def _setup(tmp_path: Path, earlier: Path, config: str = QUICK) -> tuple[Path, Path]:
    cfg = tmp_path / "exp.yaml"
    cfg.write_text(config)
    shutil.copytree(earlier, tmp_path / "prev")
    return cfg, tmp_path / "prev"


# ------------------------------------------------------------------------------------------ jaxci run --out
def test_run_refuses_current_folder_with_user_files(tmp_path, monkeypatch, capsys):
    work = tmp_path / "work"
    work.mkdir()
    (work / "cfg.yaml").write_text(QUICK)
    (work / "notes.txt").write_text("my notes")
    monkeypatch.chdir(work)
    before = snapshot(tmp_path)
    code, out, err = cli(capsys, "run", "cfg.yaml", "--out", ".", "--force", "--quiet")
    assert code == 2 and out == ""
    one_line(err, "nothing was written")
    assert snapshot(tmp_path) == before


def test_run_refuses_foreign_folder(tmp_path, capsys):
    (tmp_path / "cfg.yaml").write_text(QUICK)
    foreign = tmp_path / "foreign"
    (foreign / "sub").mkdir(parents=True)
    (foreign / "thesis.tex").write_text("precious")
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "run", tmp_path / "cfg.yaml", "--out", foreign, "--force", "--quiet")
    assert code == 2
    one_line(err, "is not a jaxci results folder")
    assert "thesis.tex" in err and "nothing was written" in err
    assert snapshot(tmp_path) == before


def test_run_refuses_results_folder_holding_an_input(tmp_path, capsys):
    res = tmp_path / "res"
    (res / "meshes").mkdir(parents=True)
    assert main(["generate", "box", "--n", "2", str(res / "meshes" / "in.vtu")]) == 0
    (res / MARKER).write_text(json.dumps({"jaxci_results": 1, "entries": ["meshes/", "meshes/in.vtu"]}))
    (tmp_path / "cfg.yaml").write_text(QUICK.replace("generate: {case: cube27}", "file: res/meshes/in.vtu"))
    capsys.readouterr()
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "run", tmp_path / "cfg.yaml", "--out", res, "--force", "--quiet")
    assert code == 2
    one_line(err, "an input of this experiment")
    assert snapshot(tmp_path) == before


def test_only_the_marker_makes_a_results_folder(tmp_path):
    """A folder is earlier results only if its marker lists what is in it: file names that look like results
    (summary.json, runs.csv, ...) are not enough."""
    mine = tmp_path / "mine"
    (mine / "figures").mkdir(parents=True)
    for name in ("summary.json", "runs.csv", "report.md", "figures/plot.png"):
        (mine / name).write_text("mine")
    assert foreign_entries(mine) == ["figures/", "report.md", "runs.csv", "summary.json"]
    (mine / MARKER).write_text(json.dumps({"jaxci_results": 1, "entries": ["figures/", "figures/plot.png",
                                                                           "report.md", "runs.csv", "summary.json"]}))
    assert foreign_entries(mine) == []
    (mine / "figures" / "notes.txt").write_text("mine")
    assert foreign_entries(mine) == ["figures/notes.txt"]
    (mine / MARKER).write_text("not json")
    assert foreign_entries(mine) == [MARKER, "figures/", "report.md", "runs.csv"]


def test_run_force_keeps_a_folder_without_marker(tmp_path, capsys):
    """``jaxci run c.yaml --out mine --force`` where mine/ holds the user's own summary.json, report.md, runs.csv
    and figures/plot.png but no marker: refused, nothing deleted."""
    (tmp_path / "c.yaml").write_text(QUICK)
    mine = tmp_path / "mine"
    (mine / "figures").mkdir(parents=True)
    for name in ("summary.json", "report.md", "runs.csv", "figures/plot.png"):
        (mine / name).write_text(f"my {name}")
    before = snapshot(tmp_path)
    code, out, err = cli(capsys, "run", tmp_path / "c.yaml", "--out", mine, "--force", "--quiet")
    assert code == 2 and out == ""
    one_line(err, "is not a jaxci results folder")
    assert MARKER in err and "nothing was written" in err
    assert snapshot(tmp_path) == before


def test_run_force_replaces_only_when_complete(tmp_path, earlier, monkeypatch, capsys):
    from jaxci.errors import InvertedMeshError

    cfg, prev = _setup(tmp_path, earlier)
    from jaxci.interface import smooth as smooth_module
    real = smooth_module.smooth
    old = snapshot(prev)

    # interrupted (KeyboardInterrupt in the main thread) after one run: earlier results untouched
    monkeypatch.setattr(smooth_module, "smooth", interrupted_on_call(real))
    code, _, err = cli(capsys, "run", cfg, "--out", prev, "--force", "--quiet")
    assert code == 130
    one_line(err, f"1 of 2 runs finished, written to {prev}.partial-1 (partial); earlier results in {prev} untouched")
    assert snapshot(prev) == old
    partial = json.loads((tmp_path / "prev.partial-1" / "summary.json").read_text())
    assert partial["partial"] is True and partial["runs_done"] == 1
    assert json.loads((tmp_path / "prev.partial-1" / MARKER).read_text())["partial"] is True

    # every run failed: earlier results kept, the failed records beside them
    def failing(*args, **kwargs):
        raise InvertedMeshError("the mesh has 3 inverted elements")

    monkeypatch.setattr(smooth_module, "smooth", failing)
    code, _, err = cli(capsys, "run", cfg, "--out", prev, "--force", "--quiet")
    assert code == 1 and "Traceback" not in err
    assert f"every run failed: written to {prev}.failed-1; earlier results in {prev} kept" in err
    assert snapshot(prev) == old

    # a complete run replaces them; nothing else changes, no temporary folder is left
    monkeypatch.setattr(smooth_module, "smooth", real)
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "run", cfg, "--out", prev, "--force", "--quiet", "--seeds", "1")
    assert code == 0 and err == ""
    assert {k.split("/")[0] for k in changes(before, snapshot(tmp_path))} == {"prev"}
    assert json.loads((prev / "summary.json").read_text())["runs_done"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml", "prev", "prev.failed-1", "prev.partial-1"]


# ------------------------------------------------------------------------------------------ one-file outputs
def test_existing_output_needs_force(tmp_path, capsys):
    mesh = tmp_path / "a.vtu"
    assert main(["generate", "box", "--n", "2", "--amplitude", "0.2", str(mesh)]) == 0
    (tmp_path / "out.vtu").write_text("keep me")
    capsys.readouterr()
    before = snapshot(tmp_path)
    for argv in (["classify", mesh, tmp_path / "out.vtu"], ["generate", "box", "--n", "2", tmp_path / "out.vtu"],
                 ["smooth", mesh, tmp_path / "out.vtu"]):
        code, out, err = cli(capsys, *argv)
        assert code == 2 and out == ""
        one_line(err, "exists; pass --force")
    assert snapshot(tmp_path) == before
    code, _, err = cli(capsys, "generate", "box", "--n", "2", tmp_path / "out.vtu", "--force")
    assert code == 0 and err == ""
    assert changes(before, snapshot(tmp_path)) == {"out.vtu"}
    (tmp_path / "folder.vtu").mkdir()
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "generate", "box", "--n", "2", tmp_path / "folder.vtu", "--force")
    assert code == 2
    one_line(err, "not a regular file")
    assert snapshot(tmp_path) == before


def test_own_input_refused_even_with_force(tmp_path, monkeypatch, capsys):
    mesh = tmp_path / "part.inp"
    assert main(["generate", "box", "--n", "2", "--amplitude", "0.2", str(mesh)]) == 0
    (tmp_path / "sub").mkdir()
    os.symlink(mesh, tmp_path / "link.inp")
    os.link(mesh, tmp_path / "hard.inp")
    monkeypatch.chdir(tmp_path / "sub")
    capsys.readouterr()
    before = snapshot(tmp_path)
    for cmd in ("classify", "smooth"):
        for target in ("../part.inp", str(mesh), "../sub/../part.inp", "../link.inp", "../hard.inp"):
            code, out, err = cli(capsys, cmd, "../part.inp", target, "--force")
            assert code == 2 and out == "", (cmd, target)
            one_line(err, "refusing to overwrite the input")
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------ inputs read through others
def _xdmf_with_data(folder: Path, name: str = "a.xdmf", data: str = "data.h5") -> Path:
    """An XDMF file whose heavy data file has another name than its own (``a.xdmf`` -> ``data.h5``)."""
    from jaxci.io import write_mesh

    write_mesh(BOX, folder / name)
    stem = Path(name).with_suffix(".h5").name
    (folder / name).write_text((folder / name).read_text().replace(f"{stem}:", f"{data}:"))
    (folder / stem).rename(folder / data)
    return folder / name


def _deck_with_include(folder: Path) -> Path:
    """main.inp, whose node lines are in nodes.inp (``*INCLUDE, INPUT=nodes.inp``)."""
    from jaxci.io import write_mesh

    write_mesh(BOX, folder / "whole.inp")
    text = (folder / "whole.inp").read_text()
    start, end = text.index("*NODE"), text.index("*ELEMENT")
    (folder / "nodes.inp").write_text(text[start:end])
    (folder / "main.inp").write_text(text[:start] + "*INCLUDE, INPUT=nodes.inp\n" + text[end:])
    (folder / "whole.inp").unlink()
    return folder / "main.inp"


def test_xdmf_heavy_data_is_an_input(tmp_path, monkeypatch, capsys):
    """a.xdmf keeps its arrays in data.h5: writing data.xdmf would write data.h5, the input's own data. Refused,
    even with --force, by the CLI and by write_mesh; the name comes from the XDMF file, not from its stem."""
    from jaxci.errors import MeshWriteError
    from jaxci.io import read_mesh, write_mesh

    _xdmf_with_data(tmp_path)
    monkeypatch.chdir(tmp_path)
    mesh = read_mesh("a.xdmf")
    assert [Path(p).name for p in mesh.input_files] == ["data.h5"]
    before = snapshot(tmp_path)
    for argv in (["smooth", "a.xdmf", "data.xdmf", "--method", "laplace"], ["classify", "a.xdmf", "data.xdmf"]):
        for force in ([], ["--force"]):  # without --force, the existing data.h5 may be named first
            code, out, err = cli(capsys, *argv, *force)
            assert code == 2 and out == "", (argv, force, err)
            one_line(err, "writes data.h5, which is the input" if force else "data.h5")
    with pytest.raises(MeshWriteError, match="data.h5: refusing to overwrite a file the mesh was read from"):
        write_mesh(mesh, "data.xdmf")
    assert snapshot(tmp_path) == before


def test_abaqus_include_is_an_input(tmp_path, monkeypatch, capsys):
    """main.inp *INCLUDEs nodes.inp: nodes.inp is an input, however it is spelled (a hard link too)."""
    from jaxci.errors import MeshWriteError
    from jaxci.io import read_mesh, write_mesh

    _deck_with_include(tmp_path)
    os.link(tmp_path / "nodes.inp", tmp_path / "hard.inp")
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    for cmd in (["smooth", "main.inp"], ["classify", "main.inp"]):
        for target in ("nodes.inp", "./nodes.inp", "hard.inp"):
            code, out, err = cli(capsys, *cmd, target, "--force")
            assert code == 2 and out == "", (cmd, target, err)
            one_line(err, "read through main.inp; refusing to overwrite the input even with --force")
    with pytest.raises(MeshWriteError, match="refusing to overwrite a file the mesh was read from"):
        write_mesh(read_mesh("main.inp"), "hard.inp")
    assert snapshot(tmp_path) == before


def test_companion_file_needs_force_too(tmp_path, monkeypatch, capsys):
    """Writing out.xdmf writes out.h5: an existing out.h5 is refused without --force like out.xdmf itself."""
    from jaxci.io import read_mesh, write_mesh

    write_mesh(BOX, tmp_path / "in.vtk")
    (tmp_path / "out.h5").write_text("mine")
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    for argv in (["generate", "box", "--n", "2", "out.xdmf"], ["classify", "in.vtk", "out.xdmf"]):
        code, _, err = cli(capsys, *argv)
        assert code == 2
        one_line(err, "out.h5: exists; pass --force")
    assert snapshot(tmp_path) == before
    code, _, err = cli(capsys, "generate", "box", "--n", "2", "out.xdmf", "--force")
    assert code == 0 and err == "" and read_mesh("out.xdmf").n_hexes == 8


def test_run_inputs_read_through_the_config_meshes(tmp_path, earlier, capsys):
    """The config's meshes and the files read through them are inputs of ``jaxci run``: a results folder that
    holds one (by path, listed in its marker, or as a hard link under a name jaxci wrote) is never replaced."""
    cfg, prev = _setup(tmp_path, earlier)
    (prev / "inc").mkdir()
    _deck_with_include(prev / "inc")
    (tmp_path / "main.inp").write_text((prev / "inc" / "main.inp").read_text().replace("INPUT=nodes.inp",
                                                                                        "INPUT=prev/inc/nodes.inp"))
    marker = json.loads((prev / MARKER).read_text())
    marker["entries"] += ["inc/", "inc/main.inp", "inc/nodes.inp"]
    (prev / MARKER).write_text(json.dumps(marker))
    cfg.write_text(QUICK.replace("generate: {case: cube27}", "file: main.inp"))
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "run", cfg, "--out", prev, "--force", "--quiet")
    assert code == 2
    one_line(err, "nodes.inp, an input of this experiment")
    assert snapshot(tmp_path) == before
    # the same file under a name jaxci wrote (a hard link): found by device and inode
    shutil.rmtree(prev / "inc")
    (prev / MARKER).write_text(json.dumps({**marker, "entries": marker["entries"][:-3]}))
    (tmp_path / "nodes.inp").unlink(missing_ok=True)
    _deck_with_include(tmp_path)
    (prev / FIRST_MESH).unlink()
    os.link(tmp_path / "nodes.inp", prev / FIRST_MESH)
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "run", cfg, "--out", prev, "--force", "--quiet")
    assert code == 2
    one_line(err, f"holds {FIRST_MESH}, which is an input of this experiment")
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------ late arrivals
def _meanwhile(monkeypatch, action):
    """Make `action()` happen while the (first) smoothing runs: something the user does while jaxci works."""
    from jaxci.interface import smooth as smooth_module
    real = smooth_module.smooth
    done = []

    def smooth(*args, **kwargs):
        if not done:
            done.append(1)
            action()
        return real(*args, **kwargs)

    monkeypatch.setattr(smooth_module, "smooth", smooth)


def _no_temporaries(folder: Path) -> None:
    assert not [p for p in folder.rglob(".*") if p.name != MARKER], sorted(folder.rglob(".*"))


def test_file_appearing_at_the_output_is_kept(tmp_path, monkeypatch, capsys):
    """Without --force, a file created at OUT (or at its companion .h5) while jaxci smooths is not replaced at
    the end: the final move itself refuses, and nothing is written (not the other file either)."""
    from jaxci.io import write_mesh

    write_mesh(BOX, tmp_path / "in.vtk")
    monkeypatch.chdir(tmp_path)
    for out, theirs in (("out.vtk", "out.vtk"), ("out.xdmf", "out.h5"), ("out.xdmf", "out.xdmf")):
        _meanwhile(monkeypatch, lambda t=theirs: Path(t).write_text("theirs"))
        code, _, err = cli(capsys, "smooth", "in.vtk", out, "--method", "laplace")
        assert code == 2, err
        one_line(err, f"{theirs}: appeared while the mesh was being written; left as it is (nothing was written)")
        assert Path(theirs).read_text() == "theirs"
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["in.vtk", theirs])
        Path(theirs).unlink()
    _no_temporaries(tmp_path)


def test_force_replaces_only_the_file_it_checked(tmp_path, monkeypatch, capsys):
    """With --force, OUT is replaced only if it is still the file that was there when the command began: one put
    in its place meanwhile is kept. The control: the same command replaces the file it checked."""
    from jaxci.io import read_mesh, write_mesh

    write_mesh(BOX, tmp_path / "in.vtk")
    (tmp_path / "out.vtk").write_text("old output")
    monkeypatch.chdir(tmp_path)

    def swap():
        os.unlink("out.vtk")
        Path("out.vtk").write_text("theirs")

    _meanwhile(monkeypatch, swap)
    code, _, err = cli(capsys, "smooth", "in.vtk", "out.vtk", "--method", "laplace", "--force")
    assert code == 2
    one_line(err, "out.vtk: was replaced by another file while the mesh was being written; left as it is")
    assert Path("out.vtk").read_text() == "theirs"
    _meanwhile(monkeypatch, lambda: None)
    code, _, err = cli(capsys, "smooth", "in.vtk", "out.vtk", "--method", "laplace", "--force")
    assert code == 0 and "error" not in err and read_mesh("out.vtk").n_hexes == 8
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.vtk", "out.vtk"]


def test_folder_appearing_at_out_is_kept(tmp_path, monkeypatch, capsys):
    """Without --force, a folder made at --out while the experiment runs (even an EMPTY one, which a plain rename
    would replace) is left as it is; the results go beside it, DIR.new-1, and the command says so (exit 2)."""
    (tmp_path / "c.yaml").write_text(QUICK)
    monkeypatch.chdir(tmp_path)
    _meanwhile(monkeypatch, lambda: os.mkdir("res"))
    code, _, err = cli(capsys, "run", "c.yaml", "--out", "res", "--quiet")
    assert code == 2
    one_line(err, "res appeared while the experiment ran; left as it is: the results (2 runs) are in res.new-1")
    assert list((tmp_path / "res").iterdir()) == []
    assert json.loads((tmp_path / "res.new-1" / "summary.json").read_text())["runs_done"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml", "res", "res.new-1"]


@pytest.mark.parametrize("change", ["file-added", "folder-swapped"])
def test_force_keeps_earlier_results_changed_meanwhile(tmp_path, earlier, monkeypatch, capsys, change):
    """With --force, earlier results are replaced only if, when the new results are moved in, they are still the
    folder that was checked and hold only what jaxci wrote: a file the user put there meanwhile, or another folder
    put in its place, is kept as it is and the results go beside it."""
    cfg, prev = _setup(tmp_path, earlier)
    if change == "file-added":
        _meanwhile(monkeypatch, lambda: (prev / "notes.txt").write_text("mine"))
        why = "prev got notes.txt, which jaxci did not write, while the experiment ran"
    else:
        def swap():
            prev.rename(tmp_path / "moved")
            shutil.copytree(tmp_path / "moved", prev)
        _meanwhile(monkeypatch, swap)
        why = "prev was replaced by another folder while the experiment ran"
    monkeypatch.chdir(tmp_path)
    old = snapshot(prev)
    code, _, err = cli(capsys, "run", "exp.yaml", "--out", "prev", "--force", "--quiet")
    assert code == 2
    one_line(err, f"{why}; left as it is: the results (2 runs) are in prev.new-1")
    assert {k: v for k, v in snapshot(prev).items() if k != "notes.txt"} == \
        {k: v for k, v in old.items() if k != "notes.txt"} or change == "folder-swapped"
    assert (prev / "summary.json").read_bytes() == old["summary.json"][0]
    assert json.loads((tmp_path / "prev.new-1" / "summary.json").read_text())["runs_done"] == 2
    _no_temporaries(tmp_path)


# ------------------------------------------------------------------------------------------ signals
pytestmark_signals = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and POSIX signals")


def _spawn(argv: list[str], cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}  # the long native call under test is XLA:CPU's
    return subprocess.Popen([sys.executable, *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(predicate, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    t0 = time.monotonic()
    while not predicate():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, "timed out"
        time.sleep(0.05)


def _handlers_installed(pid: int) -> bool:
    """Whether the jaxci command `pid` catches SIGTERM yet (its interrupt guard is installed)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(int(ln.split()[1], 16) for ln in status.splitlines() if ln.startswith("SigCgt:"))
    return bool(mask & (1 << (signal.SIGTERM - 1)))


def _signal(proc: subprocess.Popen, signum: int) -> tuple[float, str]:
    """Send `signum`, wait; returns (seconds to exit, stderr)."""
    t = time.monotonic()
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    return time.monotonic() - t, err


#: `jaxci smooth` whose smoothing is an XLA loop that never ends (compiled first, the flag written just before it
#: runs): the main thread is inside XLA for as long as the test wants.
XLA_FOREVER = """\
import importlib, sys
from pathlib import Path
FLAG = Path(sys.argv[1])
sm = importlib.import_module("jaxci.interface.smooth")
def forever(*args, **kwargs):
    import jax
    loop = jax.jit(lambda x: jax.lax.while_loop(lambda c: c[1] >= 0, lambda c: (c[0] * 0.5 + 1.0, c[1]), (x, 0))[0])
    run = loop.lower(1.0).compile()
    FLAG.write_text("in XLA")
    run(1.0).block_until_ready()
sm.smooth = forever
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[2:]]
entry()
"""


@pytestmark_signals
def test_sigterm_during_long_smoothing(tmp_path):
    """SIGTERM while the main thread is inside a jitted computation that would never end: exit 143 within
    seconds, no output, no temporary file."""
    assert main(["generate", "box", "--n", "2", str(tmp_path / "box.vtu")]) == 0
    before = snapshot(tmp_path)
    flag = tmp_path.parent / f"{tmp_path.name}.xla"
    proc = _spawn(["-c", XLA_FOREVER, str(flag), "smooth", "box.vtu", "o.vtu"], tmp_path)
    _wait_for(flag.exists, proc)
    seconds, err = _signal(proc, signal.SIGTERM)
    assert proc.returncode == 143 and seconds < 3.0, (proc.returncode, seconds, err)
    one_line(err, "jaxci: interrupted (SIGTERM)")
    assert snapshot(tmp_path) == before


def _check_partial(tmp_path: Path, prev: Path, old: dict, err: str, signame: str) -> None:
    one_line(err, f"jaxci: interrupted ({signame}): 1 of 2 runs finished, written to prev.partial-1 (partial); "
                  f"earlier results in prev untouched")
    assert snapshot(prev) == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml", "prev", "prev.partial-1"]
    summary = json.loads((tmp_path / "prev.partial-1" / "summary.json").read_text())
    assert summary["partial"] is True and summary["runs_done"] == 1 and summary["runs_planned"] == 2
    assert (tmp_path / "prev.partial-1" / FIRST_MESH).is_file()
    assert not [p for p in (tmp_path / "prev.partial-1").rglob(".*") if p.name != MARKER]


#: `jaxci run` as a child script (argv: a flag file, then jaxci's arguments) whose second smoothing is held by the
#: code put at HOLD (which writes the flag once the hold begins: the first run is finished and written into the
#: temporary folder by then).
SECOND_HELD = """\
import ctypes, importlib, signal, sys, time
from pathlib import Path
FLAG = Path(sys.argv[1])
sm = importlib.import_module("jaxci.interface.smooth")
real, calls = sm.smooth, []
def held(*args, **kwargs):
    calls.append(1)
    if len(calls) == 2:
HOLD
    return real(*args, **kwargs)
sm.smooth = held
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[2:]]
entry()
"""

#: The second smoothing never ends by itself: it waits in Python, signals not blocked.
SECOND_WAITS = SECOND_HELD.replace("HOLD", """\
        FLAG.write_text("second run")
        time.sleep(600)""")


@pytestmark_signals
def test_sigint_run_over_earlier_results(tmp_path, earlier):
    """Ctrl-C of `jaxci run --force` during its second run (in flight by construction: it waits for the signal):
    the earlier results stay byte for byte, the finished run goes to prev.partial-1."""
    _setup(tmp_path, earlier)
    old = snapshot(tmp_path / "prev")
    flag = tmp_path.parent / f"{tmp_path.name}.second"
    proc = _spawn(["-c", SECOND_WAITS, str(flag), "run", "exp.yaml", "--out", "prev", "--force", "--quiet"],
                  tmp_path)
    _wait_for(flag.exists, proc)
    seconds, err = _signal(proc, signal.SIGINT)
    assert proc.returncode == 130 and seconds < 3.0, (proc.returncode, seconds, err)
    _check_partial(tmp_path, tmp_path / "prev", old, err, "SIGINT")


#: `jaxci run --force` paused inside the move of its results into place (just before the swap of the two folders
#: in `jaxci.experiments.results._put_in_place`), until the test creates the file GO.
PAUSED_COMMIT = """\
import sys, time
from pathlib import Path
FLAG, GO = Path(sys.argv[1]), Path(sys.argv[1] + ".go")
import jaxci.experiments.results as results
real, calls = results.exchange, []
def paused(src, dst):
    calls.append(1)
    if len(calls) == 1:
        FLAG.write_text("moving")
        t = time.monotonic()
        while not GO.exists() and time.monotonic() - t < 60:
            time.sleep(0.01)
    return real(src, dst)
results.exchange = paused
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[2:]]
entry()
"""


@pytestmark_signals
def test_sigterm_while_results_are_put_in_place(tmp_path, earlier):
    """SIGTERM while `jaxci run --force` moves its complete results in (about to swap them with the earlier ones):
    the move is finished, not cut in half, and the signal is not lost: exit 143, the new results in prev, nothing
    left aside, no "Exception ignored" from the interrupt."""
    cfg, prev = _setup(tmp_path, earlier)
    flag = tmp_path.parent / f"{tmp_path.name}.moving"
    proc = _spawn(["-c", PAUSED_COMMIT, str(flag), "run", "exp.yaml", "--out", "prev", "--force", "--quiet"],
                  tmp_path)
    _wait_for(flag.exists, proc)
    proc.send_signal(signal.SIGTERM)
    Path(f"{flag}.go").write_text("go")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, (proc.returncode, err)
    one_line(err, "jaxci: interrupted (SIGTERM): 2 of 2 runs finished, written to prev")
    assert "Exception ignored" not in err and "earlier results" not in err
    summary = json.loads((prev / "summary.json").read_text())
    assert summary["runs_done"] == 2 and summary["partial"] is False
    assert json.loads((prev / MARKER).read_text())["partial"] is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml", "prev"]


#: The second smoothing is stuck in a native call that does not look at signals (signals blocked in the main
#: thread): only the watchdog can act on SIGTERM.
STUCK = SECOND_HELD.replace("HOLD", """\
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        FLAG.write_text("stuck")
        ctypes.CDLL(None).sleep(60)""")


@pytestmark_signals
def test_sigterm_run_stuck_in_native_code(tmp_path, earlier):
    """SIGTERM while the main thread cannot run Python: the watchdog writes the finished run beside the earlier
    results and exits 143 about a second later."""
    _setup(tmp_path, earlier)
    old = snapshot(tmp_path / "prev")
    flag = tmp_path.parent / f"{tmp_path.name}.stuck"
    proc = _spawn(["-c", STUCK, str(flag), "run", "exp.yaml", "--out", "prev", "--force", "--quiet"], tmp_path)
    _wait_for(flag.exists, proc)
    seconds, err = _signal(proc, signal.SIGTERM)
    assert proc.returncode == 143 and 0.9 < seconds < 3.0, (proc.returncode, seconds, err)
    _check_partial(tmp_path, tmp_path / "prev", old, err, "SIGTERM")


#: `jaxci generate` stuck in the middle of write_mesh (its temporary folder made): the watchdog removes it.
STUCK_WRITE = """\
import ctypes, signal, sys, tempfile
from pathlib import Path
import jaxci.io
from jaxci.io._place import temporary_prefix
FLAG = Path(sys.argv[1])
def stuck(mesh, path, **kwargs):
    path = Path(path)
    tmp = Path(tempfile.mkdtemp(prefix=temporary_prefix(path.name), dir=path.parent))
    (tmp / path.name).write_text("half a mesh")
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    FLAG.write_text("stuck")
    ctypes.CDLL(None).sleep(60)
jaxci.io.write_mesh = stuck
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[2:]]
entry()
"""


@pytestmark_signals
def test_sigint_during_write_leaves_no_temporary(tmp_path):
    (tmp_path / ".o.vtu.older.tmp").mkdir()  # not jaxci's: left alone
    (tmp_path / ".jaxci-tmp-1-o.vtu.older").mkdir()  # another jaxci's, still running (pid 1): left alone
    before = snapshot(tmp_path)
    flag = tmp_path.parent / f"{tmp_path.name}.stuck"
    proc = _spawn(["-c", STUCK_WRITE, str(flag), "generate", "box", "--n", "2", "o.vtu"], tmp_path)
    _wait_for(flag.exists, proc)
    seconds, err = _signal(proc, signal.SIGINT)
    assert proc.returncode == 130 and seconds < 3.0, (proc.returncode, seconds, err)
    one_line(err, "jaxci: interrupted (SIGINT)")
    assert snapshot(tmp_path) == before


#: `jaxci generate` busy in Python with garbage collections, whose callbacks (JAX's and one more) take most of
#: the time: the handler's KeyboardInterrupt, which Python would ignore inside a callback, must not be lost.
GC_BUSY = """\
import gc, sys, time
from pathlib import Path
import jaxci.mesh.generate
FLAG = Path(sys.argv[1])
def busy(*args, **kwargs):
    def slow_callback(phase, info):
        t = time.monotonic()
        while time.monotonic() - t < 0.002:
            pass
    gc.callbacks.append(slow_callback)
    FLAG.write_text("busy")
    while True:
        gc.collect()
jaxci.mesh.generate.perturb_box = busy
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[2:]]
entry()
"""


@pytestmark_signals
def test_sigterm_inside_gc_callback_not_lost(tmp_path):
    before = snapshot(tmp_path)
    flag = tmp_path.parent / f"{tmp_path.name}.busy"
    proc = _spawn(["-c", GC_BUSY, str(flag), "generate", "box", "o.vtu"], tmp_path)
    _wait_for(flag.exists, proc)
    time.sleep(0.2)
    seconds, err = _signal(proc, signal.SIGTERM)
    assert proc.returncode == 143 and seconds < 0.9, (proc.returncode, seconds, err)  # not the watchdog's 3 s
    one_line(err, "jaxci: interrupted (SIGTERM)")
    assert snapshot(tmp_path) == before


#: A `sitecustomize` that holds the jaxci command still while it starts: the import of ``jaxci.errors`` (the first
#: after jaxci's start-up handlers, `jaxci.runtime.process.quiet_interrupts_while_starting`) waits until the signal
#: ends it.
HELD_IMPORT = """\
import os, sys, time
class _Hold:
    def find_spec(self, name, path=None, target=None):
        if name == "jaxci.errors" and os.environ.get("JAXCI_TEST_FLAG"):
            open(os.environ["JAXCI_TEST_FLAG"], "w").write("importing")
            time.sleep(600)
        return None
sys.meta_path.insert(0, _Hold())
"""


@pytestmark_signals
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_while_starting_is_quiet(tmp_path, signum):
    """Ctrl-C (or SIGTERM) while Python imports jaxci's modules, before the command's handlers: exit 128 + the
    signal, no traceback, nothing written. In flight by construction: an import waits for the signal."""
    site = tmp_path.parent / f"{tmp_path.name}.site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(HELD_IMPORT)
    flag = tmp_path.parent / f"{tmp_path.name}.importing"
    before = snapshot(tmp_path)
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXCI_TEST_FLAG": str(flag),
           "PYTHONPATH": os.pathsep.join([str(site), *filter(None, [os.environ.get("PYTHONPATH")])])}
    proc = subprocess.Popen([sys.executable, "-m", "jaxci", "generate", "box", "--n", "2", "o.vtu"], cwd=tmp_path,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for(flag.exists, proc)
    seconds, err = _signal(proc, signum)
    assert proc.returncode == 128 + signum and seconds < 3.0, (proc.returncode, seconds, err)
    assert err == "", err
    assert snapshot(tmp_path) == before
