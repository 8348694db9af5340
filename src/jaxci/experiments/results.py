"""`jaxci.experiments.results`: the output folder of `jaxci.experiments.runner.run_experiment`, written so that no data
is lost.

Rules (`stage` checks them before anything runs; a refusal is a `ConfigError` and nothing is written):

- A folder that does not exist is created. An existing folder needs ``force``, and is replaced only if it is a
  jaxci results folder holding nothing jaxci did not write: its marker file `MARKER` (``.jaxci-results``, a
  small JSON written into every results folder) lists every file and folder of it (a folder written before
  markers existed is recognised by its file names: ``summary.json``, ``runs.csv``, ``meshes/*.vtu``, ...). An
  empty folder may be used too. It must not be, or hold, the current folder or an input of the experiment.
- The new results are written into a hidden temporary sibling folder (``.<name>.*.tmp``, every file via a
  temporary file and `os.replace`) and moved into place at the end (`Staged.commit`): earlier results are
  replaced only by a complete run. A partial run (interrupted) or one where every run failed goes into the
  folder itself if it did not exist or was empty, else beside it, into the first free ``<name>.partial-N`` or
  ``<name>.failed-N`` (N = 1, 2, ...): the earlier results stay as they were.
- `uninterrupted` holds off a `KeyboardInterrupt` of the jaxci command's signal handler until the two renames
  that swap a folder are done (the handler asks `defer_interrupt`); this module installs no signal handler.

Files and folders get the permissions of the process umask (``0o666``/``0o777`` masked), like any file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

from ..errors import ConfigError

#: The marker file of a results folder: JSON ``{"jaxci_results": 1, "jaxci": version, "partial": bool,
#: "entries": [relative paths, folders ending in "/"]}``.
MARKER = ".jaxci-results"

#: What a results folder written before `MARKER` existed may hold.
_LEGACY = re.compile(r"(summary\.json|history\.json|runs\.csv|report\.md|meshes/|figures/|meshes/[^/]+\.vtu"
                     r"|figures/[^/]+\.png)")


@dataclasses.dataclass
class Staged:
    """An output folder checked by `stage`: `out` as given, the temporary folder `tmp` the results are written
    into, `earlier` (whether `out` holds earlier results, kept unless the new run is complete) and, once
    `commit` is done, `committed` (where the results went)."""

    out: Path
    tmp: Path
    earlier: bool
    committed: Path | None = None

    def commit(self, *, complete: bool, partial: bool) -> Path:
        """Write the marker, then move `tmp` into place: onto `out` when the run is `complete` or `out` held no
        earlier results, else to the first free sibling ``<out>.partial-N`` (`partial`) or ``<out>.failed-N``.
        Returns where the results went (also set as `committed`)."""
        for p in list(self.tmp.rglob(".*.tmp")):  # an interrupted atomic write's temporary file or folder
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
        write_marker(self.tmp, partial=partial)
        os.chmod(self.tmp, 0o777 & ~_umask())
        with uninterrupted():
            if complete or not self.earlier:
                replace_dir(self.tmp, self.out)
                self.committed = self.out
            else:
                self.committed = _move_beside(self.tmp, self.out, "partial" if partial else "failed")
        return self.committed

    def discard(self) -> None:
        """Remove the temporary folder (nothing was committed)."""
        if self.committed is None:
            shutil.rmtree(self.tmp, ignore_errors=True)


def stage(out: str | os.PathLike, key: str, force: bool, inputs=()) -> Staged:
    """Check the output folder `out` (named `key` in messages: ``--out`` or the config line) against the rules
    of this module and make the temporary sibling folder; `inputs` are the experiment's input files. Raises
    `ConfigError` (one sentence, "nothing was written") when `out` may not be used."""
    out = Path(out)
    earlier = False
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise ConfigError(f"{key}: {out} exists and is not a folder (nothing was written)")
        if not force:
            raise ConfigError(f"{key}: {out} exists; pass --force to replace it (nothing was written)")
        _check_replaceable(out, key, inputs)
        try:
            earlier = any(out.iterdir())
        except OSError as e:
            raise ConfigError(f"{key}: cannot read {out} ({e.strerror or e}); nothing was written") from None
    parent = out.absolute().parent
    created, p = [], parent
    while not p.exists():
        created.append(p)
        p = p.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{_name(out)}.", suffix=".tmp", dir=parent))
    except OSError as e:
        for c in created:
            with contextlib.suppress(OSError):
                c.rmdir()
        raise ConfigError(f"{key}: cannot write {out} ({e.strerror or e}); nothing was written") from None
    return Staged(out, tmp, earlier)


def _name(out: Path) -> str:
    return out.absolute().name or "results"


def _within(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _check_replaceable(out: Path, key: str, inputs) -> None:
    real = out.resolve()
    if _within(Path.cwd().resolve(), real):
        raise ConfigError(f"{key}: {out} is or holds the current folder; refusing to replace it even with --force "
                          f"(nothing was written); choose another folder")
    for p in inputs:
        if _within(Path(p).resolve(), real):
            raise ConfigError(f"{key}: {out} holds {p}, an input of this experiment; refusing to replace it even "
                              f"with --force (nothing was written)")
    foreign = foreign_entries(out)
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise ConfigError(f"{key}: {out} is not a jaxci results folder (it holds {shown}, not written by jaxci); "
                          f"--force only replaces earlier results, so nothing was written; choose a new or empty "
                          f"folder")


def foreign_entries(folder: Path, limit: int = 4) -> list[str]:
    """Up to `limit` entries of `folder` (relative paths, folders ending in ``/``) that jaxci did not write:
    none for a results folder (`MARKER`), every top-level entry for a folder that is not one."""
    listed = None
    marker = folder / MARKER
    if marker.is_file():
        try:
            data = json.loads(marker.read_text())
            listed = set(data["entries"]) if data.get("jaxci_results") == 1 else None
        except (OSError, ValueError, KeyError, TypeError):
            listed = None
    elif (folder / "summary.json").is_file():
        listed = _LEGACY
    found = []
    if listed is None:
        return sorted(p.name + "/" * p.is_dir() for p in folder.iterdir())[:limit]
    for entry in _walk(folder):
        ok = _LEGACY.fullmatch(entry) if listed is _LEGACY else entry in listed
        if not ok and entry != MARKER:
            found.append(entry)
            if len(found) >= limit:
                break
    return found


def _walk(folder: Path):
    """Relative paths of everything under `folder` (folders with a trailing ``/``; symbolic links not followed)."""
    for root, dirs, files in os.walk(folder):
        rel = os.path.relpath(root, folder)
        prefix = "" if rel == "." else rel.replace(os.sep, "/") + "/"
        for d in sorted(dirs):
            yield prefix + d + "/"
        for f in sorted(files):
            yield prefix + f


def write_marker(folder: Path, *, partial: bool) -> None:
    """Write `MARKER` into `folder`, listing everything in it."""
    from .. import __version__

    entries = [e for e in _walk(folder) if e != MARKER]
    write_text(folder / MARKER, json.dumps({"jaxci_results": 1, "jaxci": __version__, "partial": partial,
                                            "entries": entries}) + "\n")


def replace_dir(tmp: Path, out: Path) -> None:
    """Rename the finished folder `tmp` onto `out`; an existing `out` is moved aside first and removed once the
    new one is in place (put back if that rename fails). Not interrupted by the jaxci command's handler."""
    out = out.absolute()
    with uninterrupted():
        if not out.exists():
            os.replace(tmp, out)
            return
        trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
        os.replace(out, trash / "old")
        try:
            os.replace(tmp, out)
        except BaseException:
            os.replace(trash / "old", out)
            trash.rmdir()
            raise
        shutil.rmtree(trash, ignore_errors=True)


def _move_beside(tmp: Path, out: Path, tag: str) -> Path:
    """Rename `tmp` to the first free ``<out>.<tag>-N`` beside `out`; returns it (spelled like `out`)."""
    base = out if out.name not in ("", ".", "..") else out.absolute()
    n = 1
    while True:
        dest = base.with_name(f"{base.name}.{tag}-{n}")
        if not (dest.exists() or dest.is_symlink()):
            try:
                os.rename(tmp, dest)
                return dest
            except OSError:  # taken meanwhile (a non-empty folder): try the next name
                if not dest.exists():
                    raise
        n += 1


def write_text(path: Path, text: str) -> None:
    """Write `text` to `path` atomically (temporary file in the same folder, then `os.replace`)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "w", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


_UMASK: list[int] = []


def _umask() -> int:
    """The process umask (read once)."""
    if not _UMASK:
        try:
            with open("/proc/self/status") as f:
                _UMASK.append(int(next(ln for ln in f if ln.startswith("Umask:")).split()[1], 8))
        except (OSError, StopIteration, ValueError):
            mask = os.umask(0o022)
            os.umask(mask)
            _UMASK.append(mask)
    return _UMASK[0]


# ---------------------------------------------------------------------------------- interrupt deferral
_shield = {"depth": 0, "pending": False}


@contextlib.contextmanager
def uninterrupted():
    """A block that a `KeyboardInterrupt` from the jaxci command's signal handler does not cut short: the
    handler asks `defer_interrupt`, and the interrupt is raised when the (outermost) block ends."""
    _shield["depth"] += 1
    try:
        yield
    finally:
        _shield["depth"] -= 1
        if _shield["depth"] == 0 and _shield["pending"]:
            _shield["pending"] = False
            raise KeyboardInterrupt


def defer_interrupt() -> bool:
    """For a signal handler (main thread): inside `uninterrupted`, note the interrupt for the end of the block
    and return True; else return False (the handler raises `KeyboardInterrupt` itself)."""
    if _shield["depth"] > 0:
        _shield["pending"] = True
        return True
    return False
