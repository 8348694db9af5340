"""Never lose or silently change a user's data: outputs refused over inputs, foreign folders and existing files
(without --force), earlier results replaced only by a complete run, and SIGINT / SIGTERM acted on within
seconds with the finished work kept and no temporary file left. Every case checks the exit code, one line on
stderr without a traceback, and that nothing but the files asked for appeared, changed or disappeared."""

from __future__ import annotations

import importlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import CUBE27_EXPERIMENT, interrupted_on_call

from jaxci.cli import main
from jaxci.experiments.results import MARKER, foreign_entries

QUICK = CUBE27_EXPERIMENT + "figures: false\n"
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
    folder = tmp_path_factory.mktemp("earlier")
    (folder / "quick.yaml").write_text(QUICK)
    assert main(["run", str(folder / "quick.yaml"), "--out", str(folder / "prev"), "--quiet"]) == 0
    return folder / "prev"


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


def test_results_folder_recognised(tmp_path):
    """The marker lists what jaxci wrote; a folder from before markers is recognised by its file names."""
    legacy = tmp_path / "legacy"
    (legacy / "meshes").mkdir(parents=True)
    for name in ("summary.json", "runs.csv", "report.md", "history.json", "meshes/a_seed0.vtu"):
        (legacy / name).write_text("x")
    assert foreign_entries(legacy) == []
    (legacy / "meshes" / "notes.txt").write_text("mine")
    assert foreign_entries(legacy) == ["meshes/notes.txt"]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "a.txt").write_text("x")
    assert foreign_entries(tmp_path / "other") == ["a.txt"]
    (tmp_path / "other" / MARKER).write_text("not json")
    assert foreign_entries(tmp_path / "other") == [MARKER, "a.txt"]


def test_run_force_replaces_only_when_complete(tmp_path, earlier, monkeypatch, capsys):
    from jaxci.errors import InvertedMeshError

    cfg, prev = _setup(tmp_path, earlier)
    smooth_module = importlib.import_module("jaxci.smooth")
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


@pytestmark_signals
def test_sigterm_during_long_smoothing(tmp_path):
    """SIGTERM while the main thread waits for a long jitted local CI: exit 143 within seconds, no output, no
    temporary file."""
    assert main(["generate", "box", "--n", "24", "--amplitude", "0.3", str(tmp_path / "box.vtu")]) == 0
    before = snapshot(tmp_path)
    proc = _spawn(["-m", "jaxci", "smooth", "box.vtu", "o.vtu", "--method", "ci"], tmp_path)
    _wait_for(lambda: _handlers_installed(proc.pid), proc)
    time.sleep(2.5)  # reading (0.1 s), set-up, compiling, then the loop (10 s or more)
    seconds, err = _signal(proc, signal.SIGTERM)
    if proc.returncode == 0:  # pragma: no cover - a machine fast enough to finish first
        pytest.skip("the smoothing finished before the signal")
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


@pytestmark_signals
def test_sigint_run_over_earlier_results(tmp_path, earlier):
    """Ctrl-C of `jaxci run --force` during its second, long run: the earlier results stay byte for byte, the
    finished run goes to prev.partial-1."""
    _setup(tmp_path, earlier, LONG)
    old = snapshot(tmp_path / "prev")
    proc = _spawn(["-m", "jaxci", "run", "exp.yaml", "--out", "prev", "--force", "--quiet"], tmp_path)
    _wait_for(lambda: any(tmp_path.glob(f".prev.*.tmp/{FIRST_MESH}")), proc)
    time.sleep(0.5)
    seconds, err = _signal(proc, signal.SIGINT)
    assert proc.returncode == 130 and seconds < 3.0, (proc.returncode, seconds, err)
    _check_partial(tmp_path, tmp_path / "prev", old, err, "SIGINT")


#: `jaxci run` whose second smoothing is stuck in a native call that does not look at signals (signals blocked
#: in the main thread): only the watchdog can act on SIGTERM.
STUCK = """\
import ctypes, importlib, signal, sys
from pathlib import Path
FLAG = Path(sys.argv[1])
sm = importlib.import_module("jaxci.smooth")
real, calls = sm.smooth, []
def stuck(*args, **kwargs):
    calls.append(1)
    if len(calls) == 2:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        FLAG.write_text("stuck")
        ctypes.CDLL(None).sleep(60)
    return real(*args, **kwargs)
sm.smooth = stuck
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[2:]]
entry()
"""


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
FLAG = Path(sys.argv[1])
def stuck(mesh, path, **kwargs):
    path = Path(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
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
    (tmp_path / ".o.vtu.older.tmp").mkdir()  # not this process's: left alone
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
import jaxci.generate
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
jaxci.generate.perturb_box = busy
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


@pytestmark_signals
@pytest.mark.parametrize("delay", [0.25, 0.5])
def test_sigint_while_starting_is_quiet(tmp_path, delay):
    """Ctrl-C during the first second (Python importing numpy and JAX, before the command's handlers): exit 130,
    no traceback, nothing written."""
    before = snapshot(tmp_path)
    proc = _spawn(["-m", "jaxci", "generate", "box", "--n", "2", "o.vtu"], tmp_path)
    time.sleep(delay)
    seconds, err = _signal(proc, signal.SIGINT)
    if proc.returncode == 0:  # it finished first: nothing to test at this delay on a fast machine
        pytest.skip("the command finished before the signal")
    if "init_import_site" in err:  # a loaded machine: still in Python's own start-up, before any jaxci code
        pytest.skip("the signal came before the interpreter had started")
    assert proc.returncode == 130, (proc.returncode, err)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    if not err.strip():
        assert snapshot(tmp_path) == before
    else:  # the command's own handler was already in place
        one_line(err, "jaxci: interrupted (SIGINT)")
