"""``jaxci smooth IN OUT --report FILE``: the report file (`jaxci.experiments.smooth_report`) is an output like
OUT and follows the same rules (`_files`): checked before any work (a ``.html``/``.htm`` or ``.png`` name; never
an input, never OUT or a file written with it; an existing file only with ``--force``; its folder must exist), and
written atomically, replacing only the file that was checked (nothing, without ``--force``), once the mesh is
written.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Report formats by extension.
REPORT_FORMATS = {".html": "html", ".htm": "html", ".png": "png"}


def report_format(path: str | os.PathLike) -> str | None:
    """``"html"`` or ``"png"`` by the extension of `path`; None for any other."""
    return REPORT_FORMATS.get(Path(path).suffix.lower())


def check_report(path: str | os.PathLike, inputs, mesh_output, *, force: bool):
    """Check that the report may be written at `path` (`_files.check_output`'s rules, and not one of the
    `mesh_output`'s targets); returns the checked `_files.Output`."""
    from ..errors import ConfigError, MeshWriteError
    from ..io._paths import same_file
    from ._files import check_output

    if report_format(path) is None:
        raise ConfigError(f"--report {path}: expected a .html (or .htm) or .png file name; nothing was written")
    for target in mesh_output.targets:
        if same_file(path, target):
            raise MeshWriteError(f"{path}: is also where the smoothed mesh goes ({target}); choose another report "
                                 f"path (nothing was written)")
    return check_output(path, inputs, force=force)


def write_report(out, data: bytes, mesh) -> None:
    """Write `data` at the checked output `out` atomically: a file in a temporary folder beside it
    (`jaxci.io._place.make_temporary`), synced, then moved in place replacing only what was checked there
    (`jaxci.io._place.place_files`); never a file `mesh` was read from."""
    from ..errors import MeshWriteError
    from ..io._paths import os_reason
    from ..io._place import Taken, make_temporary, place_files, sync_folder, sync_tree
    from ._interrupt import completed, removing_temporaries

    out.check_inputs(mesh)
    path = Path(out.path)
    with removing_temporaries(path):
        try:
            temporary = make_temporary(path.parent, path.name)
        except OSError as exc:
            raise MeshWriteError(f"{path}: cannot write the report ({os_reason(exc)})") from None
        try:
            tmp = temporary.path / path.name
            umask = os.umask(0)
            os.umask(umask)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 & ~umask)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            sync_tree(tmp)
            place_files([(tmp, path)], {path: out.allowed[os.path.abspath(path)]})
            sync_folder(path.parent)
        except Taken as exc:
            raise MeshWriteError(exc.message("the report", "the report was not written")) from None
        except OSError as exc:
            raise MeshWriteError(f"{path}: cannot write the report ({os_reason(exc)})") from None
        finally:
            temporary.remove()
    completed(f"wrote {path} (complete)")
