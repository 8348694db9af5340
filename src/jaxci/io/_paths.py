"""What a path names, for reading: a regular file, or a one-line reason why not, before anything is opened.

Opening a FIFO (named pipe) for reading waits for a writer, and reading a character device such as ``/dev/zero``
never ends; a name longer than the file system allows (``ENAMETOOLONG``) or a folder reads as an odd ``OSError``.
`check_regular` turns each into a `MeshReadError` naming the file, and `open_text` opens a text file without
ever waiting on a FIFO (``O_NONBLOCK`` for the open, then ``fstat``). Every reader of `jaxci.io` goes through
them: `jaxci.io.read_mesh` for the file it is given, the Abaqus reader for its ``*INCLUDE`` files, the XDMF reader
for the HDF5 files its data items name.

`same_file` is the test a write uses against every input of a mesh (`jaxci.io.input_paths`): the same file
spelled differently, through a symbolic or a hard link, counts.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from ..errors import MeshReadError

#: What a non-regular file is, in words, by its `stat` type.
_KINDS = {
    stat.S_IFIFO: "a FIFO (named pipe)",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFSOCK: "a socket",
}


def os_reason(exc: OSError) -> str:
    """The reason of an `OSError` in words (``file name too long``, ``permission denied``, ...)."""
    if exc.errno == errno.ENAMETOOLONG:
        return "file name too long for the file system"
    if exc.strerror:
        return exc.strerror[0].lower() + exc.strerror[1:]
    return str(exc) or type(exc).__name__


def not_regular(mode: int, what: str) -> str | None:
    """Why a file of `stat` mode `mode` cannot be read as a `what` (``"mesh file"``), or None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    article = "an" if what[:1].lower() in "aeiou" else "a"
    if stat.S_ISDIR(mode):
        return f"is a folder, not {article} {what}"
    kind = _KINDS.get(stat.S_IFMT(mode), "not a regular file")
    return f"is {kind}, not a regular file; jaxci reads {article} {what} only from a regular file"


def check_regular(path: str | os.PathLike, what: str = "mesh file", shown: str | None = None) -> None:
    """A `MeshReadError` (``<shown>: <why>``) unless `path` names an existing regular file (symbolic links
    followed). `shown` is the name in the message (default: `path`)."""
    shown = os.fspath(path) if shown is None else shown
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise MeshReadError(f"{shown}: no such file") from None
    except NotADirectoryError:
        raise MeshReadError(f"{shown}: no such file (a part of the path is not a folder)") from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the name
        why = os_reason(exc) if isinstance(exc, OSError) else "the name holds a NUL character"
        raise MeshReadError(f"{shown}: cannot read ({why})") from None
    why = not_regular(st.st_mode, what)
    if why is not None:
        raise MeshReadError(f"{shown}: {why}")


def open_text(path: str | os.PathLike, what: str, errors: str = "strict"):
    """`path` opened as UTF-8 text (``newline=""``), refusing anything but a regular file without blocking on a
    FIFO; `MeshReadError` naming the file otherwise."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise MeshReadError(f"{os.fspath(path)}: no such file") from None
    except IsADirectoryError:
        raise MeshReadError(f"{os.fspath(path)}: is a folder, not a {what}") from None
    except (OSError, ValueError) as exc:
        why = os_reason(exc) if isinstance(exc, OSError) else "the name holds a NUL character"
        raise MeshReadError(f"{os.fspath(path)}: cannot read ({why})") from None
    try:
        why = not_regular(os.fstat(fd).st_mode, what)
        if why is not None:
            raise MeshReadError(f"{os.fspath(path)}: {why}")
        os.set_blocking(fd, True)
        return open(fd, encoding="utf-8", errors=errors, newline="", closefd=True)
    except BaseException:
        os.close(fd)
        raise


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether `a` and `b` name the same file: the same real path, or the same device and inode."""
    try:
        if os.path.realpath(a) == os.path.realpath(b):
            return True
        return os.path.samefile(a, b)
    except (OSError, ValueError):  # one of them does not exist, or cannot be looked up
        return False


def resolve_beside(name: str, base: str | os.PathLike) -> Path:
    """The file a reference `name` inside the file `base` means: absolute as it is, else relative to `base`'s
    folder."""
    p = Path(name)
    return p if p.is_absolute() else Path(base).parent / p
