"""The JAX engine's compiled entry points stored as XLA executables: a later process neither traces, lowers nor
compiles them.

JAX's persistent compilation cache (`jaxci.runtime.compile_cache`) saves the XLA compile of a program seen before, but
JAX finds a program in it by the hash of its lowered module, so every process still traces and lowers each
jitted function before it can look it up (measured on 2 cores at 10,648 hexahedra: 1.6 s tracing
`_laplace_run`, 0.3-2.7 s the L-BFGS loop, in every process). `exportable(fn)` calls a jitted entry point through
its compiled executable instead (`jax.experimental.serialize_executable`), kept in the cache folder under a key
(`jaxci.runtime._keys`) of all that its tracing and compilation depend on: the function (module, name, code,
closures) and jit's options; the static arguments and the pytree structure of the arguments; each dynamic
argument's shape, dtype, weak type and platform; JAX's trace context (x64, default device, ...); the ``JAXCI_*``
variables and the CPUs the process may use; the versions of Python and of the traced packages (jax and jaxlib
among them: an executable is only valid for the XLA that built it); a hash of jaxci's own files.

A later process with that key reads the executable, registers the custom-call targets it calls (jaxci's own,
through `jaxci.runtime.compile_cache.register_target`) and runs it: a few milliseconds a program, where lowering
a stored `jax.export` module and looking its executable up in JAX's cache took 15-50 ms (and 0.3-0.6 s of set-up
for the first: MLIR, and scipy's LAPACK for the CPU's kernels). The process that stores a program runs that same
executable, so both run one program: the same results. The seconds spent reading, deserializing, serializing and
writing programs are reported to `jax.monitoring` as `EVENT` and count as compilation
(`jaxci.runtime.transfer.compile_totals`, ``exported``).

A call runs as a plain jitted call (JAX's persistent cache only), counted with its reason in
`jaxci.runtime.compile_cache.stats`, where it cannot be keyed (`jaxci.runtime._keys.Unkeyable`: a static value of a
type not known to be deterministic, a device array in a static argument, arrays sharded over several devices, jit
options such as donation or shardings), where the program calls LAPACK (its kernels are set up by lowering, which
a load skips), where it does not compile ahead of time or its executable cannot be serialized, and where a
program's first call fails (its entry is removed: the next process stores it again; a genuine error comes back
from the plain call). A call inside another traced function (tracer arguments) belongs to the outer program and
runs as the function.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import importlib
import importlib.util
import io
import pickle
import sys
import threading
import time
import types
from collections.abc import Callable

import numpy as np

from . import compile_cache
from ._keys import (
    KEYED_BY_STATE,
    SIMPLE,
    Keyer,
    Unkeyable,
    environment,
    qualified,
    sha,
    state,
    trace_context,
    trace_context_key,
    treedef_key,
)
from ._lazy import compute_platform, jax

#: Bump when the entries' layout changes (part of every key).
FORMAT = 2
#: The jax.monitoring duration event of the seconds spent reading, deserializing, serializing and writing programs.
EVENT = "/jaxci/compile/exported_duration"
#: The jax.monitoring duration event of the host seconds spent keying a call and importing what lowering needs
#: (not compilation, not device time: `jaxci.runtime.transfer.program` counts them as host time).
HOST_EVENT = "/jaxci/compile/exported_host_duration"
#: Held while JAX's compilation cache is off for one compilation (`_compiled_here`).
_CACHE_SWITCH = threading.Lock()

#: Programs kept in memory per entry point (the least recently used dropped first).
MEMORY = 16


@dataclasses.dataclass
class _Split:
    """One call's arguments: the pytree of the non-static ones and its leaves (`dynamic`: which are traced), and
    the static arguments of a `jax.jit` function (position or name, value)."""

    treedef: object
    leaves: list
    dynamic: tuple[bool, ...]
    static: tuple

    def dyn(self) -> list:
        return [v for v, d in zip(self.leaves, self.dynamic, strict=True) if d]

    def fixed(self) -> tuple:
        return tuple(v for v, d in zip(self.leaves, self.dynamic, strict=True) if not d)

    def rebuild(self, dyn) -> tuple[tuple, dict]:
        it = iter(dyn)
        leaves = [next(it) if d else v for v, d in zip(self.leaves, self.dynamic, strict=True)]
        args, kwargs = jax.tree_util.tree_unflatten(self.treedef, leaves)
        args = list(args)
        for where, value in self.static:
            if isinstance(where, int):
                args[where] = value
            else:
                kwargs[where] = value
        return tuple(args), kwargs


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic))


class _Target:
    """What a jitted function's calls need: how its arguments split (`kind` ``"jit"``: all but the static ones
    traced; ``"filter"``: the arrays traced, as `equinox.filter_jit`), and its name; `kind` None, with `why`,
    for a function that is not exported."""

    def __init__(self, fn):
        self.fn, self.kind, self.why = fn, None, ""
        self.raw = getattr(fn, "__wrapped__", fn)
        self.name = getattr(self.raw, "__name__", "program")
        info = getattr(fn, "_jit_info", None)
        if info is not None:  # jax.jit
            if any((info.donate_argnums, info.donate_argnames, info.user_specified_in_shardings, info.device,
                    info.backend, info.compiler_options_kvs, info.keep_unused)):
                self.why = "jit options (donation, shardings, device or compiler options)"
                return
            self.kind, self.argnums, self.argnames = "jit", set(info.static_argnums), set(info.static_argnames)
        elif type(fn).__module__.startswith("equinox") and hasattr(fn, "lower"):  # equinox.filter_jit
            if getattr(fn, "donate_first", False) or getattr(fn, "donate_rest", False):
                self.why = "buffer donation"
                return
            self.kind = "filter"
        else:
            self.why = f"not a jitted function ({type(fn).__name__})"

    def split(self, args: tuple, kwargs: dict) -> _Split:
        if self.kind == "filter":
            leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
            return _Split(treedef, leaves, tuple(_is_array(v) for v in leaves), ())
        static = tuple((i, a) for i, a in enumerate(args) if i in self.argnums)
        static += tuple(sorted((k, v) for k, v in kwargs.items() if k in self.argnames))
        tree = (tuple(None if i in self.argnums else a for i, a in enumerate(args)),
                {k: v for k, v in kwargs.items() if k not in self.argnames})
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        return _Split(treedef, leaves, (True,) * len(leaves), static)


class _Nested(Exception):
    """A call with tracer arguments: part of an outer program."""


def _avals(split: _Split) -> tuple[tuple, str]:
    """``(shape, dtype, weak_type)`` of each dynamic leaf, and the platform the call computes on."""
    avals, platforms = [], set()
    for v in split.dyn():
        if isinstance(v, jax.core.Tracer):
            raise _Nested
        if isinstance(v, jax.Array):
            devices = v.sharding.device_set
            if len(devices) != 1:
                raise Unkeyable(f"an array sharded over {len(devices)} devices")
            platforms.add(next(iter(devices)).platform)
        elif not (_is_array(v) or type(v) in (bool, int, float, complex)):
            raise Unkeyable(f"a dynamic argument of type {qualified(type(v))}")
        aval = jax.typeof(v)
        if isinstance(v, jax.Array) and aval.dtype != v.dtype:  # jit converts it; an executable takes it as it is
            raise Unkeyable(f"a {v.dtype} device array narrowed to {aval.dtype} (x64 off)")
        avals.append((tuple(aval.shape), aval.dtype, bool(aval.weak_type)))
    if len(platforms) > 1:
        raise Unkeyable(f"arrays on several platforms ({', '.join(sorted(platforms))})")
    return tuple(avals), _lowering_platform(platforms.pop() if platforms else compute_platform())


def _lowering_platform(platform: str) -> str:
    """`platform` as `jax.export` lowers for it: ``"gpu"`` is ``"cuda"`` or ``"rocm"`` (whichever JAX has)."""
    from jax._src import xla_bridge

    try:
        return xla_bridge.canonicalize_platform(platform)
    except Exception as e:  # noqa: BLE001 - no such backend: not exported
        raise Unkeyable(f"no lowering platform for {platform!r}") from e


def _key(t: _Target, split: _Split, avals: tuple, platform: str) -> str:
    keyer = Keyer()
    return sha("\n".join([
        f"format {FORMAT}", f"function {t.kind} {keyer(t.raw)}", f"static {keyer(split.static)}",
        f"static leaves {keyer(split.fixed())}", f"arguments {treedef_key(split.treedef, keyer)}",
        f"avals {[(shape, str(dtype), weak) for shape, dtype, weak in avals]}", f"platform {platform}",
        f"context {trace_context_key(trace_context(), keyer)}", f"environment {environment()}"]).encode())


# ------------------------------------------------------------------------------------------------ entries
def _singleton(module: str, name: str):
    """A module-level instance by its name (how `_Pickler` stores one: a sentinel keeps its identity)."""
    return getattr(importlib.import_module(module), name)


class _Pickler(pickle.Pickler):
    """pickle, with the stateless instances a module holds (sentinels such as equinox's ``Missing`` in a pytree
    node's data) stored as that module's attribute, so that they load as the same object."""

    def reducer_override(self, obj):
        t = type(obj)
        if (isinstance(obj, (type, types.FunctionType)) or t in SIMPLE or not t.__module__.startswith(KEYED_BY_STATE)
                or state(obj)):
            return NotImplemented
        module = sys.modules.get(t.__module__)
        for name, value in vars(module).items() if module is not None else ():
            if value is obj:
                return _singleton, (t.__module__, name)
        return NotImplemented


def _dumps(entry: dict) -> bytes:
    buf = io.BytesIO()
    _Pickler(buf, protocol=pickle.HIGHEST_PROTOCOL).dump(entry)
    return buf.getvalue()


def _named(fn: Callable, name: str) -> Callable:
    """`fn` under `name` (what JAX calls the program in its logs, events and persistent cache)."""
    fn.__name__ = fn.__qualname__ = name
    return fn


def _timed(fn: Callable, *args):
    t0 = time.perf_counter()
    try:
        return fn(*args)
    finally:
        jax.monitoring.record_event_duration_secs(EVENT, time.perf_counter() - t0)


class _Program:
    """A stored program: called with a call's dynamic leaves, it returns the function's output pytree.
    `fresh` until its first call has run (`entry`: its file). `compiled`: the XLA executable (a
    `jax.stages.Compiled` of the function of the flat dynamic leaves), run as it is: no tracing, no lowering."""

    def __init__(self, compiled, tree, mask: tuple[bool, ...], static: list, entry: str):
        self.tree, self.mask, self.static, self.entry, self.fresh = tree, mask, static, entry, True
        self.compiled = compiled

    def __call__(self, dyn: list):
        out = self.compiled(*dyn)
        if not any(isinstance(v, jax.Array) and v.committed for v in dyn):
            out = [_uncommitted(v) for v in out]
        out, static = iter(out), iter(self.static)
        return jax.tree_util.tree_unflatten(self.tree, [next(out) if m else next(static) for m in self.mask])


def _uncommitted(x):
    """`x` (a single-device array) as an uncommitted array on the same buffer: a jitted function's outputs are
    committed only where an input was, but JAX commits every output of an exported program (its lowering counts
    the program's output memory as a transfer), and a later jitted call would compile again for committed
    inputs. Through JAX's array class (no public way); where that fails, `x` itself."""
    if not x.committed:
        return x
    try:
        from jax._src.array import ArrayImpl

        return ArrayImpl(x.aval, x.sharding, x._arrays, committed=False, _skip_checks=True)
    except Exception:  # noqa: BLE001 - another jax: committed outputs cost at most a compilation
        return x


def _trees(n_in: int, n_out: int):
    """The pytree structures of a flat program's inputs and outputs (`jax.experimental.serialize_executable`)."""
    return jax.tree_util.tree_structure(((0,) * n_in, {})), jax.tree_util.tree_structure([0] * n_out)


def _load(file: str, key: str) -> _Program | None:
    """The stored program of `key` (None: not stored, or unreadable and removed)."""
    from jax.experimental.serialize_executable import deserialize_and_load

    entry = compile_cache.read_entry(file)
    if entry is None:
        return None
    try:
        blob = entry["executable"]
        if entry.get("format") != FORMAT or entry.get("key") != key or entry.get("checksum") != sha(blob):
            raise ValueError("another key or format, or a corrupt program")
        missing = [t for t in entry["targets"] if not compile_cache.ensure_target(t)]
        if missing:
            raise Unkeyable(f"custom call {', '.join(missing)} not registered")
        compiled = deserialize_and_load(blob, *_trees(entry["inputs"], sum(entry["mask"])))
        tree, mask, static = entry["tree"], tuple(entry["mask"]), list(entry["static"])
    except Unkeyable:
        raise
    except Exception as e:  # noqa: BLE001 - any unreadable entry is a miss
        compile_cache.discard(file, f"{type(e).__name__}: {e}")
        return None
    return _Program(compiled, tree, mask, static, file)


def _compiled_here(lowered):
    """`lowered` compiled by XLA in this process, not loaded from JAX's persistent compilation cache: XLA:CPU
    serializes an executable it loaded from there without the code of some of its functions, and a later process
    that loads the stored program fails when it runs it ("Function wrapped_iota not found"; it happened whenever
    jaxci's key of a program changed while JAX's did not: another ``JAXCI_*`` variable, an upgrade, a spoilt
    entry rewritten, or the same program stored twice in one process). JAX decides once per process whether its
    cache is used, so turning the cache off is not enough: its state is reset, around this compilation, to be
    checked again (off inside, on after). The cost: a compilation where JAX's cache would have served one, once
    per stored program."""
    try:
        from jax._src.config import enable_compilation_cache
        from jax.experimental.compilation_cache.compilation_cache import reset_cache

        off = enable_compilation_cache(False)
    except Exception as e:  # noqa: BLE001 - another jax: no stored programs rather than broken ones
        raise Unkeyable(f"JAX's compilation cache cannot be turned off for one compilation ({e})") from e
    with _CACHE_SWITCH:
        try:
            with off:
                reset_cache()  # checked again at this compilation: off
                return lowered.compile()
        finally:
            reset_cache()  # and at the next one: as configured


def _export(t: _Target, split: _Split, avals: tuple, file: str, key: str) -> _Program:
    """Trace, lower and compile the program of this call (its flat dynamic leaves in, its array leaves out), store
    its executable, and return it (what a later process runs)."""
    from jax.experimental.serialize_executable import serialize

    box = {}

    def flat(*dyn):
        args, kwargs = split.rebuild(dyn)
        leaves, tree = jax.tree_util.tree_flatten(t.fn(*args, **kwargs))
        mask = tuple(isinstance(v, jax.Array) for v in leaves)
        box.update(tree=tree, mask=mask, static=[v for v, m in zip(leaves, mask, strict=True) if not m])
        return [v for v, m in zip(leaves, mask, strict=True) if m]

    specs = [jax.ShapeDtypeStruct(shape, dtype, weak_type=weak) for shape, dtype, weak in avals]
    try:
        lowered = jax.jit(_named(flat, t.name)).lower(*specs)
        text = lowered.as_text()
        if "lapack" in text:  # its kernels are set up by lowering (scipy's LAPACK), which a later load skips
            raise Unkeyable("it calls LAPACK")
        compiled = _compiled_here(lowered)
    except Unkeyable:
        raise
    except Exception as e:  # noqa: BLE001 - a genuine error: the plain call repeats it
        raise Unkeyable(f"it does not compile ahead of time: {type(e).__name__}: {str(e)[:200]}") from e

    def store():
        blob, _, _ = serialize(compiled)
        targets = [name for name in compile_cache.own_targets() if f"@{name}(" in text or f'"{name}"' in text]
        data = _dumps({"format": FORMAT, "key": key, "checksum": sha(blob), "executable": blob, "targets": targets,
                       "inputs": len(specs), **box})
        back = pickle.loads(data)
        if back["tree"] != box["tree"] or back["static"] != box["static"]:
            raise Unkeyable("its output's structure does not survive pickling")
        compile_cache.write_entry(file, data)

    try:
        _timed(store)
    except Unkeyable:
        raise
    except Exception as e:  # noqa: BLE001 - not serializable: the program runs as the function
        raise Unkeyable(f"its executable cannot be stored: {type(e).__name__}: {str(e)[:200]}") from e
    return _Program(compiled, box["tree"], box["mask"], box["static"], file)


def _prepare(t: _Target, split: _Split, avals: tuple, platform: str):
    """The program of a call not seen in this process: read from the cache, else exported and stored; None (with
    the reason counted) where it cannot be."""
    try:
        t0 = time.perf_counter()
        key = _key(t, split, avals, platform)
        file = f"{t.name[:40]}-{key[:40]}.jxp"
        jax.monitoring.record_event_duration_secs(HOST_EVENT, time.perf_counter() - t0)
        prog = _timed(_load, file, key)
        if prog is not None:
            compile_cache.count("loaded")
            return prog
        prog = _export(t, split, avals, file, key)
        compile_cache.count("exported")
        return prog
    except Unkeyable as e:
        compile_cache.count("plain", str(e))
        return None
    except Exception as e:  # noqa: BLE001 - never the user's error: the plain call repeats a genuine one
        compile_cache.count("plain", f"{type(e).__name__}: {str(e)[:200]}")
        return None


# ----------------------------------------------------------------------------------------------- the wrapper
@functools.cache
def _serializable() -> bool:
    return importlib.util.find_spec("flatbuffers") is not None


def exportable(fn: Callable) -> Callable:
    """`fn` (a `jax.jit` or `equinox.filter_jit` function, or one of `jaxci.runtime._lazy`'s) called through exported
    programs (see the module docstring); the same arguments, the same results."""
    built = getattr(fn, "built", None)
    resolved: list[_Target] = []
    memo: collections.OrderedDict = collections.OrderedDict()
    refused: set[str] = set()
    lock = threading.Lock()

    def plain(why: str, args, kwargs):
        with lock:
            first = why not in refused
            refused.add(why)
        if first:
            compile_cache.count("plain", why)
        return fn(*args, **kwargs)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if compile_cache.exported_dir() is None:
            return fn(*args, **kwargs)
        if not resolved:
            resolved.append(_Target(built() if built is not None else fn))
        t = resolved[0]
        try:
            if t.kind is None:
                raise Unkeyable(t.why)
            if not _serializable():
                raise Unkeyable("the flatbuffers package (jax.export's serialization) is not installed")
            split = t.split(args, kwargs)
            avals, platform = _avals(split)
            mkey = (split.treedef, split.static, split.fixed(), avals, platform, trace_context())
            hash(mkey)
        except _Nested:
            return fn(*args, **kwargs)
        except Exception as e:  # noqa: BLE001 - Unkeyable, or unhashable static values: as jit would say
            return plain(str(e) if isinstance(e, Unkeyable) else f"{type(e).__name__}: {e}", args, kwargs)
        with lock:
            prog = memo.get(mkey, False)
            if prog is not False:
                memo.move_to_end(mkey)
        if prog is False:
            prog = _prepare(t, split, avals, platform)
            with lock:
                memo[mkey] = prog
                while len(memo) > MEMORY:
                    memo.popitem(last=False)
        if prog is None:
            return fn(*args, **kwargs)
        if not prog.fresh:
            return prog(split.dyn())
        try:  # its first call compiles it (from the persistent cache): a program that fails is not used again
            out = jax.block_until_ready(prog(split.dyn()))  # (an error of the run itself comes when it ends)
        except Exception as e:  # noqa: BLE001 - the plain call repeats a genuine error
            compile_cache.discard(prog.entry, f"{type(e).__name__}: {str(e)[:200]}")
            compile_cache.count("plain", "an exported program failed")
            with lock:
                memo[mkey] = None
            return fn(*args, **kwargs)
        prog.fresh = False
        return out

    return call
