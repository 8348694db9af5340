"""The O(boundary) tables of the boundary constraints, built in numpy from the boundary nodes' coordinates only.

`boundary_tables` computes what `jaxci.geometry.projection.Constraints` holds besides its per-node arrays: the
tangent bases of the SURFACE nodes and the tangents of the EDGE nodes, the candidate triangles and segments of
each, the packed triangle and segment tables. It numbers the nodes it is given 0 .. m - 1 in increasing order
(a monotone relabelling, so every list and sum comes out in the order `build_constraints` had with the mesh's
numbering), so its work never depends on the number of nodes of the mesh: `build_constraints` (the host) gives
it the boundary nodes' coordinates from the mesh's points, `jaxci.geometry.device_constraints` downloads them
from the device.

`BoundaryTables` keeps the result in float64 with the nodes it is about: the host side of a run on the device
(`jaxci.geometry.device_constraints.project_boundary`: the exact search of
`jaxci.geometry.projection.project_np` on the boundary nodes only).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._closest import SEG_ROWS, TRI_ROWS, segment_table, triangle_table
from .boundary import face_normals, unit_rows
from .topology import csr_gather, incidence, unique_per_row


@dataclasses.dataclass(frozen=True, eq=False)
class BoundaryTables:
    """The boundary part of a mesh's constraints, in numpy (float64 geometry, int32 candidates).

    **Fields:**

    - `surface_nodes`, `edge_nodes`, `corner_nodes`: sorted int64 node indices of each class, shapes ``(ns,)``,
      ``(ne,)``, ``(nc,)``.
    - `surface_group`, `edge_group`: the patch of each SURFACE node, the curve of each EDGE node (int32).
    - `corner_points`: the original coordinates of the CORNER nodes, ``(nc, 3)``.
    - `surface_basis` ``(ns, 2, 3)``, `edge_tangent` ``(ne, 3)``, `surface_cand` ``(max(ns, 1), K_tri)``,
      `edge_cand` ``(max(ne, 1), K_seg)``, `triangles` ``(19, nt)``, `triangle_patch` ``(nt,)``, `segments`
      ``(8, nsg)``, `segment_curve` ``(nsg,)``: as `jaxci.geometry.projection.Constraints`' fields of those names.
    """

    surface_nodes: np.ndarray
    edge_nodes: np.ndarray
    corner_nodes: np.ndarray
    surface_group: np.ndarray
    edge_group: np.ndarray
    corner_points: np.ndarray
    surface_basis: np.ndarray
    edge_tangent: np.ndarray
    surface_cand: np.ndarray
    edge_cand: np.ndarray
    triangles: np.ndarray
    triangle_patch: np.ndarray
    segments: np.ndarray
    segment_curve: np.ndarray


def boundary_tables(nodes: np.ndarray, coords: np.ndarray, faces: np.ndarray, face_patch: np.ndarray,
                    feature_edges: np.ndarray, edge_curve: np.ndarray, surface_nodes: np.ndarray,
                    surface_group: np.ndarray, edge_nodes: np.ndarray, edge_group: np.ndarray,
                    corner_nodes: np.ndarray, triangles: bool = True) -> BoundaryTables:
    """The `BoundaryTables` of a classified boundary, from the coordinates of its nodes only.

    **Arguments:**

    - `nodes`: sorted int64 ``(m,)``, every node of `faces`, `feature_edges`, `surface_nodes`, `edge_nodes` and
      `corner_nodes`; `coords` ``(m, 3)``: their coordinates (float64: the original geometry).
    - `faces` ``(n_faces, 4)``, `face_patch` ``(n_faces,)``: the boundary faces and their patches
      (`jaxci.geometry.boundary.BoundaryInfo`); `feature_edges` ``(n_fe, 2)``, `edge_curve` ``(n_fe,)``.
    - `surface_nodes`, `edge_nodes`, `corner_nodes`: the sorted nodes of each class; `surface_group`,
      `edge_group`: the patch of each surface node, the curve of each edge node.
    - `triangles`: False leaves the triangle table out (`triangles` and `triangle_patch` None; `surface_triangles`
      makes them where a projection needs them: `jaxci.geometry.projection.HostConstraints`).

    **Returns:** a `BoundaryTables`; its arrays equal those `jaxci.geometry.projection.build_constraints` puts in
    `Constraints` (before the dtype).
    """
    nodes = np.asarray(nodes, dtype=np.int64)
    pts = np.asarray(coords, dtype=np.float64)
    m = len(nodes)

    def local(a):
        return np.searchsorted(nodes, np.asarray(a, dtype=np.int64))

    faces_l, fedges_l = local(faces).reshape(-1, 4), local(feature_edges).reshape(-1, 2)
    surf, edge = local(surface_nodes), local(edge_nodes)
    group = np.full(m, -1, dtype=np.int64)
    group[surf], group[edge] = surface_group, edge_group
    # normals of surface nodes: area-weighted over the faces of their own patch around them (every face around a
    # surface node, except for a corner or edge node made a surface node by `jaxci.geometry.boundary.slide_on_surface`)
    normals = np.zeros((len(surf), 3))
    if len(faces_l) and len(surf):
        normals = unit_rows(_node_sums(faces_l, m, surf, face_normals(pts, faces_l), face_patch, group))
    tris, tri_patch = surface_triangles(pts, faces_l, face_patch) if triangles else (None, None)
    tri_cand = surface_candidates(faces_l, m, surf, face_patch, group)
    if len(fedges_l):
        segs, seg_curve = segment_table(pts, fedges_l), edge_curve
    else:
        segs, seg_curve = np.zeros((SEG_ROWS, 1)), np.full(1, -1)
    return BoundaryTables(
        surface_nodes=np.asarray(surface_nodes, dtype=np.int64),
        edge_nodes=np.asarray(edge_nodes, dtype=np.int64),
        corner_nodes=np.asarray(corner_nodes, dtype=np.int64),
        surface_group=np.asarray(surface_group, dtype=np.int32),
        edge_group=np.asarray(edge_group, dtype=np.int32),
        corner_points=pts[local(corner_nodes)].reshape(-1, 3),
        surface_basis=_tangent_bases(normals),
        edge_tangent=_edge_tangents(pts, fedges_l, edge),
        surface_cand=tri_cand,
        edge_cand=_ring_candidates(fedges_l, m, edge, edge_curve, group),
        triangles=tris,
        triangle_patch=tri_patch,
        segments=segs,
        segment_curve=np.asarray(seg_curve),
    )


def surface_candidates(faces: np.ndarray, n_nodes: int, surface_nodes: np.ndarray, face_patch: np.ndarray,
                       group: np.ndarray) -> np.ndarray:
    """`BoundaryTables.surface_cand`: each of `surface_nodes`' candidate triangles (the four of each face of its
    own patch within its 2-ring of boundary faces), int32 ``(max(ns, 1), K)``; `faces` ``(n_faces, 4)`` of node
    numbers below `n_nodes`, `face_patch` their patches, `group` ``(n_nodes,)`` each surface node's patch. The same
    numbers in any numbering of the nodes that keeps their order."""
    quad_cand = _ring_candidates(faces, n_nodes, surface_nodes, face_patch, group)
    # (in int32 throughout: an int64 temporary of every candidate was 20 MB at 216,000 hexahedra)
    out = (4 * quad_cand[:, :, None] + np.arange(4, dtype=quad_cand.dtype)).reshape(len(quad_cand), -1)
    return out.astype(np.int32, copy=False)


def surface_triangles(points: np.ndarray, faces: np.ndarray, face_patch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(triangles, triangle_patch)`` of `BoundaryTables`: the packed triangle table of the boundary faces `faces`
    ``(n_faces, 4)`` (indices into `points`, float64 ``(n, 3)``; `jaxci.geometry._closest.triangle_table`) and the
    patch of each triangle (`face_patch` ``(n_faces,)``, each face's four times); one unused triangle of patch -1
    where there is no face."""
    if len(faces):
        return triangle_table(points, faces), np.repeat(face_patch, 4)
    return np.zeros((TRI_ROWS, 1)), np.full(1, -1)


def _pad_rows(indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """CSR rows as a dense (n_rows, max_len) int32 array, short rows padded by repeating their first entry.
    At least shape (1, 1) (a row of zeros) when there is nothing."""
    n_rows = len(indptr) - 1
    lens = np.diff(indptr)
    width = max(int(lens.max(initial=0)), 1)
    out = np.zeros((max(n_rows, 1), width), dtype=np.int32)
    if n_rows:
        out[:n_rows] = indices[np.minimum(indptr[:-1], max(len(indices) - 1, 0))][:, None]
        rows = np.repeat(np.arange(n_rows), lens)
        out[rows, np.arange(len(indices)) - np.repeat(indptr[:-1], lens)] = indices
    return out


def _ring_candidates(
    cells: np.ndarray, n_nodes: int, nodes: np.ndarray, cell_group: np.ndarray, node_group: np.ndarray
) -> np.ndarray:
    """For each of `nodes`, the cells (faces or segments) of its own group within its 2-ring, padded. Made
    `RING_BLOCK` nodes at a time (each row is its node's alone: the same rows in any blocks)."""
    if not len(cells):
        return np.zeros((1, 1), dtype=np.int32)
    indptr, indices = incidence(cells, n_nodes)
    nodes = np.asarray(nodes, dtype=np.int64)
    k = cells.shape[1]
    counts, kept = [], []
    for lo in range(0, len(nodes), RING_BLOCK):
        block = nodes[lo:lo + RING_BLOCK]
        owner, c = csr_gather(indptr, indices, block)  # the cells around each node
        near_p, near = unique_per_row(np.repeat(owner, k), cells[c].ravel(), len(block))  # their nodes (1-ring)
        owner, c = csr_gather(indptr, indices, near)  # the cells around those
        ring_p, ring = unique_per_row(np.repeat(np.arange(len(block)), np.diff(near_p))[owner], c, len(block))
        del owner, c, near
        rows = np.repeat(np.arange(len(block)), np.diff(ring_p))
        keep = cell_group[ring] == node_group[block][rows]
        counts.append(np.bincount(rows[keep], minlength=len(block)))
        kept.append(ring[keep].astype(np.int32))
    indptr = np.zeros(len(nodes) + 1, dtype=np.int64)
    np.cumsum(np.concatenate(counts) if counts else np.zeros(0, np.int64), out=indptr[1:])
    return _pad_rows(indptr, np.concatenate(kept) if kept else np.zeros(0, np.int32))


#: Nodes per block of `_ring_candidates` (its 1- and 2-rings' pairs and their sort, about 1.4 kB a surface node:
#: 30 MB of cube60_pert's set-up peak at once).
RING_BLOCK = 4096


def _node_sums(cells: np.ndarray, n_nodes: int, nodes: np.ndarray, values: np.ndarray, cell_group: np.ndarray,
               node_group: np.ndarray) -> np.ndarray:
    """For each of `nodes`, the sum of `values` ``(n_cells, d)`` over the distinct cells of its own group it
    belongs to (``cell_group[cell] == node_group[node]``): shape ``(len(nodes), d)`` (a triangle stored as
    ``[a, b, c, c]`` counts once for ``c``)."""
    indptr, indices = incidence(cells, n_nodes)
    owner, c = csr_gather(indptr, indices, np.asarray(nodes, dtype=np.int64))
    mine = cell_group[c] == node_group[np.asarray(nodes)[owner]]
    ptr, c = unique_per_row(owner[mine], c[mine], len(nodes))
    owner = np.repeat(np.arange(len(nodes)), np.diff(ptr))
    return np.stack([np.bincount(owner, values[c, j], minlength=len(nodes)) for j in range(values.shape[1])],
                    axis=1)


def _tangent_bases(normals: np.ndarray) -> np.ndarray:
    """Orthonormal tangent pairs (m, 2, 3) of unit normals (m, 3) (an arbitrary pair for a zero normal)."""
    m = len(normals)
    helper = np.zeros((m, 3))
    helper[np.arange(m), np.argmin(np.abs(normals), axis=1)] = 1.0
    t1 = unit_rows(helper - (helper * normals).sum(1, keepdims=True) * normals)
    t2 = np.cross(normals, t1)
    t2 = np.where(np.linalg.norm(t2, axis=1, keepdims=True) > 0, t2, unit_rows(np.cross(t1, helper[:, ::-1])))
    return np.stack([t1, t2], axis=1)


def _edge_tangents(points: np.ndarray, fedges: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """Unit tangents (m, 3) of EDGE nodes from their two feature edges (bisecting a slight turn)."""
    if not len(edge):
        return np.zeros((0, 3))
    owner, e = csr_gather(*incidence(fedges, len(points)), edge)
    other = np.where(fedges[e, 0] == edge[owner], fedges[e, 1], fedges[e, 0])
    first = np.r_[True, owner[1:] != owner[:-1]]  # each EDGE node has exactly two feature edges
    prev, nxt = other[first], other[~first]
    return unit_rows(unit_rows(points[edge] - points[prev]) + unit_rows(points[nxt] - points[edge]))
