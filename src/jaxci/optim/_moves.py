"""What the local optimizers share: per-node move bases, projected trial positions, coloured sweeps.

A movable node v has a basis B_v of shape ``(3, 3)`` whose columns span its free directions: the identity for an
INTERIOR node, the two surface tangents (third column 0) for a SURFACE node, the curve tangent (other columns
0) for an EDGE node. A trial position is ``project(x_v + B_v u)`` for a 3-vector u whose unused entries are
ignored, so every trial lies on the node's constraint. CORNER and fixed nodes never move.

On a mixed mesh the local objective of a node also counts the corners of the wedges, pyramids and tetrahedra
around it (`ColouredStars.xnodes`..., rows of `jaxci.mixed.CornerTable`; a pyramid sub-tetrahedron counts only
as a barrier): `local_sum`, `local_count`, `local_scale`. On a hexahedral mesh those arrays have a zero-size
axis and the functions are the hexahedral ones (a static branch).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..boundary import CORNER, EDGE, INTERIOR, SURFACE
from ..mixed import CornerTable, local_extra_length, local_extra_terms, node_corner_rows
from ..projection import Constraints, project_nodes
from ._local import ColourBatches, NodeStars, chunked, colour_batches, local_length, local_terms, node_stars


def node_bases(cons: Constraints) -> jnp.ndarray:
    """Per-node move basis, shape ``(n_nodes, 3, 3)`` (columns = free directions; zeros for fixed ones)."""
    cls = np.asarray(cons.node_class)
    n = len(cls)
    B = np.zeros((n, 3, 3))
    B[cls == INTERIOR] = np.eye(3)
    surf, edge = np.asarray(cons.surface_nodes), np.asarray(cons.edge_nodes)
    if len(surf):
        B[surf, :, 0] = np.asarray(cons.surface_basis)[:, 0]
        B[surf, :, 1] = np.asarray(cons.surface_basis)[:, 1]
    if len(edge):
        B[edge, :, 0] = np.asarray(cons.edge_tangent)
    return jnp.asarray(B, dtype=cons.x_orig.dtype)


def free_dims(cons: Constraints) -> np.ndarray:
    """Number of free coordinates per node (3/2/1/0 for interior/surface/edge/corner), shape ``(n_nodes,)``."""
    return np.array([3, 2, 1, 0])[np.asarray(cons.node_class)]


@dataclasses.dataclass(frozen=True)
class ColouredStars:
    """Per colour, padded: the movable nodes, their stars and bases, ready to pass into a jitted sweep.

    Within a colour the nodes are laid out by class, in fixed slots: `n_interior` interior, then `n_surface`
    surface, then `n_edge` edge nodes (the same slot sizes for every colour, padded), so that only surface
    slots are projected onto triangles and only edge slots onto segments.

    - `nodes` ``(n_colours, M)`` (padding: index n_nodes, dropped on write); `mask` ``(n_colours, M)``;
    - `star` ``(n_colours, M, K, 8)``; `smask` ``(n_colours, M, K)``; `basis` ``(n_colours, M, 3, 3)``;
    - `dims` ``(n_colours, M)`` free coordinates per node.
    - `plane` ``(n_colours, M, 7)``: for a SURFACE node whose ring of boundary faces is planar, the original
      position (3), the plane's unit normal (3) and the radius of the disk around the original position that
      its ring of faces covers; radius 0 (never used) otherwise. Inside that disk, the orthogonal projection
      onto the plane IS the nearest point of the patch, so the triangle search can be skipped (exactly).
    - `xnodes` ``(n_colours, M, Kx, 4)``, `xwinv` ``(n_colours, M, Kx, 9)``, `xweight`, `xmask`
      ``(n_colours, M, Kx)``: the non-hexahedral corners around each node (`jaxci.mixed.CornerTable` rows);
      Kx = 0 on a hexahedral mesh.
    """

    nodes: jnp.ndarray
    mask: jnp.ndarray
    star: jnp.ndarray
    smask: jnp.ndarray
    basis: jnp.ndarray
    dims: jnp.ndarray
    plane: jnp.ndarray
    xnodes: jnp.ndarray
    xwinv: jnp.ndarray
    xweight: jnp.ndarray
    xmask: jnp.ndarray
    n_interior: int
    n_surface: int
    n_edge: int


jax.tree_util.register_dataclass(
    ColouredStars,
    data_fields=["nodes", "mask", "star", "smask", "basis", "dims", "plane", "xnodes", "xwinv", "xweight", "xmask"],
    meta_fields=["n_interior", "n_surface", "n_edge"],
)


def planar_rings(points: np.ndarray, faces: np.ndarray, cons: Constraints) -> np.ndarray:
    """Per node, ``(origin (3), normal (3), radius)`` of its planar ring of boundary faces, shape ``(n, 7)``.

    The ring is the set of candidate faces the projection searches (the 2-ring of the node on its own patch,
    `Constraints.surface_cand`); the radius is the distance from the node to the outer boundary of their union
    (edges used by one face of the ring), so the ring covers that disk. The radius is 0 for nodes that are not
    SURFACE nodes, or whose ring is not planar to 1e-12 relative.
    """
    n = len(points)
    out = np.zeros((n, 7))
    surf = np.asarray(cons.surface_nodes)
    if len(surf) == 0 or len(faces) == 0:
        return out
    ring = np.sort(np.asarray(cons.surface_cand)[: len(surf)] // 4, axis=1)  # (ns, K) faces, each 4 times
    # the normal from the float64 geometry of the node's first ring face (the constraints' bases may be float32:
    # their rounding alone made every plane that is not axis-aligned fail the 1e-12 planarity test)
    f0 = points[faces[ring[:, 0]]]  # (ns, 4, 3); a triangle [a, b, c, c] gives (c - a) x (c - b)
    normal = np.cross(f0[:, 2] - f0[:, 0], f0[:, 3] - f0[:, 1])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    first = np.ones(ring.shape, bool)
    first[:, 1:] = ring[:, 1:] != ring[:, :-1]  # unique faces per row
    # compact each row to its unique faces (padded with repeats of the first): 4x less work below
    keep = np.argsort(~first, axis=1, kind="stable")[:, : int(first.sum(axis=1).max())]
    ring = np.take_along_axis(ring, keep, axis=1)
    first = np.take_along_axis(first, keep, axis=1)
    ring = np.where(first, ring, ring[:, :1])
    quad = faces[ring]  # (ns, Kf, 4)
    x0 = points[surf]
    dev = np.abs(np.einsum("skcd,sd->skc", points[quad] - x0[:, None, None], normal)).max(axis=(1, 2))
    a = quad
    b = np.roll(quad, -1, axis=2)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    # -1 = a duplicate face or the side (c, c) of a triangle [a, b, c, c]
    key = np.where(first[..., None] & (lo != hi), lo * n + hi, -1).reshape(len(surf), -1)  # (ns, 4Kf)
    order = np.argsort(key, axis=1)
    ks = np.take_along_axis(key, order, axis=1)
    single = np.ones(ks.shape, bool)
    single[:, 1:] &= ks[:, 1:] != ks[:, :-1]
    single[:, :-1] &= ks[:, :-1] != ks[:, 1:]
    single &= ks >= 0
    pa, pb = points[ks // n], points[ks % n]
    d = pb - pa
    rel = x0[:, None] - pa
    t = np.clip(np.einsum("skd,skd->sk", rel, d) / np.maximum(np.einsum("skd,skd->sk", d, d), 1e-300), 0, 1)
    dist = np.linalg.norm(rel - t[..., None] * d, axis=-1)
    radius = np.where(single, dist, np.inf).min(axis=1)
    planar = np.isfinite(radius) & (dev <= 1e-12 * np.maximum(radius, 1e-300))
    out[surf[planar], :3] = x0[planar]
    out[surf[planar], 3:6] = normal[planar]
    out[surf[planar], 6] = radius[planar]
    return out


def coloured_stars(hexes: np.ndarray, cons: Constraints, colour: np.ndarray, faces: np.ndarray,
                   table: CornerTable | None = None) -> ColouredStars:
    """Group the movable nodes (class != CORNER) by `colour`, by class within a colour, with stars and bases.

    `faces` are the boundary faces (``BoundaryInfo.topology.faces``), for the planar-ring shortcut; `table` the
    non-hexahedral corners (`jaxci.mixed.corner_table`; default none). The colouring must not give one colour to
    two nodes of any cell (hexahedron or not).
    """
    cls = np.asarray(cons.node_class)
    n = len(cls)
    colour = np.asarray(colour)
    stars: NodeStars = node_stars(hexes, n)
    colours = np.unique(colour[cls != CORNER]) if (cls != CORNER).any() else np.zeros(1, np.int64)
    parts = []
    for c in (INTERIOR, SURFACE, EDGE):
        cb: ColourBatches = colour_batches(colour, cls == c, n, colours=colours)
        parts.append(cb)
    nodes = np.concatenate([p.nodes for p in parts], axis=1)
    mask = np.concatenate([p.mask for p in parts], axis=1)
    safe = np.minimum(nodes, n - 1)
    B = np.asarray(node_bases(cons))
    dims = free_dims(cons)
    dtype = cons.x_orig.dtype
    if table is None or not table.n_rows:
        xnodes, xwinv = np.zeros(nodes.shape + (0, 4), np.int32), np.zeros(nodes.shape + (0, 9))
        xweight, xmask = np.zeros(nodes.shape + (0,)), np.zeros(nodes.shape + (0,), bool)
    else:
        rows, rmask = node_corner_rows(table, n)
        rows, rmask = rows[safe], rmask[safe] & mask[..., None]
        xnodes, xwinv, xweight, xmask = table.nodes[rows], table.winv[rows], table.weight[rows], rmask
    return ColouredStars(
        nodes=jnp.asarray(nodes.astype(np.int32)),
        mask=jnp.asarray(mask),
        star=jnp.asarray(stars.star[safe].astype(np.int32, copy=False)),
        smask=jnp.asarray(stars.mask[safe] & mask[..., None]),
        basis=jnp.asarray(B[safe], dtype=cons.x_orig.dtype),
        dims=jnp.asarray(np.where(mask, dims[safe], 0).astype(np.int32)),
        plane=jnp.asarray(planar_rings(np.asarray(cons.x_orig, np.float64), faces, cons)[safe] * mask[..., None],
                          dtype=cons.x_orig.dtype),
        xnodes=jnp.asarray(xnodes.astype(np.int32)),
        xwinv=jnp.asarray(xwinv, dtype=dtype),
        xweight=jnp.asarray(xweight, dtype=dtype),
        xmask=jnp.asarray(xmask),
        n_interior=parts[0].nodes.shape[1],
        n_surface=parts[1].nodes.shape[1],
        n_edge=parts[2].nodes.shape[1],
    )


def stars_have_extra(cs: ColouredStars) -> bool:
    """Whether `cs` holds non-hexahedral corners (static: a shape)."""
    return cs.xnodes.shape[-2] > 0


def local_sum(x, cs_i: ColouredStars, E, y):
    """Sum of (kappa/3)^2 over every corner the nodes of one colour move, with the nodes at `y` ``(M, S, 3)``:
    the hexahedral corners (`local_terms` on the gathered stars `E`) plus the non-hexahedral ones; ``(M, S)``,
    ``inf`` where one is inverted (or a pyramid sub-tetrahedron)."""
    total = local_terms(E, cs_i.smask, y)
    if stars_have_extra(cs_i):
        v = jnp.minimum(cs_i.nodes, x.shape[0] - 1)
        total = total + local_extra_terms(x, v, cs_i.xnodes, cs_i.xwinv, cs_i.xweight, cs_i.xmask, y)
    return total


def chunked_local_sum(x, cs_i: ColouredStars, E, y, chunk: int):
    """`local_sum` over S trials in chunks of `chunk` trials."""
    return chunked(lambda t: local_sum(x, cs_i, E, t), y, chunk)


def local_count(cs_i: ColouredStars):
    """Number of objective corners each node of one colour moves, ``(M,)`` (4 per hexahedron around it)."""
    count = 4 * jnp.sum(cs_i.smask, axis=-1)
    if stars_have_extra(cs_i):
        count = count + jnp.sum(cs_i.xmask & (cs_i.xweight > 0), axis=-1)
    return count


def local_scale(x, cs_i: ColouredStars, E):
    """Local length scale of each node of one colour, ``(M,)``: the mean hexahedral edge length at it
    (`local_length`), or for a node of non-hexahedral cells only, the mean distance to their nodes."""
    h = local_length(E, cs_i.smask)
    if stars_have_extra(cs_i):
        v = jnp.minimum(cs_i.nodes, x.shape[0] - 1)
        h = jnp.where(h > 0, h, local_extra_length(x, v, cs_i.xnodes, cs_i.xweight, cs_i.xmask))
    return h


def colour_slice(cs: ColouredStars, i):
    """The arrays of colour `i` (a traced index), as a `ColouredStars` without the colour axis."""
    return jax.tree_util.tree_map(lambda a: a[i], cs)


def project_trials(cons: Constraints, cs_i: ColouredStars, trials):
    """Project trial positions of shape ``(M, S, 3)`` of the nodes of one colour onto their constraints.

    Interior slots are returned unchanged. Surface slots whose ring is planar and whose trials all stay inside
    the disk their ring covers (`planar_rings`) take the orthogonal projection onto the plane, which is then the
    exact nearest point of the patch; otherwise (one `lax.cond` per colour) every boundary slot goes through
    `jaxci.projection.project_nodes` (nearest point of its patch or curve).
    """
    a, b = cs_i.n_interior, cs_i.n_interior + cs_i.n_surface
    M, S, _ = trials.shape
    if b == M and a == M:
        return trials
    n = cons.x_orig.shape[0]
    part = trials[a:]
    idx = jnp.broadcast_to(jnp.minimum(cs_i.nodes[a:], n - 1)[:, None], part.shape[:2]).reshape(-1)

    def full():
        return project_nodes(cons, idx, part.reshape(-1, 3)).reshape(M - a, S, 3)

    if b - a and b == M:  # only surface slots: the planar shortcut may skip the search
        pl = cs_i.plane[a:b, None]  # (m, 1, 7)
        o, nrm, r = pl[..., :3], pl[..., 3:6], pl[..., 6]
        flat = part - nrm * jnp.sum((part - o) * nrm, axis=-1, keepdims=True)
        inside = jnp.sum((flat - o) ** 2, axis=-1) < (0.999 * r) ** 2
        ok = jnp.all(inside | ~cs_i.mask[a:b, None])
        proj = jax.lax.cond(ok, lambda: flat, full)
    elif b - a:
        pl = cs_i.plane[a:b, None]
        o, nrm, r = pl[..., :3], pl[..., 3:6], pl[..., 6]
        flat = part[: b - a] - nrm * jnp.sum((part[: b - a] - o) * nrm, axis=-1, keepdims=True)
        inside = jnp.sum((flat - o) ** 2, axis=-1) < (0.999 * r) ** 2
        ok = jnp.all(inside | ~cs_i.mask[a:b, None])
        edge_idx = jnp.broadcast_to(jnp.minimum(cs_i.nodes[b:], n - 1)[:, None], (M - b, S)).reshape(-1)

        def shortcut():
            pe = project_nodes(cons, edge_idx, part[b - a:].reshape(-1, 3)).reshape(M - b, S, 3)
            return jnp.concatenate([flat, pe], axis=0)

        proj = jax.lax.cond(ok, shortcut, full)
    else:
        proj = full()
    return jnp.concatenate([trials[:a], proj], axis=0)
