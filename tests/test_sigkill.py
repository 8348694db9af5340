"""SIGKILL, which no handler sees, at any instant of a command that replaces an output: ``jaxci smooth --force``
over an existing output (a VTK file, and in-place rewrites of Exodus, Abaqus and Nastran files, the input in
another folder) and ``jaxci run --force`` over earlier results. After every kill each output is the complete old
one or the complete new one (byte-compared; a results folder's timings differ from run to run, so a new one is
checked whole: every file its marker lists and nothing else, every run finished, the meshes byte for byte), no
input changed, and nothing else is left but jaxci's temporary folders (``.jaxci-tmp-<pid>-...``), which the next
run removes (the decoys of the user, and of a jaxci still running, stay).

The kill instants: by default two per command, just before and just after the rename that puts the output in
place (a hook in the child process kills it there, `KILLER`); under ``-m deep`` every file-system step of the
command (every create, open, rename, removal under the work folder) and 30 instants spread in time over a whole
run, from its start to its end.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import CUBE27_EXPERIMENT

from jaxci.cli import main
from jaxci.experiments.results import MARKER
from jaxci.io._place import TEMP_PREFIX, remove_stale

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGKILL and renameat2: Linux")

#: Instants in time over a whole run, for the deep sweep.
TIME_INSTANTS = 30

#: The jaxci command in a child process that kills itself (SIGKILL) at one file-system step under ROOT.
#: argv: ROOT, TARGET (the output, absolute), SPEC, LOG, then jaxci's arguments. SPEC: "count" (run through, write
#: the steps to LOG), "step:N" (killed at the N-th step, 1-based) or "swap:K" (killed K steps after the first
#: rename onto TARGET began; 0: at it, before it is done). A step is an audit event that names a path under ROOT
#: (open, mkdir, rename, removal, ...) or a ``renameat2`` call (`jaxci.io._place._renameat2`, which no audit event
#: shows); the kill comes before the step is done.
KILLER = """\
import atexit, os, signal, sys
ROOT, TARGET, SPEC, LOG = sys.argv[1:5]
CWD = os.getcwd()
EVENTS = {"open", "os.mkdir", "os.rename", "os.remove", "os.rmdir", "os.link", "os.symlink", "os.chmod",
          "os.truncate", "os.utime", "shutil.rmtree", "shutil.copyfile", "shutil.move", "tempfile.mkdtemp",
          "tempfile.mkstemp"}
steps, swap = [], []

def names(args):
    for a in args:
        if isinstance(a, (str, bytes)) or hasattr(a, "__fspath__"):
            p = os.fsdecode(os.fspath(a))
            yield p if os.path.isabs(p) else os.path.join(CWD, p)

def step(event, paths):
    paths = [p for p in paths if p == ROOT or p.startswith(ROOT + os.sep)]
    if not paths:
        return
    steps.append(f"{event} {' '.join(paths)}")
    if not swap and event in ("renameat2", "os.rename", "os.link") and TARGET in paths:
        swap.append(len(steps))
    kind, _, n = SPEC.partition(":")
    if (kind == "step" and len(steps) == int(n)) or (kind == "swap" and swap and len(steps) == swap[0] + int(n)):
        os.kill(os.getpid(), signal.SIGKILL)

def hook(event, args):
    if event in EVENTS:
        step(event, names(args[:1] if event == "open" else args))  # open's other arguments: mode, flags

import jaxci.io._place as place
real = place._renameat2
def renameat2(src, dst, flags):
    step("renameat2", names((src, dst)))
    return real(src, dst, flags)
place._renameat2 = renameat2
if SPEC == "count":
    atexit.register(lambda: open(LOG, "w").write("\\n".join(steps)))
sys.addaudithook(hook)
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[5:]]
entry()
"""


def tree(folder: Path) -> dict[str, bytes | None]:
    """Every entry under `folder` (hidden ones too): folders as None, files as their bytes."""
    return {p.relative_to(folder).as_posix(): None if p.is_dir() else p.read_bytes() for p in sorted(folder.rglob("*"))}


class Case:
    """One command that replaces an output: its work folder (inputs in ``src/``), its jaxci arguments, the old
    output and, once `finish` ran it to the end, the new one."""

    def __init__(self, work: Path, argv: list[str], output: str):
        self.work, self.argv, self.output = work, argv, work / output
        self.old = self._contents()
        self.inputs = tree(work / "src")
        self.new = None
        # decoys that only look like temporaries: a user's file, and a running jaxci's folder (pid 1 is alive)
        self.decoys = [self.output.parent / f".{self.output.name}.mine.tmp", self.output.parent / f"{TEMP_PREFIX}1-x.y"]
        self.decoys[0].write_text("the user's")
        self.decoys[1].mkdir()
        self.expected = {p.name for p in self.output.parent.iterdir()}

    def _contents(self):
        return tree(self.output) if self.output.is_dir() else self.output.read_bytes()

    def spawn(self, spec: str, log: Path) -> subprocess.Popen:
        argv = [sys.executable, "-c", KILLER, str(self.work), str(self.output), spec, str(log), *self.argv]
        return subprocess.Popen(argv, cwd=self.work, env={**os.environ, "JAX_PLATFORMS": "cpu"},
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def check(self, what: str) -> str:
        """After a kill: the output old or new whole, the inputs as they were, nothing else but temporaries.
        Puts the old output back; returns "old" or "new"."""
        assert tree(self.work / "src") == self.inputs, f"{what}: an input changed"
        for p in self.output.parent.iterdir():
            assert p.name in self.expected or p.name.startswith(TEMP_PREFIX), f"{what}: left {p.name}"
        assert all(d.exists() for d in self.decoys), f"{what}: a decoy was removed"
        now = self._contents()
        if now == self.old:
            return "old"
        self.check_new(now, what)
        self.restore()
        return "new"

    def check_new(self, now, what: str) -> None:
        """`now`, not the old output, is the new one: the same bytes as every new one before (the first is kept)."""
        if self.new is None:
            self.new = now
        assert now == self.new, f"{what}: {self.output.name} is neither the old one nor the new one"

    def restore(self) -> None:
        if self.output.is_dir():
            shutil.rmtree(self.output)
            self.output.mkdir()
            for rel, data in self.old.items():
                if data is None:
                    (self.output / rel).mkdir(exist_ok=True)
                else:
                    (self.output / rel).write_bytes(data)
        else:
            self.output.write_bytes(self.old)

    def finish(self, log: Path) -> float:
        """Run the command to its end (counting its steps into `log`); its output is the new one, no temporary
        of a killed run is left. Returns its wall time."""
        t = time.monotonic()
        proc = self.spawn("count", log)
        _, err = proc.communicate(timeout=300)
        seconds = time.monotonic() - t
        assert proc.returncode == 0, err
        self.check_new(self._contents(), "a complete run")
        left = {p.name for p in self.output.parent.iterdir()} - self.expected
        assert not left, f"the next run left {left}"
        assert all(d.exists() for d in self.decoys)
        self.restore()
        return seconds


class ResultsCase(Case):
    """``jaxci run --force`` over earlier results: a new folder is complete (its timings differ from run to run)."""

    def check_new(self, now, what: str) -> None:
        entries = json.loads(now[MARKER])["entries"]
        assert sorted([*entries, MARKER]) == sorted(k + "/" * (v is None) for k, v in now.items()), what
        summary = json.loads(now["summary.json"])
        assert not summary["partial"] and summary["runs_done"] == summary["runs_planned"] == 2, what
        if self.new is None:
            self.new = now
        meshes = [k for k in now if k.startswith("meshes/")]
        assert set(now) == set(self.new) and meshes and all(now[k] == self.new[k] for k in meshes), what


def _smooth_case(work: Path, ext: str) -> Case:
    (work / "src").mkdir()
    (work / "out").mkdir()
    assert main(["generate", "box", "--n", "5", "--amplitude", "0.3", f"src/in.{ext}"]) == 0
    assert main(["generate", "box", "--n", "5", "--amplitude", "0.2", "--seed", "1", f"out/out.{ext}"]) == 0
    return Case(work, ["smooth", f"src/in.{ext}", f"out/out.{ext}", "--force", "--quiet"], f"out/out.{ext}")


def _run_case(work: Path) -> Case:
    (work / "src").mkdir()
    (work / "src" / "exp.yaml").write_text(CUBE27_EXPERIMENT + "figures: false\n")
    assert main(["run", "src/exp.yaml", "--out", "prev", "--quiet"]) == 0
    return ResultsCase(work, ["run", "src/exp.yaml", "--out", "prev", "--force", "--quiet"], "prev")


CASES = {"vtk": lambda w: _smooth_case(w, "vtk"), "exodus": lambda w: _smooth_case(w, "e"),
         "abaqus": lambda w: _smooth_case(w, "inp"), "nastran": lambda w: _smooth_case(w, "bdf"), "run": _run_case}


def _kill(case: Case, spec: str, log: Path) -> str:
    proc = case.spawn(spec, log)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == -9, (spec, proc.returncode, err)  # killed at that step, not ended by itself
    return case.check(spec)


def _kill_in_time(case: Case, delay: float, log: Path) -> str:
    proc = case.spawn("none", log)
    time.sleep(delay)
    proc.kill()
    _, err = proc.communicate(timeout=300)
    assert proc.returncode in (0, -9), (delay, proc.returncode, err)
    return case.check(f"SIGKILL at {delay:.2f} s")


@pytest.mark.parametrize("name", sorted(CASES))
def test_sigkill_at_the_swap(tmp_path, monkeypatch, capsys, name):
    """Killed just after, and just before, the rename that puts the output in place: the new output, then the
    old one; the next run removes the temporary folders the kills left, and writes the same new output."""
    monkeypatch.chdir(tmp_path)
    case = CASES[name](tmp_path)
    capsys.readouterr()
    log = tmp_path.parent / f"{tmp_path.name}.steps"
    assert _kill(case, "swap:1", log) == "new"
    assert _kill(case, "swap:0", log) == "old"
    left = [p for p in case.output.parent.iterdir() if p.name.startswith(TEMP_PREFIX) and p not in case.decoys]
    assert len(left) == 1, left  # the second run's (the new output, not yet swapped in): it removed the first's
    case.finish(log)


@pytest.mark.deep
@pytest.mark.parametrize("name", sorted(CASES))
def test_sigkill_at_every_step_and_instant(tmp_path, monkeypatch, capsys, name):
    """Killed at every file-system step of the command, each from the same start, then at `TIME_INSTANTS`
    instants spread over a whole run (its start to its end), each run finding what the kills before it left (so
    also killed while it removes them); the next run removes what the kills left."""
    monkeypatch.chdir(tmp_path)
    case = CASES[name](tmp_path)
    capsys.readouterr()
    log = tmp_path.parent / f"{tmp_path.name}.steps"
    seconds = case.finish(log)
    steps = log.read_text().splitlines()
    assert any(s.startswith("renameat2") and str(case.output) in s for s in steps), steps
    seen = []
    for n in range(1, len(steps) + 1):  # each from the same start: what the kill left removed first
        seen.append(_kill(case, f"step:{n}", log))
        remove_stale(case.output.parent)
    assert "old" in seen and "new" in seen, seen
    seen = [_kill_in_time(case, seconds * (k + 0.5) / TIME_INSTANTS, log) for k in range(TIME_INSTANTS)]
    assert "old" in seen, seen
    case.finish(log)
