"""Where the time of a run goes: wall seconds per phase, and the JAX compilation inside each phase.

`PhaseClock` times named phases (``with clock.phase("read"): ...``); JAX reports every compilation through
`jax.monitoring` (tracing, lowering to MLIR, and the XLA backend compile or its persistent-cache load), and a
listener registered once per process adds those durations up, so each phase also says how much of it was
compilation and how many functions were compiled or loaded from the persistent compilation cache.

Library code only records; whoever runs the clock (the CLI's ``--verbose``) may pass ``on_event`` to hear of
each phase as it starts and ends.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable

from .memory import release_free_memory

#: jax.monitoring duration events that are compilation (names as in jax._src.dispatch).
_COMPILE_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "backend",
}
_CACHE_HIT = "/jax/compilation_cache/cache_hits"

_lock = threading.Lock()
_totals = {"trace": 0.0, "lower": 0.0, "backend": 0.0, "compiled": 0, "cache_hits": 0}
_registered = False


def _on_duration(event: str, duration: float, **_) -> None:
    kind = _COMPILE_EVENTS.get(event)
    if kind is not None:
        with _lock:
            _totals[kind] += float(duration)
            if kind == "backend":
                _totals["compiled"] += 1


def _on_event(event: str, **_) -> None:
    if event == _CACHE_HIT:
        with _lock:
            _totals["cache_hits"] += 1


def compile_totals() -> dict:
    """Compilation so far in this process: seconds of ``trace``, ``lower``, ``backend`` (XLA compile or
    persistent-cache load), ``compiled`` (backend compilations, cache loads included) and ``cache_hits``.

    The listener is registered when JAX is imported (`jaxci._lazy.when_imported`), not by this call: a run that
    never imports JAX compiled nothing and does not import it to say so."""
    global _registered
    if not _registered:
        from ._lazy import when_imported

        _registered = True
        when_imported("jax", _register)
    with _lock:
        return dict(_totals)


def _register() -> None:
    from jax import monitoring

    monitoring.register_event_duration_secs_listener(_on_duration)
    monitoring.register_event_listener(_on_event)


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
      (record: the phase's `as_dict` entry so far) or ``"progress"`` (record ``{"text": ...}``: a line of
      progress inside a long phase, `progress`).
    """

    def __init__(self, on_event: Callable[[str, str, dict | None], None] | None = None):
        self.on_event = on_event
        self._phases: dict[str, dict] = {}
        compile_totals()  # register the listener before the first phase compiles anything

    def add(self, name: str, seconds: float, compile_seconds: float = 0.0, compiled: int = 0,
            cache_hits: int = 0) -> None:
        """Add a phase measured elsewhere (e.g. the process start-up)."""
        rec = self._phases.setdefault(name, {"seconds": 0.0, "compile_seconds": 0.0, "compiled": 0,
                                             "cache_hits": 0})
        rec["seconds"] += seconds
        rec["compile_seconds"] += compile_seconds
        rec["compiled"] += compiled
        rec["cache_hits"] += cache_hits

    @contextlib.contextmanager
    def phase(self, name: str):
        """Time the body as phase `name` (a phase run twice adds up)."""
        if self.on_event is not None:
            self.on_event("start", name, None)
        release_free_memory()  # the last phase's freed temporaries off the resident set before this one's arrays
        c0, t0 = compile_totals(), time.perf_counter()
        try:
            yield
        finally:
            c1 = compile_totals()
            self.add(name, time.perf_counter() - t0,
                     sum(c1[k] - c0[k] for k in ("trace", "lower", "backend")),
                     c1["compiled"] - c0["compiled"], c1["cache_hits"] - c0["cache_hits"])
            if self.on_event is not None:
                self.on_event("end", name, dict(self._phases[name]))

    def progress(self, name: str, text: str) -> None:
        """Report progress inside phase `name` (to `on_event`; nothing is recorded)."""
        if self.on_event is not None:
            self.on_event("progress", name, {"text": text})

    def as_dict(self) -> dict:
        """``{phase: {seconds, compile_seconds, compiled, cache_hits}}`` plus ``"total"`` (sums)."""
        out = {k: {kk: (round(vv, 4) if isinstance(vv, float) else vv) for kk, vv in v.items()}
               for k, v in self._phases.items()}
        tot = {k: sum(v[k] for v in self._phases.values()) for k in ("seconds", "compile_seconds", "compiled",
                                                                       "cache_hits")}
        out["total"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in tot.items()}
        return out
