"""Midside nodes of quadratic cells: the node on each edge of a cell held as its linear cell plus
`CellBlock.midside` (edges in the order of `jaxci.cells.EDGES`, -1 where an edge has none; numpy only).

`check_midside` checks one block's midside array, `midside_table` gathers the midside nodes of all blocks with the
corner nodes of their edges (checking that each belongs to one edge and is no cell's corner), and `place_midside`
moves them with their edges when the corner nodes move (`HexMesh.with_points`).
"""

from __future__ import annotations

import numpy as np

from ..cells import EDGES
from ..errors import MeshError
from .blocks import CellBlock, block_label, int_array
from .frame import unit_frame

#: Relative distance from its edge's midpoint (to the edge length) below which a midside node counts as ON the
#: midpoint (a straight edge; files keep 13-14 digits): `HexMesh.with_points` then puts it exactly there.
MIDPOINT_TOLERANCE = 1e-9


def check_midside(blk: CellBlock, bi: int, data: np.ndarray, ids, n: int, where: str) -> np.ndarray:
    """The midside nodes of block `bi` as an int64 array of shape ``(n_cells, n_edges)``, checked: a type with
    edges (`EDGES`), one entry per edge, indices in [-1, `n`); `MeshError` otherwise. `data` is the block's
    connectivity, `ids` its element ids (for the message), `where` the message's prefix."""
    mid = int_array(blk.midside, f"{where}midside nodes of cell block {bi} ({blk.type})")
    if blk.type not in EDGES:
        raise MeshError(f"{where}cell block {bi} ({blk.type}) has midside nodes; only hexahedron, wedge, "
                        f"pyramid and tetra blocks can (quadratic cells as linear cells plus midside nodes)")
    shape = (len(data), len(EDGES[blk.type]))
    if mid.shape != shape:
        raise MeshError(f"{where}midside nodes of cell block {bi} ({blk.type}) have shape {mid.shape}, "
                        f"expected {shape}")
    bad = (mid < -1) | (mid >= n)
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        raise MeshError(f"{where}{blk.type} element {block_label(CellBlock(blk.type, data, ids), row)} "
                        f"has midside node index {int(mid[row][bad[row]][0])}, out of range [0, {n})")
    return mid


def midside_table(blocks, corner_used: np.ndarray, where: str, label) -> tuple[np.ndarray, np.ndarray]:
    """Midside nodes of all blocks (sorted, unique) and their edges' corner nodes; checks that each node belongs
    to one edge and is no cell's corner (`MeshError` naming the node and both elements otherwise)."""
    rows = []  # (midside node, corner a, corner b, block, cell)
    for bi, b in enumerate(blocks):
        if b.midside is None or not len(b.data):
            continue
        mid = np.asarray(b.midside)
        ends = np.asarray(b.data)[:, EDGES[b.type]]  # (N, E, 2)
        cell = np.broadcast_to(np.arange(len(mid))[:, None], mid.shape)
        has = mid >= 0
        lo, hi = np.sort(ends, axis=2)[..., 0], np.sort(ends, axis=2)[..., 1]
        rows.append(np.stack([mid[has], lo[has], hi[has], np.full(int(has.sum()), bi), cell[has]], axis=1))
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.int64)
    t = np.concatenate(rows)
    t = t[np.lexsort((t[:, 4], t[:, 3], t[:, 0]))]

    def elem(r) -> str:
        blk = blocks[int(r[3])]
        return f"{blk.type} element {block_label(blk, int(r[4]))}"

    corner = corner_used[t[:, 0]]
    if corner.any():
        r = t[int(np.flatnonzero(corner)[0])]
        raise MeshError(
            f"{where}node {label(int(r[0]))} is a midside node of {elem(r)} (edge {label(int(r[1]))}-"
            f"{label(int(r[2]))}) and a corner node of a cell; a midside node belongs to one edge only"
        )
    same = t[1:, 0] == t[:-1, 0]
    clash = same & ((t[1:, 1] != t[:-1, 1]) | (t[1:, 2] != t[:-1, 2]))
    if clash.any():
        k = int(np.flatnonzero(clash)[0])
        r, s = t[k], t[k + 1]
        raise MeshError(
            f"{where}midside node {label(int(r[0]))} is shared inconsistently: it lies on edge "
            f"{label(int(r[1]))}-{label(int(r[2]))} of {elem(r)} but on edge {label(int(s[1]))}-{label(int(s[2]))} "
            f"of {elem(s)} ({int(clash.sum())} such nodes); a midside node belongs to one edge only"
        )
    first = np.concatenate([[True], ~same])
    return t[first, 0], t[first][:, 1:3]


def place_midside(old: np.ndarray, new: np.ndarray, nodes: np.ndarray, ends: np.ndarray, how: str) -> int:
    """Puts the midside nodes `nodes` ``(m,)`` of `new` ``(n_nodes, 3)`` (in place) on the midpoints of their edges'
    corner nodes `ends` ``(m, 2)`` in `new`: ``how="midpoint"`` exactly there, ``"follow"`` plus the offset each had
    from its edge's midpoint in `old` ``(n_nodes, 3)`` (0 below `MIDPOINT_TOLERANCE` times the edge length).

    **Returns:** how many keep an offset (nodes on curved edges; 0 for ``"midpoint"``).
    """
    a, b = ends[:, 0], ends[:, 1]
    centre = 0.5 * (new[a] + new[b])
    curved = 0
    if how == "follow":
        offset = old[nodes] - 0.5 * (old[a] + old[b])
        unit = unit_frame(old)[1]  # lengths compared in the unit frame: no overflow of squares at 1e300
        length = np.linalg.norm((old[b] - old[a]) / unit, axis=1)
        straight = np.linalg.norm(offset / unit, axis=1) <= MIDPOINT_TOLERANCE * length
        offset[straight] = 0.0
        curved = int((~straight).sum())
        centre += offset
    new[nodes] = centre
    return curved
