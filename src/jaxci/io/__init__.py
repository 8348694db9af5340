"""Reading and writing hexahedral meshes: the meshio formats that carry hexahedra, and ANSYS text.

`read_mesh` / `write_mesh` pick the format from the file extension through `FORMATS` (or, in the API, take
``file_format=``, one of its values or ``"gmsh22"``). ANSYS NLIST/ELIST listings are read with
`read_ansys_listing`, or with `read_mesh` given the pair ``(nlist, elist)`` or one ``.lis`` / ``.txt`` file
holding both listings. Every reader records the other files it opened (``*INCLUDE`` files, an XDMF file's
data files) in `HexMesh.input_files`; `write_mesh` never overwrites any file a mesh was read from (`input_paths`),
writes atomically (with its companion files, `companion_files`), and warns (`LossyWriteWarning`) about what a
format cannot hold.
"""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

from ..errors import MeshWriteError, UnsupportedFormatError, UsageError
from ..mesh import HexMesh
from ._abaqus import read_abaqus
from ._abaqus_write import write_abaqus
from ._ansys_apdl import read_apdl
from ._ansys_apdl_write import write_apdl
from ._ansys_listing import read_ansys_listing as read_ansys_listing
from ._exodus import read_exodus
from ._exodus_write import write_exodus
from ._lsdyna import read_lsdyna
from ._lsdyna_write import write_lsdyna
from ._medit import read_medit, write_medit
from ._meshio import LossyWriteWarning as LossyWriteWarning
from ._meshio import read_meshio, write_meshio
from ._nastran import read_nastran
from ._nastran_write import write_nastran
from ._paths import check_regular, same_file
from ._place import Taken, make_temporary, place_files, sync_folder, sync_tree

#: File extension (lower case) -> format name. ``.msh`` is Gmsh (written as 4.1; ``file_format="gmsh22"``
#: writes 2.2), ``.inp`` is Abaqus, ``.mac``/``.apdl``/``.ans``/``.cdb`` are ANSYS APDL input files and
#: archives (their NBLOCK/EBLOCK mesh), ``.lis``/``.txt`` are ANSYS NLIST + ELIST listings (read only),
#: ``.e``/``.exo``/``.ex2``/``.g`` Exodus II, ``.bdf``/``.nas``/``.dat`` Nastran bulk data (a ``.dat`` holding
#: ANSYS NBLOCK data is read as APDL), ``.k``/``.key``/``.dyn`` LS-DYNA keyword decks, ``.mesh`` Medit.
FORMATS: dict[str, str] = {
    ".vtk": "vtk",
    ".vtu": "vtu",
    ".msh": "gmsh",
    ".inp": "abaqus",
    ".xdmf": "xdmf",
    ".xmf": "xdmf",
    ".e": "exodus",
    ".exo": "exodus",
    ".ex2": "exodus",
    ".g": "exodus",
    ".bdf": "nastran",
    ".nas": "nastran",
    ".dat": "nastran",
    ".k": "lsdyna",
    ".key": "lsdyna",
    ".dyn": "lsdyna",
    ".mesh": "medit",
    ".mac": "apdl",
    ".apdl": "apdl",
    ".ans": "apdl",
    ".cdb": "apdl",
    ".lis": "ansys-listing",
    ".txt": "ansys-listing",
}

_READERS = {
    "vtk": lambda path: read_meshio(path, "vtk"),
    "vtk51": lambda path: read_meshio(path, "vtk"),
    "vtu": lambda path: read_meshio(path, "vtu"),
    "gmsh": lambda path: read_meshio(path, "gmsh"),
    "gmsh22": lambda path: read_meshio(path, "gmsh22"),
    "abaqus": read_abaqus,
    "xdmf": lambda path: read_meshio(path, "xdmf"),
    "apdl": read_apdl,
    "ansys-listing": read_ansys_listing,
    "exodus": read_exodus,
    "nastran": read_nastran,
    "lsdyna": read_lsdyna,
    "medit": read_medit,
}

_WRITERS = {
    "vtk": lambda mesh, path: write_meshio(mesh, path, "vtk"),
    "vtk51": lambda mesh, path: write_meshio(mesh, path, "vtk51"),
    "vtu": lambda mesh, path: write_meshio(mesh, path, "vtu"),
    "gmsh": lambda mesh, path: write_meshio(mesh, path, "gmsh"),
    "gmsh22": lambda mesh, path: write_meshio(mesh, path, "gmsh22"),
    "abaqus": write_abaqus,
    "xdmf": lambda mesh, path: write_meshio(mesh, path, "xdmf"),
    "apdl": write_apdl,
    "exodus": write_exodus,
    "nastran": write_nastran,
    "lsdyna": write_lsdyna,
    "medit": write_medit,
}


def _format_of(path: Path, file_format: str | None, table: dict) -> str:
    if file_format is not None:
        if not isinstance(file_format, str):
            raise UsageError(f"file_format must be a format name (str) or None, got {type(file_format).__name__}")
        if file_format not in table:
            raise UnsupportedFormatError(
                f"{path}: unknown file format {file_format!r}; known: {', '.join(sorted(table))}"
            )
        return file_format
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        known = ", ".join(ext for ext, f in FORMATS.items() if f in table)
        raise UnsupportedFormatError(
            f"{path}: unknown mesh file extension {path.suffix or '(none)'!r}; known extensions: {known}"
        )
    return fmt


def _as_path(path, func: str) -> Path:
    """`path` as a `Path`, or a `UsageError` saying what was passed instead."""
    if isinstance(path, str | os.PathLike) and not isinstance(path, bytes):
        p = Path(path)
        if str(p) in ("", "."):
            raise UsageError(f"{func}: the file path is empty")
        return p
    what = type(path).__module__ + "." + type(path).__qualname__ if type(path).__module__ != "builtins" else \
        type(path).__name__
    hint = " (the mesh comes first: write_mesh(mesh, path))" if isinstance(path, HexMesh) else ""
    raise UsageError(f"{func}: path must be a file path (str or os.PathLike), got {what}{hint}")


def read_mesh(path: str | os.PathLike | tuple, *, file_format: str | None = None) -> HexMesh:
    """Read a hexahedral mesh file.

    **Arguments:**

    - `path`: the file; or a pair ``(nlist, elist)`` of ANSYS listing files. A single ``.lis`` / ``.txt`` file
      may hold both the NLIST and the ELIST output (sections are found by their column headers).
    - `file_format`: keyword only; a format name (a value of `FORMATS`, or ``"gmsh22"``) to use instead of
      the one the extension says.

    **Returns:** a `HexMesh` with ``source`` set to the file, carrying the file's other cell blocks, data,
    sets and ids (see `write_mesh` for which format holds what).

    Raises `MeshReadError` (missing, unreadable, truncated or corrupt file, a folder, a FIFO or device, a name
    too long for the file system, counts that disagree with their headers, duplicate or out-of-range ids),
    `UnsupportedFormatError` (unknown extension or format name), `MeshError` (no hexahedra, non-finite
    coordinates, bad node index) or `UsageError` (`path` not a path), each with a one-line message naming the file.
    """
    if isinstance(path, tuple | list):
        if len(path) != 2 or file_format not in (None, "ansys-listing"):
            raise UnsupportedFormatError(
                f"a pair of files is read as ANSYS (NLIST, ELIST) listings only, got {len(path)} paths and "
                f"file_format={file_format!r}"
            )
        paths = [_as_path(p, "read_mesh") for p in path]
        for p in paths:
            check_regular(p)  # a folder, a FIFO, a device, a name too long: said in words, nothing opened
        return read_ansys_listing(*paths)
    path = _as_path(path, "read_mesh")
    check_regular(path)
    fmt = _format_of(path, file_format, _READERS)
    return _READERS[fmt](path)


def input_paths(mesh: HexMesh) -> list[Path]:
    """The files a write must never replace for `mesh`: every file it was read from, its `source` and its
    `HexMesh.input_files` (the other files its reader opened: ``*INCLUDE`` files, an XDMF file's HDF5 data, ...),
    those that exist. A mesh with an XDMF source and no `input_files` (made by hand) also counts the ``.h5`` file
    of the same name."""
    if not mesh.source:
        return [Path(p) for p in mesh.input_files if os.path.lexists(p)]
    paths = [Path(mesh.source)] if os.path.lexists(mesh.source) else [Path(s) for s in mesh.source.split(" + ")]
    paths += [Path(p) for p in mesh.input_files]
    if not mesh.input_files:
        paths += [p.with_suffix(".h5") for p in paths if p.suffix.lower() in (".xdmf", ".xmf")]
    return list(dict.fromkeys(p for p in paths if os.path.lexists(p)))


def _refuse_input(target: Path, inputs: list[Path]) -> None:
    for p in inputs:
        if same_file(target, p):
            through = "" if same_file(p, inputs[0]) else f" (through {inputs[0]})"
            raise MeshWriteError(
                f"{target}: refusing to overwrite a file the mesh was read from{through} (inputs are never "
                f"overwritten); write to a new file"
            )


def companion_files(path: str | os.PathLike, *, file_format: str | None = None) -> list[Path]:
    """The files `write_mesh` writes beside `path` (XDMF: the ``.h5`` data file of the same name), which it
    checks and places as it does `path`."""
    path = Path(path)
    try:
        fmt = _format_of(path, file_format, _WRITERS)
    except UnsupportedFormatError:
        return []
    return [path.with_suffix(".h5")] if fmt == "xdmf" else []


def write_mesh(mesh: HexMesh, path: str | os.PathLike, *, file_format: str | None = None,
               overwrite: bool | dict = True) -> None:
    """Write a mesh file, atomically, never over a file the mesh was read from.

    What each format keeps (coordinates are float64-exact except APDL; hexahedra keep their node order and
    handedness: mirrored hexahedra, `HexMesh.hex_mirrored`, are mirrored back):

    | format (extensions)          | point / cell data    | point / cell sets    | field data    | ids | deck (4) |
    |------------------------------|----------------------|----------------------|---------------|-----|----------|
    | VTU (`.vtu`)                 | kept, with dtypes    | kept (1)             | dropped       | no  | no       |
    | legacy VTK (`.vtk`)          | kept, with dtypes    | kept (1)             | dropped       | no  | no       |
    | Gmsh 4.1 / 2.2 (`.msh`)      | kept, ints -> float64 | physical groups only | physical names | no | no       |
    | Abaqus (`.inp`)              | dropped              | kept                 | dropped       | yes | yes      |
    | XDMF (`.xdmf`, `.xmf`) (2)   | kept, with dtypes    | kept (1)             | dropped       | no  | no       |
    | ANSYS APDL (`.mac`, `.apdl`, `.ans`, `.cdb`) | `ansys:*` only | components (3) | `ansys:*` only | yes | yes |
    | Exodus II (`.e`, `.exo`, `.ex2`, `.g`) (5) | dropped | node sets; block names | dropped | yes | yes |
    | Nastran (`.bdf`, `.nas`, `.dat`) | `nastran:pid` only | dropped             | dropped       | yes | yes      |
    | LS-DYNA (`.k`, `.key`, `.dyn`) | `lsdyna:pid` only  | dropped              | dropped       | yes | yes      |
    | Medit (`.mesh`)              | `medit:ref` only     | `corners` only       | dropped       | no  | no       |

    (1) as 0/1 integer data named ``set:NAME``, turned back into sets on reading. (2) with a ``.h5`` data file
    beside it; needs the h5py package. (3) CMBLOCK node / element components, for set names ANSYS accepts.
    (4) A mesh read from an Abaqus deck or an APDL file / CDB archive carries the file's text (field data
    ``abaqus:deck``, ``ansys:deck``). Written to the same kind of file while it still has the file's nodes, ids,
    cells, element types and sets (only its coordinates changed, as after smoothing), the file is written back
    with only the coordinates of its node lines rewritten: materials, sections, steps, loads and every other line
    jaxci does not model are kept byte for byte. Otherwise, and in every other format, a `LossyWriteWarning`
    names the keyword blocks or commands lost.
    Abaqus keeps the element type of each block (``C3D8R``, ...; ``abaqus:element_types``) and writes a mesh from
    another format with ``C3D8``, ``C3D20`` (hexahedra with midside nodes), ``C3D6``, ``C3D4``, ``S4``, ...
    APDL holds hexahedra, wedges, pyramids and tetrahedra only (8-node bricks, SOLID186 20-node bricks and their
    degenerate forms, SOLID285/187 tetrahedra), with 14 significant digits per coordinate, and keeps the element
    types (``ET``) and key options of a file it read; ids of any size up to int64 are written in integer fields
    wide enough for them (mapdl-archive, with int32 ids, reads ids up to 2147483647). The midside nodes of quadratic
    cells (`CellBlock.midside`) are written by APDL, Abaqus, Exodus and Nastran only; the other formats write the
    linear cells with a `LossyWriteWarning` (the midside nodes stay in the file as unreferenced points, at their
    moved positions).
    (5) Exodus in place: the source file copied with only its coordinate variables replaced (results, QA and
    info records, maps, side sets and attributes kept); `jaxci.io._exodus_write`. Nastran and LS-DYNA decks in
    place: only the moved nodes' coordinate fields rewritten, each in its own width (`jaxci.io._nastran_write`,
    `jaxci.io._lsdyna_write`). ``.dat`` holding ANSYS ``NBLOCK`` data is read and written as APDL.
    Every `LossyWriteWarning` is issued before the file is written. Details in the docstrings of
    `jaxci.io._meshio`, `jaxci.io._abaqus_write` and `jaxci.io._ansys_apdl_write`.

    **Arguments:**

    - `mesh`: the `HexMesh` to write.
    - `path`: the file to write. The file (and its companions, `companion_files`) is written under a temporary
      name in a new hidden folder beside it (``.jaxci-tmp-<pid>-<name>.*``, `jaxci.io._place.make_temporary`),
      synced to the disk, then moved into place, all files or none, so a failed write leaves nothing behind. A
      file that is replaced is swapped out in one step (``renameat2(RENAME_EXCHANGE)``, else `os.replace`): even
      a SIGKILL leaves the old file or the new one whole, and the next write in that folder removes the
      temporary folder a killed jaxci left (`jaxci.io._place.remove_stale`).
    - `file_format`: keyword only; a format name to use instead of the one the extension says.
    - `overwrite`: keyword only. True (default): an existing regular file at `path` or a companion's name is
      replaced. False: none is; the final move itself refuses (``renameat2(RENAME_NOREPLACE)`` or a hard link),
      so a file that appears while the mesh is written is not replaced either. A dict ``{file: identity}``
      (`jaxci.io._place.identity`, None for "no file"): each file may replace only the file that was there when
      its identity was taken (what the ``jaxci`` command does with ``--force``).

    **Returns:** nothing. Issues a `LossyWriteWarning` when the format drops part of the mesh; raises
    `MeshWriteError` naming `path` (never the temporary file) when the target or a companion is one of the mesh's
    input files (`input_paths`: ``source`` and ``input_files``), is a file `overwrite` does not allow, or the
    write fails (unwritable folder, full disk, a mesh the format cannot hold), `UnsupportedFormatError` for an
    unknown extension, and `UsageError` when `mesh` is not a `HexMesh` or `path` not a path.
    """
    if not isinstance(mesh, HexMesh):
        what = type(mesh).__module__ + "." + type(mesh).__qualname__ if type(mesh).__module__ != "builtins" \
            else type(mesh).__name__
        hint = " (the mesh comes first: write_mesh(mesh, path))" if isinstance(mesh, str | os.PathLike) else \
            " (make one with jaxci.mesh.hex_mesh(points, hexes))" if what == "numpy.ndarray" else ""
        raise UsageError(f"write_mesh: mesh must be a jaxci HexMesh, got {what}{hint}")
    path = _as_path(path, "write_mesh")
    if file_format == "ansys-listing" or (file_format is None and FORMATS.get(path.suffix.lower()) == "ansys-listing"):
        raise UnsupportedFormatError(
            f"{path}: ANSYS NLIST/ELIST listings are read only; write an APDL input file (.mac) instead"
        )
    fmt = _format_of(path, file_format, _WRITERS)
    inputs = input_paths(mesh)
    for target in (path, *companion_files(path, file_format=file_format)):
        _refuse_input(target, inputs)
        if overwrite is False and os.path.lexists(target):
            raise MeshWriteError(f"{target}: exists; not replaced (overwrite=False), nothing was written")
    quadratic = sum(len(b.data) for b in mesh.cells if b.midside is not None)
    if quadratic and fmt not in ("apdl", "abaqus", "exodus", "nastran"):
        warnings.warn(
            f"{path.name}: {fmt} gets the {quadratic} quadratic cells as linear cells (their corner nodes); their "
            f"midside nodes are written as unreferenced points. Write .inp, .cdb or .mac to keep them",
            LossyWriteWarning,
            stacklevel=2,
        )
    folder = path.parent
    if not folder.is_dir():
        raise MeshWriteError(f"{path}: folder {folder} does not exist")
    if path.is_dir():
        raise MeshWriteError(f"{path}: is a folder")
    try:
        temporary = make_temporary(folder, path.name)
    except OSError as exc:
        raise MeshWriteError(f"{path}: cannot write in folder {folder} ({_os_reason(exc, folder)})") from exc
    tmp = temporary.path
    try:
        _WRITERS[fmt](mesh, tmp / path.name)
        produced = sorted(tmp.iterdir(), key=lambda p: p.name == path.name)  # companions first, the file last
        sync_tree(tmp)  # on the disk before the rename: a crash never leaves a renamed but empty file
        for p in produced:
            _refuse_input(folder / p.name, inputs)
        if overwrite is True:
            allowed = None
        else:  # False: no file may be replaced; a dict: only the one it names for each target (absent: none)
            given = {} if overwrite is False else {os.path.abspath(k): v for k, v in overwrite.items()}
            allowed = {folder / p.name: given.get(os.path.abspath(folder / p.name)) for p in produced}
        place_files([(p, folder / p.name) for p in produced], allowed)
        sync_folder(folder)
    except Taken as exc:
        raise MeshWriteError(exc.message("the mesh", "nothing was written")) from None
    except MeshWriteError as exc:  # name the output, never the hidden temporary file
        raise MeshWriteError(str(exc).replace(str(tmp / path.name), str(path)).replace(str(tmp), str(folder))) \
            from exc
    except OSError as exc:
        raise MeshWriteError(f"{path}: cannot write ({_os_reason(exc, folder)})") from exc
    finally:
        temporary.remove()


def _os_reason(exc: OSError, folder: Path) -> str:
    """What went wrong, in words: the system's message for an errno, else the exception's text (numpy's "problem
    writing element 555 to file" says nothing of a full disk: the free space tells)."""
    if exc.errno is not None and exc.strerror:
        return exc.strerror
    try:
        full = shutil.disk_usage(folder).free < 1 << 20
    except OSError:
        full = False
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"no space left on device: {text}" if full else text
