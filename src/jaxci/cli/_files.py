"""Output files of the commands that write one mesh (`smooth`, `classify`, `generate`): checked before any work.

`check_output` refuses (a `MeshWriteError`, one line, exit 2, nothing written):

- an output that is one of the command's inputs, even with ``--force`` (`os.path.samefile`, so the same file
  spelled differently, through a symbolic or hard link, counts), XDMF's ``.h5`` data file included;
- an existing output without ``--force``, and with ``--force`` anything but a regular file (a folder, a device);
- an output whose folder does not exist (before a long smoothing, not after).

The file itself is then written atomically by `jaxci.io.write_mesh` inside `_interrupt.removing_temporaries`.
"""

from __future__ import annotations

import os
from pathlib import Path

_XDMF = (".xdmf", ".xmf")


def _with_data_file(path: Path) -> list[Path]:
    """`path` and, for XDMF, the ``.h5`` data file written beside it."""
    return [path, path.with_suffix(".h5")] if path.suffix.lower() in _XDMF else [path]


def _same(a: Path, b: Path) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist
        return False


def check_output(output: str | os.PathLike, inputs=(), *, force: bool) -> Path:
    """Check that the command may write `output` (see the module docstring); returns it as a `Path`."""
    from ..errors import MeshWriteError

    output = Path(output)
    sources = [q for p in inputs for q in _with_data_file(Path(p))]
    for target in _with_data_file(output):
        for src in sources:
            if _same(target, src):
                what = "is" if target == output else f"writes {target}, which is"
                raise MeshWriteError(f"{output}: {what} the input {src}; refusing to overwrite the input even "
                                     f"with --force; choose another output path")
    for target in _with_data_file(output):
        if target.exists() or target.is_symlink():
            if not force:
                raise MeshWriteError(f"{target}: exists; pass --force to overwrite it (nothing was written)")
            if not target.is_file():
                raise MeshWriteError(f"{target}: exists and is not a regular file; --force only replaces a file "
                                     f"(nothing was written)")
    folder = output.parent
    if not folder.is_dir():
        raise MeshWriteError(f"{output}: folder {folder} does not exist (nothing was written)")
    return output
