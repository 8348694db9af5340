"""The last window of ``jaxci run --force``: a SIGTERM or SIGINT that comes once the results are complete (moved
into place, or while the command prints, or while the process's exit handlers run) ends with exit 143 / 130 and
the one line ``jaxci: interrupted (SIGTERM): 2 of 2 runs finished, written to prev (complete)``, the new results
in place, nothing else left. By default at four points, each held by the child until the signal came (`PAUSED`);
under ``-m deep`` also SIGTERM at 20 instants over the last 40% of a run's time."""

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
from helpers import complete_results

from jaxci.experiments.results import MARKER

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals")

#: `jaxci run` in a child (argv: a flag file, the point, then jaxci's arguments) that stops at the point named
#: until the test writes FLAG.go (or 60 s): "committed" (the results just moved in, inside `run_experiment`),
#: "returned" (`run_experiment` returned to the command), "command" (the command returned to `jaxci.cli`),
#: "exit" (the process's exit handlers, after the command).
PAUSED = """\
import atexit, sys, time
from pathlib import Path
FLAG, GO, WHERE = Path(sys.argv[1]), Path(sys.argv[1] + ".go"), sys.argv[2]

def pause():
    FLAG.write_text(WHERE)
    t = time.monotonic()
    while not GO.exists() and time.monotonic() - t < 60:
        time.sleep(0.01)

def after(module, name):
    real = getattr(module, name)
    def wrapped(*args, **kwargs):
        out = real(*args, **kwargs)
        pause()
        return out
    setattr(module, name, wrapped)

import jaxci.cli._run as command
import jaxci.experiments.results as results
import jaxci.experiments.runner as runner
if WHERE == "committed":
    after(results.Staged, "commit")
elif WHERE == "returned":
    after(runner, "run_experiment")
elif WHERE == "command":
    after(command, "run")
else:
    atexit.register(pause)
from jaxci.cli import entry
sys.argv = ["jaxci", *sys.argv[3:]]
entry()
"""

COMPLETE = "2 of 2 runs finished, written to prev (complete)"


@pytest.fixture(scope="module")
def earlier(tmp_path_factory):
    """A complete results folder of QUICK, to copy as the earlier results of a test."""
    return complete_results(tmp_path_factory)


def _setup(tmp_path: Path, earlier: Path) -> str:
    (tmp_path / "exp.yaml").write_text(QUICK)
    shutil.copytree(earlier, tmp_path / "prev")
    return (tmp_path / "prev" / "summary.json").read_text()


def _spawn(argv: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *argv], cwd=cwd, env={**os.environ, "JAX_PLATFORMS": "cpu"},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _check_new_results(tmp_path: Path, old_summary: str) -> None:
    prev = tmp_path / "prev"
    summary = (prev / "summary.json").read_text()
    assert summary != old_summary and json.loads(summary)["runs_done"] == 2
    assert json.loads((prev / MARKER).read_text())["partial"] is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml", "prev"]


@pytest.mark.parametrize(("where", "signum"), [("committed", signal.SIGTERM), ("returned", signal.SIGTERM),
                                               ("command", signal.SIGTERM), ("exit", signal.SIGTERM),
                                               ("exit", signal.SIGINT)])
def test_signal_after_the_results_are_complete(tmp_path, earlier, where, signum):
    old = _setup(tmp_path, earlier)
    flag = tmp_path.parent / f"{tmp_path.name}.flag"
    proc = _spawn(["-c", PAUSED, str(flag), where, "run", "exp.yaml", "--out", "prev", "--force", "--quiet"],
                  tmp_path)
    t0 = time.monotonic()
    while not flag.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < 300, "timed out"
        time.sleep(0.02)
    proc.send_signal(signum)
    Path(f"{flag}.go").write_text("go")
    out, err = proc.communicate(timeout=60)
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, (proc.returncode, err)
    assert out == "" and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"jaxci: interrupted ({name})") and COMPLETE in err, err
    _check_new_results(tmp_path, old)


@pytest.mark.deep
def test_sigterm_over_the_end_of_a_run(tmp_path, earlier):
    """SIGTERM at 20 instants over the last 40% of a run's time: each ends either by itself (the signal came
    after its end: exit 0, no line) or with 143 and one line, which says "(complete)" whenever the new results
    are in place, and "(partial)" with the earlier results untouched otherwise; never killed by the signal."""
    old = _setup(tmp_path, earlier)
    argv = ["-m", "jaxci", "run", "exp.yaml", "--out", "prev", "--force", "--quiet"]
    t = time.monotonic()
    proc = _spawn(argv, tmp_path)
    assert proc.wait(timeout=300) == 0
    seconds = time.monotonic() - t
    outcomes = []
    for k in range(20):
        shutil.rmtree(tmp_path)
        tmp_path.mkdir()
        _setup(tmp_path, earlier)
        proc = _spawn(argv, tmp_path)
        time.sleep(seconds * (0.6 + 0.4 * k / 19))
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode in (0, 143), (k, proc.returncode, err)
        if proc.returncode == 0:
            assert err == "", err
            _check_new_results(tmp_path, old)
        elif COMPLETE in err or "as the command ended" in err:
            assert err.startswith("jaxci: interrupted (SIGTERM)") and err.count("\n") == 1, err
            _check_new_results(tmp_path, old)
        else:
            assert "(partial); earlier results in prev untouched" in err and err.count("\n") == 1, err
            assert (tmp_path / "prev" / "summary.json").read_text() == old
        outcomes.append(proc.returncode)
    assert 143 in outcomes, outcomes
