"""The free coordinates of a mesh as one flat vector, for the gradient solvers and the untangler.

The unknowns are the free coordinates of `jaxci.geometry.projection` (3 per interior node, 2 per surface node, 1 per
edge node; corner nodes fixed), divided by the local edge length h of their node: ``u = h * v`` and the solvers see
``v``. Node coordinates are ``project(x0 + B u)`` (`Parametrisation.points`), so every iterate lies on the
original boundary. Where every moving boundary node stays inside the flat (planar or straight) part of the
boundary around it, the projection is the identity and is skipped (`Parametrisation.shortcut`).

Setup is vectorised numpy (on a shared 2-core Xeon: `node_lengths` 0.7-1.0 s at 10^6 hexahedra, perturb_box(100),
2026-11-27; the flat regions 0.4 s at 60^3 = 216,000 elements).
"""

from __future__ import annotations

import numpy as np

from ..cells import CORNER_NEIGHBOURS
from ..geometry.boundary import BoundaryInfo
from ..geometry.projection import Constraints, n_free, project, project_np
from ..metrics import objective as mixed
from ..runtime._lazy import enable_x64, is_jax_array, jax, jit, jnp, pytree_dataclass
from ..runtime.transfer import program, to_host
from ._buckets import bucket, free_index, free_layout, pad_connectivity, pad_rows, padded_constraints, to_device


@pytree_dataclass(static=("shortcut", "strict"))
class Parametrisation:
    """Node coordinates from scaled free coordinates ``v``: ``project(cons, x0 + B (scale * v))``.

    Built by `make_parametrisation`; a pytree (pass it INTO jitted functions).

    **Fields:** `cons` the `Constraints`; `x0` base coordinates ``(n, 3)``; `scale` ``(n_free,)`` unit of each
    free coordinate; `flat_nodes` ``(m,)``, `flat_origin` ``(m, 3)``, `flat_radius` ``(m,)``: for every moving
    boundary node, a disk (surface) or interval (edge) around its original position on which the boundary is
    planar (straight); `shortcut`: True when every moving boundary node has one (static); `strict` (static,
    default False): with `shortcut`, never project: a point with a node outside its flat region is all NaN, so a
    solver rejects it (`jaxci.optim.gradient.minimise` runs strict first: the compiled loop is 40% smaller).

    While every boundary node lies inside its flat region, ``x0 + B u`` is already on the boundary and its
    projection is itself, so `points` skips the search over candidate triangles (exactly: same value, same
    derivative ``B``); otherwise it calls `jaxci.geometry.projection.project` (exact value; with `shortcut` the
    derivative is still ``B``, the tangent map, so that the backward pass keeps no residuals of the projection).
    """

    cons: Constraints
    x0: jax.Array
    scale: jax.Array
    flat_nodes: jax.Array
    flat_origin: jax.Array
    flat_radius: jax.Array
    shortcut: bool
    strict: bool = False

    @property
    def n_free(self) -> int:
        return int(self.scale.shape[0])

    def lift(self, v):
        """``x0 + B (scale * v)`` without projection, shape ``(n, 3)``."""
        return lift_points(jnp, self.x0, self.scale, self.cons, v)

    def points(self, v):
        """Node coordinates of shape ``(n, 3)`` for scaled free coordinates `v` of shape ``(n_free,)``."""
        x = self.lift(v)
        if not self.shortcut:
            return project(self.cons, x)
        inside = self.inside(x)
        if self.strict:  # no projection compiled: a node outside its flat region makes every coordinate NaN
            return jnp.where(inside, x, jnp.nan)
        # outside: the exact projection, differentiated as the lift (B, its derivative on the flat regions); a
        # differentiated projection branch keeps its residuals even when not taken (zeros), which cost 35 ms per
        # gradient at 60^3
        return jax.lax.cond(inside, lambda y: y, lambda y: y + jax.lax.stop_gradient(project(self.cons, y) - y), x)

    def inside(self, x):
        """Whether every moving boundary node of `x` ``(n, 3)`` lies inside its flat region (with `shortcut`):
        a boolean scalar."""
        d = x[self.flat_nodes] - self.flat_origin
        return jnp.all(jnp.sum(d * d, axis=-1) < (0.999 * self.flat_radius) ** 2)

    def reach(self, v) -> float:
        """How far the moving boundary nodes of `v` went into their flat regions: the largest distance from the
        region's origin over 0.999 times its radius (float64; < 1: `points` needs no projection). For a device
        parametrisation and a device `v`, on the device (one scalar comes down)."""
        if is_jax_array(self.x0) and is_jax_array(v):
            with enable_x64():
                return float(to_host(lift_reach(self, v, None)[1]))
        return float(self.reach_of(self._lift_np(v)))

    def final_points(self, v, project=None):
        """`points` of `v`, in float64 outside `jax.jit` (the exact `jaxci.geometry.projection.project_np` only
        where a node left its flat region), returned in the dtype of `x0`: compiling `points` for this one call cost
        0.5 s of the 729-element cold start, running it op by op 1 s. For a device parametrisation and a device
        `v`, the lift and the test run on the device (one scalar comes down); only where a node left its flat
        region do the points come to the host for the exact projection, or, given `project` (a function of device
        coordinates ``(n, 3)``: the run whose mesh lives on the device), go to it instead."""
        if is_jax_array(self.x0) and is_jax_array(v):
            with enable_x64():
                x, r = lift_reach(self, v, np.dtype(self.x0.dtype))
            if self.shortcut and float(to_host(r)) < 1.0:
                return x
            if project is not None:
                return project(x)
            v = to_host(v)
        x = self._lift_np(v)
        if not (self.shortcut and self.reach_of(x) < 1.0):
            x = project_np(self.cons, x)
        return to_device(x, self.x0.dtype)

    def _lift_np(self, v):
        f64 = np.float64
        return lift_points(np, np.asarray(self.x0, f64), np.asarray(self.scale, f64), self.cons, np.asarray(v, f64))

    def reach_of(self, x, xp=np):
        """`reach` of the node coordinates `x` ``(n, 3)``, with `xp` numpy (float64) or `jax.numpy` (traceable):
        a scalar."""
        d = x[self.flat_nodes] - xp.asarray(self.flat_origin, x.dtype)
        r = 0.999 * xp.asarray(self.flat_radius, x.dtype)
        dist = xp.sqrt(xp.sum(d * d, axis=-1))
        return xp.max(xp.where(r > 0, dist / xp.where(r > 0, r, 1.0), xp.inf), initial=0.0)


@program
@jit(static_argnames=("dtype",))
def lift_reach(par: Parametrisation, v, dtype):
    """`Parametrisation.lift` and `Parametrisation.reach` of a device `v` on the device, float64: ``(points,
    reach)``, the lifted points in `dtype` (None: none)."""
    f64 = jnp.float64
    x = lift_points(jnp, par.x0.astype(f64), par.scale.astype(f64), par.cons, v.astype(f64))
    return (None if dtype is None else x.astype(dtype)), par.reach_of(x, jnp)


def pad_parametrisation(par: Parametrisation) -> tuple[Parametrisation, np.ndarray]:
    """`par` padded to the size class of its mesh (`jaxci.optim._buckets`): ``(padded, index)``; on the device
    for a device `par` (one program: nothing moves between host and device), else built in numpy and placed.

    Nodes, the interior / surface / edge blocks of the free coordinates, the flat regions and every array of
    the constraints (`jaxci.optim._buckets.pad_constraints`) are rounded up to the ladder, with at least one
    padding node (the dummy node every padded entry points to). Padded free coordinates have scale 0 and a zero
    basis: they never move a node and their gradient is exactly 0; the padded flat regions are the dummy node's
    own position with radius 1 (always inside). `index` ``(n_free,)`` (numpy, from the sizes alone) is the
    position of every real free coordinate in the padded vector: ``v = v_pad[index]`` (on the device:
    `unpad_free`).
    """
    n_pad = bucket(int(par.x0.shape[0]) + 1)
    index = free_index(free_layout(par.cons), _padded_layout(par.cons))
    if is_jax_array(par.x0):
        return _pad_parametrisation_device(par, n_pad), index
    host = jax.tree_util.tree_map(np.asarray, par)
    return to_device(_padded_parametrisation(host, n_pad)), index


def _padded_layout(cons: Constraints) -> tuple[int, int, int]:
    """`free_layout` of `cons` padded (`jaxci.optim._buckets.pad_constraints`: each node list to the ladder)."""
    return tuple(bucket(k) for k in free_layout(cons))


@program
@jit(static_argnames=("n_pad",))
def _pad_parametrisation_device(par: Parametrisation, n_pad: int) -> Parametrisation:
    return _padded_parametrisation(par, n_pad)


def pad_problem_device(par: Parametrisation, conn, n_elements: int):
    """`pad_parametrisation` of a device `par` with its hexahedra `conn` ``(8, N)`` padded to `n_elements`
    (`jaxci.optim._buckets.pad_connectivity`) in the same program (one compilation per mesh size):
    ``(padded, index, conn, weight)``."""
    n_pad = bucket(int(par.x0.shape[0]) + 1)
    padded, c, w = _pad_problem_device(par, conn, n_pad, int(n_elements))
    return padded, free_index(free_layout(par.cons), _padded_layout(par.cons)), c, w


@program
@jit(static_argnames=("n_pad", "n_elements"))
def _pad_problem_device(par: Parametrisation, conn, n_pad: int, n_elements: int):
    c, w = pad_connectivity(conn.astype(jnp.int32), n_elements, par.x0.dtype)
    return _padded_parametrisation(par, n_pad), c, w


def _padded_parametrisation(par: Parametrisation, n_pad: int) -> Parametrisation:
    """`pad_parametrisation`'s padded `par`, over the array module of its arrays (numpy, or jax.numpy under
    `jax.jit`): the scale's blocks with zeros after each (no scatter)."""
    xp = jnp if is_jax_array(par.x0) else np
    n = par.x0.shape[0]
    (ni, ns, ne), (pi, ps, pe) = free_layout(par.cons), _padded_layout(par.cons)
    dtype = par.x0.dtype
    s = par.scale.astype(dtype)
    blocks = [s[: 3 * ni], xp.zeros(3 * (pi - ni), dtype), s[3 * ni : 3 * ni + 2 * ns], xp.zeros(2 * (ps - ns), dtype),
              s[3 * ni + 2 * ns :], xp.zeros(pe - ne, dtype)]
    m = bucket(par.flat_nodes.shape[0])
    return Parametrisation(
        cons=padded_constraints(par.cons, n_pad),
        x0=pad_rows(par.x0, n_pad, 0.0),
        scale=xp.concatenate(blocks),
        flat_nodes=pad_rows(par.flat_nodes.astype(np.int32), m, n),
        flat_origin=pad_rows(par.flat_origin.astype(dtype), m, 0.0),
        flat_radius=pad_rows(par.flat_radius.astype(dtype), m, 1.0),
        shortcut=par.shortcut,
        strict=par.strict,
    )


@program
@jit(static_argnames=("real", "padded"))
def unpad_free(v, real: tuple[int, int, int], padded: tuple[int, int, int]):
    """The real free coordinates ``(n_free,)`` of a padded vector `v` (`pad_parametrisation`'s layout; `real`
    and `padded` the `jaxci.optim._buckets.free_layout` of the constraints before and after padding), on the
    device: three slices."""
    (ni, ns, ne), (pi, ps, _) = real, padded
    return jnp.concatenate([v[: 3 * ni], v[3 * pi : 3 * pi + 2 * ns], v[3 * pi + 2 * ps : 3 * pi + 2 * ps + ne]])


def lift_points(xp, x0, scale, c: Constraints, v):
    """``x0 + B (scale * v)`` with `xp` = `jax.numpy` (traceable) or `numpy` (float64, in place on a copy)."""
    u = scale * v
    ni, ns = c.interior_nodes.shape[0], c.surface_nodes.shape[0]
    moves = (
        (c.interior_nodes, u[: 3 * ni].reshape(ni, 3)),
        (c.surface_nodes, xp.einsum("sk,skd->sd", u[3 * ni : 3 * ni + 2 * ns].reshape(ns, 2),
                                    xp.asarray(c.surface_basis).astype(x0.dtype))),
        (c.edge_nodes, u[3 * ni + 2 * ns :, None] * xp.asarray(c.edge_tangent).astype(x0.dtype)),
    )
    if xp is np:
        x = np.array(x0)
        for nodes, d in moves:
            x[np.asarray(nodes)] += d  # each node in one class at most once
        return x
    x = x0
    for nodes, d in moves:
        x = x.at[nodes].add(d)
    return x


def lift_transpose_np(scale: np.ndarray, c: Constraints, g: np.ndarray) -> np.ndarray:
    """``scale * B^T g`` (numpy): a gradient ``(n, 3)`` with respect to the node coordinates taken to the scaled
    free coordinates of `lift_points` (the adjoint of its linear part), shape ``(n_free,)``."""
    gi = g[np.asarray(c.interior_nodes)].reshape(-1)
    gs = np.einsum("sd,skd->sk", g[np.asarray(c.surface_nodes)], np.asarray(c.surface_basis, g.dtype)).reshape(-1)
    ge = np.sum(g[np.asarray(c.edge_nodes)] * np.asarray(c.edge_tangent, g.dtype), axis=-1)
    return scale * np.concatenate([gi, gs, ge])


def flat_surface_rings(points: np.ndarray, info: BoundaryInfo, cons: Constraints) -> np.ndarray:
    """Per SURFACE node (``cons.surface_nodes`` order, shape ``(ns, 7)``) the origin (3), normal (3) and radius of
    its planar ring of boundary faces (radius 0: none; `jaxci.optim._moves.planar_rings`). Kept on
    `info` for these `points` (the untangling stage, the smoothing of one run and its escape's sweeps share it:
    0.1 s at 27,000 hexahedra)."""
    from ._moves import surface_node_rings

    cached = getattr(info, "_flat_rings", None)
    if cached is not None and cached[0] is points:
        return cached[1]
    # made for the surface nodes only (`planar_rings`' rows of them): the (n, 7) array of every node was 58 MB at
    # 10^6 hexahedra, kept, and then 13 MB at 216,000 as a temporary
    rings = surface_node_rings(points, info.topology.faces, cons)
    object.__setattr__(info, "_flat_rings", (points, rings))  # a frozen dataclass; a cache is not a field
    return rings


def flat_intervals(points: np.ndarray, fe: np.ndarray, edge_nodes: np.ndarray) -> np.ndarray:
    """Per EDGE node of `edge_nodes` ``(ne,)``, the half-length of the straight interval around it made by its two
    feature edges of `fe` ``(m, 2)`` (node pairs; 0: none, as for a node with other than two), vectorised over the
    nodes; straightness is tested in the float64 geometry (the constraints' tangents may be float32). `points` are
    indexed by node (any array with the rows of the nodes of `fe`)."""
    out = np.zeros(len(edge_nodes))
    if not len(edge_nodes) or not len(fe):
        return out
    # each node's feature edges: the other end of each, the edges of a node in their order in `fe`
    ends = fe.reshape(-1)
    other = fe[:, ::-1].reshape(-1)
    order = np.argsort(ends, kind="stable")
    ends, other = ends[order], other[order]
    lo = np.searchsorted(ends, edge_nodes, "left")
    two = np.searchsorted(ends, edge_nodes, "right") - lo == 2
    j = np.flatnonzero(two)
    if not len(j):
        return out
    v = edge_nodes[j]
    rel = points[other[np.stack([lo[j], lo[j] + 1], axis=1)]] - points[v][:, None]  # (k, 2, 3)
    chord = rel[:, 1] - rel[:, 0]
    t = chord / np.maximum(np.linalg.norm(chord, axis=1), 1e-300)[:, None]
    along = np.einsum("kij,kj->ki", rel, t)
    perp = np.linalg.norm(rel - along[..., None] * t[:, None], axis=2)
    r = np.min(np.abs(along), axis=1)
    ok = (along.min(axis=1) < 0) & (0 < along.max(axis=1)) & (perp.max(axis=1) <= 1e-12 * np.maximum(r, 1e-300))
    out[j[ok]] = r[ok]
    return out


def node_lengths(hexes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean length of the hex edges at each node, shape ``(n,)`` (numpy float64; 0 for unused nodes).

    Over the incident elements, the three edges of the element at the node (each edge once per element), as
    `jaxci.optim._local.local_length` computes it for one node.
    """
    p = np.asarray(points, dtype=np.float64)
    hexes = np.asarray(hexes)
    corners = hexes.T  # (8, N): each corner's nodes (a view)
    n = len(p)
    # added in the order of one pass over every edge's first node, then every edge's second (np.add.at adds in
    # order); each edge's lengths made for each pass (the same numbers twice: the 12 N lengths of every element
    # kept, with a copy of the corners and the gathered coordinates of a block, were 46 MB at 216,000 hexahedra)
    total, length = np.zeros(n), np.empty(corners.shape[1])
    for end in (0, 1):
        for i, j in _EDGE_ENDS.T:
            for s in range(0, len(length), _LENGTH_BLOCK):
                d = p.take(corners[j, s : s + _LENGTH_BLOCK], axis=0)  # (b, 3) C-contiguous rows: einsum's
                d -= p.take(corners[i, s : s + _LENGTH_BLOCK], axis=0)  # rounding depends on the layout, not b
                np.sqrt(np.einsum("nd,nd->n", d, d), out=length[s : s + _LENGTH_BLOCK])
            np.add.at(total, corners[(i, j)[end]], length)
    count = 3 * np.bincount(hexes.ravel(), minlength=n)  # every corner is an end of 3 edges
    return np.divide(total, count, out=np.zeros(n), where=count > 0)


#: Elements per block of `node_lengths`' gathers (2 x 3 floats each: 3 MB).
_LENGTH_BLOCK = 1 << 16

#: The 12 edges of a hexahedron (local nodes i < j joined by an edge), from `CORNER_NEIGHBOURS`.
_EDGE_ENDS = np.array(sorted({(min(i, int(j)), max(i, int(j))) for i in range(8) for j in CORNER_NEIGHBOURS[i]})).T


def free_lengths(mesh, cons: Constraints, points=None) -> np.ndarray:
    """Local edge length of the node of every free coordinate (the `jaxci.geometry.projection` layout), float64
    ``(n_free,)``: `node_lengths` over the hexahedra; for a node of non-hexahedral cells only, the mean edge
    length of its cells (`jaxci.metrics.objective.node_lengths`); 0 for a node of no cell.
    """
    pts = mesh.points if points is None else points
    h = node_lengths(mesh.hexes, pts)
    if mixed.has_extra(mesh):
        h = np.where(h > 0, h, mixed.node_lengths(mesh, np.asarray(pts, dtype=np.float64)))
    inter, surf, edge = (np.asarray(a) for a in (cons.interior_nodes, cons.surface_nodes, cons.edge_nodes))
    return np.concatenate([np.repeat(h[inter], 3), np.repeat(h[surf], 2), h[edge]])


def make_parametrisation(mesh, info: BoundaryInfo, cons: Constraints, x0=None, *, scaled: bool = True,
                         dtype=None) -> Parametrisation:
    """Build the `Parametrisation` of a mesh's free coordinates.

    **Arguments:**

    - `mesh`: the `HexMesh` (its coordinates are the original geometry the constraints were built from).
    - `info`, `cons`: its `BoundaryInfo` and `Constraints`.
    - `x0`: base coordinates ``(n, 3)`` (default: the mesh's); boundary nodes must lie on the boundary.
    - `scaled`: unknowns in units of the local edge length of their node (default True).
    - `dtype`: float dtype (default: that of `cons`).

    **Returns:** a `Parametrisation` (x0 at v = 0).
    """
    dtype = cons.x_orig.dtype if dtype is None else dtype
    pts = np.asarray(mesh.points, dtype=np.float64)
    base = pts if x0 is None else np.asarray(x0, dtype=np.float64)
    c = cons
    inter, surf, edge = (np.asarray(a) for a in (c.interior_nodes, c.surface_nodes, c.edge_nodes))
    if scaled:
        scale = free_lengths(mesh, c, base)
        scale = np.where(scale > 0, scale, 1.0)
    else:
        scale = np.ones(n_free(c))
    rings = flat_surface_rings(pts, info, c)
    tangent = np.asarray(c.edge_tangent, dtype=np.float64)
    r_edge = flat_intervals(pts, np.asarray(info.feature_edges), edge)
    nodes = np.concatenate([surf, edge]).astype(np.int64)
    origin = pts[nodes]
    radius = np.concatenate([rings[:, 6], r_edge])
    # base points must lie on their plane / line for x0 + B u to stay on it, to the precision of the working dtype
    # (a float32 start is off a plane that is not axis-aligned by its rounding, and the tangents may be float32)
    tol = np.maximum(1e-12 * radius, 64 * np.finfo(dtype).eps * np.abs(base[nodes]).max(axis=1, initial=0.0))
    if len(surf):
        normal = rings[:, 3:6]
        off = np.abs(np.einsum("sd,sd->s", base[surf] - pts[surf], normal))
        radius[: len(surf)] = np.where(off <= tol[: len(surf)], radius[: len(surf)], 0.0)
    if len(edge):
        rel = base[edge] - pts[edge]
        perp = np.linalg.norm(rel - np.einsum("ed,ed->e", rel, tangent)[:, None] * tangent, axis=1)
        k = len(surf)
        radius[k:] = np.where(perp <= tol[k:], radius[k:], 0.0)
    shortcut = bool(len(nodes)) and bool(np.all(radius > 0))
    # to_device: no compilation per shape (jnp.asarray of a numpy array compiles a small program for each); numpy
    # constraints (the numpy path, `build_constraints(device=False)`) give a numpy parametrisation
    put = to_device if is_jax_array(c.x_orig) else (lambda a, dt: np.asarray(a, dtype=np.dtype(dt)))
    return Parametrisation(
        cons=c,
        x0=put(base, dtype),
        scale=put(scale, dtype),
        flat_nodes=put(nodes, np.int32),
        flat_origin=put(origin, dtype),
        flat_radius=put(radius, dtype),
        shortcut=shortcut,
    )
