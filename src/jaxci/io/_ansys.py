"""ANSYS meshes: the brick model shared by the NLIST/ELIST listing reader and the APDL NBLOCK/EBLOCK reader/writer.

Both ANSYS text formats describe a mesh the same way: node numbers with coordinates, and solid bricks (SOLID185,
or the corner nodes of SOLID186) with an element number, the attributes MAT TYP REL ESY SEC and the eight nodes
I J K L M N O P. I J K L go around one face, M N O P around the opposite one, M above I: that is VTK's
hexahedron order 0..7 unchanged. ANSYS writes wedges, pyramids and tetrahedra as degenerate bricks, which jaxci
turns into proper cells (kept and written back, not smoothed as hexahedra):

| ANSYS nodes I..P  | shape        | jaxci cell block, VTK node order |
|-------------------|--------------|----------------------------------|
| I J K K M N O O   | wedge/prism  | ``wedge``   (I, J, K, M, N, O)   |
| I J K L M M M M   | pyramid      | ``pyramid`` (I, J, K, L, M)      |
| I J K K M M M M   | tetrahedron  | ``tetra``   (I, J, K, M)         |

The wedge keeps the brick's winding: triangle 0 1 2 turns counter-clockwise seen from triangle 3 4 5, as in Gmsh,
ANSYS and VTK >= 9.7 (VTK before 9.7 numbered wedges the opposite way round and shows these with negative volume).
Any other repeated-node pattern is an error. ANSYS node numbers become `HexMesh.node_ids`, element numbers
`CellBlock.ids`, and MAT TYP REL ESY SEC the integer cell data ``ansys:mat``, ``ansys:typ``, ``ansys:rel``,
``ansys:esy``, ``ansys:sec``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import MeshReadError, MeshWriteError
from ..mesh import CellBlock, HexMesh

#: Names of the cell data that hold an ANSYS element's attributes, in ELIST column order.
ATTRIBUTES = ("ansys:mat", "ansys:typ", "ansys:rel", "ansys:esy", "ansys:sec")
#: Attribute values given to elements that have none (a mesh read from another format).
DEFAULT_ATTRIBUTES = (1, 1, 1, 0, 1)

#: Columns of a brick's I..P that make each jaxci cell type, and the number of distinct nodes it has.
_FROM_BRICK = {
    "hexahedron": ([0, 1, 2, 3, 4, 5, 6, 7], 8),
    "wedge": ([0, 1, 2, 4, 5, 6], 6),
    "pyramid": ([0, 1, 2, 3, 4], 5),
    "tetra": ([0, 1, 2, 4], 4),
}
#: Inverse: which node of each cell goes to I..P of the degenerate brick ANSYS stores.
TO_BRICK = {
    "hexahedron": [0, 1, 2, 3, 4, 5, 6, 7],
    "wedge": [0, 1, 2, 2, 3, 4, 5, 5],
    "pyramid": [0, 1, 2, 3, 4, 4, 4, 4],
    "tetra": [0, 1, 2, 2, 3, 3, 3, 3],
}


@dataclasses.dataclass(frozen=True)
class Bricks:
    """An ANSYS mesh as its text formats hold it; rows keep where they came from for error messages.

    **Arguments:**

    - `node_ids`: node numbers, shape ``(n,)``; `points`: their coordinates, shape ``(n, 3)``.
    - `elem_ids`: element numbers, shape ``(m,)``; `attrs`: MAT TYP REL ESY SEC, shape ``(m, 5)``.
    - `corners`: node numbers I..P of each brick, shape ``(m, 8)``.
    - `files`: the files read; `node_src`, `elem_src`: (file index, line number) of each row, shapes ``(n, 2)``
      and ``(m, 2)``.
    - `n_midside`: how many elements were listed with 20 nodes (SOLID186: only the 8 corners are kept).
    """

    node_ids: np.ndarray
    points: np.ndarray
    elem_ids: np.ndarray
    attrs: np.ndarray
    corners: np.ndarray
    files: tuple[str, ...]
    node_src: np.ndarray
    elem_src: np.ndarray
    n_midside: int = 0

    def where_node(self, k: int) -> str:
        return f"{self.files[self.node_src[k, 0]]}, line {self.node_src[k, 1]}"

    def where_elem(self, k: int) -> str:
        return f"{self.files[self.elem_src[k, 0]]}, line {self.elem_src[k, 1]}"


def _first_duplicate(ids: np.ndarray) -> tuple[int, int] | None:
    """Positions (first, second) of the first repeated value of `ids` in file order, or None."""
    order = np.argsort(ids, kind="stable")
    same = np.flatnonzero(ids[order][1:] == ids[order][:-1])
    if len(same) == 0:
        return None
    pairs = np.stack([order[same], order[same + 1]], axis=1)
    return tuple(int(p) for p in pairs[np.argmin(pairs[:, 1])])


def to_hexmesh(b: Bricks, source: str, node_list: str) -> HexMesh:
    """Build the `HexMesh` of an ANSYS mesh: map node numbers, turn degenerate bricks into cells.

    **Arguments:** `b` the parsed rows; `source` the value of `HexMesh.source` (the file or files read);
    `node_list` what the nodes came from, for messages (``"NLIST"``, ``"NBLOCK"``).

    **Returns:** a `HexMesh` with blocks ``hexahedron``, then ``wedge``, ``pyramid``, ``tetra`` when present.
    """
    if (dup := _first_duplicate(b.node_ids)) is not None:
        i, j = dup
        raise MeshReadError(f"{b.where_node(j)}: node {b.node_ids[j]} listed twice (first at {b.where_node(i)})")
    if (dup := _first_duplicate(b.elem_ids)) is not None:
        i, j = dup
        raise MeshReadError(
            f"{b.where_elem(j)}: element {b.elem_ids[j]} listed twice (first at {b.where_elem(i)})"
        )
    order = np.argsort(b.node_ids)
    sorted_ids = b.node_ids[order]
    pos = np.minimum(np.searchsorted(sorted_ids, b.corners), len(sorted_ids) - 1)
    missing = sorted_ids[pos] != b.corners
    if missing.any():
        k, c = (int(v) for v in np.argwhere(missing)[0])
        raise MeshReadError(
            f"{b.where_elem(k)}: element {b.elem_ids[k]} references node {b.corners[k, c]}, which is not in "
            f"the {node_list} ({int(missing.any(axis=1).sum())} such elements)"
        )
    conn = order[pos]  # (m, 8) 0-based node indices

    srt = np.sort(conn, axis=1)
    distinct = 1 + (srt[:, 1:] != srt[:, :-1]).sum(axis=1)
    c = conn
    kl, op, mn, no = c[:, 2] == c[:, 3], c[:, 6] == c[:, 7], c[:, 4] == c[:, 5], c[:, 5] == c[:, 6]
    kind = {
        "hexahedron": distinct == 8,
        "wedge": kl & op & (distinct == 6),
        "pyramid": mn & no & op & (distinct == 5),
        "tetra": kl & mn & no & op & (distinct == 4),
    }
    known = np.zeros(len(c), bool)
    for mask in kind.values():
        known |= mask
    if not known.all():
        k = int(np.flatnonzero(~known)[0])
        raise MeshReadError(
            f"{b.where_elem(k)}: element {b.elem_ids[k]} repeats nodes (I..P = "
            f"{' '.join(str(v) for v in b.corners[k])}) in a way that is not a wedge (K=L, O=P), pyramid "
            f"(M=N=O=P) or tetrahedron (K=L, M=N=O=P)"
        )

    blocks, cell_data = [], {name: [] for name in ATTRIBUTES}
    for cell_type, mask in kind.items():
        if not mask.any():
            continue
        cols, _ = _FROM_BRICK[cell_type]
        blocks.append(CellBlock(cell_type, c[mask][:, cols], b.elem_ids[mask]))
        for a, name in enumerate(ATTRIBUTES):
            cell_data[name].append(b.attrs[mask, a])
    notes = []
    converted = {t: int(kind[t].sum()) for t in ("wedge", "pyramid", "tetra") if kind[t].any()}
    if converted:
        parts = ", ".join(f"{n} to {t}" for t, n in converted.items())
        notes.append(
            f"{sum(converted.values())} degenerate bricks converted ({parts}); kept and written back, not "
            f"smoothed as hexahedra"
        )
    if b.n_midside:
        notes.append(
            f"{b.n_midside} elements listed with 20 nodes (SOLID186): read as 8-node bricks from their corner "
            f"nodes I..P; the midside nodes are kept as unreferenced nodes"
        )
    return HexMesh(
        np.asarray(b.points, dtype=np.float64),
        tuple(blocks),
        cell_data=cell_data,
        node_ids=b.node_ids,
        source=source,
        notes=tuple(notes),
    )


def from_hexmesh(mesh: HexMesh, cells: list[CellBlock], where: str) -> tuple[Bricks, list[str]]:
    """The ANSYS bricks of `mesh` for writing, and the cell types that ANSYS bricks cannot hold.

    **Arguments:**

    - `mesh`: the mesh (node ids, ``ansys:*`` cell data).
    - `cells`: its cell blocks as the file should hold them (`jaxci.io._meshio.file_cells`).
    - `where`: the file being written, for messages.

    **Returns:** `(bricks, dropped)`; `dropped` names the blocks left out (``"12 quad"``). Nodes without ids are
    numbered 1..n, elements without ids from one past the largest element id.
    """
    node_ids = np.arange(1, mesh.n_nodes + 1) if mesh.node_ids is None else np.asarray(mesh.node_ids, np.int64)
    known_ids = [np.asarray(blk.ids) for blk in cells if blk.ids is not None and blk.type in TO_BRICK]
    next_id = int(max((ids.max() for ids in known_ids if len(ids)), default=0)) + 1
    corners, elem_ids, attrs, dropped = [], [], [], []
    for i, blk in enumerate(cells):
        if blk.type not in TO_BRICK:
            dropped.append(f"{len(blk.data)} {blk.type}")
            continue
        n = len(blk.data)
        corners.append(node_ids[blk.data[:, TO_BRICK[blk.type]]])
        if blk.ids is None:
            elem_ids.append(np.arange(next_id, next_id + n))
            next_id += n
        else:
            elem_ids.append(np.asarray(blk.ids, np.int64))
        cols = []
        for name, default in zip(ATTRIBUTES, DEFAULT_ATTRIBUTES, strict=True):
            values = mesh.cell_data[name][i] if name in mesh.cell_data else np.full(n, default)
            cols.append(np.asarray(values).astype(np.int64))
        attrs.append(np.stack(cols, axis=1))
    empty8 = np.zeros((0, 8), np.int64)
    b = Bricks(
        node_ids=node_ids,
        points=mesh.points,
        elem_ids=np.concatenate(elem_ids) if elem_ids else np.zeros(0, np.int64),
        attrs=np.concatenate(attrs) if attrs else np.zeros((0, 5), np.int64),
        corners=np.concatenate(corners) if corners else empty8,
        files=(where,),
        node_src=np.zeros((mesh.n_nodes, 2), np.int64),
        elem_src=np.zeros((sum(map(len, elem_ids)), 2), np.int64),
    )
    for ids, what in ((b.node_ids, "node"), (b.elem_ids, "element")):
        if (dup := _first_duplicate(ids)) is not None:
            raise MeshWriteError(f"{where}: {what} id {ids[dup[1]]} is used twice; ANSYS ids must be unique")
        if len(ids) and ids.min() < 1:
            raise MeshWriteError(f"{where}: {what} id {ids.min()} is not positive; ANSYS ids start at 1")
    return b, dropped
