"""JAX on first use: the numpy path of a small mesh never imports it.

``import jax`` (with equinox) is 0.4-0.5 s of a 1-2 s ``jaxci smooth`` on a mesh of a few thousand hexahedra,
which runs entirely in numpy and C (`jaxci.optim.host`, `jaxci.native`). The modules on that path (mesh model,
boundary, constraints, quality report, untangling set-up) also hold the JAX kernels of the compiled path, so they
name JAX through this module:

- `jax`, `jnp`: stand-ins for the modules that import them on the first attribute access (so a function
  that uses ``jnp.where`` imports JAX when it runs, not when its module is imported);
- `jit`, `filter_jit`: `jax.jit` / `equinox.filter_jit` built on the first call (or by the wrapper's
  ``built()``, which returns it);
- `pytree_dataclass`: a frozen dataclass that is a JAX pytree (array fields are leaves, the fields named
  `static` are auxiliary data, as `equinox.field(static=True)`), registered with JAX when JAX is imported,
  whoever imports it (`when_imported`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import importlib.abc
import sys
import threading
from collections.abc import Callable


class LazyModule:
    """A stand-in for the module `name`, imported on the first attribute access."""

    def __init__(self, name: str):
        self._name = name

    def __getattr__(self, attr: str):
        return getattr(importlib.import_module(self._name), attr)

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


jax = LazyModule("jax")
jnp = LazyModule("jax.numpy")


def loaded() -> bool:
    """Whether JAX is imported (a function may then use it at no import cost)."""
    return "jax" in sys.modules


def compute_platform() -> str:
    """The platform JAX computes on here: that of the default device a `jax.default_device` context sets (a GPU
    machine asked to run on its CPU), else JAX's default backend's (``"cpu"``, ``"gpu"``, ``"tpu"``)."""
    return getattr(jax.config.jax_default_device, "platform", None) or jax.default_backend()


def is_jax_array(a) -> bool:
    """Whether `a` is a JAX array (False, without importing JAX, while JAX is not imported)."""
    return loaded() and isinstance(a, sys.modules["jax"].Array)


def enable_x64(needed: bool = True):
    """`jax.enable_x64(True)` where the block uses JAX (`needed`) or JAX is imported anyway; else a null context
    (a block on the numpy path, which must not import JAX for its settings)."""
    if needed or loaded():
        return jax.enable_x64(True)
    return contextlib.nullcontext()


def jit(fn: Callable | None = None, **kwargs):
    """`jax.jit(fn, **kwargs)`, built on the first call (usable as ``@jit`` or ``@jit(static_argnums=...)``)."""
    return _deferred("jax", "jit", fn, kwargs)


def filter_jit(fn: Callable | None = None, **kwargs):
    """`equinox.filter_jit(fn, **kwargs)`, built on the first call."""
    return _deferred("equinox", "filter_jit", fn, kwargs)


def _deferred(module: str, name: str, fn, kwargs):
    if fn is None:
        return lambda f: _deferred(module, name, f, kwargs)
    built = []

    def build():
        if not built:
            built.append(getattr(importlib.import_module(module), name)(fn, **kwargs))
        return built[0]

    @functools.wraps(fn)
    def wrapper(*args, **kw):
        return (built[0] if built else build())(*args, **kw)

    wrapper.built = build  # the jitted function itself (`jaxci.runtime._export` reads its options)
    return wrapper


# ---------------------------------------------------------------------------------------------- post-import hooks
_hooks: dict[str, list[Callable[[], None]]] = {}
_lock = threading.Lock()


class _Finder(importlib.abc.MetaPathFinder):
    """Runs the hooks of `_hooks` once their module has executed."""

    def find_spec(self, fullname, path, target=None):
        if fullname not in _hooks:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None and spec.loader is not None and hasattr(spec.loader, "exec_module"):
                spec.loader = _Loader(spec.loader, fullname)
                return spec
        return None


class _Loader(importlib.abc.Loader):
    def __init__(self, loader, name: str):
        self._loader, self._name = loader, name

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module):
        self._loader.exec_module(module)
        _run_hooks(self._name)

    def __getattr__(self, attr):  # get_resource_reader, is_package, ... of the real loader
        return getattr(self._loader, attr)


_finder = _Finder()


def _run_hooks(name: str) -> None:
    with _lock:
        hooks = _hooks.pop(name, [])
        if not _hooks and _finder in sys.meta_path:
            sys.meta_path.remove(_finder)
    for hook in hooks:
        hook()


def when_imported(name: str, hook: Callable[[], None]) -> None:
    """Call `hook()` once module `name` is imported: now if it is, else right after its import."""
    with _lock:
        if name not in sys.modules:
            _hooks.setdefault(name, []).append(hook)
            if _finder not in sys.meta_path:
                sys.meta_path.insert(0, _finder)
            return
    hook()


def pytree_dataclass(cls=None, *, static: tuple[str, ...] = ()):
    """Make `cls` a frozen dataclass and, once JAX is imported, a JAX pytree: the fields named in `static` are
    auxiliary data (hashable; part of a jitted function's cache key), every other field a child."""
    if cls is None:
        return lambda c: pytree_dataclass(c, static=static)
    cls = dataclasses.dataclass(frozen=True, eq=False)(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    data = [n for n in names if n not in static]

    def register():
        import jax

        jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=list(static))

    when_imported("jax", register)
    return cls
