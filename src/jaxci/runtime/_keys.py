"""Keys of the JAX engine's exported programs (`jaxci.runtime._export`): texts that are equal in two processes exactly
when tracing would give the same program.

`Keyer` writes a value as a deterministic text, or raises `Unkeyable`: the simple Python values, containers,
dtypes, enums, small numpy arrays (by their bytes), functions (module, name, bytecode, constants, closures,
defaults; the source of a module outside jaxci and the versioned packages), `functools.partial`, jitted
functions, dataclasses (equinox modules are) and the instances of jaxci's, equinox's, optimistix's and lineax's
own classes (by their attributes). Anything else (an open file, a device array, a class of another library)
cannot be keyed, and its program is not exported. `environment` is what the process adds: the ``JAXCI_*``
variables, the CPUs it may use, the versions of Python and of the traced packages, a hash of jaxci's files.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import os
import sys
import types
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path

import numpy as np

from ._lazy import jax
from .process import schedulable_cpus

#: Packages whose versions are part of the key (their code is traced).
VERSIONED = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy")
#: Modules of pure-Python classes whose instances are keyed by their attributes (their code is versioned or hashed).
KEYED_BY_STATE = ("jaxci.", "equinox.", "optimistix.", "lineax.")
#: Types written as their repr.
SIMPLE = (type(None), type(Ellipsis), bool, int, float, complex, str, bytes)
#: Largest numpy array keyed by its contents (a static array is a constant of the program).
MAX_STATIC_BYTES = 1 << 16
#: The environment variable of the cache folder: not part of any key (moving the cache keeps its entries).
_CACHE_ENV = "JAXCI_CACHE_DIR"


class Unkeyable(Exception):
    """A call whose program cannot be keyed or exported; the message says why."""


def sha(data: bytes) -> str:
    """The SHA-256 of `data`, in hexadecimal."""
    return hashlib.sha256(data).hexdigest()


def qualified(t) -> str:
    """``module.qualname`` of a class or function."""
    return f"{getattr(t, '__module__', '?')}.{getattr(t, '__qualname__', getattr(t, '__name__', '?'))}"


@functools.cache
def _file_hash(path: str) -> str:
    with open(path, "rb") as f:
        return sha(f.read())


@functools.cache
def package_hash() -> str:
    """A hash of jaxci's own files (sources and the C extension): any change to them makes new keys."""
    root = Path(__file__).resolve().parents[1]  # the jaxci package (this module lives in jaxci/runtime/)
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".so", ".pyd", ".c") and p.is_file()):
        h.update(str(path.relative_to(root)).encode() + b"\0" + _file_hash(str(path)).encode())
    return h.hexdigest()


@functools.cache
def versions() -> str:
    """Python's version and those of `VERSIONED`."""
    out = [sys.version]
    for pkg in VERSIONED:
        try:
            out.append(f"{pkg}={metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            out.append(f"{pkg}=-")
    return ";".join(out)


def environment() -> str:
    """What the process adds to every key: the ``JAXCI_*`` variables (not the cache folder's), the CPUs it may use
    (the C kernel's threads are a constant of its custom call), `versions` and `package_hash`."""
    env = sorted((k, v) for k, v in os.environ.items() if k.startswith("JAXCI_") and k != _CACHE_ENV)
    return repr((env, schedulable_cpus(), versions(), package_hash()))


def state(obj) -> list[tuple[str, object]]:
    """The attributes of `obj`, sorted by name: its ``__dict__`` and every ``__slots__`` entry."""
    out = dict(getattr(obj, "__dict__", {}))
    for cls in type(obj).__mro__:
        for slot in getattr(cls, "__slots__", ()):
            if slot not in ("__dict__", "__weakref__") and hasattr(obj, slot):
                out[slot] = getattr(obj, slot)
    return sorted(out.items())


def _module_hash(module: str) -> str:
    """The hash of the source of `module` where neither jaxci's hash nor a version covers it ("" where one does)."""
    if module.partition(".")[0] in ("jaxci", *VERSIONED, "builtins"):
        return ""
    path = getattr(sys.modules.get(module), "__file__", None)
    if not path:
        raise Unkeyable(f"a function of {module}, which has no source file")
    return _file_hash(path)


class Keyer:
    """A deterministic text for a value, the same in every process for equal values, or `Unkeyable`."""

    def __init__(self):
        self._active: set[int] = set()

    def __call__(self, obj, depth: int = 0) -> str:
        if depth > 64:
            raise Unkeyable("values nested too deep")
        t, d = type(obj), depth + 1
        if t in SIMPLE:
            return f"{t.__name__}:{obj!r}"
        if isinstance(obj, (tuple, list)):  # a named tuple by its type and values (it has no state of its own)
            name = t.__name__ if t in (tuple, list) else qualified(t)
            return f"{name}({','.join(self(o, d) for o in obj)})"
        if isinstance(obj, (set, frozenset)):
            return f"set({','.join(sorted(self(o, d) for o in obj))})"
        if isinstance(obj, Mapping):
            return f"{qualified(t)}{{{','.join(sorted(f'{self(k, d)}:{self(v, d)}' for k, v in obj.items()))}}}"
        if isinstance(obj, type):
            return f"type:{qualified(obj)}"
        if isinstance(obj, enum.Enum):
            return f"enum:{qualified(t)}.{obj.name}"
        if isinstance(obj, np.dtype):
            return f"dtype:{obj}:{obj.str}"
        if isinstance(obj, (np.ndarray, np.generic)):
            if obj.dtype == object or obj.nbytes > MAX_STATIC_BYTES:
                raise Unkeyable(f"a static numpy array of {obj.nbytes} bytes")
            return f"ndarray:{obj.dtype}:{obj.shape}:{sha(np.ascontiguousarray(obj).tobytes())}"
        if isinstance(obj, jax.Array):
            raise Unkeyable("a device array in a static argument or a closure")
        if isinstance(obj, jax.Device):
            return f"device:{obj.platform}:{obj.device_kind}:{obj.id}"
        return self._callable(obj, d) if callable(obj) and not dataclasses.is_dataclass(obj) else self._object(obj, d)

    def _callable(self, obj, depth: int) -> str:
        if isinstance(obj, functools.partial):
            return f"partial({self(obj.func, depth)};{self(obj.args, depth)};{self(obj.keywords, depth)})"
        if isinstance(obj, types.FunctionType):
            return self._function(obj, depth)
        if isinstance(obj, types.MethodType):
            return f"method({self(obj.__func__, depth)};{self(obj.__self__, depth)})"
        if isinstance(obj, (types.BuiltinFunctionType, np.ufunc)):
            owner = getattr(obj, "__self__", None)
            if owner is not None and not isinstance(owner, types.ModuleType):
                raise Unkeyable(f"a bound built-in method {obj!r}")
            return f"builtin:{getattr(obj, '__module__', None)}.{getattr(obj, '__qualname__', obj.__name__)}"
        if hasattr(obj, "_jit_info") and hasattr(obj, "__wrapped__"):  # a jax.jit function
            info = obj._jit_info
            return f"jit({self(obj.__wrapped__, depth)};{info.static_argnums};{info.static_argnames})"
        return self._object(obj, depth)

    def _object(self, obj, depth: int) -> str:
        t = type(obj)
        if dataclasses.is_dataclass(obj):
            fields = ",".join(f"{f.name}={self(getattr(obj, f.name), depth)}" for f in dataclasses.fields(obj))
            return f"{qualified(t)}({fields})"
        if t.__module__.startswith(KEYED_BY_STATE) or qualified(t) == "jax._src.core.AxisEnv":
            return f"{qualified(t)}{{{','.join(f'{k}={self(v, depth)}' for k, v in state(obj))}}}"
        raise Unkeyable(f"a static value of type {qualified(t)}")

    def _function(self, f, depth: int) -> str:
        if id(f) in self._active:  # a closure that refers to itself
            return f"recursive:{f.__qualname__}"
        self._active.add(id(f))
        try:
            module = f.__module__ or ""
            cells = []
            for cell in f.__closure__ or ():
                try:
                    cells.append(self(cell.cell_contents, depth))
                except ValueError:  # an empty cell
                    cells.append("empty")
            return (f"fn:{module}.{f.__qualname__}:{self._code(f.__code__, depth)}:{_module_hash(module)}:"
                    f"({','.join(cells)}):{self(f.__defaults__, depth)}:{self(f.__kwdefaults__, depth)}")
        finally:
            self._active.discard(id(f))

    def _code(self, code: types.CodeType, depth: int) -> str:
        consts = [self._code(c, depth) if isinstance(c, types.CodeType) else self(c, depth) for c in code.co_consts]
        return sha(code.co_code + repr((code.co_names, code.co_varnames, consts)).encode())


def treedef_key(treedef, keyer: Keyer) -> str:
    """The node types and node data of `treedef` (a custom node's static fields, a dict's keys), keyed."""
    data = treedef.node_data()
    if data is None:
        return "*"
    kind, aux = data
    return f"{qualified(kind)}[{keyer(aux)}]({','.join(treedef_key(c, keyer) for c in treedef.children())})"


def trace_context() -> tuple:
    """JAX's trace context: the configuration that tracing depends on (x64, default device, promotion, ...);
    hashable, what `jax.jit` keys its own cache with."""
    from jax._src import config

    return config.trace_context()


def trace_context_key(context: tuple, keyer: Keyer) -> str:
    """`context` keyed, each value beside its option's name."""
    from jax._src import config

    names = config.trace_context_names() if hasattr(config, "trace_context_names") else ()
    return keyer(tuple(zip(names, context, strict=False)) if names else context)
