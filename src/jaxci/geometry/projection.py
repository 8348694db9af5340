"""Projection of nodes back onto the ORIGINAL boundary of a mesh, and the free coordinates of the movable nodes.

**Geometry kept.** Every boundary quadrilateral of the input mesh is split into four triangles around its centroid
(the mean of its corners): no diagonal is preferred, a planar quad gives four coplanar triangles (so planar patches
are reproduced exactly), and a warped quad is approximated by a surface symmetric in its corners. A boundary
triangle (of a wedge, pyramid or tetrahedron, stored as ``[a, b, c, c]``, `jaxci.geometry.topology`) is split around its
centroid the same way and is reproduced exactly. Feature curves are kept as the polylines of their feature edges.
Each triangle belongs to the patch of its quad, each segment to one curve (`jaxci.geometry.boundary`).

**Projection.** A SURFACE node goes to the nearest point of its own patch, an EDGE node to the nearest point
of its own curve, a CORNER node back to its original position; INTERIOR nodes do not move. Restricting the
search to the node's own patch or curve stops a node from jumping across a thin wall or onto another face.

- `project_np` (numpy) searches the whole patch or curve (a k-d tree of triangle centroids, queried within a
  radius that provably holds the nearest triangle), so it is exact for any displacement.
- `project` and `project_nodes` (JAX, jit-able, differentiable) compare a FIXED-size list of candidates per
  node: the triangles of the quads of its own patch within its 2-ring on the original boundary (K_tri = 4 x
  the largest such 2-ring: 16 quads = 64 triangles on a structured grid), or the segments of its own curve
  within its 2-ring (K_seg, 4 on a chain). Shorter lists are padded by repeating an entry. Both agree whenever
  the nearest point lies in the 2-ring, i.e. for moves of up to about one element.

The nearest point of a triangle is its orthogonal projection if that falls inside (with a relative tolerance
of 256 machine epsilons), else the nearest point of its sides. Inside projections win ties, up to rounding
noise (side points carry a penalty of (64 eps)^2 times the squared quad size): at a node sitting exactly on a
mesh vertex the derivative of the projection is then the tangent projector of a triangle, not zero. All
geometry-only quantities (unit normals, inverse Gram matrices, inverse lengths) are precomputed, so the kernel
has no division or square root.

**Parametrisation.** For gradient methods the free coordinates are a flat vector ``u`` in three blocks, nodes
by increasing index within each: 3 per INTERIOR node (its displacement), 2 per SURFACE node (coordinates in an
orthonormal tangent basis of the original area-weighted node normal), 1 per EDGE node (along the unit tangent
of its curve); none for CORNER nodes. ``params_to_points(c, u, x0) = project(c, x0 + B u)``. On planar patches
and straight curves the projection is exact, so its derivative is too: at ``u = 0`` the Jacobian is exactly
``B``. An ``n^3`` box has ``3 (n-1)^3 + 12 (n-1)^2 + 12 (n-1)`` free coordinates (2400 for n = 9).

Index and geometry arrays live in `Constraints`, a pytree passed INTO jitted functions (closed-over arrays
become compile-time constants and compile far slower). Kernels use a structure-of-arrays layout and 1-D
gathers, the fast form on XLA:CPU.
"""

# ruff: noqa: F722  (jaxtyping shape strings such as "n 3" are not forward references)
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from .._lazy import filter_jit, jax, jnp, pytree_dataclass
from ..mesh import HexMesh
from ._closest import (
    SD,
    SEG_ROWS,
    TN,
    TRI_ROWS,
    candidate_rows,
    closest_on_segments,
    closest_on_triangles,
    inside_tolerance,
    line_point,
    nearest_candidates,
    plane_point,
    segment_bump,
    segment_centres,
    segment_table,
    triangle_centres,
    triangle_table,
)
from .boundary import CORNER, EDGE, INTERIOR, SURFACE, BoundaryInfo, face_normals

if TYPE_CHECKING:
    from jaxtyping import Array, Float, Int
from .topology import csr_gather, incidence, unique_per_row


@pytree_dataclass
class Constraints:
    """The boundary constraints of a mesh as a pytree of arrays, to pass INTO jitted functions.

    Built by `build_constraints`. Index arrays are int32, geometry is in the float dtype chosen there; the
    arrays are JAX arrays on the default device, or numpy arrays for the numpy path (``device=False``).

    **Fields:**

    - `x_orig`: original node coordinates, shape ``(n_nodes, 3)`` (corners are restored to them).
    - `node_class`: class of each node (`jaxci.geometry.boundary.INTERIOR` ... `CORNER`), shape ``(n_nodes,)``.
    - `group`: patch id of SURFACE nodes, curve id of EDGE nodes, -1 otherwise; shape ``(n_nodes,)``.
    - `row`: position of a SURFACE (EDGE) node in `surface_nodes` (`edge_nodes`), 0 otherwise.
    - `interior_nodes`, `surface_nodes`, `edge_nodes`, `corner_nodes`: sorted node indices of each class.
    - `surface_basis`: orthonormal tangent pair of each SURFACE node, shape ``(n_surface, 2, 3)``.
    - `edge_tangent`: unit tangent of each EDGE node, shape ``(n_edge, 3)``.
    - `surface_cand`: candidate triangles of each SURFACE node, shape ``(max(n_surface, 1), K_tri)``.
    - `edge_cand`: candidate segments of each EDGE node, shape ``(max(n_edge, 1), K_seg)``.
    - `triangles`: the 4 triangles of every original boundary quad, packed: one row per precomputed quantity
      (see the module source), shape ``(19, n_triangles)``.
    - `triangle_patch`: patch of each triangle, shape ``(n_triangles,)``.
    - `segments`: the feature edges, packed (start, direction, inverse squared length, squared length), shape
      ``(8, n_segments)``.
    - `segment_curve`: curve of each segment, shape ``(n_segments,)``.
    """

    x_orig: Float[Array, "n 3"]
    node_class: Int[Array, " n"]
    group: Int[Array, " n"]
    row: Int[Array, " n"]
    interior_nodes: Int[Array, " ni"]
    surface_nodes: Int[Array, " ns"]
    edge_nodes: Int[Array, " ne"]
    corner_nodes: Int[Array, " nc"]
    surface_basis: Float[Array, "ns 2 3"]
    edge_tangent: Float[Array, "ne 3"]
    surface_cand: Int[Array, "ms kt"]
    edge_cand: Int[Array, "me ks"]
    triangles: Float[Array, "19 nt"]
    triangle_patch: Int[Array, " nt"]
    segments: Float[Array, "8 nsg"]
    segment_curve: Int[Array, " nsg"]


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
    """For each of `nodes`, the cells (faces or segments) of its own group within its 2-ring, padded."""
    if not len(cells):
        return np.zeros((1, 1), dtype=np.int32)
    indptr, indices = incidence(cells, n_nodes)
    owner, c = csr_gather(indptr, indices, np.asarray(nodes, dtype=np.int64))  # the cells around each node
    k = cells.shape[1]
    near_p, near = unique_per_row(np.repeat(owner, k), cells[c].ravel(), len(nodes))  # their nodes (1-ring)
    owner, c = csr_gather(indptr, indices, near)  # the cells around those
    ring_p, ring = unique_per_row(np.repeat(np.arange(len(nodes)), np.diff(near_p))[owner], c, len(nodes))
    rows = np.repeat(np.arange(len(nodes)), np.diff(ring_p))
    keep = cell_group[ring] == node_group[nodes][rows]
    indptr = np.zeros(len(nodes) + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows[keep], minlength=len(nodes)), out=indptr[1:])
    return _pad_rows(indptr, ring[keep])


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


def _unit_rows(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def _tangent_bases(normals: np.ndarray) -> np.ndarray:
    """Orthonormal tangent pairs (m, 2, 3) of unit normals (m, 3) (an arbitrary pair for a zero normal)."""
    m = len(normals)
    helper = np.zeros((m, 3))
    helper[np.arange(m), np.argmin(np.abs(normals), axis=1)] = 1.0
    t1 = _unit_rows(helper - (helper * normals).sum(1, keepdims=True) * normals)
    t2 = np.cross(normals, t1)
    t2 = np.where(np.linalg.norm(t2, axis=1, keepdims=True) > 0, t2, _unit_rows(np.cross(t1, helper[:, ::-1])))
    return np.stack([t1, t2], axis=1)


def _edge_tangents(points: np.ndarray, fedges: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """Unit tangents (m, 3) of EDGE nodes from their two feature edges (bisecting a slight turn)."""
    if not len(edge):
        return np.zeros((0, 3))
    owner, e = csr_gather(*incidence(fedges, len(points)), edge)
    other = np.where(fedges[e, 0] == edge[owner], fedges[e, 1], fedges[e, 0])
    first = np.r_[True, owner[1:] != owner[:-1]]  # each EDGE node has exactly two feature edges
    prev, nxt = other[first], other[~first]
    return _unit_rows(_unit_rows(points[edge] - points[prev]) + _unit_rows(points[nxt] - points[edge]))


def build_constraints(mesh: HexMesh, info: BoundaryInfo, *, dtype=None, device: bool = True) -> Constraints:
    """Keep a copy of the boundary of `mesh` and precompute everything the projections need.

    **Arguments:**

    - `mesh`: the mesh whose CURRENT coordinates are the original geometry to project onto.
    - `info`: its `BoundaryInfo` (from `jaxci.geometry.boundary.classify_boundary`).
    - `dtype`: float dtype of the geometry arrays; default JAX's default float (float64 under
      ``jax_enable_x64``, else float32). Keyword only argument.
    - `device`: put the arrays on JAX's default device (default; for jitted functions, which would copy numpy
      arrays in at every call), or keep them in numpy (the numpy path: JAX is not imported).

    **Returns:** a `Constraints`.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    pts = np.asarray(mesh.points, dtype=np.float64)
    n = mesh.n_nodes
    cls = np.asarray(info.node_class)
    faces, fedges = info.topology.faces, info.feature_edges
    group = np.where(cls == SURFACE, info.patch_id, np.where(cls == EDGE, info.curve_id, -1)).astype(np.int32)
    nodes = {c: np.flatnonzero(cls == c) for c in (INTERIOR, SURFACE, EDGE, CORNER)}
    surf, edge = nodes[SURFACE], nodes[EDGE]
    row = np.zeros(n, dtype=np.int32)
    row[surf] = np.arange(len(surf))
    row[edge] = np.arange(len(edge))
    # normals of surface nodes: area-weighted over the faces of their own patch around them (every face around a
    # surface node, except for a corner or edge node made a surface node by `jaxci.geometry.boundary.slide_on_surface`)
    normals = np.zeros((len(surf), 3))
    if len(faces) and len(surf):
        normals = _unit_rows(_node_sums(faces, n, surf, face_normals(pts, faces), info.face_patch, group))
    if len(faces):
        tris, tri_patch = triangle_table(pts, faces), np.repeat(info.face_patch, 4)
    else:
        tris, tri_patch = np.zeros((TRI_ROWS, 1)), np.full(1, -1)
    quad_cand = _ring_candidates(faces, n, surf, info.face_patch, group)
    tri_cand = (4 * quad_cand[:, :, None] + np.arange(4)).reshape(len(quad_cand), -1)
    if len(fedges):
        segs, seg_curve = segment_table(pts, fedges), info.edge_curve
    else:
        segs, seg_curve = np.zeros((SEG_ROWS, 1)), np.full(1, -1)

    put = jax.device_put if device else (lambda a: a)

    def i32(a):  # converted on the host: jnp.asarray compiles a small program per shape
        return put(np.asarray(a, dtype=np.int32))

    def f(a):
        return put(np.asarray(a, dtype=np.dtype(dtype)))

    return Constraints(
        x_orig=f(pts),
        node_class=i32(cls),
        group=i32(group),
        row=i32(row),
        interior_nodes=i32(nodes[INTERIOR]),
        surface_nodes=i32(surf),
        edge_nodes=i32(edge),
        corner_nodes=i32(nodes[CORNER]),
        surface_basis=f(_tangent_bases(normals)),
        edge_tangent=f(_edge_tangents(pts, fedges, edge)),
        surface_cand=i32(tri_cand),
        edge_cand=i32(_ring_candidates(fedges, n, edge, info.edge_curve, group)),
        triangles=f(tris),
        triangle_patch=i32(tri_patch),
        segments=f(segs),
        segment_curve=i32(seg_curve),
    )


# ---------------------------------------------------------------------------------------------------- JAX


@filter_jit
def project(constraints: Constraints, points: Float[Array, "*batch n 3"]) -> Float[Array, "*batch n 3"]:
    """Project every node onto the original boundary (JAX; jit-able and differentiable).

    SURFACE nodes go to the nearest point of their candidate triangles, EDGE nodes to the nearest point of their
    candidate segments, CORNER nodes to their original position; INTERIOR nodes are returned unchanged.

    **Arguments:**

    - `constraints`: the `Constraints` of the mesh (a pytree of arrays: pass it as an argument under `jax.jit`).
    - `points`: node coordinates of shape ``(n_nodes, 3)``, or ``(..., n_nodes, 3)`` for a batch (a cohort of
      candidate meshes).

    **Returns:** the projected coordinates, same shape and dtype as `points`.
    """
    c = constraints
    x = jnp.asarray(points)
    ns, ne = c.surface_nodes.shape[0], c.edge_nodes.shape[0]
    if ns:
        tab, cand = c.triangles.astype(x.dtype), c.surface_cand[:ns]
        p = nearest_candidates(jnp, x[..., c.surface_nodes, :], tab, cand, closest_on_triangles,
                               inside_tolerance(x.dtype))
        x = x.at[..., c.surface_nodes, :].set(p)
    if ne:
        tab, cand = c.segments.astype(x.dtype), c.edge_cand[:ne]
        p = nearest_candidates(jnp, x[..., c.edge_nodes, :], tab, cand, closest_on_segments, inside_tolerance(x.dtype))
        x = x.at[..., c.edge_nodes, :].set(p)
    return x.at[..., c.corner_nodes, :].set(c.x_orig[c.corner_nodes].astype(x.dtype))


def project_near_np(constraints: Constraints, points: np.ndarray) -> np.ndarray:
    """`project` in numpy (the candidate triangles and segments of each node, as under `jax.jit`; float64): a
    `NearProjector` that remembers nothing, so every node searches all its candidates.

    For displacements within a node's ring of boundary faces (a solver's iterates); `project_np` searches whole
    patches and handles any displacement. **Returns** a new float64 array of shape ``(n_nodes, 3)``."""
    return NearProjector(constraints)(points)[0]


class NearProjector:
    """`project_near_np` that starts from each boundary node's triangle (segment) of the solver's iterate.

    A solver's next trial moves a node by a fraction of its cell, so its orthogonal projection nearly always
    falls inside the triangle the node had at the iterate: that is tested first (one triangle per node instead of
    the ~70 of its 2-ring: 6 ms -> ~1 ms per projection at 2360 hexahedra), and only the nodes that left it
    search all their candidates. Where a point near a concave part of the boundary is inside its old triangle's
    prism and yet nearer to another triangle, it keeps the old one: a point on the boundary either way.

    The remembered triangles change only when the solver accepts a trial (`commit`), never during a line search:
    a rejected long trial that carried a node to another triangle must not change what the iterate's
    neighbourhood projects to (measured on pave3: the objective then jumped between trials 1e-6 apart and the
    line search stalled 2% above the optimum). A point inside its old triangle's prism may still be nearer to
    another candidate (near a concave part of the boundary): each candidate whose bounding sphere comes nearer
    than the old triangle's plane is searched too, so the result is always the nearest candidate point, as with
    no memory (keeping the old one made the projection jump where the point left the prism: pave3's line
    search stalled there at F 0.327 against 0.318).
    """

    def __init__(self, constraints: Constraints):
        from .. import native

        self.c, self.rows = host_constraints(constraints)
        # candidate column per surface node, per edge node; -1: not known (search all its candidates)
        self.hint = tuple(np.full(int(n.shape[0]), -1, np.int64) for n in (self.c.surface_nodes, self.c.edge_nodes))
        #: per kind, the bounding spheres of the cells (centres (nc, 3), radii (nc,)), for the numpy search
        self.spheres = (_sphere(self.c.triangles, triangle_centres), _sphere(self.c.segments, segment_centres))
        #: the C loop of `jaxci.native` (the same search, one pass per node): its int64 arrays, or None (numpy)
        self._tiled = {}  # `project_many`'s index arrays per (kind, number of meshes)
        self._native = None if not native.AVAILABLE else tuple(
            (np.ascontiguousarray(nodes, np.int64), np.ascontiguousarray(cand, np.int64),
             np.ascontiguousarray(table, np.float64), np.ascontiguousarray(np.column_stack(sphere), np.float64))
            for nodes, cand, table, sphere in ((self.c.surface_nodes, self.c.surface_cand, self.c.triangles,
                                                self.spheres[0]),
                                               (self.c.edge_nodes, self.c.edge_cand, self.c.segments,
                                                self.spheres[1])))

    def commit(self, hint) -> None:
        """Remember `hint` (from `__call__`) for the next projections."""
        self.hint = hint

    @property
    def native_tables(self) -> tuple:
        """Per kind (surface, edge), the ``(candidates, table, spheres)`` arrays of the C search (int64 / float64,
        contiguous), for a C kernel that projects points itself (`jaxci.native.ci_visit`); None without the C
        kernels."""
        return None if self._native is None else tuple(t[1:] for t in self._native)

    def project_many(self, points: np.ndarray, keep: np.ndarray | None = None) -> None:
        """Project the boundary nodes of S meshes `points` (float64 ``(S, n, 3)``, in place) as `__call__` does,
        each starting from the remembered cells (not changed): one C search over all of them (the trial meshes of
        `jaxci.optim.host_global`); `keep` (optional, boolean ``(S, n)``): nodes left where they are. The C
        search only (`jaxci.native.AVAILABLE`)."""
        from .. import native

        S, n = points.shape[:2]
        flat = points.reshape(-1, 3)
        for kind, (nodes, cand, table, spheres) in enumerate(self._native):
            if not len(nodes):
                continue
            key = (kind, S)
            if key not in self._tiled:
                self._tiled[key] = ((np.arange(S)[:, None] * n + nodes[None]).ravel(), np.tile(cand, (S, 1)))
            many, cands = self._tiled[key]
            active = np.arange(len(many)) if keep is None else np.flatnonzero(~keep[:, nodes].ravel())
            if len(active):
                native.near_project(flat, many, active, np.tile(self.hint[kind], S), cands, table, spheres, kind,
                                    inside_tolerance(np.float64), segment_bump(np.float64))
        points[:, self.c.corner_nodes] = self.c.x_orig[self.c.corner_nodes]

    def project_rows(self, kind: int, rows: np.ndarray, points: np.ndarray, hint: np.ndarray) -> None:
        """Project `points` (float64 ``(r, 3)``, in place) each onto the candidates of one boundary node: point i
        onto those of row ``rows[i]`` of `kind` (0: the surface nodes, 1: the edge nodes), starting from the
        candidate column ``hint[i]`` (int64, -1: search all; updated in place): the trial positions of the local
        moves of `jaxci.optim.host_local`. The C search only (`jaxci.native.AVAILABLE`)."""
        from .. import native

        nodes, cand, table, spheres = self._native[kind]
        idx = np.arange(len(rows), dtype=np.int64)
        native.near_project(points, idx, idx, hint, np.ascontiguousarray(cand[rows]), table, spheres, kind,
                            inside_tolerance(np.float64), segment_bump(np.float64))

    def __call__(self, points: np.ndarray, keep: np.ndarray | None = None):
        """``(x, hint)``: the projected coordinates (a new float64 ``(n, 3)`` array) and the candidate column
        each boundary node ended on (for `commit` and `pullback`; -1 where unknown). `keep` (optional, boolean
        ``(n,)``): nodes left where they are, e.g. those inside a flat part of the boundary, where the point
        is its own projection (their hint stays as it was)."""
        c = self.c
        x = np.array(points, dtype=np.float64)
        tol = inside_tolerance(np.float64)
        if self._native is not None:
            from .. import native

            out = []
            for kind, (nodes, cand, table, spheres) in enumerate(self._native):
                hint = self.hint[kind].copy()
                active = np.arange(len(nodes)) if keep is None else np.flatnonzero(~keep[nodes])
                if len(active):
                    native.near_project(x, nodes, active, hint, cand, table, spheres, kind, tol,
                                        segment_bump(np.float64))
                out.append(hint)
            x[c.corner_nodes] = c.x_orig[c.corner_nodes]
            return x, tuple(out)
        kinds = ((c.surface_nodes, c.triangles, c.surface_cand, closest_on_triangles, plane_point),
                 (c.edge_nodes, c.segments, c.edge_cand, closest_on_segments, line_point))
        out = []
        for kind, (nodes, table, cand, closest, orthogonal) in enumerate(kinds):
            hint = self.hint[kind].copy()
            active = np.arange(len(nodes)) if keep is None else np.flatnonzero(~keep[nodes])
            if not len(active):
                out.append(hint)
                continue
            xs = x[nodes[active]]
            todo = hint[active] < 0
            known = np.flatnonzero(~todo)
            if len(known):
                rows = active[known]
                cell = cand[rows, hint[rows]]
                found = orthogonal(tuple(xs[known].T), table[:, cell], tol)
                p, inside = np.stack(found[0], axis=-1), found[2 if kind == 0 else 1]
                # inside, but a candidate whose bounding sphere comes nearer may hold a nearer point: search all
                centre, radius = self.spheres[kind]
                gap = np.linalg.norm(xs[known][:, None] - centre[cand[rows]], axis=-1) - radius[cand[rows]]
                near2 = np.sum((xs[known] - p) ** 2, axis=1)
                other = ((gap <= 0) | (gap * gap < near2[:, None])).sum(axis=1) > 1  # the hint's own passes
                inside &= ~other
                x[nodes[rows[inside]]] = p[inside]
                todo[known[~inside]] = True
            if todo.any():
                rows = active[todo]
                gathered = [r[rows] for r in self.rows[kind]]
                p, score = closest(np, tuple(xs[todo].T[:, :, None]), gathered, tol)
                k = np.argmin(score, axis=-1)
                pick = np.arange(len(k))
                x[nodes[rows]] = np.stack([pj[pick, k] for pj in p], axis=-1)
                hint[rows] = k
            out.append(hint)
        x[c.corner_nodes] = c.x_orig[c.corner_nodes]
        return x, tuple(out)

    def pullback(self, g: np.ndarray, hint, keep: np.ndarray | None = None) -> np.ndarray:
        """The gradient `g` ``(n, 3)`` at points projected with `hint` (`__call__`, with the same `keep`) taken
        back through the projection: on a surface node minus its component along its triangle's normal, on an
        edge node its component along its segment (the derivative of the projection onto a plane or a line);
        nodes of `keep` unchanged. A new array."""
        c, g = self.c, np.array(g)
        for kind, (nodes, table, cand, row) in enumerate(((c.surface_nodes, c.triangles, c.surface_cand, TN),
                                                          (c.edge_nodes, c.segments, c.edge_cand, SD))):
            rows = np.flatnonzero(hint[kind] >= 0) if keep is None else np.flatnonzero((hint[kind] >= 0)
                                                                                       & ~keep[nodes])
            if not len(rows):
                continue
            cell = cand[rows, hint[kind][rows]]
            d = table[row : row + 3, cell].T
            d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
            sel = nodes[rows]
            along = np.sum(g[sel] * d, axis=1, keepdims=True) * d
            g[sel] = g[sel] - along if kind == 0 else along
        return g


def _sphere(table, centre_radius):
    centre, radius = centre_radius(np.asarray(table, dtype=np.float64))
    return centre, radius * (1 + 1e-12)  # rounding must not prune a cell that holds the nearest point


def host_constraints(c: Constraints) -> tuple[Constraints, tuple]:
    """``(c as numpy with float64 geometry, (triangle rows, segment rows) gathered at the candidates)``, cached
    on `c` (converted once per solve, not once per objective evaluation)."""
    cached = getattr(c, "_host_cache", None)
    if cached is None:
        def conv(a):
            a = np.asarray(a)
            return a.astype(np.float64) if np.issubdtype(a.dtype, np.floating) else a

        h = dataclasses.replace(c, **{f.name: conv(getattr(c, f.name)) for f in dataclasses.fields(c)})
        ns, ne = h.surface_nodes.shape[0], h.edge_nodes.shape[0]
        rows = (candidate_rows(h.triangles, h.surface_cand[:ns]) if ns else None,
                candidate_rows(h.segments, h.edge_cand[:ne]) if ne else None)
        cached = (h, rows)
        object.__setattr__(c, "_host_cache", cached)  # a frozen dataclass; a cache is not a field
    return cached


@filter_jit
def project_nodes(
    constraints: Constraints, node_idx: Int[Array, " m"], points: Float[Array, "*batch m 3"]
) -> Float[Array, "*batch m 3"]:
    """Project the new positions of some nodes only (JAX; jit-able and differentiable).

    For per-node or per-colour batches: each position is projected by the rule of its node's class (see
    `project`). The triangle and the segment candidates are both evaluated for every node (fixed shapes), and the
    one of its class is kept.

    **Arguments:**

    - `constraints`: the `Constraints` of the mesh.
    - `node_idx`: node indices, integer array of shape ``(m,)`` (any classes, repeats allowed).
    - `points`: new positions of these nodes, shape ``(m, 3)`` or ``(..., m, 3)``.

    **Returns:** the projected positions, same shape and dtype as `points`.
    """
    c = constraints
    x = jnp.asarray(points)
    idx = jnp.asarray(node_idx)
    cls, row = c.node_class[idx][:, None], c.row[idx]
    cand = c.surface_cand[jnp.minimum(row, c.surface_cand.shape[0] - 1)]
    ps = nearest_candidates(jnp, x, c.triangles.astype(x.dtype), cand, closest_on_triangles, inside_tolerance(x.dtype))
    cand = c.edge_cand[jnp.minimum(row, c.edge_cand.shape[0] - 1)]
    pe = nearest_candidates(jnp, x, c.segments.astype(x.dtype), cand, closest_on_segments, inside_tolerance(x.dtype))
    fixed = c.x_orig[idx].astype(x.dtype)
    return jnp.where(cls == SURFACE, ps, jnp.where(cls == EDGE, pe, jnp.where(cls == CORNER, fixed, x)))


# ---------------------------------------------------------------------------------------------------- numpy


def _search(table, cells, x, closest, centre_radius):
    """Exact nearest points of `x` (m, 3) on the cells `table[:, cells]`, via a k-d tree of cell centres.

    The nearest cell centre at distance d0 bounds the distance to the nearest point; a cell whose centre is
    farther than d0 + (largest cell radius) cannot hold a nearer point.
    """
    from scipy.spatial import cKDTree  # here, not at the top: its import is 0.3-0.5 s of a command's start

    centre, radius = centre_radius(table[:, cells])
    tree = cKDTree(centre)
    d0, _ = tree.query(x)
    lists = tree.query_ball_point(x, d0 + radius.max() * (1 + 1e-9) + 1e-300)
    lens = np.fromiter((len(v) for v in lists), dtype=np.int64, count=len(lists))
    flat = np.fromiter((i for v in lists for i in v), dtype=np.int64, count=int(lens.sum()))
    owner = np.repeat(np.arange(len(x)), lens)
    p, score = closest(np, tuple(x[owner].T), table[:, cells[flat]], inside_tolerance(np.float64))
    order = np.lexsort((score, owner))
    first = order[np.r_[True, owner[order][1:] != owner[order][:-1]]]
    return np.stack(p, axis=1)[first]


def project_np(constraints: Constraints, points: np.ndarray) -> np.ndarray:
    """Project every node onto the original boundary, exactly, in numpy float64.

    Like `project`, but each SURFACE (EDGE) node searches ALL triangles (segments) of its patch (curve), so any
    displacement is handled. Builds one k-d tree per patch and curve on each call.

    **Arguments:**

    - `constraints`: the `Constraints` of the mesh.
    - `points`: node coordinates, array of shape ``(n_nodes, 3)``.

    **Returns:** a new float64 array of shape ``(n_nodes, 3)``.
    """
    c = constraints
    x = np.array(points, dtype=np.float64)
    group = np.asarray(c.group)
    for nodes, table, cell_group, closest, centres in (
        (c.surface_nodes, c.triangles, c.triangle_patch, closest_on_triangles, triangle_centres),
        (c.edge_nodes, c.segments, c.segment_curve, closest_on_segments, segment_centres),
    ):
        nodes = np.asarray(nodes)
        table = np.asarray(table, dtype=np.float64)
        cell_group = np.asarray(cell_group)
        for g in np.unique(group[nodes]):
            sel = nodes[group[nodes] == g]
            x[sel] = _search(table, np.flatnonzero(cell_group == g), x[sel], closest, centres)
    corners = np.asarray(c.corner_nodes)
    x[corners] = np.asarray(c.x_orig, dtype=np.float64)[corners]
    return x


# ---------------------------------------------------------------------------------------------------- parameters


def n_free(constraints: Constraints) -> int:
    """Number of free coordinates: 3 per interior, 2 per surface, 1 per edge node (a Python int)."""
    c = constraints
    return 3 * c.interior_nodes.shape[0] + 2 * c.surface_nodes.shape[0] + c.edge_nodes.shape[0]


def _split(constraints: Constraints, u):
    c = constraints
    ni, ns = c.interior_nodes.shape[0], c.surface_nodes.shape[0]
    if u.shape[-1] != n_free(c):
        raise ValueError(
            f"the parameter vector has {u.shape[-1]} entries but the constraints have {n_free(c)} free "
            f"coordinates (3 per interior, 2 per surface, 1 per edge node)"
        )
    lead = u.shape[:-1]
    return (
        u[..., : 3 * ni].reshape(lead + (ni, 3)),
        u[..., 3 * ni : 3 * ni + 2 * ns].reshape(lead + (ns, 2)),
        u[..., 3 * ni + 2 * ns :],
    )


@filter_jit
def params_to_points(
    constraints: Constraints, u: Float[Array, "*batch n_free"], x0: Float[Array, "*batch n 3"]
) -> Float[Array, "*batch n 3"]:
    """Node coordinates ``project(x0 + B u)`` from the free coordinates `u` (JAX, differentiable).

    **Arguments:**

    - `constraints`: the `Constraints` of the mesh.
    - `u`: free coordinates, shape ``(n_free,)`` or ``(..., n_free)``: interior displacements (node-major,
      x y z), then surface tangent coordinates (node-major, 2 each), then edge tangent coordinates.
    - `x0`: base coordinates of shape ``(n_nodes, 3)`` (broadcast against the batch of `u`), normally on the
      boundary already.

    **Returns:** coordinates of shape ``(..., n_nodes, 3)`` in the dtype of `x0` and `u` combined.
    """
    c = constraints
    u = jnp.asarray(u)
    ui, us, ue = _split(c, u)
    x0 = jnp.asarray(x0)
    x = jnp.broadcast_to(x0, jnp.broadcast_shapes(u.shape[:-1] + x0.shape[-2:], x0.shape)).astype(
        jnp.result_type(x0, u)
    )
    x = x.at[..., c.interior_nodes, :].add(ui)
    x = x.at[..., c.surface_nodes, :].add(jnp.einsum("...sk,skd->...sd", us, c.surface_basis.astype(x.dtype)))
    x = x.at[..., c.edge_nodes, :].add(ue[..., None] * c.edge_tangent.astype(x.dtype))
    return project(c, x)


@filter_jit
def points_to_params(
    constraints: Constraints, points: Float[Array, "*batch n 3"], x0: Float[Array, "*batch n 3"]
) -> Float[Array, "*batch n_free"]:
    """The free coordinates ``B^T (points - x0)`` of a displacement (zero for ``points == x0``).

    It inverts `params_to_points` for displacements along the tangents of planar patches and straight curves.

    **Arguments:** `constraints`; `points` and `x0` of shape ``(..., n_nodes, 3)``.

    **Returns:** an array of shape ``(..., n_free)``.
    """
    c = constraints
    d = jnp.asarray(points) - jnp.asarray(x0)
    lead = d.shape[:-2]
    ui = d[..., c.interior_nodes, :].reshape(lead + (-1,))
    us = jnp.einsum("...sd,skd->...sk", d[..., c.surface_nodes, :], c.surface_basis.astype(d.dtype))
    ue = (d[..., c.edge_nodes, :] * c.edge_tangent.astype(d.dtype)).sum(-1)
    return jnp.concatenate([ui, us.reshape(lead + (-1,)), ue], axis=-1)
