"""`jaxci.experiments.results`: the output folder of `jaxci.experiments.runner.run_experiment`, written so that no data
is lost.

Rules (`stage` checks them before anything runs; a refusal is a `ConfigError` and nothing is written):

- A folder that does not exist is created. An existing folder needs ``force``, and is replaced only if it is a
  jaxci results folder holding nothing jaxci did not write: its marker file `MARKER` (``.jaxci-results``, a
  small JSON written into every results folder) lists every file and folder of it. A folder without the marker
  is never replaced, whatever its files are called; an empty folder may be used. It must not be, or hold, the
  current folder or an input of the experiment (its config, its mesh files and every file read through them:
  `jaxci.io.input_paths`; by path and by device and inode, so a hard link counts).
- The new results are written into a hidden temporary sibling folder (``.jaxci-tmp-<pid>-<name>.*``,
  `jaxci.io._place.make_temporary`; every file via a temporary file and `os.replace`), synced to the disk and
  moved into place at the end (`Staged.commit`): earlier results are replaced only by a complete run, and in one
  step (``renameat2(RENAME_EXCHANGE)`` swaps the two folders), so that even a SIGKILL leaves DIR holding the
  earlier results or the new ones, whole; the earlier ones, swapped out to the temporary name, are then removed
  (by the next run in that folder if the process was killed first: `jaxci.io._place.remove_stale`). Where the
  system cannot swap two folders, the earlier results are first moved aside (``.jaxci-old-<name>.*``, never
  removed by a later run), and a SIGKILL between the two renames leaves them there. A partial run (interrupted)
  or one where every run failed goes into the folder itself if it did not exist or was empty, else beside it,
  into the first free ``<name>.partial-N`` or ``<name>.failed-N`` (N = 1, 2, ...): the earlier results stay as
  they were.
- The checks hold at the moment of the move, not only at the start: the new folder is renamed without replacing
  anything (`jaxci.io._place.rename_noreplace`, so not even an empty folder made meanwhile), and a folder that is
  replaced is checked again (the same folder, by device and inode, still holding only what jaxci wrote and no
  input) before and after it is swapped out (swapped back if it changed), and only then removed. A folder that
  appeared, or changed, while the experiment ran is left as it is and the results go beside it,
  ``<name>.new-N`` (`Staged.taken` says why).
- `uninterrupted` holds off a `KeyboardInterrupt` of the jaxci command's signal handler until the renames
  that swap a folder are done (the handler asks `defer_interrupt`); this module installs no signal handler.

Files and folders get the permissions of the process umask (``0o666``/``0o777`` masked), like any file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import os
import shutil
import tempfile
from pathlib import Path

from ..errors import ConfigError
from ..io._paths import os_reason
from ..io._place import (
    TEMP_PREFIX,
    Temporary,
    exchange,
    identity,
    make_temporary,
    rename_noreplace,
    same_inode,
    sync_folder,
    sync_tree,
)

#: The marker file of a results folder: JSON ``{"jaxci_results": 1, "jaxci": version, "partial": bool,
#: "entries": [relative paths, folders ending in "/"]}``.
MARKER = ".jaxci-results"

@dataclasses.dataclass
class Staged:
    """An output folder checked by `stage`: `out` as given, the temporary folder `tmp` the results are written
    into, `earlier` (whether `out` holds earlier results, kept unless the new run is complete), `ident` (device
    and inode of `out` when it was checked; None when it did not exist), `inputs` (the identities of the
    experiment's input files) and, once `commit` is done, `committed` (where the results went) and `taken` (why
    they are not in `out` although the run was complete: it appeared or changed meanwhile; else None)."""

    out: Path
    temporary: Temporary
    earlier: bool
    ident: tuple[int, int, int] | None = None
    inputs: frozenset = frozenset()
    committed: Path | None = None
    taken: str | None = None

    @property
    def tmp(self) -> Path:
        return self.temporary.path

    def commit(self, *, complete: bool, partial: bool, inputs=()) -> Path:
        """Write the marker, then move `tmp` into place: onto `out` when the run is `complete` or `out` held no
        earlier results, else to the first free sibling ``<out>.partial-N`` (`partial`) or ``<out>.failed-N``;
        to ``<out>.new-N`` when `out` is no longer what `stage` checked (`taken`). `inputs`: more input files
        known by now (read through the meshes), never removed with `out`. Returns where the results went (also
        set as `committed`)."""
        # an interrupted atomic write's temporary file or folder
        for p in [*self.tmp.rglob(".*.tmp"), *self.tmp.rglob(f"{TEMP_PREFIX}*")]:
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            elif p.exists():
                p.unlink(missing_ok=True)
        write_marker(self.tmp, partial=partial)
        os.chmod(self.tmp, 0o777 & ~_umask())
        sync_tree(self.tmp)  # every file on the disk before the folder is renamed into place
        try:
            with uninterrupted():
                self._move(complete, partial, inputs)
        finally:
            self.temporary.release()
        sync_folder(self.out.absolute().parent)
        return self.committed

    def _move(self, complete: bool, partial: bool, inputs) -> None:
        if complete or not self.earlier:
            try:
                _put_in_place(self.tmp, self.out, self.ident, self.inputs | _identities(inputs))
                self.committed = self.out
            except _NotOurs as e:
                self.taken = str(e)
                self.committed = _move_beside(self.tmp, self.out, "new")
        else:
            self.committed = _move_beside(self.tmp, self.out, "partial" if partial else "failed")

    def discard(self) -> None:
        """Remove the temporary folder (nothing was committed)."""
        if self.committed is None:
            self.temporary.remove()


def stage(out: str | os.PathLike, key: str, force: bool, inputs=()) -> Staged:
    """Check the output folder `out` (named `key` in messages: ``--out`` or the config line) against the rules
    of this module and make the temporary sibling folder; `inputs` are the experiment's input files. Raises
    `ConfigError` (one sentence, "nothing was written") when `out` may not be used."""
    out = Path(out)
    earlier = False
    ids = _identities(inputs)
    try:
        ident = identity(out)
    except OSError as e:
        raise ConfigError(f"{key}: cannot write {out} ({os_reason(e)}); nothing was written") from None
    if ident is not None:
        if not out.is_dir():
            raise ConfigError(f"{key}: {out} exists and is not a folder (nothing was written)")
        if out.is_symlink():
            raise ConfigError(f"{key}: {out} is a symbolic link to a folder; --force replaces only a folder itself "
                              f"(nothing was written); give the folder's own path")
        if not force:
            raise ConfigError(f"{key}: {out} exists; pass --force to replace it (nothing was written)")
        _check_replaceable(out, key, inputs, ids)
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
        temporary = make_temporary(parent, out.absolute().name or "results")
    except OSError as e:
        for c in created:
            with contextlib.suppress(OSError):
                c.rmdir()
        raise ConfigError(f"{key}: cannot write {out} ({e.strerror or e}); nothing was written") from None
    return Staged(out, temporary, earlier, ident, ids)


def _within(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _check_replaceable(out: Path, key: str, inputs, ids: frozenset) -> None:
    real = out.resolve()
    if _within(Path.cwd().resolve(), real):
        raise ConfigError(f"{key}: {out} is or holds the current folder; refusing to replace it even with --force "
                          f"(nothing was written); choose another folder")
    for p in inputs:
        if _within(Path(p).resolve(), real):
            raise ConfigError(f"{key}: {out} holds {p}, an input of this experiment; refusing to replace it even "
                              f"with --force (nothing was written)")
    held = _input_inside(out, ids)
    if held is not None:
        raise ConfigError(f"{key}: {out} holds {held}, which is an input of this experiment (a link to it); "
                          f"refusing to replace it even with --force (nothing was written)")
    foreign = foreign_entries(out)
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise ConfigError(f"{key}: {out} is not a jaxci results folder (it holds {shown}, not written by jaxci; "
                          f"no {MARKER} marker lists them); --force only replaces earlier results, so nothing was "
                          f"written; choose a new or empty folder")


def foreign_entries(folder: Path, limit: int = 4) -> list[str]:
    """Up to `limit` entries of `folder` (relative paths, folders ending in ``/``) that jaxci did not write:
    those its marker (`MARKER`) does not list; every top-level entry of a folder without a readable marker."""
    listed = None
    marker = folder / MARKER
    if marker.is_file() and not marker.is_symlink():
        try:
            data = json.loads(marker.read_text())
            listed = set(data["entries"]) if data.get("jaxci_results") == 1 else None
        except (OSError, ValueError, KeyError, TypeError):
            listed = None
    if listed is None:
        return sorted(p.name + "/" * (p.is_dir() and not p.is_symlink()) for p in folder.iterdir())[:limit]
    return list(itertools.islice((e for e in _walk(folder) if e not in listed and e != MARKER), limit))


def _identities(paths) -> frozenset:
    """(device, inode) of each of `paths` that exists (links followed)."""
    out = set()
    for p in paths:
        try:
            st = os.stat(p)
        except (OSError, ValueError):
            continue
        out.add((st.st_dev, st.st_ino))
    return frozenset(out)


def _input_inside(folder: Path, ids: frozenset) -> str | None:
    """The first entry under `folder` (relative path; links not followed) that is one of the files `ids`."""
    if not ids:
        return None
    for root, _, files in os.walk(folder):
        for f in files:
            p = os.path.join(root, f)
            with contextlib.suppress(OSError):
                st = os.lstat(p)
                if (st.st_dev, st.st_ino) in ids:
                    return os.path.relpath(p, folder)
    return None


class _NotOurs(Exception):
    """The output folder is not what `stage` checked any more (the message says what it is now)."""


def _not_ours(folder: Path, ident: tuple[int, int, int], ids: frozenset, shown: Path) -> str | None:
    """Why the folder at `folder` may not be replaced (not the folder `ident` checked by `stage`, a file jaxci did
    not write, an input of the experiment), or None."""
    if not same_inode(identity(folder), ident):
        return f"{shown} was replaced by another folder while the experiment ran"
    if foreign := foreign_entries(folder, limit=1):
        return f"{shown} got {foreign[0]}, which jaxci did not write, while the experiment ran"
    if (held := _input_inside(folder, ids)) is not None:
        return f"{shown} holds {held}, an input of this experiment"
    return None


def _put_in_place(tmp: Path, out: Path, ident: tuple[int, int, int] | None, ids: frozenset) -> None:
    """Rename `tmp` to `out`. `ident` None: nothing may be at `out`. Else `out` (that folder, checked by `stage`)
    is checked again (the same folder, only what jaxci wrote, no input), swapped with `tmp` in one step and
    checked once more where it went (swapped back if it changed in between), then removed; where the system
    cannot swap two folders, moved aside, checked, and put back if anything fails. `_NotOurs` when `out` is not
    what was checked."""
    shown, out = out, out.absolute()
    if ident is None:
        try:
            rename_noreplace(tmp, out)
        except FileExistsError:
            raise _NotOurs(f"{shown} appeared while the experiment ran") from None
        return
    now = identity(out)
    if now is None:  # removed meanwhile: nothing to replace, and nothing may appear
        return _put_in_place(tmp, shown, None, ids)
    why = _not_ours(out, ident, ids, shown)
    if why is not None:
        raise _NotOurs(why)
    try:
        swapped = exchange(tmp, out)
    except FileNotFoundError:  # removed meanwhile: nothing to replace, and nothing may appear
        return _put_in_place(tmp, shown, None, ids)
    if swapped:  # the earlier results are at tmp's name now
        why = _not_ours(tmp, ident, ids, shown)
        if why is not None:
            exchange(tmp, out)
            raise _NotOurs(why)
        shutil.rmtree(tmp, ignore_errors=True)
        return
    _move_aside_and_put_in_place(tmp, out, shown, ident, ids)


def _move_aside_and_put_in_place(tmp: Path, out: Path, shown: Path, ident: tuple[int, int, int],
                                 ids: frozenset) -> None:
    """`_put_in_place` where two folders cannot be swapped in one step: `out` moved aside into
    ``.jaxci-old-<name>.*`` (a name that no later run removes), checked, and removed once `tmp` is in place."""
    trash = Path(tempfile.mkdtemp(prefix=f".jaxci-old-{out.name}.", dir=out.parent))
    old = trash / "old"
    try:
        os.rename(out, old)
    except FileNotFoundError:  # removed meanwhile: nothing to replace, and nothing may appear
        trash.rmdir()
        return _put_in_place(tmp, shown, None, ids)
    except OSError:
        trash.rmdir()
        raise
    why = _not_ours(old, ident, ids, shown)
    if why is None:
        try:
            rename_noreplace(tmp, out)
        except FileExistsError:
            why = f"{shown} appeared while the experiment ran"
        except BaseException:
            _put_back(old, out, trash)
            raise
        else:
            shutil.rmtree(trash, ignore_errors=True)
            return
    kept = _put_back(old, out, trash)
    raise _NotOurs(why + ("" if kept == out else f" (the folder that was there is now {kept})"))


def _put_back(old: Path, out: Path, trash: Path) -> Path:
    """Move the folder `old` (moved aside from `out`) back to `out`, or beside it if `out` is taken; returns
    where it is."""
    try:
        rename_noreplace(old, out)
        where = out
    except FileExistsError:
        where = _move_beside(old, out, "earlier")
    with contextlib.suppress(OSError):
        trash.rmdir()
    return where


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


def _move_beside(tmp: Path, out: Path, tag: str) -> Path:
    """Rename `tmp` to the first free ``<out>.<tag>-N`` beside `out` (never onto anything, not even an empty
    folder); returns it (spelled like `out`)."""
    base = out if out.name not in ("", ".", "..") else out.absolute()
    n = 1
    while True:
        dest = base.with_name(f"{base.name}.{tag}-{n}")
        if not os.path.lexists(dest):
            try:
                rename_noreplace(tmp, dest)
                return dest
            except FileExistsError:  # taken meanwhile: try the next name
                pass
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
