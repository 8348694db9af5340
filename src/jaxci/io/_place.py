"""Putting finished files and folders in place without replacing what is not ours, even when it appears late.

A check at the start of a command ("OUT does not exist", "OUT is the file we may replace") holds only until the
final rename: a file created at OUT while jaxci works would be replaced by `os.replace`, and `os.rename` of a
folder onto an EMPTY folder succeeds on Linux. So the final move checks again, atomically where the system allows:

- `rename_noreplace` (no file or folder may be at the target): ``renameat2(RENAME_NOREPLACE)`` (Linux 3.15+, most
  local file systems); else, for a file, a hard link to the target name (which fails if the name is taken) and
  the removal of the temporary name; for a folder, an exclusive ``mkdir`` of the target and a rename onto that
  empty folder of ours. `FileExistsError` when the target is taken.
- `place_files` moves several files (a mesh and its companion files) as one: each target must be what the
  caller allows there (`ANY` regular file, nothing, or the very file, by device, inode and change time, that was
  checked earlier: ``renameat2(RENAME_EXCHANGE)`` swaps it out atomically and swaps back if it is another file). If one
  target is refused or fails, the targets already placed are put back as they were. `Taken` says which.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import os
import stat
from collections.abc import Mapping, Sequence
from pathlib import Path

_NOREPLACE, _EXCHANGE = 1, 2
_AT_FDCWD = -100
#: errnos of renameat2 that mean "not supported here" (old kernel, a file system without the flag, a sandbox).
_UNSUPPORTED = {errno.EINVAL, errno.ENOSYS, errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP}


class _Any:
    def __repr__(self) -> str:
        return "ANY"


#: `place_files`: any regular file (or nothing) may be replaced at this target.
ANY = _Any()


class Taken(FileExistsError):
    """A target of `place_files` holds something the caller did not allow: `path`, and `changed` (True: the file
    that was checked earlier was replaced by another; False: something appeared where nothing was)."""

    def __init__(self, path: Path, changed: bool):
        super().__init__(errno.EEXIST, "taken", str(path))
        self.path, self.changed = Path(path), changed

    def message(self, what: str, kept: str) -> str:
        """A writer's line for it: `path` appeared (or was replaced) while `what` was being written; `kept` says what
        the writer left."""
        why = "was replaced by another file" if self.changed else "appeared"
        return f"{self.path}: {why} while {what} was being written; left as it is ({kept})"


def identity(path: str | os.PathLike) -> tuple[int, int, int] | None:
    """(device, inode, change time in ns) of what `path` names itself (a link is not followed), or None when
    nothing is there. The change time tells a file put in place of another apart even when the system gives it
    the inode number the other just freed, and a file changed since it was looked at."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    return st.st_dev, st.st_ino, st.st_ctime_ns


def same_inode(a: tuple | None, b: tuple | None) -> bool:
    """Whether two `identity` values are the same file (device and inode; a rename changes the change time)."""
    return a is not None and b is not None and a[:2] == b[:2]


def _libc_renameat2():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_RENAMEAT2 = [_libc_renameat2()]


def _renameat2(src, dst, flags: int) -> bool:
    """``renameat2(src, dst, flags)``: True when done, False when not supported here; `OSError` otherwise."""
    fn = _RENAMEAT2[0]
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), flags) == 0:
        return True
    err = ctypes.get_errno()
    if err in _UNSUPPORTED:
        return False
    raise OSError(err, os.strerror(err), os.fspath(dst))


def rename_noreplace(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Rename the file or folder `src` to `dst` unless something (even an empty folder) is at `dst`:
    `FileExistsError` then, with `src` left as it was."""
    try:
        if _renameat2(src, dst, _NOREPLACE):
            return
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
            raise FileExistsError(errno.EEXIST, "exists", os.fspath(dst)) from None
        raise
    if stat.S_ISDIR(os.lstat(src).st_mode):
        os.mkdir(dst)  # FileExistsError if taken; then the folder is ours, and empty
        try:
            os.rename(src, dst)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.rmdir(dst)  # only if still empty: something put there meanwhile stays
            if exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
                raise FileExistsError(errno.EEXIST, "exists", os.fspath(dst)) from None
            raise
        return
    try:
        os.link(src, dst)  # FileExistsError if taken
    except FileExistsError:
        raise
    except OSError:  # no hard links on this file system: the check and the rename, as close as they can be
        if os.path.lexists(dst):
            raise FileExistsError(errno.EEXIST, "exists", os.fspath(dst)) from None
        os.rename(src, dst)
        return
    os.unlink(src)


def exchange(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Swap `a` and `b` atomically; False when the system cannot."""
    return _renameat2(a, b, _EXCHANGE)


def place_files(moves: Sequence[tuple[Path, Path]], allowed: Mapping[Path, object] | None = None) -> None:
    """Move each finished file ``src`` to its target ``dst`` (same file system), all or none.

    **Arguments:**

    - `moves`: ``(src, dst)`` pairs, in the order to place them (companion files first, the main file last).
    - `allowed`: per target, what may be replaced there: `ANY` (any regular file), None (nothing: the target must
      not exist) or the `identity` of the file checked earlier (the same file, unchanged since). A target missing
      from the mapping, or `allowed` None, is `ANY`.

    **Returns:** nothing. Raises `Taken` when a target holds something else (after putting back the targets
    already placed), `OSError` when a rename fails (the same). A replaced file is removed only once every
    target is in place; until then it waits beside its replacement's temporary name.
    """
    done: list[tuple[Path, Path | None, tuple[int, int] | None]] = []  # (dst, backup or None, new identity)
    try:
        for src, dst in moves:
            want = ANY if allowed is None else allowed.get(dst, ANY)
            backup = _place_one(Path(src), Path(dst), want)
            done.append((Path(dst), backup, identity(dst)))
    except BaseException:
        for dst, backup, ident in reversed(done):
            with contextlib.suppress(OSError):
                if backup is not None:
                    os.replace(backup, dst)
                elif ident is not None and identity(dst) == ident:
                    os.unlink(dst)
        raise
    for _, backup, _ in done:
        if backup is not None:
            with contextlib.suppress(OSError):
                os.unlink(backup)


def _place_one(src: Path, dst: Path, want) -> Path | None:
    """Place one file; returns where the file it replaced now is (for a roll-back), or None."""
    current = identity(dst)
    if current is None or want is None:
        try:
            rename_noreplace(src, dst)
        except FileExistsError:
            raise Taken(dst, changed=want is not None and want is not ANY) from None
        return None
    if want is not ANY and current != want:
        raise Taken(dst, changed=True)
    if stat.S_ISDIR(os.lstat(dst).st_mode):
        raise IsADirectoryError(errno.EISDIR, "is a folder", os.fspath(dst))
    if exchange(src, dst):  # the old file is now at src: check it is the one allowed, else swap back
        old = identity(src)
        if (want is not ANY and not same_inode(old, want)) or stat.S_ISDIR(os.lstat(src).st_mode):
            exchange(src, dst)
            raise Taken(dst, changed=True)
        return src
    backup = src.with_name(src.name + ".old")
    try:
        os.link(dst, backup)
    except OSError:
        backup = None
    os.replace(src, dst)
    return backup


# ------------------------------------------------------------------------------------ temporary files and folders
#: Every temporary file or folder jaxci makes beside an output starts with this, then the process id and the
#: output's name: ``.jaxci-tmp-<pid>-<name>.<random>``. Only such names are ever removed as stale (`remove_stale`).
TEMP_PREFIX = ".jaxci-tmp-"
#: The longest part of the output's name kept in a temporary name (a name of 255 bytes still gets a temporary).
_NAME_CHARS = 100


class Temporary:
    """A temporary folder beside an output (`make_temporary`): its `path`, locked (``flock``) by this process until
    `release` (or the process's end, even by SIGKILL), so that `remove_stale` of another process leaves it alone."""

    def __init__(self, path: Path, fd: int):
        self.path, self._fd = path, fd

    def release(self) -> None:
        """Unlock (the folder itself is left as it is: removed, renamed into place, or stale)."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None

    def remove(self) -> None:
        """Remove the folder (if still there under its temporary name), then unlock."""
        import shutil

        shutil.rmtree(self.path, ignore_errors=True)
        self.release()


def temporary_prefix(name: str) -> str:
    """The start of the temporary names that this process makes for an output `name`."""
    return f"{TEMP_PREFIX}{os.getpid()}-{name[:_NAME_CHARS]}."


def make_temporary(folder: str | os.PathLike, name: str) -> Temporary:
    """A new, locked temporary folder in `folder` for the output `name` (`TEMP_PREFIX`); stale temporaries of
    killed jaxci processes in `folder` are removed first (`remove_stale`). `OSError` when it cannot be made."""
    import fcntl
    import tempfile

    remove_stale(folder)
    path = Path(tempfile.mkdtemp(prefix=temporary_prefix(name), dir=folder))
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    fcntl.flock(fd, fcntl.LOCK_EX)
    return Temporary(path, fd)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        return True
    return True


def remove_stale(folder: str | os.PathLike) -> list[str]:
    """Remove the temporary files and folders that jaxci processes which are no longer running left in `folder`
    (a SIGKILL, a power cut): entries named `TEMP_PREFIX` ``<pid>-...`` whose process is gone and whose lock
    (`Temporary`) nobody holds. Nothing else is touched. Returns the names removed."""
    import fcntl
    import shutil

    removed = []
    try:
        names = [e for e in os.listdir(folder) if e.startswith(TEMP_PREFIX)]
    except OSError:
        return removed
    for name in names:
        pid = name[len(TEMP_PREFIX):].split("-", 1)[0]
        if not pid.isdigit() or _alive(int(pid)):
            continue
        path = os.path.join(folder, name)
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # BlockingIOError: another process holds it
            if stat.S_ISDIR(os.fstat(fd).st_mode):
                shutil.rmtree(path)
            else:
                os.unlink(path)
            removed.append(name)
        except OSError:
            pass
        finally:
            os.close(fd)
    return removed


def sync_tree(path: str | os.PathLike) -> None:
    """``fsync`` the file `path`, or every file and folder under the folder `path` (the folder last): what is
    renamed into place afterwards is on the disk, not only in the page cache."""
    paths = []
    if os.path.isdir(path):
        for root, _, files in os.walk(path, topdown=False):
            paths += [os.path.join(root, f) for f in files] + [root]
    else:
        paths = [path]
    for p in paths:
        _fsync(p)


def sync_folder(folder: str | os.PathLike) -> None:
    """``fsync`` a folder: the renames done in it are on the disk."""
    _fsync(folder)


def _fsync(path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # a file system without fsync on folders (some network ones): the rename is still atomic
        pass
    finally:
        os.close(fd)
