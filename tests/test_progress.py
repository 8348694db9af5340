"""Progress on long work: `jaxci.runtime.phases`' progress and step events (nothing when nobody listens), the command's
progress line (`jaxci.cli._progress.Display`), and through real processes: on a terminal (a pseudo-terminal the
test opens) `jaxci smooth` and `jaxci run` draw it; piped, or with ``--quiet``, stderr stays empty; ``-v`` keeps its
phase lines."""

from __future__ import annotations

import io
import os
import select
import subprocess
import sys

import pytest
from helpers import CUBE27_EXPERIMENT, MESQUITE

from jaxci import native
from jaxci.cli._progress import Display, step_text
from jaxci.runtime import phases
from jaxci.runtime.phases import PhaseClock

PAVE3 = MESQUITE / "pave3.e.vtk"  # 106 inverted elements: untangling rounds, then a few hundred L-BFGS steps


# ---------------------------------------------------------------------------------------------- events
def test_nobody_listening_costs_a_test_and_reports_nothing():
    assert phases.stepper("L-BFGS") is None  # outside any phase
    clock = PhaseClock()
    with clock.phase("smooth"):
        assert phases.stepper("L-BFGS") is None  # a clock without a listener
        phases.progress("nothing to hear this")


def test_steps_and_stages_reach_the_running_phase(monkeypatch):
    events = []
    clock = PhaseClock(lambda kind, name, rec: events.append((kind, name, rec)))
    monkeypatch.setattr(phases, "STEP_INTERVAL", 3600.0)
    with clock.phase("smooth"):
        tick = phases.stepper("L-BFGS")
        for k in range(1, 50):
            tick(k, 1.0 / k, 1.0 + 1.0 / k)
        phases.progress("lbfgs run 1: 49 steps")
    steps = [rec for kind, _, rec in events if kind == "step"]
    assert steps == [{"stage": "L-BFGS", "unit": "step", "step": 1, "F": 1.0, "worst": 2.0}]  # the first, then
    # nothing within the interval
    assert ("progress", "smooth", {"text": "lbfgs run 1: 49 steps"}) in events
    assert [k for k, _, _ in events] == ["start", "step", "progress", "end"]
    monkeypatch.setattr(phases, "STEP_INTERVAL", 0.0)
    events.clear()
    with clock.phase("smooth"):
        tick = phases.stepper("local CI", "sweep")
        for k in range(5):
            tick(k, None, None)
    assert [rec["step"] for kind, _, rec in events if kind == "step"] == [0, 1, 2, 3, 4]
    assert phases.stepper("L-BFGS") is None  # the phase is over


def test_listening_reaches_clocks_made_without_a_listener():
    import jaxci
    from jaxci.mesh.generate import perturb_box

    events = []
    with phases.listening(lambda kind, name, rec: events.append((kind, name, rec))):
        jaxci.smooth(perturb_box(3, 3, 3, amplitude=0.2, seed=1))
    assert ("start", "smooth", None) in events
    assert any(kind == "step" and name == "smooth" and rec["stage"] == "L-BFGS" for kind, name, rec in events)
    events.clear()
    jaxci.smooth(perturb_box(3, 3, 3, amplitude=0.2, seed=1))  # no longer listening
    assert events == []


def test_display_draws_in_place_and_erases():
    out = io.StringIO()
    d = Display(live=True, verbose=False, stream=out)
    d.on_event("start", "smooth", None)
    d.on_event("step", "smooth", {"stage": "L-BFGS", "unit": "step", "step": 12, "F": 0.5, "worst": 1.25})
    d.close()
    text = out.getvalue()
    assert "\r\x1b[2Kjaxci: [" in text and "smooth: L-BFGS step 12: F 0.5, worst kappa/3 1.25" in text
    assert text.endswith("\x1b[2K") and "\x1b[?25h" in text  # erased, the cursor shown: the next line starts clean
    assert text.count("\n") == text.count("\x1b[1A")  # nothing permanent without --verbose (every newline taken back)
    d.close()  # twice is harmless
    assert out.getvalue() == text


def test_display_verbose_lines_without_a_terminal():
    out = io.StringIO()
    d = Display(live=False, verbose=True, stream=out)
    d.on_event("start", "untangle", None)
    d.on_event("progress", "untangle", {"text": "round 1: min det J 0.002"})
    d.on_event("step", "smooth", {"stage": "L-BFGS", "unit": "step", "step": 3, "F": 1.0, "worst": 2.0})
    d.on_event("end", "untangle", {"seconds": 1.5, "compile_seconds": 0.0, "compiled": 0, "cache_hits": 0})
    d.close()
    assert out.getvalue().splitlines() == ["jaxci: untangle  ... round 1: min det J 0.002",
                                           "jaxci: untangle      1.50 s"]
    assert "\x1b" not in out.getvalue()
    assert step_text({"stage": "global CI", "unit": "learning attempt", "step": 7, "F": 0.1, "worst": None}) == \
        "global CI learning attempt 7: F 0.1"


# ---------------------------------------------------------------------------------------------- processes
def _run(argv, *, tty: bool, cwd, timeout=240) -> tuple[int, str, str]:
    """Run ``python -m jaxci ARGV`` with stderr on a pseudo-terminal (`tty`) or a pipe; ``(code, out, err)``."""
    cmd = [sys.executable, "-m", "jaxci", *map(str, argv)]
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}  # the terminal's width decides
    env["JAXCI_HUGEPAGES"] = "0"  # (pytest-xdist's workers set COLUMNS=80, which the line would honour)
    if not tty:
        p = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=timeout, env=env)
        return p.returncode, p.stdout, p.stderr
    import fcntl
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 250, 0, 0))  # 250 columns: lines not cut
    p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=slave, cwd=cwd, env=env)
    os.close(slave)
    err = b""
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 0.1)
            if ready:
                try:
                    chunk = os.read(master, 1 << 16)
                except OSError:  # the child closed its end
                    break
                if not chunk:
                    break
                err += chunk
            elif p.poll() is not None:
                break
        out = p.stdout.read().decode()
        code = p.wait(timeout=timeout)
    finally:
        os.close(master)
        if p.poll() is None:
            p.kill()
    return code, out, err.decode(errors="replace")


@pytest.mark.shared
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pseudo-terminals as on Linux")
def test_smooth_shows_progress_on_a_terminal_only(tmp_path):
    code, out, err = _run(["smooth", PAVE3, "a.vtk"], tty=True, cwd=tmp_path)
    assert code == 0, err
    assert "\r\x1b[2K" in err  # drawn in place
    assert "untangle: round 1: min det J" in err  # a stage inside a phase
    assert "smooth: L-BFGS step 1: F " in err and "worst kappa/3 " in err  # a step, F and the worst element
    assert err.endswith("\x1b[2K")  # erased before the result was printed
    assert "after (" in out and "\x1b" not in out

    code, out, err = _run(["smooth", PAVE3, "b.vtk"], tty=False, cwd=tmp_path)
    assert code == 0 and err == ""  # piped: nothing
    code, out, err = _run(["smooth", PAVE3, "c.vtk", "--quiet"], tty=True, cwd=tmp_path)
    assert code == 0 and err == ""  # --quiet: nothing, even on a terminal
    code, out, err = _run(["smooth", PAVE3, "d.vtk", "-v", "--quiet"], tty=True, cwd=tmp_path)
    assert code == 0 and "\x1b" not in err
    lines = err.replace("\r", "").splitlines()
    assert any(line.startswith("jaxci: untangle ") for line in lines) and lines[-1].startswith("jaxci: total")


@pytest.mark.skipif(not native.AVAILABLE, reason="needs the C kernels (jaxci.native)")
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pseudo-terminals as on Linux")
def test_run_shows_the_run_and_its_steps_on_a_terminal(tmp_path):
    (tmp_path / "exp.yaml").write_text(CUBE27_EXPERIMENT.replace("seeds: [0, 1]", "seeds: [0]\nfigures: false"))
    code, out, err = _run(["run", "exp.yaml", "--out", "r1"], tty=True, cwd=tmp_path)
    assert code == 0, err
    assert "run 1/1: cube27 / CI local / seed 0 | smooth" in err
    assert "local CI sweep 1: F " in err
    assert err.endswith("\x1b[2K")
    code, out, err = _run(["run", "exp.yaml", "--out", "r2"], tty=False, cwd=tmp_path)
    assert code == 0 and err == ""


def test_display_verbose_lines_print_above_the_live_line(monkeypatch):
    """On a terminal with ``--verbose``: a finished phase's line is printed once, permanently, above the live
    line, which goes on below it with every step reported, and is erased at the end."""
    from jaxci.cli import _progress

    monkeypatch.setattr(_progress, "REFRESH", 100.0)  # no redraw by the refresh thread during the test
    out = io.StringIO()
    d = Display(live=True, verbose=True, stream=out)
    d.on_event("start", "smooth", None)
    d.on_event("step", "smooth", {"stage": "L-BFGS", "unit": "step", "step": 1, "F": 0.5, "worst": 1.25})
    d.on_event("step", "smooth", {"stage": "L-BFGS", "unit": "step", "step": 2, "F": 0.4, "worst": 1.2})
    d.on_event("end", "smooth", {"seconds": 1.5, "compile_seconds": 0.25, "compiled": 2, "cache_hits": 0})
    d.on_event("start", "checks", None)
    d.close()
    text = out.getvalue()
    permanent = "jaxci: smooth        1.50 s (compilation 0.25 s, 2 compiled)\n"
    assert text.count(permanent) == 1
    assert text.index("L-BFGS step 1: F 0.5") < text.index("L-BFGS step 2: F 0.4") < text.index(permanent)
    assert "checks ..." in text[text.index(permanent):]  # the live line again, below the permanent one
    assert text.endswith("\x1b[2K")
