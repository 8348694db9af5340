"""Output files of the commands that write one mesh (`smooth`, `classify`, `generate`): checked before any work,
and put in place so that nothing that is not ours is replaced, even if it appears while the command works.

`check_output` refuses (a `MeshWriteError`, one line, exit 2, nothing written):

- an output, or a file the output's format writes beside it (XDMF's ``.h5``: `jaxci.io.companion_files`), that
  is one of the command's inputs, even with ``--force`` (`jaxci.io._paths.same_file`: the same file spelled
  differently, through a symbolic or hard link, counts). The inputs are the files named on the command line and,
  once the mesh is read, every other file its reader opened (`Output.check_inputs`: ``*INCLUDE`` files, the HDF5
  files an XDMF file names; `jaxci.io.input_paths`);
- an existing output or companion without ``--force``, and with ``--force`` anything but a regular file (a
  folder, a device);
- an output whose folder does not exist (before a long smoothing, not after), or whose name the file system
  cannot hold.

`Output.write` then writes the mesh atomically (`jaxci.io.write_mesh` inside `_interrupt.removing_temporaries`)
with ``overwrite`` set to what was checked: without ``--force`` the final move refuses any file that appeared at
the output's name meanwhile; with ``--force`` it replaces only the very file (device, inode, change time) that was
there when it was checked, unchanged, or nothing. Once it is in place, an interrupt's line says so
(`_interrupt.completed`).
"""

from __future__ import annotations

import dataclasses
import os
import stat
from pathlib import Path


def _stat(path: Path, follow: bool = True) -> os.stat_result | None:
    """`os.stat` (`follow`) or `os.lstat` of `path`, None when nothing is there; a `MeshWriteError` for a name the
    file system cannot look up (too long, a part not a folder, no permission)."""
    from ..errors import MeshWriteError
    from ..io._paths import os_reason

    try:
        return os.stat(path) if follow else os.lstat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise MeshWriteError(f"{path}: cannot write ({os_reason(exc)}); nothing was written") from None
    except ValueError:
        raise MeshWriteError(f"{path}: cannot write (the name holds a NUL character); nothing was written") from None


@dataclasses.dataclass
class Output:
    """A checked output: its `path`, the files written with it (`targets`: the path and its companions) and, per
    target (absolute path), the identity of the file ``--force`` may replace there (None: no file may be);
    `written`: the identities of the targets just after `write` wrote them (None before it has)."""

    path: Path
    targets: tuple[Path, ...]
    allowed: dict[str, tuple[int, int, int] | None]
    written: tuple | None = None

    def check_inputs(self, mesh) -> None:
        """Refuse a target that is one of the files `mesh` was read from (`jaxci.io.input_paths`)."""
        from ..io import input_paths

        _refuse_inputs(self.path, self.targets, input_paths(mesh), mesh.source)

    def write(self, mesh) -> None:
        """Write `mesh` to `path` (`check_inputs` first), replacing only what was checked."""
        from ..io import write_mesh
        from ..io._place import identity
        from ._interrupt import completed, removing_temporaries

        self.check_inputs(mesh)
        with removing_temporaries(self.path):
            write_mesh(mesh, self.path, overwrite=self.allowed)
        self.written = tuple(identity(t) for t in self.targets)
        completed(f"wrote {self.path} (complete)")


def _refuse_inputs(output: Path, targets, inputs, source=None) -> None:
    from ..errors import MeshWriteError
    from ..io._paths import same_file

    for target in targets:
        for src in inputs:
            if same_file(target, src):
                what = "is" if target == output else f"writes {target}, which is"
                read = "" if source is None or same_file(src, source) else f", read through {source}"
                raise MeshWriteError(f"{output}: {what} the input {src}{read}; refusing to overwrite the input even "
                                     f"with --force; choose another output path")


def targets_of(output: str | os.PathLike) -> tuple[Path, ...]:
    """The files written for `output`: the path and its companions (`jaxci.io.companion_files`)."""
    from ..io import companion_files

    output = Path(output)
    return (output, *companion_files(output))


def refuse_inputs(output: str | os.PathLike, inputs) -> None:
    """The first check of `check_output` alone: a `MeshWriteError` if `output` or a companion is one of `inputs`
    (``jaxci smooth IN... --out-dir DIR`` runs it over every output and every input before any other check)."""
    _refuse_inputs(Path(output), targets_of(output), [Path(p) for p in inputs])


def check_output(output: str | os.PathLike, inputs=(), *, force: bool) -> Output:
    """Check that the command may write `output` (see the module docstring); returns the checked `Output`."""
    from ..errors import MeshWriteError
    from ..io._place import identity

    output = Path(output)
    targets = targets_of(output)
    _refuse_inputs(output, targets, [Path(p) for p in inputs])
    allowed = {}
    for target in targets:
        lst = _stat(target, follow=False)
        st = _stat(target) if lst is not None else None  # None for a link to nothing
        if lst is not None:
            if not force:
                raise MeshWriteError(f"{target}: exists; pass --force to overwrite it (nothing was written)")
            if st is None or not stat.S_ISREG(st.st_mode):
                raise MeshWriteError(f"{target}: exists and is not a regular file; --force only replaces a file "
                                     f"(nothing was written)")
        allowed[os.path.abspath(target)] = identity(target) if lst is not None else None
    folder = output.parent
    st = _stat(folder)
    if st is None or not stat.S_ISDIR(st.st_mode):
        raise MeshWriteError(f"{output}: folder {folder} does not exist (nothing was written)")
    return Output(output, targets, allowed)
