"""Mesh files through meshio: legacy VTK, VTU, Gmsh 2.2 / 4.1 and XDMF.

Each format is read with its own meshio reader (``meshio.vtu.read``, ``meshio.gmsh.read``, ...), never with
``meshio.read``, which prints and calls ``sys.exit`` on a corrupt file. Every failure becomes a
`jaxci.MeshReadError` / `jaxci.MeshWriteError` with a one-line message naming the file; whatever meshio would
print is turned into a `warnings.warn`.

The table of what each format keeps is in the docstring of `jaxci.io.write_mesh`. Details:

- Hexahedra keep VTK node order in all of them: meshio reorders no linear cell for these formats (Abaqus C3D8
  and Gmsh's hexahedron number their nodes as VTK does; the round-trip tests check it).
- Legacy VTK is written as ASCII 4.2 (the version every reader reads; ``file_format="vtk51"`` writes 5.1), float64
  exact; binary legacy VTK files from other tools store big-endian arrays, which are read back in native byte
  order.
- ``file_format="gmsh"`` writes Gmsh 4.1, ``"gmsh22"`` writes 2.2, both binary. Integer point/cell data read
  back as float64. Cell blocks without Gmsh tags get ``gmsh:physical`` 0 and ``gmsh:geometrical`` = block
  number + 1 (and, for 4.1, ``gmsh:dim_tags`` point data), so those appear on reading back. ``gmsh:physical``
  / ``gmsh:geometrical`` / ``gmsh:dim_tags`` read from a Gmsh file are ordinary cell / point data and are
  kept; meshio's ``gmsh:bounding_entities`` is not a cell set and is dropped on reading. Gmsh 2.2 drops other
  cell data of a mesh with several cell blocks (meshio 5.3.5 splits it wrongly on reading).
- XDMF needs the ``h5py`` package, for reading and for writing; the heavy data go to a ``.h5`` file beside it.

Sets in VTU, VTK and XDMF: a cell set ``NAME`` is written as integer cell data ``set:NAME`` (1 in the set, 0
elsewhere) and a point set as point data ``set:NAME``; on reading, 0/1 integer data named ``set:...`` become
sets again. Node ids (`HexMesh.node_ids`) and element ids (`CellBlock.ids`) are kept only by the Abaqus and ANSYS
APDL formats (`jaxci.io._abaqus`, `jaxci.io._ansys_apdl`), and so is the text of a source deck (``abaqus:deck``,
``ansys:deck`` field data). Anything a format drops is reported with a `LossyWriteWarning`, before writing.

Counts are checked against the headers that announce them (`jaxci.io._counts`, `jaxci.io._gmsh_counts`): a file
whose POINTS, CELLS, CELL_TYPES, POINT_DATA or CELL_DATA (legacy VTK), NumberOfPoints / NumberOfCells / offsets (VTU),
Dimensions (XDMF) or $Nodes / $Elements (Gmsh) disagree with what the file holds is a truncated or corrupt file, and
so is a Gmsh file that defines a node or element tag twice or whose elements list undefined nodes.
"""

from __future__ import annotations

import binascii
import contextlib
import importlib.util
import io
import os
import warnings
import zlib
from pathlib import Path

import meshio
import numpy as np

from ..errors import JaxciError, MeshReadError, MeshWriteError
from ..mesh import CellBlock, HexMesh, mirrored_block
from ..mesh.convert import SET_PREFIX, meshio_fields
from ._counts import check_vtk, check_vtu, check_xdmf, diagnose_vtk, read_vtu, vtu_header
from ._gmsh_counts import check_gmsh
from ._losses import SOURCE_FIELDS, deck_losses
from ._paths import check_regular


class LossyWriteWarning(UserWarning):
    """`write_mesh` wrote a format that cannot hold part of the mesh (see the table in `jaxci.io.write_mesh`)."""


def warn_lost(path, fmt: str, lost: list[str], stacklevel: int = 3) -> None:
    """A writer's `LossyWriteWarning`: what the file `path` of format `fmt` leaves out (`lost`), if anything;
    `stacklevel` as ``warnings.warn`` would count it from the writer."""
    if lost:
        warnings.warn(f"{os.path.basename(path)}: {fmt} drops {'; '.join(lost)}", LossyWriteWarning,
                      stacklevel=stacklevel + 1)


def write_text(path, text: str, fmt: str, lost: list[str], errors: str = "strict") -> None:
    """A text writer's last step: its `LossyWriteWarning` (`warn_lost`), then `text` written to `path` (UTF-8,
    line endings as they are; `errors` the encoding error handler: ``"surrogateescape"`` for a deck's own bytes)."""
    warn_lost(path, fmt, lost, stacklevel=4)
    with open(path, "w", encoding="utf-8", errors=errors, newline="") as f:
        f.write(text)


#: meshio's own reader of each format (never ``meshio.read``: it calls ``sys.exit`` on a corrupt file); VTU's with
#: jaxci's check of its cell arrays (`jaxci.io._counts.read_vtu`).
_READERS = {
    "vtk": meshio.vtk.read,
    "vtu": read_vtu,
    "gmsh": meshio.gmsh.read,
    "gmsh22": meshio.gmsh.read,
    "xdmf": meshio.xdmf.read,
}

#: meshio's writer of each format, with jaxci's choices of variant.
_WRITERS = {
    "vtk": lambda path, m: meshio.vtk.write(path, m, "4.2", binary=False),  # what every reader reads (Mesquite too)
    "vtk51": lambda path, m: meshio.vtk.write(path, m, "5.1", binary=False),  # only when asked: file_format="vtk51"
    "vtu": lambda path, m: meshio.vtu.write(path, m, binary=True, compression="zlib"),
    "gmsh": lambda path, m: meshio.gmsh.write(path, m, "4.1", binary=True),
    "gmsh22": lambda path, m: meshio.gmsh.write(path, m, "2.2", binary=True),
    "xdmf": meshio.xdmf.write,
}

#: Messages meshio prints that say nothing to a jaxci user (jaxci chose ASCII legacy VTK on purpose).
_MESHIO_NOISE = ("VTK ASCII files are only meant for debugging",)

#: Errors a meshio reader raises on a bad file.
_READ_ERRORS = (
    meshio.ReadError,
    meshio._exceptions.CorruptionError,  # raised by the VTU reader, not exported by meshio
    ValueError,
    KeyError,
    IndexError,
    TypeError,
    AttributeError,
    AssertionError,
    EOFError,
    OverflowError,  # a number beyond int64 where meshio converts to numpy integers
    UnicodeDecodeError,
    RuntimeError,
    SyntaxError,  # xml.etree.ElementTree.ParseError
    zlib.error,  # a corrupt compressed VTU block
    binascii.Error,  # corrupt base64 in a VTU
    MemoryError,  # a corrupt size field that asks numpy for a huge array
)


@contextlib.contextmanager
def _meshio_output_as_warnings(category=UserWarning):
    """Run meshio with its console output captured; re-issue each printed line as a warning."""
    buf = io.StringIO()
    try:
        with contextlib.redirect_stderr(buf), contextlib.redirect_stdout(buf):
            yield
    finally:
        for line in buf.getvalue().splitlines():
            line = line.strip()
            if line and not any(noise in line for noise in _MESHIO_NOISE):
                warnings.warn(f"meshio: {line}", category, stacklevel=4)


def _needs_h5py(path: Path, fmt: str, error) -> None:
    if fmt == "xdmf" and importlib.util.find_spec("h5py") is None:
        raise error(f"{path}: XDMF needs the h5py package, which is not installed (pip install h5py)")


def _describe(exc: BaseException) -> str:
    """A short reason from a reader's exception (meshio often raises a bare ``ReadError()``)."""
    if isinstance(exc, UnicodeDecodeError):
        return f"undecodable byte at offset {exc.start}"
    text = " ".join(str(exc).split())
    if isinstance(exc, KeyError | IndexError):
        text = f"{type(exc).__name__} {text}".strip()
    return text if len(text) < 160 else text[:160] + "..."


#: Format names in messages.
_TITLES = {"vtk": "legacy VTK", "vtk51": "legacy VTK", "vtu": "VTU", "gmsh": "Gmsh", "gmsh22": "Gmsh",
           "xdmf": "XDMF"}


# ---------------------------------------------------------------------------------------------------- reading
def read_meshio(path: Path, fmt: str) -> HexMesh:
    """Read `path` in meshio format `fmt` (a key of `_READERS`) into a `HexMesh` with ``source=str(path)``.

    **Arguments:**

    - `path`: an existing file.
    - `fmt`: ``"vtk"``, ``"vtu"``, ``"gmsh"``, ``"gmsh22"`` or ``"xdmf"``.

    **Returns:** a `HexMesh` carrying the file's point/cell data, point/cell sets and field data.
    """
    _needs_h5py(path, fmt, MeshReadError)
    data_files = xdmf_data_files(path) if fmt == "xdmf" else []
    try:
        if fmt in ("gmsh", "gmsh22"):
            check_gmsh(path)
        with _meshio_output_as_warnings():
            m = _READERS[fmt](path)
    except OSError as exc:
        if exc.errno is None:
            raise MeshReadError(f"{path}: corrupt or truncated {_TITLES[fmt]} file ({_describe(exc)})") from exc
        raise MeshReadError(f"{path}: cannot read ({exc.strerror})") from exc
    except _READ_ERRORS as exc:
        if isinstance(exc, JaxciError):
            raise
        why = _describe(exc)
        if fmt == "vtk" and (diagnosis := diagnose_vtk(path)) is not None:
            raise MeshReadError(f"{path}: corrupt or truncated legacy VTK file: {diagnosis}") from exc
        if fmt == "vtu" and not why:
            why = f"the arrays disagree with the header, or are cut short: {vtu_header(path)}".rstrip(": ")
        raise MeshReadError(f"{path}: corrupt or truncated {_TITLES[fmt]} file{f' ({why})' if why else ''}") from exc
    if fmt == "vtk":
        check_vtk(path, m)
    elif fmt == "vtu":
        check_vtu(path, m)
    elif fmt == "xdmf":
        check_xdmf(path, m)
    try:
        return HexMesh(**meshio_fields(m, path), input_files=tuple(str(p) for p in data_files))
    except JaxciError:
        raise
    except (ValueError, TypeError, IndexError) as exc:
        raise MeshReadError(f"{path}: inconsistent {_TITLES[fmt]} file ({_describe(exc)})") from exc


def xdmf_data_files(path: Path) -> list[Path]:
    """The files an XDMF file's data items name (``Format="HDF"``: ``name.h5:/dataset``, relative to the XDMF
    file's folder; ``Format="Binary"``: a raw file, as meshio opens it), each checked to be a regular file before
    meshio opens it (a FIFO would hang it). An XML file that does not parse is left to meshio."""
    from xml.etree import ElementTree as ET

    try:
        root = ET.parse(str(path)).getroot()
    except (ET.ParseError, OSError):
        return []
    found: dict[Path, str] = {}
    for item in root.iter("DataItem"):
        kind, text = item.attrib.get("Format"), (item.text or "").strip()
        if not text or kind not in ("HDF", "Binary"):
            continue
        name = text.split(":")[0] if kind == "HDF" else text
        found.setdefault(Path(path).resolve().parent / name if kind == "HDF" else Path(name), name)
    for p, name in found.items():
        check_regular(p, "HDF5 data file" if p.suffix.lower() in (".h5", ".hdf5", ".hdf") else "data file",
                      shown=f"{path}: its data file {name}")
    return list(found)


# ---------------------------------------------------------------------------------------------------- writing
def file_cells(mesh: HexMesh) -> list[CellBlock]:
    """The cell blocks as the file should hold them: hexahedra (and their midside nodes) mirrored back when
    `HexMesh.hex_mirrored`."""
    if not mesh.hex_mirrored:
        return list(mesh.cells)
    return [mirrored_block(b) if b.type == "hexahedron" else b for b in mesh.cells]


def write_meshio(mesh: HexMesh, path: Path, fmt: str) -> None:
    """Write `mesh` to `path` in meshio format `fmt` (a key of `_WRITERS`); `path` is written directly.

    **Arguments:**

    - `mesh`: the mesh; hexahedra are written in the file's own handedness (see `HexMesh.hex_mirrored`).
    - `path`: the file to write (`jaxci.io.write_mesh` passes a temporary name and moves it into place).
    - `fmt`: ``"vtk"``, ``"vtu"``, ``"gmsh"`` (4.1), ``"gmsh22"`` or ``"xdmf"``.

    **Returns:** nothing. Issues one `LossyWriteWarning` listing what the format cannot hold, if anything, before
    writing. `OSError` from writing propagates (`jaxci.io.write_mesh` reports it).
    """
    _needs_h5py(path, fmt, MeshWriteError)
    try:
        m, lost = _to_meshio(mesh, fmt, path)
    except (ValueError, KeyError, IndexError, TypeError) as exc:
        if isinstance(exc, JaxciError):
            raise
        raise MeshWriteError(f"{path}: meshio cannot write this mesh as {_TITLES[fmt]} ({_describe(exc)})") from exc
    warn_lost(path, fmt, lost, stacklevel=4)
    try:
        with _meshio_output_as_warnings(LossyWriteWarning):
            _WRITERS[fmt](path, m)
    except OSError:
        raise
    except (meshio.WriteError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise MeshWriteError(f"{path}: meshio cannot write this mesh as {_TITLES[fmt]} ({_describe(exc)})") from exc


def _to_meshio(mesh: HexMesh, fmt: str, path: Path) -> tuple[meshio.Mesh, list[str]]:
    gmsh = fmt in ("gmsh", "gmsh22")  # VTK, VTU and XDMF keep every point and cell datum, and no field data
    cells = file_cells(mesh)
    point_data = {k: np.asarray(v) for k, v in mesh.point_data.items()}
    cell_data = {k: [np.asarray(a) for a in v] for k, v in mesh.cell_data.items()}
    field_data = {k: v for k, v in mesh.field_data.items() if k not in SOURCE_FIELDS}
    lost = [what for _, what in deck_losses(mesh, fmt)]

    if gmsh:  # cell sets only as Gmsh physical groups
        dropped = sorted(set(mesh.cell_sets) - set(field_data))
        if dropped:
            lost.append(f"cell sets {dropped} (only Gmsh physical groups are kept)")
        if mesh.point_sets:
            lost.append(f"point sets {sorted(mesh.point_sets)}")
    else:  # sets as 0/1 integer data named set:NAME
        for name, idx in mesh.point_sets.items():
            mask = np.zeros(mesh.n_nodes, np.int32)
            mask[np.asarray(idx)] = 1
            point_data[SET_PREFIX + name] = mask
        for name, per_block in mesh.cell_sets.items():
            masks = [np.zeros(len(b.data), np.int32) for b in cells]
            for mask, idx in zip(masks, per_block, strict=True):
                mask[np.asarray(idx)] = 1
            cell_data[SET_PREFIX + name] = masks

    if fmt == "gmsh22" and len(cells) > 1:
        data = sorted(k for k in cell_data if k not in ("gmsh:physical", "gmsh:geometrical"))
        if data:  # meshio 5.3.5 splits Gmsh 2.2 ElementData wrongly over several blocks and cannot read it back
            lost.append(f"cell data {data} (Gmsh 2.2 element data of several cell blocks does not read back)")
            cell_data = {k: v for k, v in cell_data.items() if k not in data}
    if gmsh:  # integer data read back as float64; field data only as physical names
        ints = [k for k, v in point_data.items() if k != "gmsh:dim_tags" and v.dtype.kind in "iub"]
        ints += [k for k, v in cell_data.items() if not k.startswith("gmsh:") and v[0].dtype.kind in "iub"]
        if ints:
            lost.append(f"the integer dtype of {sorted(ints)} (read back as float64)")
        bad = [k for k, v in field_data.items() if np.shape(v) != (2,) or np.asarray(v).dtype.kind not in "iu"]
        if bad:
            lost.append(f"field data {sorted(bad)} (only Gmsh physical names [tag, dim] are kept)")
        field_data = {k: np.asarray(v) for k, v in field_data.items() if k not in bad}
    elif field_data:
        lost.append(f"field data {sorted(field_data)}")
        field_data = {}

    if mesh.node_ids is not None or any(b.ids is not None for b in cells):
        lost.append("node and element ids (nodes and elements are numbered from 1)")

    if gmsh:
        _add_gmsh_tags(cells, cell_data, point_data, mesh.n_nodes, fmt, path)
    m = meshio.Mesh(mesh.points, [(b.type, b.data) for b in cells], point_data=point_data, cell_data=cell_data,
                    field_data=field_data)  # the sets are data or physical groups by now
    return m, lost


def _add_gmsh_tags(cells, cell_data, point_data, n_nodes: int, fmt: str, path: Path) -> None:
    """Give every block Gmsh tags (physical 0, geometrical = block number + 1) and, for 4.1, node entities."""
    if "gmsh:geometrical" not in cell_data:
        cell_data["gmsh:geometrical"] = [np.full(len(b.data), i + 1, np.int32) for i, b in enumerate(cells)]
    if "gmsh:physical" not in cell_data:
        cell_data["gmsh:physical"] = [np.zeros(len(b.data), np.int32) for b in cells]
    if fmt != "gmsh" or "gmsh:dim_tags" in point_data:
        return
    # Gmsh 4.1 groups nodes by geometric entity (dim, tag) and meshio needs every block's entity to own at least
    # one node: all nodes go to the first block of highest dimension, then each other block claims one node.
    dims = [meshio.CellBlock(b.type, b.data[:0]).dim for b in cells]
    geo = [int(g[0]) if len(g) else i + 1 for i, g in enumerate(cell_data["gmsh:geometrical"])]
    main = int(np.argmax(dims))
    dim_tags = np.tile([dims[main], geo[main]], (n_nodes, 1))
    free = np.ones(n_nodes, bool)
    for i, b in enumerate(cells):
        if (dims[i], geo[i]) == (dims[main], geo[main]):
            continue
        cand = b.data.ravel()[free[b.data.ravel()]]
        if len(cand) == 0:
            raise MeshWriteError(f"{path}: cannot give cell block {i} ({b.type}) a Gmsh 4.1 entity; use gmsh22")
        dim_tags[cand[0]] = (dims[i], geo[i])
        free[cand[0]] = False
    if free.sum() == 0:
        raise MeshWriteError(f"{path}: cannot assign Gmsh 4.1 node entities to this mesh; use gmsh22")
    point_data["gmsh:dim_tags"] = dim_tags
