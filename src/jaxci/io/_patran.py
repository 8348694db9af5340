"""Node order of the solid elements of Exodus II and Nastran (both follow PATRAN's element library) against jaxci's.

The corner nodes are numbered as VTK numbers them (`jaxci.mesh`): a brick's 1-4 around one face, 5-8 around the
opposite face; a wedge's 1-3 and 4-6 its two triangles; a pyramid's 1-4 its base and 5 its apex. The midside nodes
come in PATRAN's edge order, which differs from `jaxci.cells.EDGES` for bricks (PATRAN: the edges of face 1-2-3-4,
then the four edges joining the faces, then those of face 5-6-7-8; jaxci: both faces' edges, then the joining
edges) and wedges; `MIDSIDE_ORDER` maps one to the other (each permutation is its own inverse).
"""

from __future__ import annotations

import numpy as np

from ..mesh import CellBlock, mirrored_block

#: Cell type -> positions, in the file's midside node list, of the midside nodes of `jaxci.cells.EDGES` (edge k
#: of jaxci's order is the file's midside node ``MIDSIDE_ORDER[type][k]``); also file order from jaxci's.
MIDSIDE_ORDER = {
    "hexahedron": np.array([0, 1, 2, 3, 8, 9, 10, 11, 4, 5, 6, 7]),
    "wedge": np.array([0, 1, 2, 6, 7, 8, 3, 4, 5]),
    "pyramid": np.arange(8),
    "tetra": np.arange(6),
}

#: Cell type -> (corner nodes, nodes with every midside node).
NODE_COUNTS = {"hexahedron": (8, 20), "wedge": (6, 15), "pyramid": (5, 13), "tetra": (4, 10)}

#: The extra nodes of an Exodus HEX27 (after its 20 nodes): the centroid, then one node per face. Face (0-based
#: corner nodes) -> position of its centre node among the 27 (SEACAS IOSS's Hex27 face order).
HEX27_FACES = {21: (0, 3, 2, 1), 22: (4, 5, 6, 7), 23: (0, 4, 7, 3), 24: (1, 2, 6, 5), 25: (0, 1, 5, 4),
               26: (2, 3, 7, 6)}
HEX27_CENTROID = 20


def split_solid(conn: np.ndarray, cell: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Corner nodes and midside nodes (in `jaxci.cells.EDGES` order, or None for a linear cell) of rows of
    PATRAN-ordered node indices `conn` of shape ``(n, k)``, k the corner count or that plus the midside count;
    midside entries < 0 (a missing node) stay as they are."""
    corners, full = NODE_COUNTS[cell]
    if conn.shape[1] == corners:
        return conn, None
    return conn[:, :corners], conn[:, corners:full][:, MIDSIDE_ORDER[cell]]


def join_solid(data: np.ndarray, midside: np.ndarray | None, cell: str) -> np.ndarray:
    """The inverse of `split_solid`: rows of corner nodes followed by the midside nodes in PATRAN's order."""
    if midside is None:
        return data
    return np.concatenate([data, np.asarray(midside)[:, MIDSIDE_ORDER[cell]]], axis=1)


def serendipity_shift(old: np.ndarray, new: np.ndarray, conn27: np.ndarray) -> np.ndarray:
    """New positions of the 7 face and centre nodes of HEX27 rows `conn27` (``(n, 27)``, file order, 0-based) when
    their other 20 nodes moved from `old` to `new` (``(n_nodes, 3)``): each keeps its offset from the point the
    20-node brick puts there (a face centre: -1/4 of its corners + 1/2 of its edge nodes; the centroid: -1/4 of the
    corners + 1/4 of the edge nodes), as `jaxci.mesh.HexMesh.with_points` keeps a midside node's offset from its
    edge's midpoint. Returns the ``(n, 7)`` node indices and their ``(n, 7, 3)`` new positions."""
    d = new - old
    corner_d = d[conn27[:, :8]]  # (n, 8, 3)
    edge_d = d[conn27[:, 8:20]]  # file edge order: 0-1, 1-2, 2-3, 3-0, 0-4, 1-5, 2-6, 3-7, 4-5, 5-6, 6-7, 7-4
    edge_ends = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 5), (2, 6), (3, 7), (4, 5), (5, 6), (6, 7), (7, 4)]
    nodes = [HEX27_CENTROID]
    shifts = [-0.25 * corner_d.sum(axis=1) + 0.25 * edge_d.sum(axis=1)]
    for pos, face in HEX27_FACES.items():
        ring = set(face)
        edges = [k for k, (a, b) in enumerate(edge_ends) if a in ring and b in ring]
        nodes.append(pos)
        shifts.append(-0.25 * corner_d[:, list(face)].sum(axis=1) + 0.5 * edge_d[:, edges].sum(axis=1))
    idx = conn27[:, nodes]
    return idx, old[idx] + np.stack(shifts, axis=1)


#: meshio's quadratic types (VTK node order: the corners, then the midside nodes in `jaxci.cells.EDGES` order).
MESHIO_QUADRATIC = {"hexahedron20": ("hexahedron", 8), "wedge15": ("wedge", 6), "pyramid13": ("pyramid", 5),
                    "tetra10": ("tetra", 4), "hexahedron27": ("hexahedron", 8)}


def file_block(blk: CellBlock, k: int, hex_mirrored: bool) -> tuple[str, np.ndarray, np.ndarray | None, list[str]]:
    """A cell block as a file of these formats holds it: (cell type, corner nodes, midside nodes in `EDGES` order
    or None, what is left out). Hexahedra are mirrored back when the mesh mirrored them (`HexMesh.hex_mirrored`);
    meshio's quadratic blocks become their linear type with midside nodes (a hexahedron27's face and centre
    nodes are left out); midside nodes missing on some edges make the cells linear."""
    b = mirrored_block(blk) if hex_mirrored and blk.type == "hexahedron" else blk
    cell, data, mid, lost = b.type, np.asarray(b.data, np.int64), b.midside, []
    if cell in MESHIO_QUADRATIC:
        cell, corners = MESHIO_QUADRATIC[cell]
        if b.type == "hexahedron27":
            lost.append(f"the face and centre nodes of the {len(data)} hexahedron27 cells of block {k}")
        data, mid = data[:, :corners], data[:, corners : corners + len(MIDSIDE_ORDER[cell])]
    if mid is not None and (np.asarray(mid) < 0).any():
        lost.append(f"the midside nodes of the {len(data)} {cell} cells of block {k}, which lack midside nodes on "
                    f"some edges (written as linear cells)")
        mid = None
    return cell, data, None if mid is None else np.asarray(mid, np.int64), lost


def named_blocks(mesh, names: dict, what: str) -> tuple[list, list[str]]:
    """``(name, rows, ids or None, block index)`` of each cell block of `mesh` that a format names (`names`: (cell
    type, with midside nodes) -> element name), rows as `file_block` gives them with the midside nodes joined
    (`join_solid`), and what is left out: `file_block`'s losses, and the blocks without a name (`what`: the
    format's word for one)."""
    out, lost = [], []
    for k, blk in enumerate(mesh.cells):
        cell, data, mid, more = file_block(blk, k, mesh.hex_mirrored)
        lost += more
        name = names.get((cell, mid is not None))
        if name is None:
            lost.append(f"{len(data)} {blk.type} cells (no {what})")
            continue
        rows = data if mid is None else join_solid(data, mid, cell)
        out.append((name, rows, None if blk.ids is None else np.asarray(blk.ids, np.int64), k))
    return out, lost
