"""Compilation once per machine: where the JAX engine keeps its compiled programs between processes.

One folder holds them: ``$JAXCI_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxci/jax``, else ``~/.cache/jaxci/jax``
(`directory`). ``JAXCI_CACHE_DIR=`` (set, empty) turns the cache off: every process then traces and compiles
its programs anew. It holds two things:

- JAX's persistent compilation cache (XLA executables, keyed by the lowered program), every program cached
  however quickly it compiled and however small (``jax_persistent_cache_min_compile_time_secs`` 0,
  ``jax_persistent_cache_min_entry_size_bytes`` -1);
- ``exported/``: the JAX engine's compiled entry points as serialized `jax.export` programs (`jaxci.runtime._export`),
  so that a later process skips tracing and lowering them, which the persistent cache alone does not.

`enable` sets it up when the JAX engine first uploads an array or calls a compiled program
(`jaxci.runtime.transfer`), not when jaxci is imported: a program that imports jaxci and never runs the JAX engine keeps
JAX's settings as they are. Where the user set JAX's own cache folder (``jax_compilation_cache_dir``), JAX's
settings are left alone and only ``exported/`` goes into jaxci's folder. The ``jaxci`` command calls `enable`
as soon as it imports JAX.

Like JAX's, the cache is trusted: whoever can write into the folder can make a later run execute their code
(its entries are pickles and executables). It is made readable by its owner only.

Entries are written atomically (a temporary file renamed into place: concurrent processes never read half an
entry); an entry that cannot be read (truncated, corrupt, from another format) is ignored and written again,
never an error. `stats` counts what this process read, wrote and compiled without the cache.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import pickle
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

from ._lazy import jax

#: The environment variable that names the folder; set and empty: no cache.
ENV = "JAXCI_CACHE_DIR"
#: The sub-folder of the exported programs.
EXPORTED = "exported"

log = logging.getLogger("jaxci.runtime.compile_cache")

_lock = threading.Lock()
_state: dict = {"done": False, "dir": None}
_stats: collections.Counter = collections.Counter()
_reasons: collections.Counter = collections.Counter()
#: Custom-call targets jaxci registers with XLA itself: name -> a function that registers it (True where it is).
_targets: dict[str, Callable[[], bool]] = {}


def directory(env: dict | None = None) -> Path | None:
    """The cache folder `env` (default ``os.environ``) asks for: ``JAXCI_CACHE_DIR`` (empty: None, no cache),
    else ``$XDG_CACHE_HOME/jaxci/jax`` (an absolute ``XDG_CACHE_HOME`` only, as the XDG specification says), else
    ``~/.cache/jaxci/jax``."""
    env = os.environ if env is None else env
    if ENV in env:
        return Path(env[ENV]).expanduser() if env[ENV] else None
    xdg = env.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path("~").expanduser() / ".cache"
    return base / "jaxci" / "jax"


def enable() -> Path | None:
    """Set up the cache once per process (later calls return at once): make the folder (owner only) and point
    JAX's persistent compilation cache at it, every program cached (no time or size threshold), unless the user
    set JAX's cache folder already. Returns the folder, or None where the cache is off (``JAXCI_CACHE_DIR=``) or
    the folder cannot be made (a read-only home: then nothing is cached, nothing fails)."""
    if _state["done"]:
        return _state["dir"]
    with _lock:
        if _state["done"]:
            return _state["dir"]
        folder = directory()
        if folder is not None:
            try:
                folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            except OSError as e:
                log.debug("no compilation cache: %s", e)
                folder = None
        if folder is not None and not jax.config.jax_compilation_cache_dir:
            jax.config.update("jax_compilation_cache_dir", str(folder))
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
            jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # -1: no size limit, no override
        _state.update(done=True, dir=folder)
        return folder


@contextlib.contextmanager
def exporting_to(folder: str | os.PathLike | None):
    """Within the block, exported programs are read from and written to ``folder/exported`` (None: none), as if
    `enable` had chosen `folder`; JAX's own cache settings are not touched (tests, benchmarks)."""
    with _lock:
        saved = dict(_state)
        _state.update(done=True, dir=None if folder is None else Path(folder))
    try:
        yield
    finally:
        with _lock:
            _state.update(saved)


def exported_dir() -> Path | None:
    """The folder of the exported programs (`enable` first), or None where the cache is off."""
    folder = enable()
    return None if folder is None else folder / EXPORTED


def register_target(name: str, ensure: Callable[[], bool]) -> None:
    """Declare an XLA custom-call target that jaxci registers itself (`jaxci.metrics.native_grad`): programs that
    call it may be exported, and before a later process loads one, ``ensure()`` registers the target (an
    exported program is compiled without tracing the code that would have registered it)."""
    _targets[name] = ensure


def own_targets() -> tuple[str, ...]:
    """The custom-call targets of `register_target`."""
    return tuple(_targets)


def ensure_target(name: str) -> bool:
    """Register custom-call target `name` with XLA (`register_target`); False where it is not jaxci's or its
    registration refuses."""
    ensure = _targets.get(name)
    try:
        return bool(ensure is not None and ensure())
    except Exception as e:  # noqa: BLE001 - a handler that cannot be registered: the program is traced instead
        log.debug("custom call %s not registered: %s", name, e)
        return False


def read_entry(name: str) -> dict | None:
    """The entry file `name` of ``exported/`` unpickled, or None where there is none, or it cannot be read (it is
    then removed: the caller writes it again)."""
    folder = exported_dir()
    if folder is None:
        return None
    path = folder / name
    try:
        with open(path, "rb") as f:
            entry = pickle.load(f)
        if not isinstance(entry, dict):
            raise ValueError(f"a {type(entry).__name__}, not an entry")
        return entry
    except FileNotFoundError:
        return None
    except Exception as e:  # noqa: BLE001 - any unreadable entry is a miss
        discard(name, f"unreadable: {e}")
        return None


def write_entry(name: str, data: bytes) -> bool:
    """Write `data` as entry file `name` of ``exported/`` atomically (a temporary file in the same folder, renamed
    into place); False, and nothing left behind, where it cannot be written."""
    folder = exported_dir()
    if folder is None:
        return False
    tmp = None
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".part")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, folder / name)
        return True
    except OSError as e:
        log.debug("exported program %s not written: %s", name, e)
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
        return False


def discard(name: str, why: str) -> None:
    """Remove entry file `name` (unreadable, or its program would not load), counted in `stats`."""
    log.debug("exported program %s discarded: %s", name, why)
    count("discarded")
    folder = _state["dir"]
    if folder is not None:
        try:
            os.unlink(folder / EXPORTED / name)
        except OSError:
            pass


def count(what: str, reason: str | None = None) -> None:
    """Add one to `stats` entry `what` (and to the reason's count)."""
    with _lock:
        _stats[what] += 1
        if reason is not None:
            _reasons[reason] += 1


def stats() -> dict:
    """What this process did with the exported programs: ``loaded`` (read from the cache), ``exported`` (traced,
    exported and written), ``discarded`` (unreadable entries removed), ``plain`` (compiled without the cache:
    the cache off, or a call that cannot be exported) and ``reasons`` (why not, counted)."""
    with _lock:
        out = {k: _stats[k] for k in ("loaded", "exported", "discarded", "plain")}
        out["reasons"] = dict(_reasons)
        return out
