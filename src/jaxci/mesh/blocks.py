"""Cell blocks: the cells of one type of a mesh (`CellBlock`), the node counts of the cell types jaxci knows, and
the mirror that turns a left-handed hexahedron right-handed (numpy only).

A block's connectivity is an integer array of shape ``(n_cells, nodes_per_cell)`` of 0-based node indices, in VTK's
node order (the hexahedron's: `jaxci.mesh`); quadratic cells are held as their linear cell plus `CellBlock.midside`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import MeshError

#: Permutation that mirrors a hexahedron (swaps the two quadrilateral faces 0123 and 4567). It is its own
#: inverse; it turns a left-handed element (all eight corner determinants negative) into a right-handed one.
MIRROR_HEX = np.array([4, 5, 6, 7, 0, 1, 2, 3], dtype=np.int64)

#: Permutation of the 12 hexahedron edges (`EDGES`) that goes with `MIRROR_HEX`.
MIRROR_HEX_EDGES = np.array([4, 5, 6, 7, 0, 1, 2, 3, 8, 9, 10, 11], dtype=np.int64)

#: Number of nodes of the cell types jaxci knows (meshio names).
NODES_PER_CELL = {
    "vertex": 1,
    "line": 2,
    "triangle": 3,
    "quad": 4,
    "tetra": 4,
    "pyramid": 5,
    "wedge": 6,
    "hexahedron": 8,
    "line3": 3,
    "triangle6": 6,
    "quad8": 8,
    "quad9": 9,
    "tetra10": 10,
    "hexahedron20": 20,
    "hexahedron27": 27,
    "wedge15": 15,
    "pyramid13": 13,
}


@dataclasses.dataclass(frozen=True, eq=False)
class CellBlock:
    """One block of cells of a single type.

    **Arguments:**

    - `type`: the meshio cell type name (``"hexahedron"``, ``"quad"``, ``"wedge"``, ...).
    - `data`: connectivity, an integer array of shape ``(n_cells, nodes_per_cell)`` of 0-based node indices.
    - `ids`: optional external element ids (ANSYS, Abaqus), shape ``(n_cells,)``.
    - `midside`: optional midside nodes of quadratic cells, shape ``(n_cells, n_edges)`` (edges in `EDGES` order;
      -1 where an edge has none); only for ``hexahedron``, ``wedge``, ``pyramid`` and ``tetra`` blocks.
    """

    type: str
    data: np.ndarray
    ids: np.ndarray | None = None
    midside: np.ndarray | None = None


def block_label(blk: CellBlock, row: int) -> str:
    """A readable label of cell `row` (0-based) of `blk`, with its file id if any."""
    if blk.ids is not None:
        return f"{int(np.asarray(blk.ids)[row])} (index {row})"
    return str(row)


def mirrored_block(b: CellBlock) -> CellBlock:
    """A hexahedron block mirrored by `MIRROR_HEX` (its midside nodes by `MIRROR_HEX_EDGES`)."""
    mid = None if b.midside is None else np.asarray(b.midside)[:, MIRROR_HEX_EDGES]
    return CellBlock(b.type, np.asarray(b.data)[:, MIRROR_HEX], b.ids, mid)


def int_array(a, name: str, dtype=np.int64) -> np.ndarray:
    """`a` as an array of node indices of `dtype` (None: an integer array as it is; floats holding whole numbers
    accepted, as int64); `MeshError` naming `name` otherwise."""
    arr = np.asarray(a)
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind == "f" and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
            arr = arr.astype(np.int64)
        else:
            raise MeshError(f"{name}: connectivity must be integer node indices, got dtype {arr.dtype}")
    return arr if dtype is None else arr.astype(dtype, copy=False)
