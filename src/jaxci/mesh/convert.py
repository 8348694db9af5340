"""A `meshio.Mesh` object as the arguments of a `HexMesh` (no file I/O, no meshio import): what
`jaxci.io` builds from the files meshio reads, and what `jaxci.mesh.as_hex_mesh` builds from a `meshio.Mesh` a
user passes to a public function. Here, below both, so that the model does not import the formats.
"""

from __future__ import annotations

import numpy as np

from ..errors import MeshReadError
from .blocks import CellBlock

#: Prefix of the point / cell data that carry a point / cell set in formats without sets.
SET_PREFIX = "set:"


def native_byte_order(a) -> np.ndarray:
    """`a` as an array in the machine's byte order (a big-endian array from a binary file converted)."""
    a = np.asarray(a)
    return a.astype(a.dtype.newbyteorder("="), copy=False) if a.dtype.byteorder not in "=|" else a


def set_mask(a) -> np.ndarray | None:
    """The boolean mask of a ``set:NAME`` data array, or None if it is not 0/1 integer data."""
    a = np.asarray(a)
    if a.ndim != 1 or a.dtype.kind not in "iub" or not np.isin(a, (0, 1)).all():
        return None
    return a.astype(bool)


def meshio_fields(m, path) -> dict:
    """The `HexMesh` constructor's arguments for a `meshio.Mesh` `m` (duck-typed: meshio is not imported here) read
    from `path` (a path or a name for messages): points, cell blocks, point and cell data, point and cell sets
    (``set:NAME`` 0/1 data arrays and meshio's sets), field data, ``source=str(path)``; `MeshReadError` for a
    mesh without nodes or cells."""
    points = np.asarray(m.points)
    n = len(points)
    if n == 0:
        raise MeshReadError(f"{path}: no nodes in the file (empty or truncated)")
    if not any(len(c.data) for c in m.cells):
        raise MeshReadError(f"{path}: {n} nodes but no cells (truncated file, or not a volume mesh)")
    cells = tuple(CellBlock(c.type, np.asarray(c.data)) for c in m.cells)

    point_data, point_sets = {}, {}
    for name, a in m.point_data.items():
        mask = set_mask(a) if name.startswith(SET_PREFIX) and len(a) == n else None
        if mask is None:
            point_data[name] = native_byte_order(a)
        else:
            point_sets[name[len(SET_PREFIX) :]] = np.flatnonzero(mask)
    for name, idx in m.point_sets.items():
        point_sets[name] = np.asarray(idx, dtype=np.int64)

    cell_data, cell_sets = {}, {}
    for name, arrays in m.cell_data.items():
        masks = [set_mask(a) for a in arrays] if name.startswith(SET_PREFIX) else [None]
        if any(mk is None for mk in masks):
            cell_data[name] = [native_byte_order(a) for a in arrays]
        else:
            cell_sets[name[len(SET_PREFIX) :]] = [np.flatnonzero(mk) for mk in masks]
    for name, per_block in m.cell_sets.items():
        if name == "gmsh:bounding_entities":  # entity tags of the Gmsh geometry, not cell indices
            continue
        cell_sets[name] = [
            np.zeros(0, np.int64) if idx is None else np.asarray(idx, dtype=np.int64) for idx in per_block
        ]

    return dict(
        points=np.asarray(points, dtype=np.float64),
        cells=cells,
        point_data=point_data,
        cell_data=cell_data,
        point_sets=point_sets,
        cell_sets=cell_sets,
        field_data={k: native_byte_order(v) if isinstance(v, np.ndarray) else v for k, v in m.field_data.items()},
        source=str(path),
    )
