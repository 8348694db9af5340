"""Trust no header: the counts a legacy VTK, VTU or XDMF file announces must match what it holds.

meshio reads what a file holds and believes what its headers say only in part: a legacy VTK file cut inside
CELL_TYPES reads as a smaller mesh, a VTU file with a wrong offset reads with other cells, and a Gmsh file whose
$Elements header disagrees with its element lines reads without complaint. These checks run on every file
`jaxci.io._meshio.read_meshio` reads and raise a `MeshReadError` naming the file and what is missing or wrong:

- legacy VTK (after meshio): POINTS, CELLS, CELL_TYPES, POINT_DATA and CELL_DATA counts against the points and cells
  read (and CELLS' size against the connectivity); when meshio fails on an ASCII file, its sections are walked to
  say which one holds more or fewer values than announced (`diagnose_vtk`);
- VTU (`read_vtu`): NumberOfPoints and NumberOfCells against the arrays; offsets increasing to the connectivity's
  length, each cell as large as its type; cell types meshio would drop are refused;
- XDMF (after meshio): the Dimensions of Geometry, Topology and Attribute data items against the HDF5 arrays;
- Gmsh 2.2 and 4.1: `jaxci.io._gmsh_counts`.
"""

from __future__ import annotations

import re
from pathlib import Path

import meshio
import numpy as np

from ..errors import MeshReadError
from ._deck import is_number

_VTK_HEADER = re.compile(rb"^[ \t]*(POINTS|CELLS|CELL_TYPES|POINT_DATA|CELL_DATA)[ \t]+(-?\d+)(?:[ \t]+(-?\d+))?",
                         re.MULTILINE)


def _cells_held(m: meshio.Mesh) -> tuple[int, int]:
    """Number of cells and of connectivity entries of a meshio mesh."""
    n = sum(len(c.data) for c in m.cells)
    size = sum(int(np.asarray(c.data).size) for c in m.cells)
    return n, size


def check_vtk(path: Path, m: meshio.Mesh) -> None:
    """Legacy VTK: the counts of the section headers against what meshio read."""
    data = path.read_bytes()
    if not re.search(rb"DATASET[ \t]+UNSTRUCTURED_GRID", data[:4096], re.IGNORECASE):
        return
    version = re.match(rb"#\s*vtk DataFile Version\s*(\d+)\.(\d+)", data)
    v5 = version is not None and int(version.group(1)) >= 5
    headers = {}
    for match in _VTK_HEADER.finditer(data):
        headers.setdefault(match.group(1).decode(), (int(match.group(2)), match.group(3) and int(match.group(3))))
    for key, (count, extra) in headers.items():
        if count < 0 or (extra is not None and extra < 0):
            raise MeshReadError(f"{path}: corrupt legacy VTK file: {key} announces a negative count "
                                f"({count}{'' if extra is None else f' {extra}'})")
    n_cells, size = _cells_held(m)
    n_points = len(m.points)
    if (problem := _vtk_index_problem(data, n_points, v5)) is not None:
        raise MeshReadError(f"{path}: corrupt legacy VTK file: {problem}")
    found = {"POINTS": n_points, "CELL_TYPES": n_cells, "POINT_DATA": n_points, "CELL_DATA": n_cells}
    what = {"POINTS": "points", "CELL_TYPES": "cell types", "POINT_DATA": "point data values",
            "CELL_DATA": "cell data values"}
    for key in ("POINTS", "CELL_TYPES", "POINT_DATA", "CELL_DATA"):
        if key in headers and headers[key][0] != found[key]:
            held = "points" if key in ("POINTS", "POINT_DATA") else "cells"
            raise MeshReadError(f"{path}: corrupt or truncated legacy VTK file: {key} announces {headers[key][0]} "
                                f"{what[key]}, the file holds {found[key]} {held}")
    if "CELLS" in headers:
        count, announced_size = headers["CELLS"]
        cells = count - 1 if v5 else count
        if cells != n_cells:
            raise MeshReadError(f"{path}: corrupt or truncated legacy VTK file: CELLS announces {cells} cells, the "
                                f"file holds {n_cells}")
        want = size if v5 else size + n_cells
        if announced_size is not None and announced_size != want:
            raise MeshReadError(f"{path}: corrupt or truncated legacy VTK file: CELLS announces {announced_size} "
                                f"connectivity entries, the cells read hold {want}")


#: A decimal integer of 10 digits or more: possibly beyond the 32-bit integers meshio reads legacy VTK cells as.
_LONG_INT = re.compile(rb"(?<![\w.+-])[+-]?\d{10,}(?![\w.])")


def _vtk_index_problem(data: bytes, n_points: int | None, v5: bool) -> str | None:
    """ASCII legacy VTK: meshio reads the CELLS section as 32-bit integers, so a larger value reads as -1 or wraps
    around (4294967297 would read as node 1). The first value of the section beyond int32, with its cell, in words;
    None when there is none (or the file is binary)."""
    head = data[:4096].split(b"\n", 3)
    if len(head) < 3 or head[2].strip().upper() != b"ASCII":
        return None
    start = re.search(rb"(?m)^[ \t]*CELLS[ \t]+\S+.*$", data)
    if start is None:
        return None
    end = re.compile(rb"(?m)^[ \t]*[A-Za-z_]").search(data, start.end() + 1)
    if v5:  # OFFSETS / CONNECTIVITY lines inside the section
        end = re.compile(rb"(?m)^[ \t]*(CELL_TYPES|POINT_DATA|CELL_DATA|FIELD)\b").search(data, start.end() + 1)
    body = data[start.end() : end.start() if end else len(data)]
    big = next((mt for mt in _LONG_INT.finditer(body) if abs(int(mt.group())) > 2**31 - 1), None)
    if big is None:
        return None
    value = int(big.group())
    has = "" if n_points is None else f" (the file has {n_points} points, indices 0 to {n_points - 1})"
    what = f"CELLS holds {value}"
    if not v5:
        tokens = body[: big.start()].split()
        k = i = 0
        while i < len(tokens):
            try:
                i += 1 + int(tokens[i])
            except ValueError:
                break
            if i <= len(tokens):
                k += 1
        what = f"CELLS lists node index {value} in cell {k}" if i > len(tokens) else \
            f"CELLS gives cell {k} {value} nodes"
    return f"{what}, beyond the 32-bit integers of legacy VTK cells and any node index{has}"


def diagnose_vtk(path: Path) -> str | None:
    """Which section of an ASCII legacy VTK file holds more or fewer values than its header announces (for a
    file meshio could not read); None when they all agree, or the file is binary or has sections not walked."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    v5 = re.match(rb"#\s*vtk DataFile Version\s*([5-9])", data) is not None
    if (problem := _vtk_index_problem(data, None, v5)) is not None:
        return problem
    lines = data.decode("latin-1").splitlines()
    if len(lines) < 4 or lines[2].strip().upper() != "ASCII":
        return None
    v5 = re.match(r"#\s*vtk DataFile Version\s*([5-9])", lines[0]) is not None
    tok = " ".join(lines[3:]).split()
    i, per = 0, None  # per: the count of the current POINT_DATA / CELL_DATA

    def take(need: int, what: str) -> str | None:
        nonlocal i
        n = 0
        while n <= need and i + n < len(tok) and is_number(tok[i + n]):
            n += 1
        i += min(n, need)
        if n < need:
            return f"{what}, the file holds {n} values"
        if n > need:
            return f"{what}, the file holds more values"
        return None

    try:
        while i < len(tok):
            kw = tok[i].upper()
            if kw == "DATASET":
                i += 2
                continue
            if kw == "POINTS":
                n = int(tok[i + 1])
                i += 3
                msg = take(3 * n, f"POINTS announces {n} points ({3 * n} values)")
            elif kw == "CELLS" and v5:
                n, m = int(tok[i + 1]), int(tok[i + 2])
                i += 3
                msg = None
                for sub, count in (("OFFSETS", n), ("CONNECTIVITY", m)):
                    if i < len(tok) and tok[i].upper() == sub:
                        i += 2
                        msg = msg or take(count, f"CELLS announces {count} "
                                                 f"{'offsets' if sub == 'OFFSETS' else 'connectivity entries'}")
            elif kw == "CELLS":
                n, m = int(tok[i + 1]), int(tok[i + 2])
                i += 3
                msg = take(m, f"CELLS announces {n} cells in {m} values")
            elif kw == "CELL_TYPES":
                n = int(tok[i + 1])
                i += 2
                msg = take(n, f"CELL_TYPES announces {n} cell types")
            elif kw in ("POINT_DATA", "CELL_DATA"):
                per = int(tok[i + 1])
                i += 2
                continue
            elif kw == "SCALARS":
                comps = int(tok[i + 3]) if is_number(tok[i + 3]) else 1
                i += 4 if is_number(tok[i + 3]) else 3
                if i < len(tok) and tok[i].upper() == "LOOKUP_TABLE":
                    i += 2
                msg = take(per * comps, f"SCALARS announce {per * comps} values")
            elif kw in ("VECTORS", "NORMALS", "TENSORS"):
                i += 3
                k = 9 if kw == "TENSORS" else 3
                msg = take(per * k, f"{kw} announce {per * k} values")
            elif kw == "FIELD":
                arrays = int(tok[i + 2])
                i += 3
                msg = None
                for k in range(arrays):
                    if i >= len(tok):
                        msg = f"FIELD announces {arrays} arrays, the file holds {k}"
                        break
                    name, comps, tuples = tok[i], int(tok[i + 1]), int(tok[i + 2])
                    i += 4
                    msg = take(comps * tuples, f"FIELD array {name} announces {comps * tuples} values")
                    if msg is not None:
                        break
            elif kw == "LOOKUP_TABLE":
                n = int(tok[i + 2])
                i += 3
                msg = take(4 * n, f"LOOKUP_TABLE announces {n} colours")
            elif i + 1 >= len(tok) and kw.isalpha():
                return f"the file ends inside the header of a section ({tok[i]!r})"
            else:
                return None  # METADATA, COLOR_SCALARS, ...: not walked
            if msg is not None:
                return msg
    except IndexError:
        return f"the file ends inside the header of a section ({' '.join(tok[i:])!r})"
    except (ValueError, TypeError):
        return None
    return None


def check_vtu(path: Path, m: meshio.Mesh) -> None:
    """VTU: NumberOfPoints / NumberOfCells of each piece, summed, against what meshio read."""
    head = path.read_bytes()
    pieces = re.findall(rb"<Piece\b[^>]*>", head)
    n_points = n_cells = 0
    for p in pieces:
        pts = re.search(rb'NumberOfPoints\s*=\s*"(\d+)"', p)
        cls = re.search(rb'NumberOfCells\s*=\s*"(\d+)"', p)
        if pts is None or cls is None:
            return
        n_points += int(pts.group(1))
        n_cells += int(cls.group(1))
    if not pieces:
        return
    held, _ = _cells_held(m)
    if n_points != len(m.points) or n_cells != held:
        raise MeshReadError(f"{path}: corrupt or truncated VTU file: the header announces {n_points} points and "
                            f"{n_cells} cells, the arrays hold {len(m.points)} points and {held} cells")


def read_vtu(path: Path) -> meshio.Mesh:
    """Read a VTU file as ``meshio.vtu.read`` does, and check each piece's cell arrays: as many offsets and types as
    NumberOfCells, offsets increasing to the connectivity's length, and each cell holding as many nodes as its
    type has (meshio slices the connectivity by the offsets and the type's size, so a wrong offset or type would
    silently give other cells); a cell type meshio cannot read (which it would drop) is refused too. When meshio
    fails, the same checks say why if they can."""
    from xml.etree import ElementTree as ET

    from meshio.vtu import _vtu

    try:
        try:
            root = ET.parse(str(path)).getroot()
        except ET.ParseError:
            root = _vtu._parse_raw_binary(str(path))
        grid, appended = _vtu.get_grid(root)
    except Exception:  # noqa: BLE001 - whatever is wrong, meshio's reader reports it below
        grid = None
    try:
        reader = _vtu.VtuReader(str(path))
    except Exception:
        if grid is not None:
            bare = _vtu.VtuReader.__new__(_vtu.VtuReader)  # only its array decoding, set up as its __init__ does
            bare.compression = root.attrib.get("compressor")
            bare.header_type = root.attrib.get("header_type", "UInt32")
            bare.byte_order = root.attrib.get("byte_order")
            bare.appended_data = appended
            try:
                _check_vtu_pieces(path, grid, bare)
            except MeshReadError:
                raise
            except Exception:  # noqa: BLE001 - no better diagnosis: meshio's error stands
                pass
        raise
    mesh = meshio.Mesh(reader.points, reader.cells, point_data=reader.point_data, cell_data=reader.cell_data,
                       field_data=reader.field_data)
    if grid is not None:
        _check_vtu_pieces(path, grid, reader)
    return mesh


def _check_vtu_pieces(path: Path, grid, reader) -> None:
    for k, piece in enumerate(grid.findall("Piece")):
        cells = piece.find("Cells")
        if cells is None:
            continue
        arrays = {da.attrib.get("Name"): np.asarray(reader.read_data(da)).ravel() for da in cells}
        _check_vtu_piece(path, k, int(piece.attrib["NumberOfCells"]), arrays)


def _check_vtu_piece(path: Path, k: int, n_cells: int, arrays: dict) -> None:
    from meshio._vtk_common import vtk_to_meshio_type

    where = f"{path}: corrupt or truncated VTU file: piece {k}"
    offsets, types, conn = (arrays.get(n) for n in ("offsets", "types", "connectivity"))
    if offsets is None or types is None or conn is None:
        raise MeshReadError(f"{where} lacks one of the cell arrays offsets, types, connectivity")
    if (types == 42).any():
        return  # polyhedra: faces and face offsets, left to meshio
    if len(offsets) != n_cells or len(types) != n_cells:
        raise MeshReadError(f"{where} announces {n_cells} cells (NumberOfCells) and holds {len(offsets)} offsets and "
                            f"{len(types)} types")
    sizes = np.diff(np.concatenate([[0], offsets.astype(np.int64)]))
    if n_cells and (sizes < 1).any():
        c = int(np.flatnonzero(sizes < 1)[0])
        raise MeshReadError(f"{where}: the offsets do not increase at cell {c} ({int(offsets[c])})")
    if n_cells and int(offsets[-1]) != len(conn):
        raise MeshReadError(f"{where}: the last offset is {int(offsets[-1])}, the connectivity holds {len(conn)} "
                            f"entries")
    for t in np.unique(types).tolist():
        name = vtk_to_meshio_type.get(int(t))
        if name is None:
            raise MeshReadError(f"{path}: holds {int((types == t).sum())} cells of VTK type {int(t)}, which jaxci "
                                f"cannot read (it would drop them)")
        width = meshio._common.num_nodes_per_cell.get(name)
        bad = (types == t) & (sizes != width) if width else np.zeros(len(types), bool)
        if bad.any():
            c = int(np.flatnonzero(bad)[0])
            raise MeshReadError(f"{where}: cell {c} has {int(sizes[c])} nodes by its offsets, but its type {int(t)} "
                                f"({name}) has {width} ({int(bad.sum())} such cells)")


def check_xdmf(path: Path, m: meshio.Mesh) -> None:
    """XDMF: the Dimensions of the Geometry, Topology and Attribute data items (and Topology's NumberOfElements)
    against the arrays meshio read from the HDF5 file (meshio reads the arrays whole, whatever the XML says)."""
    from xml.etree import ElementTree as ET

    try:
        root = ET.parse(str(path)).getroot()
    except (ET.ParseError, OSError):
        return
    grids = root.findall(".//Grid")
    if len(grids) != 1:
        return  # collections and time series: left to meshio
    grid = grids[0]
    n_points, n_cells = len(m.points), sum(len(c.data) for c in m.cells)

    def dims(item) -> list[int] | None:
        d = item.find("DataItem") if item is not None else None
        try:
            return [int(v) for v in d.attrib["Dimensions"].split()] if d is not None else None
        except (KeyError, ValueError):
            return None

    def fail(what: str):
        raise MeshReadError(f"{path}: corrupt XDMF file: {what}")

    geo = dims(grid.find("Geometry"))
    if geo is not None and int(np.prod(geo)) != 3 * n_points:
        fail(f"the Geometry announces {' x '.join(map(str, geo))} values, the data hold {n_points} points")
    topo = grid.find("Topology")
    if topo is not None:
        announced = topo.attrib.get("NumberOfElements")
        if announced is not None and int(announced) != n_cells:
            fail(f"the Topology announces {announced} elements, the data hold {n_cells}")
        t = dims(topo)
        if topo.attrib.get("TopologyType", "").lower() != "mixed" and len(m.cells) == 1:
            width = int(np.shape(m.cells[0].data)[1])
            if t is not None and (t[0] != n_cells or (len(t) > 1 and t[1] != width)):
                fail(f"the Topology data item announces {' x '.join(map(str, t))} values, the data hold {n_cells} "
                     f"elements of {width} nodes")
            per = topo.attrib.get("NodesPerElement")
            if per is not None and per.strip() != str(width):
                fail(f"the Topology announces {per} nodes per element, the data hold {width}")
    for att in grid.findall("Attribute"):
        d = dims(att)
        want = n_points if att.attrib.get("Center", "Node") == "Node" else n_cells
        if d is not None and att.attrib.get("Center", "Node") in ("Node", "Cell") and d[0] != want:
            fail(f"attribute {att.attrib.get('Name')!r} announces {d[0]} values, the mesh has {want} "
                 f"{'points' if want == n_points else 'cells'}")


def vtu_header(path: Path) -> str:
    """The counts a VTU file's pieces announce, for a message about a file meshio could not read."""
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError:
        return ""
    counts = re.findall(rb'Number(?:OfPoints|OfCells)\s*=\s*"\d+"', head)
    return " ".join(c.decode() for c in counts[:4])
