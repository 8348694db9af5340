"""Where the time of a run goes: wall seconds per phase, and the JAX compilation inside each phase.

`PhaseClock` times named phases (``with clock.phase("read"): ...``); JAX reports every compilation through
`jax.monitoring` (tracing, lowering to MLIR, and the XLA backend compile or its persistent-cache load; jaxci
adds its reading and writing of exported programs, `jaxci.runtime._export`), and a listener registered once per
process adds those durations up (`jaxci.runtime.transfer.compile_totals`), so each phase also says how much of it
was compilation (``compile_seconds``: the sum of `jaxci.runtime.transfer.COMPILE_KINDS`) and how many functions
were compiled or loaded from the persistent compilation cache.

Library code only records; whoever runs the clock (the command line) may pass ``on_event`` to hear of each
phase as it starts and ends, and of the progress inside it: code deep inside a phase (a solver's loop) reports
through `progress` (a stage: a restart, a round) and `stepper` (a loop's steps, at most one report per
`STEP_INTERVAL` seconds), which cost nothing when nobody listens. `listening` gives a listener to the clocks made
without one (those of each `jaxci.smooth` call of an experiment).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import time
from collections.abc import Callable

from . import transfer
from .memory import release_free_memory
from .transfer import compile_totals  # noqa: F401  (also reached as jaxci.runtime.phases.compile_totals)

#: What `PhaseClock` records of each phase (and ``host_s``, derived: `PhaseClock.add`).
_FIELDS = ("seconds", "compile_seconds", "compiled", "cache_hits", "h2d_bytes", "d2h_bytes", "device_s")

#: Seconds between two reports of a loop's steps (`stepper`): a terminal's line redrawn a few times a second.
STEP_INTERVAL = 0.2

#: ``(on_event, phase name)`` of the phase running in this context (None: nobody listens), for `progress` and
#: `stepper`.
_running: contextvars.ContextVar = contextvars.ContextVar("jaxci_running_phase", default=None)
#: The listener of clocks made without one (`listening`).
_ambient: contextvars.ContextVar = contextvars.ContextVar("jaxci_phase_listener", default=None)

def process_age() -> float | None:
    """Seconds since this process started (Linux ``/proc``; None elsewhere): the start-up and import time of a
    command, measured when its ``main`` begins (a re-exec keeps the process, so it is included)."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


class PhaseClock:
    """Wall time and compilation per named phase, in the order the phases first ran.

    - `on_event`: optional ``on_event(kind, name, record)``, kind ``"start"`` (record None), ``"end"``
      (record: the phase's `as_dict` entry so far), ``"progress"`` (record ``{"text": ...}``: a stage inside a
      long phase, `PhaseClock.progress` and `progress`) or ``"step"`` (record ``{"stage", "unit", "step", "F",
      "worst"}``: a loop's latest step, `stepper`; F and worst (max kappa/3) may be None). Default: the
      listener of `listening`, if any.
    """

    def __init__(self, on_event: Callable[[str, str, dict | None], None] | None = None):
        self.on_event = on_event if on_event is not None else _ambient.get()
        self._phases: dict[str, dict] = {}
        compile_totals()  # register the listener before the first phase compiles anything

    def add(self, name: str, seconds: float, compile_seconds: float = 0.0, compiled: int = 0,
            cache_hits: int = 0, h2d_bytes: int = 0, d2h_bytes: int = 0, device_s: float = 0.0) -> None:
        """Add a phase measured elsewhere (e.g. the process start-up). Its ``host_s`` is what is left of
        `seconds` outside compiled programs (`device_s`) and compilation."""
        rec = self._phases.setdefault(name, dict.fromkeys(_FIELDS, 0))
        for key, value in zip(_FIELDS, (seconds, compile_seconds, compiled, cache_hits, h2d_bytes, d2h_bytes,
                                        device_s), strict=False):
            rec[key] += value
        rec["host_s"] = max(0.0, rec["seconds"] - rec["device_s"] - rec["compile_seconds"])

    @contextlib.contextmanager
    def phase(self, name: str):
        """Time the body as phase `name` (a phase run twice adds up)."""
        if self.on_event is not None:
            self.on_event("start", name, None)
        release_free_memory()  # the last phase's freed temporaries off the resident set before this one's arrays
        c0, m0, t0 = compile_totals(), transfer.totals(), time.perf_counter()
        token = _running.set(None if self.on_event is None else (self.on_event, name))
        try:
            yield
        finally:
            _running.reset(token)
            c1, m1 = compile_totals(), transfer.totals()
            self.add(name, time.perf_counter() - t0,
                     sum(c1[k] - c0[k] for k in transfer.COMPILE_KINDS),
                     c1["compiled"] - c0["compiled"], c1["cache_hits"] - c0["cache_hits"],
                     *(m1[k] - m0[k] for k in ("h2d_bytes", "d2h_bytes", "device_s")))
            if self.on_event is not None:
                self.on_event("end", name, dict(self._phases[name]))

    def progress(self, name: str, text: str) -> None:
        """Report progress inside phase `name` (to `on_event`; nothing is recorded)."""
        if self.on_event is not None:
            self.on_event("progress", name, {"text": text})

    def as_dict(self) -> dict:
        """``{phase: {seconds, compile_seconds, compiled, cache_hits, h2d_bytes, d2h_bytes, device_s, host_s}}``
        plus ``"total"`` (sums): `jaxci.runtime.transfer`'s bytes moved each way between host and device, seconds inside
        compiled programs, and seconds outside them and compilation."""
        out = {k: {kk: (round(vv, 4) if isinstance(vv, float) else vv) for kk, vv in v.items()}
               for k, v in self._phases.items()}
        tot = {k: sum(v[k] for v in self._phases.values()) for k in (*_FIELDS, "host_s")}
        out["total"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in tot.items()}
        return out


def progress(text: str) -> None:
    """Report a stage inside the running phase (``"progress"`` event: a solver's restart, a presmoothing) to its
    clock's listener; nothing when nobody listens."""
    running = _running.get()
    if running is not None:
        running[0]("progress", running[1], {"text": text})


def stepper(stage: str, unit: str = "step") -> Callable[..., None] | None:
    """A reporter of a loop's steps inside the running phase: ``tick(step, F=None, worst=None)`` sends a
    ``"step"`` event (`stage`, e.g. ``"L-BFGS"``, what a step is called, `unit`, e.g. ``"sweep"``, the step, F and
    the worst element's kappa/3) at the first call and then at most once every `STEP_INTERVAL` seconds. None
    when nobody listens, so that a loop pays one test a step: ``if tick is not None: tick(k, f, kmax)``."""
    running = _running.get()
    if running is None:
        return None
    on_event, name = running
    due = [0.0]

    def tick(step: int, f: float | None = None, worst: float | None = None) -> None:
        now = time.monotonic()
        if now < due[0]:
            return
        due[0] = now + STEP_INTERVAL
        on_event("step", name, {"stage": stage, "unit": unit, "step": int(step), "F": None if f is None else float(f),
                                "worst": None if worst is None else float(worst)})

    return tick


@contextlib.contextmanager
def listening(on_event: Callable[[str, str, dict | None], None] | None):
    """Within the body, a `PhaseClock` made without a listener reports to `on_event` (`jaxci run`: the phases
    and progress of each run's `jaxci.smooth`)."""
    token = _ambient.set(on_event)
    try:
        yield
    finally:
        _ambient.reset(token)
