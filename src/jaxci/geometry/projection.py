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
  the nearest point lies in the 2-ring, i.e. for moves of up to about one element. The host solvers' numpy
  version of `project`, starting from each node's last cell, is `jaxci.geometry.near.NearProjector`; its
  candidates follow the node (the 2-ring of an anchor that moves with it: `jaxci.geometry.anchors`), so that
  its nodes slide as far as the solver takes them.

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

from ..mesh import HexMesh
from ..mesh.sorting import sorted_unique
from ..runtime._lazy import filter_jit, jax, jnp, pytree_dataclass, when_imported
from ._closest import (
    closest_on_segments,
    closest_on_triangles,
    inside_tolerance,
    nearest_candidates,
    segment_centres,
    triangle_centres,
)
from .boundary import CORNER, EDGE, INTERIOR, SURFACE, BoundaryInfo

if TYPE_CHECKING:
    from jaxtyping import Array, Float, Int
from .tables import boundary_tables, surface_candidates, surface_triangles


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


def build_constraints(mesh: HexMesh, info: BoundaryInfo, *, dtype=None, device: bool = True) -> Constraints:
    """Keep a copy of the boundary of `mesh` and precompute everything the projections need.

    **Arguments:**

    - `mesh`: the mesh whose CURRENT coordinates are the original geometry to project onto.
    - `info`: its `BoundaryInfo` (from `jaxci.geometry.boundary.classify_boundary`).
    - `dtype`: float dtype of the geometry arrays; default JAX's default float (float64 under
      ``jax_enable_x64``, else float32). Keyword only argument.
    - `device`: put the arrays on JAX's default device (default; for jitted functions, which would copy numpy
      arrays in at every call), or keep them in numpy (the numpy path: JAX is not imported).

    **Returns:** a `Constraints`. Its per-node arrays are built here from the mesh's points (O(mesh); on the
    device, `jaxci.geometry.device_constraints.device_constraints` builds them there), its boundary tables by
    `jaxci.geometry.tables.boundary_tables` from the boundary nodes' coordinates. In numpy float64
    (``device=False``) a `HostConstraints`, whose triangle table is made on first read.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    pts = np.asarray(mesh.points, dtype=np.float64)
    n = mesh.n_nodes
    cls = np.asarray(info.node_class)
    group = np.where(cls == SURFACE, info.patch_id, np.where(cls == EDGE, info.curve_id, -1)).astype(np.int32)
    nodes = {c: info.nodes_of(c) for c in (INTERIOR, SURFACE, EDGE, CORNER)}
    surf, edge = nodes[SURFACE], nodes[EDGE]
    row = np.zeros(n, dtype=np.int32)
    row[surf] = np.arange(len(surf))
    row[edge] = np.arange(len(edge))
    # the tables from the coordinates of the boundary nodes (those of the faces, the feature edges, each class)
    faces, fedges = info.topology.faces, info.feature_edges
    need = sorted_unique(np.concatenate([faces.ravel(), fedges.ravel(), surf, edge, nodes[CORNER]]).astype(np.int64))
    lazy = not device and np.dtype(dtype) == np.float64  # the triangle table on first use (`HostConstraints`)
    tables = boundary_tables(need, pts[need], faces, info.face_patch, fedges, info.edge_curve, surf,
                             np.asarray(info.patch_id)[surf], edge, np.asarray(info.curve_id)[edge], nodes[CORNER],
                             triangles=not lazy)

    put = jax.device_put if device else (lambda a: a)

    def i32(a):  # converted on the host: jnp.asarray compiles a small program per shape
        return put(np.asarray(a, dtype=np.int32))

    def f(a):
        return put(np.asarray(a, dtype=np.dtype(dtype)))

    fields = dict(
        x_orig=f(pts),
        node_class=i32(cls),
        group=i32(group),
        row=i32(row),
        interior_nodes=i32(nodes[INTERIOR]),
        surface_nodes=i32(surf),
        edge_nodes=i32(edge),
        corner_nodes=i32(nodes[CORNER]),
        **{k: (i32 if getattr(tables, k).dtype.kind in "iu" else f)(getattr(tables, k)) for k in TABLE_FIELDS
           if getattr(tables, k) is not None},
    )
    if not lazy:
        return Constraints(**fields)
    return HostConstraints.deferred(fields, faces, info.face_patch)


class HostConstraints(Constraints):
    """`Constraints` in numpy float64 (`build_constraints` with ``device=False`` and float64) whose triangle table
    (`triangles`, `triangle_patch`) is made on first read: 19 float64 numbers a triangle, four triangles a boundary
    face (12.5 MB of cube60_pert's 216,000 hexahedra), which only a projection of a surface node by a search reads,
    and the host solvers search for no node inside a flat part of the boundary (`jaxci.optim.host.HostObjective`):
    on a box, never. The table made is `jaxci.geometry.tables.surface_triangles` of ``x_orig`` and the boundary
    faces, the same numbers `jaxci.geometry.tables.boundary_tables` gives. An instance made by
    `dataclasses.replace` holds every field."""

    @classmethod
    def deferred(cls, fields: dict, faces: np.ndarray, face_patch: np.ndarray) -> HostConstraints:
        """The constraints of `fields` (every field but the triangle table's two) whose table is made from the
        boundary faces `faces` ``(n_faces, 4)`` (node indices) and their patches `face_patch` on first read."""
        out = object.__new__(cls)
        for k, v in fields.items():
            object.__setattr__(out, k, v)
        object.__setattr__(out, "_faces", (faces, face_patch))
        return out

    @property
    def has_triangles(self) -> bool:
        """Whether the triangle table is made (read, or given)."""
        return "triangles" in self.__dict__

    def __getattr__(self, name: str):  # only for attributes not set: the triangle table's, before it is made
        faces = self.__dict__.get("_faces")
        if name not in ("triangles", "triangle_patch", "surface_cand") or faces is None:
            raise AttributeError(f"'{type(self).__name__}' object has no attribute '{name}'")
        if name == "surface_cand":  # let go by `drop_candidates`: made again, the same numbers
            cand = surface_candidates(faces[0], len(self.x_orig), np.asarray(self.surface_nodes, np.int64), faces[1],
                                      np.asarray(self.group))
            object.__setattr__(self, "surface_cand", cand)
            return cand
        tris, patch = surface_triangles(self.x_orig, *faces)
        object.__setattr__(self, "triangles", np.asarray(tris, np.float64))
        object.__setattr__(self, "triangle_patch", np.asarray(patch, np.int32))
        return self.__dict__[name]

    def drop_candidates(self) -> None:
        """Let the surface nodes' candidate triangles go (`surface_cand`; 5 MB at 216,000 hexahedra, made again,
        the same numbers, on the next read): for a solver that searches for no node (`jaxci.optim.host.
        HostObjective` where every moving boundary node stays in its flat region)."""
        if "_faces" in self.__dict__:
            self.__dict__.pop("surface_cand", None)

    def drop_triangles(self) -> None:
        """Let the triangle table go where it was made here (it is made again, the same numbers, on the next
        read): for a caller that read it for one search of its own (`project_np`)."""
        if "_faces" in self.__dict__:
            self.__dict__.pop("triangles", None)
            self.__dict__.pop("triangle_patch", None)


def _register_host_constraints():
    jax.tree_util.register_dataclass(HostConstraints, data_fields=[f.name for f in dataclasses.fields(Constraints)],
                                     meta_fields=[])


when_imported("jax", _register_host_constraints)


#: The fields of `Constraints` that `jaxci.geometry.tables.BoundaryTables` holds too.
TABLE_FIELDS = ("surface_basis", "edge_tangent", "surface_cand", "edge_cand", "triangles", "triangle_patch",
                "segments", "segment_curve")


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
    for nodes, tab, cand, closest in ((c.surface_nodes, c.triangles, c.surface_cand, closest_on_triangles),
                                      (c.edge_nodes, c.segments, c.edge_cand, closest_on_segments)):
        if nodes.shape[0]:
            p = nearest_candidates(jnp, x[..., nodes, :], tab.astype(x.dtype), cand[: nodes.shape[0]], closest,
                                   inside_tolerance(x.dtype))
            x = x.at[..., nodes, :].set(p)
    return x.at[..., c.corner_nodes, :].set(c.x_orig[c.corner_nodes].astype(x.dtype))


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


def _search(table, cells, x, closest, centre_radius, eps: float = float(np.finfo(np.float64).eps)):
    """Exact nearest points of `x` (m, 3) on the cells `table[:, cells]`, via a k-d tree of cell centres.

    The nearest cell centre, at distance d0, and the point `closest` finds on its cell, at distance d1, bound the
    distance to the nearest point by ``b = min(d0, d1)``; a cell j whose centre is farther than ``b + r_j`` (its
    radius, plus a margin for rounding) cannot hold a nearer point. Each point's candidates are the cells within
    that bound (found with k nearest-neighbour queries, k doubled for the points whose k-th neighbour is still
    within it; no Python lists), and always the cell of the nearest centre; the winner is the lowest score, a tie
    going to the lowest cell. `eps`: the machine epsilon of the table as the constraints hold it (float32 tables
    are consistent to their own rounding only: a wider margin).
    """
    from scipy.spatial import cKDTree  # here, not at the top: its import is 0.3-0.5 s of a command's start

    centre, radius = centre_radius(table[:, cells])
    tree = cKDTree(centre, balanced_tree=False)  # built 2-3 times faster, same distances (a tie in d0 may pick
    # another cell, whose point gives another valid bound)
    d0, i0 = tree.query(x)
    tol = inside_tolerance(np.float64)
    _, s1 = closest(np, tuple(x.T), table[:, cells[i0]], tol)
    r_max = float(radius.max())
    # rounding: relative to the cells' size and to the coordinates' magnitude (the distances of far-off meshes)
    margin = max(1e-9, 100.0 * eps) * r_max + 1e-12 * max(float(np.abs(centre).max()), float(np.abs(x).max()))
    bound = np.fmin(np.sqrt(s1), d0) + (margin + 1e-300)  # d0 where that point's score is NaN
    reach = np.minimum(bound + r_max, d0 + r_max * (1 + 1e-9) + 1e-300)  # nor beyond d0 + the largest radius
    radius = np.append(radius, 0.0)  # the radius of a missing neighbour (index len(cells), at infinity)
    # the nearest centre's cell first, for every point (far off, d0 + r_max rounds to d0: it may be the only one)
    owner, cand = [np.arange(len(x))], [i0]
    rows, k = np.arange(len(x)), min(16, len(cells))
    while len(rows):
        # the query keeps distances strictly below its bound: one ulp above the reach keeps those at it
        upper = float(np.nextafter(reach[rows].max(), np.inf))
        d, i = (a.reshape(len(rows), k) for a in tree.query(x[rows], k=k, distance_upper_bound=upper))
        keep = (d <= bound[rows, None] + radius[i]) & (d <= reach[rows, None]) & (i != i0[rows, None])
        done = (d[:, -1] > reach[rows]) | (k == len(cells))  # the k-th neighbour beyond reach: all were found
        r, c = np.nonzero(keep[done])
        owner.append(rows[done][r])
        cand.append(i[done][r, c])
        rows, k = rows[~done], min(2 * k, len(cells))
    owner, cand = np.concatenate(owner), np.concatenate(cand)
    p, score = closest(np, tuple(x[owner].T), table[:, cells[cand]], tol)
    # each point's lowest score, then its lowest cell among those (ufunc.at: no sort)
    best = np.full(len(x), np.inf)
    with np.errstate(invalid="ignore"):  # a NaN score: see below
        np.minimum.at(best, owner, score)
    tie = score == best[owner]
    low = np.full(len(x), len(cells))
    np.minimum.at(low, owner[tie], cand[tie])
    win = np.flatnonzero(tie & (cand == low[owner]))
    if len(win) != len(x):  # a NaN score (np.lexsort sorts it after every number) or a point without candidates
        order = np.lexsort((cand, score, owner))
        return np.stack([pj[order[np.r_[True, owner[order][1:] != owner[order][:-1]]]] for pj in p], axis=1)
    out = np.empty((len(x), 3))
    out[owner[win]] = np.stack([pj[win] for pj in p], axis=1)
    return out


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
    # a triangle table made for this search alone is not kept (`HostConstraints`: the presmoothing's projection
    # held it through the whole solve: 36 MB at 10^6 hexahedra)
    made_here = isinstance(c, HostConstraints) and not c.has_triangles
    x = np.array(points, dtype=np.float64)
    group = np.asarray(c.group)
    surf, edge, corners = (np.asarray(a) for a in (c.surface_nodes, c.edge_nodes, c.corner_nodes))
    x[surf], x[edge] = project_on_groups(c, x[surf], group[surf], x[edge], group[edge])
    x[corners] = np.asarray(c.x_orig, dtype=np.float64)[corners]
    if made_here:
        c.drop_triangles()
    return x


def project_on_groups(tables, xs: np.ndarray, surface_group: np.ndarray, xe: np.ndarray,
                      edge_group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`project_np`'s exact search for some points only: the points `xs` ``(k, 3)`` onto the patches
    `surface_group` ``(k,)``, the points `xe` ``(l, 3)`` onto the curves `edge_group` ``(l,)``.

    **Arguments:** `tables`: a `Constraints` or a `jaxci.geometry.tables.BoundaryTables` (its `triangles`,
    `triangle_patch`, `segments`, `segment_curve` are read); then the points and their groups.

    **Returns:** the nearest points ``(k, 3)`` and ``(l, 3)``, float64.
    """
    out = []
    for x, node_group, table, cell_group, closest, centres in (
        (xs, surface_group, tables.triangles, tables.triangle_patch, closest_on_triangles, triangle_centres),
        (xe, edge_group, tables.segments, tables.segment_curve, closest_on_segments, segment_centres),
    ):
        x = np.array(x, dtype=np.float64).reshape(-1, 3)
        node_group = np.asarray(node_group)
        table = np.asarray(table)
        eps = float(np.finfo(table.dtype).eps) if table.dtype.kind == "f" else float(np.finfo(np.float64).eps)
        table = table.astype(np.float64, copy=False)
        cell_group = np.asarray(cell_group)
        for g in np.unique(node_group):
            sel = np.flatnonzero(node_group == g)
            x[sel] = _search(table, np.flatnonzero(cell_group == g), x[sel], closest, centres, eps)
        out.append(x)
    return out[0], out[1]


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
