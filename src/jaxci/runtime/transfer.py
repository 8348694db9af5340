"""The JAX engine's traffic between the host and the device, and its time inside compiled programs, counted.

A run on the JAX engine keeps its arrays on the device from the mesh's upload to the result's download; what
crosses between them does so through the two functions of this module, never implicitly (``np.asarray`` of a
device array, a numpy array passed to a jitted function: under ``jax.transfer_guard("disallow")`` both raise):

- `to_device` puts a numpy array (or a pytree of them) on the device, converted to its dtype on the host (no
  compilation: ``jnp.asarray`` of a numpy array compiles a small program per shape in jax 0.10);
- `to_host` brings device arrays back as numpy arrays.

Both add the bytes they move to process-wide totals (`totals`: ``h2d_bytes``, ``d2h_bytes``). `program` wraps a
compiled entry point (a jitted function called from Python): each call waits for its outputs and adds the
seconds it took, less any compilation it triggered (`compile_totals`: JAX reports every compilation through
`jax.monitoring`, tracing, lowering to MLIR and the XLA backend compile or its persistent-cache load, and a
listener registered once per process adds those durations up), to ``device_s``, the time inside compiled
programs. `jaxci.runtime.phases.PhaseClock` records the three per phase, and each phase's ``host_s``:
its seconds outside compiled programs and compilation. A compiled call that is not wrapped counts as host time,
so ``host_s`` is an upper bound.

The numpy path (the host engine) moves nothing and never imports JAX for this module.
"""

from __future__ import annotations

import functools
import threading
import time

import numpy as np

from . import compile_cache
from ._export import EVENT as _EXPORTED_EVENT
from ._export import HOST_EVENT as _PREPARE_EVENT
from ._export import exportable
from ._lazy import jax, loaded

#: jax.monitoring duration events that are compilation (names as in jax._src.dispatch, and `jaxci.runtime._export`'s
#: reading, deserializing, serializing and writing of exported programs).
_COMPILE_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "backend",
    _EXPORTED_EVENT: "exported",
    _PREPARE_EVENT: "prepare",  # host seconds keying an exported program's call: neither compilation nor device
}
_CACHE_HIT = "/jax/compilation_cache/cache_hits"
#: The seconds of `compile_totals` that are compilation (the phases' ``compile_seconds``).
COMPILE_KINDS = ("trace", "lower", "backend", "exported")

_clock = threading.Lock()
_compile = {"trace": 0.0, "lower": 0.0, "backend": 0.0, "exported": 0.0, "prepare": 0.0, "compiled": 0,
            "cache_hits": 0}
_registered = False


def _on_duration(event: str, duration: float, **_) -> None:
    kind = _COMPILE_EVENTS.get(event)
    if kind is not None:
        with _clock:
            _compile[kind] += float(duration)
            if kind == "backend":
                _compile["compiled"] += 1


def _on_event(event: str, **_) -> None:
    if event == _CACHE_HIT:
        with _clock:
            _compile["cache_hits"] += 1


def compile_totals() -> dict:
    """Compilation so far in this process: seconds of ``trace``, ``lower``, ``backend`` (XLA compile or
    persistent-cache load) and ``exported`` (exported programs read or written: `jaxci.runtime._export`; ``prepare``:
    the host seconds keying their calls, not compilation), ``compiled``
    (backend compilations, cache loads included) and ``cache_hits``.

    The listener is registered when JAX is imported (`jaxci.runtime._lazy.when_imported`), not by this call: a run that
    never imports JAX compiled nothing and does not import it to say so."""
    global _registered
    if not _registered:
        from ._lazy import when_imported

        _registered = True
        when_imported("jax", _register)
    with _clock:
        return dict(_compile)


def _register() -> None:
    from jax import monitoring

    monitoring.register_event_duration_secs_listener(_on_duration)
    monitoring.register_event_listener(_on_event)


_lock = threading.Lock()
_totals = {"h2d_bytes": 0, "d2h_bytes": 0, "device_s": 0.0}
#: Nesting depth of `program` calls in this thread: only the outermost one is timed.
_depth = threading.local()


def totals() -> dict:
    """The process's totals so far: ``h2d_bytes``, ``d2h_bytes`` (bytes moved through `to_device` and
    `to_host`) and ``device_s`` (seconds inside `program` calls, compilation excluded)."""
    with _lock:
        return dict(_totals)


def _add(key: str, value) -> None:
    with _lock:
        _totals[key] += value


def _nbytes(tree) -> int:
    if not loaded():
        return 0
    return int(sum(getattr(a, "nbytes", 0) for a in jax.tree_util.tree_leaves(tree)))


def host_dtype(a, dtype=None) -> np.ndarray:
    """`a` as the numpy array `to_device` puts on the device: `dtype`, or its own canonicalised as JAX would
    (int32 / float32 unless ``jax_enable_x64``). Kept on the host: for an array padded before it goes there."""
    a = np.asarray(a)
    if dtype is None:
        dtype = jax.dtypes.canonicalize_dtype(a.dtype)
    return np.asarray(a, dtype=np.dtype(dtype))


def to_device(a, dtype=None):
    """`a` (a numpy array, a scalar, or a pytree of them) as device arrays of `dtype` (default: each its own,
    canonicalised), on JAX's default device; the bytes are counted (``h2d_bytes``). The first upload of a process
    sets up the compilation cache (`jaxci.runtime.compile_cache.enable`)."""
    compile_cache.enable()
    if isinstance(a, (np.ndarray, np.generic, int, float, bool)) or dtype is not None:
        out = jax.device_put(host_dtype(a, dtype))
    else:
        out = jax.device_put(jax.tree_util.tree_map(host_dtype, a))
    _add("h2d_bytes", _nbytes(out))
    return out


def to_host(a):
    """Device arrays `a` (an array or a pytree) as numpy arrays (numpy leaves pass through); the bytes of the
    device arrays are counted (``d2h_bytes``). `explicit` is True while it runs. Without JAX loaded nothing can
    be on a device: `a` is returned as it is (the host engine never imports JAX)."""
    if not loaded():
        return a
    _explicit.on = True
    try:
        out = jax.device_get(a)
    finally:
        _explicit.on = False
    _add("d2h_bytes", _nbytes([v for v in jax.tree_util.tree_leaves(a) if isinstance(v, jax.Array)]))
    return out


#: Whether this thread is inside `to_host` (`explicit`).
_explicit = threading.local()


def explicit() -> bool:
    """Whether this thread is inside `to_host`: a test that refuses every other device-to-host copy asks (JAX's
    transfer guard refuses implicit host-to-device transfers on every platform, but not the copies of a CPU
    array to numpy, which its buffer protocol makes without JAX)."""
    return getattr(_explicit, "on", False)


def program(fn):
    """`fn` (a compiled entry point: a `jax.jit` or `equinox.filter_jit` function, or `jaxci.runtime._lazy`'s) compiled
    once per machine and timed. Its calls go through exported programs in the compilation cache
    (`jaxci.runtime._export`: a later process at a size seen before neither traces nor compiles it; the first call sets
    the cache up, `jaxci.runtime.compile_cache.enable`). Each outermost call waits for its outputs
    (`jax.block_until_ready`) and adds its seconds, less the compilation it triggered, to ``device_s``. Nested
    calls (a program calling another from Python) are timed once, by the outermost."""
    run = exportable(fn)

    @functools.wraps(fn)
    def timed(*args, **kwargs):
        depth = getattr(_depth, "n", 0)
        if depth:
            return run(*args, **kwargs)
        _depth.n = 1
        try:
            c0, t0 = compile_totals(), time.perf_counter()
            out = jax.block_until_ready(run(*args, **kwargs))
            c1 = compile_totals()
            compiling = sum(c1[k] - c0[k] for k in (*COMPILE_KINDS, "prepare"))  # "prepare": host time
            _add("device_s", max(0.0, time.perf_counter() - t0 - compiling))
            return out
        finally:
            _depth.n = 0

    def lower(*args, **kwargs):
        """The jitted function's own ahead-of-time lowering (its HLO, its compiled memory analysis)."""
        built = getattr(fn, "built", None)
        return (built() if built is not None else fn).lower(*args, **kwargs)

    timed.lower = lower
    return timed
