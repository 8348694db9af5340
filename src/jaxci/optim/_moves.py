"""What the local optimizers share: per-node move bases, projected trial positions, coloured sweeps.

A movable node v has a basis B_v of shape ``(3, 3)`` whose columns span its free directions: the identity for an
INTERIOR node, the two surface tangents (third column 0) for a SURFACE node, the curve tangent (other columns
0) for an EDGE node. A trial position is ``project(x_v + B_v u)`` for a 3-vector u whose unused entries are
ignored, so every trial lies on the node's constraint. CORNER and fixed nodes never move.

On a mixed mesh the local objective of a node also counts the corners of the wedges, pyramids and tetrahedra
around it (`ColouredStars.xnodes`..., rows of `jaxci.metrics.objective.CornerTable`; a pyramid sub-tetrahedron counts
only as a barrier): `local_sum`, `local_count`, `local_scale`. On a hexahedral mesh those arrays have a zero-size
axis and the functions are the hexahedral ones (a static branch).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry.boundary import CORNER, EDGE, INTERIOR, SURFACE
from ..geometry.projection import Constraints, project_nodes
from ..metrics.objective import CornerTable, local_extra_length, local_extra_terms, node_corner_rows
from ..runtime._lazy import jax, jnp, when_imported
from ._buckets import bucket, device_dtype, pad_constraints, pad_rows, padded_connectivity, to_device
from ._local import NodeStars, chunked, colour_batches, local_length, local_terms, node_stars, star_nodes


def node_rows(cons: Constraints) -> np.ndarray:
    """Each node's row in the constraints' surface list and in their edge list, int64 ``(2, n_nodes + 1)`` (-1: not
    in it; the last column stands for a padding node)."""
    rows = np.full((2, len(np.asarray(cons.node_class)) + 1), -1, np.int64)
    for r, nodes in zip(rows, (cons.surface_nodes, cons.edge_nodes), strict=True):
        r[np.asarray(nodes)] = np.arange(len(nodes))
    return rows


def node_bases(cons: Constraints, nodes: np.ndarray | None = None, rows: np.ndarray | None = None) -> np.ndarray:
    """Per-node move basis in the constraints' dtype (columns = free directions; zeros for fixed ones), numpy
    ``(n_nodes, 3, 3)``, or of `nodes` alone ``(len(nodes), 3, 3)`` (`rows`: `node_rows`, made where not given)."""
    cls = np.asarray(cons.node_class)
    nodes = np.arange(len(cls)) if nodes is None else np.asarray(nodes)
    rows = node_rows(cons) if rows is None else rows
    B = np.zeros((len(nodes), 3, 3))
    B[cls[nodes] == INTERIOR] = np.eye(3)
    srow, erow = rows[0][nodes], rows[1][nodes]
    on_surface, on_edge = srow >= 0, erow >= 0
    if on_surface.any():
        B[on_surface, :, :2] = np.asarray(cons.surface_basis, np.float64)[srow[on_surface]].transpose(0, 2, 1)
    if on_edge.any():
        B[on_edge, :, 0] = np.asarray(cons.edge_tangent, np.float64)[erow[on_edge]]
    return B.astype(np.asarray(cons.x_orig).dtype)


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
    - `star` ``(n_colours, M, K, 8)`` the relabelled node lists of each slot's hexahedra, or their incidences
      ``(n_colours, M, K)`` (`jaxci.optim.device_stars`; relabelled in the sweep: `jaxci.optim._local.star_coords`);
      `smask` ``(n_colours, M, K)``; `basis` ``(n_colours, M, 3, 3)``;
    - `dims` ``(n_colours, M)`` free coordinates per node.
    - `plane` ``(n_colours, M, 7)``: for a SURFACE node whose ring of boundary faces is planar, the original
      position (3), the plane's unit normal (3) and the radius of the disk around the original position that
      its ring of faces covers; radius 0 (never used) otherwise. Inside that disk, the orthogonal projection
      onto the plane IS the nearest point of the patch, so the triangle search can be skipped (exactly).
    - `xnodes` ``(n_colours, M, Kx, 4)``, `xwinv` ``(n_colours, M, Kx, 9)``, `xweight`, `xmask`
      ``(n_colours, M, Kx)``: the non-hexahedral corners around each node (`jaxci.metrics.objective.CornerTable` rows);
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


when_imported("jax", lambda: jax.tree_util.register_dataclass(
    ColouredStars,
    data_fields=["nodes", "mask", "star", "smask", "basis", "dims", "plane", "xnodes", "xwinv", "xweight", "xmask"],
    meta_fields=["n_interior", "n_surface", "n_edge"],
))


#: Surface nodes per block of `planar_rings` (its per-face temporaries: ~5 kB a node; 300 MB at once on a 60^3
#: box's 21,000 surface nodes; 4096 a block were 20 MB of the untangling's peak there, 1024 are 5 MB).
RING_CHUNK = 1024


def _ring_normal(points, faces, ring, xp=np):
    """The unit normal of each node's first ring face (`planar_rings`), from the float64 geometry (the
    constraints' bases may be float32: their rounding alone made every plane that is not axis-aligned fail the
    1e-12 planarity test); `ring` the nodes' ring faces ``(m, K)`` (repeats allowed). `xp`: the array module."""
    f0 = points[faces[xp.min(ring, axis=1)]]  # (m, 4, 3); a triangle [a, b, c, c] gives (c - a) x (c - b)
    normal = xp.cross(f0[:, 2] - f0[:, 0], f0[:, 3] - f0[:, 1])
    length = xp.sqrt(xp.sum(normal * normal, axis=1, keepdims=True))
    return xp.where(length > 0, normal / xp.where(length > 0, length, 1.0), 0.0)


def _side_distance(x0, pa, pb, xp):
    """The distance from the points `x0` ``(..., 3)`` to the segments from `pa` to `pb` (broadcast)."""
    d = pb - pa
    rel = x0 - pa
    t = xp.clip(xp.sum(rel * d, axis=-1) / xp.maximum(xp.sum(d * d, axis=-1), 1e-300), 0, 1)
    rel = rel - t[..., None] * d
    return xp.sqrt(xp.sum(rel * rel, axis=-1))


def _ring_radius(points, faces, ring, surf, normal, n: int, xp=np):
    """``(radius, deviation)`` of the planar rings of the surface nodes `surf` ``(m,)`` with ring faces `ring`
    ``(m, K)`` (repeats allowed) and first-face normals `normal` ``(m, 3)`` (`planar_rings`): the distance to the
    outer boundary of the ring's faces (the sides used by one ring face), and the largest distance of a ring node
    from the plane of the first face. `xp`: numpy (rows compacted to their distinct faces and the outer sides
    picked out: 2x faster) or `jax.numpy` (fixed shapes: every side measured, the others masked; with x64)."""
    ring = xp.sort(ring, axis=1)  # (m, K) faces, a face possibly several times
    first = xp.concatenate([xp.ones((ring.shape[0], 1), bool), ring[:, 1:] != ring[:, :-1]], axis=1)
    if xp is np:  # compact each row to its unique faces (padded with repeats of the first): 4x less work below
        keep = np.argsort(~first, axis=1, kind="stable")[:, : int(first.sum(axis=1).max())]
        ring = np.take_along_axis(ring, keep, axis=1)
        first = np.take_along_axis(first, keep, axis=1)
        ring = np.where(first, ring, ring[:, :1])
    quad = faces[ring]  # (m, Kf, 4)
    x0 = points[surf]
    rel = points[quad] - x0[:, None, None]  # (m, Kf, 4, 3)
    dev = xp.max(xp.abs(xp.einsum("skcd,sd->skc", rel, normal)), axis=(1, 2))
    del rel
    b = xp.roll(quad, -1, axis=2)
    lo, hi = xp.minimum(quad, b), xp.maximum(quad, b)
    # -1 = a duplicate face or the side (c, c) of a triangle [a, b, c, c]
    key = xp.where(first[..., None] & (lo != hi), lo.astype(xp.int64) * n + hi, -1).reshape(ring.shape[0], -1)
    ks = xp.sort(key, axis=1)
    edge = xp.full((ks.shape[0], 1), -2, ks.dtype)
    single = ((ks != xp.concatenate([ks[:, 1:], edge], axis=1)) & (ks != xp.concatenate([edge, ks[:, :-1]], axis=1))
              & (ks >= 0))
    if xp is not np:
        ia, ib = (xp.where(single, k, 0) for k in (ks // n, ks % n))
        dist = _side_distance(x0[:, None], points[ia], points[ib], xp)
        return xp.min(xp.where(single, dist, xp.inf), axis=1), dev
    row, col = np.nonzero(single)  # the outer sides alone (about a quarter of them), row by row
    ia, ib = np.divmod(ks[row, col], n)
    dist = _side_distance(x0[row], points[ia], points[ib], np)
    radius = np.full(len(surf), np.inf)
    if len(row):
        start = np.flatnonzero(np.concatenate([[True], row[1:] != row[:-1]]))
        radius[row[start]] = np.minimum.reduceat(dist, start)
    return radius, dev


def planar_rings(points: np.ndarray, faces: np.ndarray, cons: Constraints) -> np.ndarray:
    """Per node, ``(origin (3), normal (3), radius)`` of its planar ring of boundary faces, shape ``(n, 7)``.

    The ring is the set of candidate faces the projection searches (the 2-ring of the node on its own patch,
    `Constraints.surface_cand`); the radius is the distance from the node to the outer boundary of their union
    (edges used by one face of the ring), so the ring covers that disk. The radius is 0 for nodes that are not
    SURFACE nodes, or whose ring is not planar to 1e-12 relative.
    """
    out = np.zeros((len(points), 7))
    out[np.asarray(cons.surface_nodes)] = surface_node_rings(points, faces, cons)
    return out


def surface_node_rings(points: np.ndarray, faces: np.ndarray, cons: Constraints) -> np.ndarray:
    """`planar_rings`' rows of the SURFACE nodes alone, in ``cons.surface_nodes`` order, shape ``(ns, 7)``: their
    rings are their candidate triangles' faces (`Constraints.surface_cand` divided by 4)."""
    surf = np.asarray(cons.surface_nodes)
    return surface_rings(points, faces, surf, np.asarray(cons.surface_cand)[: len(surf)] // 4)


def surface_rings(points, faces, surf, ring, xp=np):
    """`planar_rings` of the surface nodes `surf` ``(m,)`` alone, ``(m, 7)``, from their ring faces `ring`
    ``(m, K)`` (indices into `faces`, repeats allowed: the candidate triangles of `Constraints.surface_cand`
    divided by 4, or each face once); `points` float64, indexed by the nodes of `faces` and `surf`. `xp`: numpy
    (in blocks of `RING_CHUNK` nodes), or `jax.numpy` (traceable, with x64: `jaxci.optim.device_stars`)."""
    if len(surf) == 0 or len(faces) == 0:
        return xp.zeros((len(surf), 7))
    n = len(points)
    normal = _ring_normal(points, faces, ring, xp)
    if xp is np:
        radius, dev = np.empty(len(surf)), np.empty(len(surf))
        for lo in range(0, len(surf), RING_CHUNK):  # in blocks: the per-face arrays are ~100 entries a node
            sl = slice(lo, lo + RING_CHUNK)
            radius[sl], dev[sl] = _ring_radius(points, faces, ring[sl], surf[sl], normal[sl], n)
    else:
        radius, dev = _ring_radius(points, faces, ring, surf, normal, n, xp)
    planar = xp.isfinite(radius) & (dev <= 1e-12 * xp.maximum(radius, 1e-300))
    out = xp.concatenate([points[surf], normal, radius[:, None]], axis=1)
    return xp.where(planar[:, None], out, 0.0)


def coloured_stars(hexes: np.ndarray, cons: Constraints, colour: np.ndarray, faces: np.ndarray,
                   table: CornerTable | None = None, place: bool = True) -> ColouredStars:
    """Group the movable nodes (class != CORNER) by `colour`, by class within a colour, with stars and bases.

    `faces` are the boundary faces (``BoundaryInfo.topology.faces``), for the planar-ring shortcut; `table` the
    non-hexahedral corners (`jaxci.metrics.objective.corner_table`; default none). The colouring must not give one
    colour to two nodes of any cell (hexahedron or not). Device arrays; with `place` False the device's layout and
    dtypes in numpy (`jaxci.optim._buckets.device_dtype`), for stars padded (`pad_stars`) before they go to the
    device. (The host sweep makes its colours of its own, one at a time: `jaxci.optim.host_local`.)
    """
    cls = np.asarray(cons.node_class)
    n = len(cls)
    colour = np.asarray(colour)
    stars: NodeStars = node_stars(hexes, n, incidences=True)
    colours = np.unique(colour[cls != CORNER]) if (cls != CORNER).any() else np.zeros(1, np.int64)
    parts = [colour_batches(colour, cls == c, n, colours) for c in (INTERIOR, SURFACE, EDGE)]
    nodes = np.concatenate([p.nodes for p in parts], axis=1)
    mask = np.concatenate([p.mask for p in parts], axis=1)
    safe = np.minimum(nodes, n - 1)
    star, nmask = stars.star[safe], stars.mask[safe]
    # the node lists of the slots' stars alone (padding: the node itself), int32 as they go
    star = star_nodes(np.asarray(hexes).astype(np.int32, copy=False), star, nmask, safe)
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
    # to_device: no compilation per shape (jnp.asarray of a numpy array compiles a small program for each)
    put = to_device if place else device_dtype
    # one table at a time, each per-node table dropped once gathered into the slots: at 216,000 hexahedra the
    # bases and planes are 16 and 13 MB a copy, and all of them at once were the untangling's peak
    basis = put(B[safe], dtype)
    del B
    plane = planar_rings(np.asarray(cons.x_orig, np.float64), faces, cons)[safe]
    plane *= mask[..., None]
    plane = put(plane, dtype)
    return ColouredStars(
        nodes=put(nodes, np.int32),
        mask=put(mask),
        star=put(star, np.int32),
        smask=put(nmask & mask[..., None]),
        basis=basis,
        dims=put(np.where(mask, dims[safe], 0), np.int32),
        plane=plane,
        xnodes=put(xnodes, np.int32),
        xwinv=put(xwinv, dtype),
        xweight=put(xweight, dtype),
        xmask=put(xmask),
        n_interior=parts[0].nodes.shape[1],
        n_surface=parts[1].nodes.shape[1],
        n_edge=parts[2].nodes.shape[1],
    )


def slot_sizes(cs: ColouredStars) -> tuple[int, int, int]:
    """The interior, surface and edge slots per colour of `cs` padded to its size class (`pad_slots`).

    A block holds the most nodes of its class in one colour, which depends on how evenly the colouring
    spread them (measured: 76 and 100 interior nodes per colour on 9x9x10 and 10x10x9 boxes, 576 and 648
    interior nodes in 8 colours): rounded up alone, two meshes of one size class got different blocks and
    compiled the sweep twice. So a block is `_SLOT_SLACK` (2 or 4) times the mean per colour of the size class
    of the class's node count (``2 bucket(total) / bucket(n_colours)``), rounded up to the ladder, or the most
    nodes in one colour if that is more (then rounded up to the ladder alone). Padded slots cost sweep time
    (up to about twice that of the interior slots) and device memory, not results: a class of `_SLACK_UNTIL`
    nodes or more (the meshes an accelerator takes) has no slack (1), its padded stars half the size.
    """
    sizes = (cs.n_interior, cs.n_surface, cs.n_edge)
    mask = np.asarray(cs.mask)
    bounds = np.cumsum((0,) + sizes)
    return padded_blocks(sizes, [int(mask[:, bounds[j] : bounds[j + 1]].sum()) for j in range(3)], mask.shape[0])


def padded_blocks(sizes, totals, n_colours: int) -> tuple[int, int, int]:
    """`slot_sizes` from the most interior, surface and edge nodes in one colour (`sizes`), their totals
    (`totals`) and the colour count."""
    c_pad = bucket(n_colours)
    out = []
    for j, m in enumerate(sizes):
        slack = 1 if without_slack(totals[j]) else _SLOT_SLACK[j]
        out.append(bucket(max(m, -(-slack * bucket(totals[j]) // c_pad))) if m else 0)
    return tuple(out)


def without_slack(total: int) -> bool:
    """Whether a class of `total` nodes gets its slots without slack (`slot_sizes`: `_SLACK_UNTIL` nodes or
    more): sized to its largest colour, not to a size class shared with other meshes."""
    return total >= _SLACK_UNTIL


#: `slot_sizes`: interior, surface, edge blocks hold this many times the mean per colour of their size class
#: (edge nodes colour least evenly: 48 of the 108 edge nodes of a 10^3 box in one of its 8 colours).
_SLOT_SLACK = (2, 2, 4)

#: `slot_sizes`: from this many nodes of a class on, no slack. At 10^6 hexahedra the slack doubled the padded
#: stars, the largest arrays of the presmoothing's device memory (`scripts/bench_device_memory.py`), and the
#: sweep's work on padded slots; a compiled sweep shared with a mesh of another colouring saves less than that.
_SLACK_UNTIL = 1 << 19


def pad_slots(v: np.ndarray, cs: ColouredStars, fill, width: int | None = None, width_fill=None) -> np.ndarray:
    """An array laid out like `cs.nodes` ``(n_colours, M, ...)`` padded to the size class of `cs`: the
    interior, surface and edge slot blocks of every colour (`slot_sizes`) and the colours rounded up to the
    ladder (`jaxci.optim._buckets.bucket`), new entries `fill`. `width`: the third axis of the real slots is
    also padded to `width`: its new entries copies of entry 0 (`width_fill` None) or `width_fill` (in the same
    single copy)."""
    v = np.asarray(v)
    sizes, padded = (cs.n_interior, cs.n_surface, cs.n_edge), slot_sizes(cs)
    C = v.shape[0]
    tail = v.shape[2:] if width is None else (width,) + v.shape[3:]
    out = np.empty((bucket(C), sum(padded)) + tail, v.dtype)  # one copy: no concatenations
    src = dst = 0
    for m, mp in zip(sizes, padded, strict=True):
        _copy_width(out[:C, dst : dst + m], v[:, src : src + m], width_fill)
        out[:C, dst + m : dst + mp] = fill
        src, dst = src + m, dst + mp
    out[C:] = fill
    return out


def _copy_width(out: np.ndarray, v: np.ndarray, fill) -> None:
    """Copy `v` ``(C, M, K, ...)`` into `out` ``(C, M, width, ...)``, the entries past K copies of entry 0 of
    the third axis (`fill` None) or `fill`; `out` of `v`'s shape: a plain copy."""
    if out.ndim < 3 or out.shape[2] == v.shape[2]:
        out[...] = v
        return
    k = v.shape[2]
    out[:, :, :k] = v
    out[:, :, k:] = v[:, :, :1] if fill is None else fill


def no_extra_slots(shape: tuple, dtype) -> dict:
    """The empty per-slot arrays of the cells other than hexahedra (`ColouredStars.xnodes`, `xwinv`, `xweight`,
    `xmask`) for slots of `shape` ``(rows, m)``, put on the device from the host (no bytes). Made inside a jitted
    program instead, XLA keeps them as constants that grow with the slots (reading the sweep data's cached
    executable took 1 s at 10^6 hexahedra)."""
    return {"xnodes": to_device(np.zeros((*shape, 0, 4), np.int32)),
            "xwinv": to_device(np.zeros((*shape, 0, 9), dtype)),
            "xweight": to_device(np.zeros((*shape, 0), dtype)),
            "xmask": to_device(np.zeros((*shape, 0), bool))}


def pad_stars(cs: ColouredStars, n_pad: int) -> ColouredStars:
    """`cs` padded to its size class (`jaxci.optim._buckets`) for node coordinates padded to `n_pad` rows:
    colours, the interior / surface / edge slots of each colour (`pad_slots`) and the star width rounded up to
    the ladder. Hexahedral meshes only (no non-hexahedral corners).

    Padded slots hold node `n_pad` (out of range: never moved, dropped on write) with mask False and star rows
    of node 0 with `smask` False; padded star columns repeat the slot's first element with `smask` False;
    padded colours have no real slot (`jaxci.optim.laplace` also bounds its loop by the real colour count).
    """
    if stars_have_extra(cs):
        raise ValueError("pad_stars: the stars of a mixed mesh are not padded")
    k_pad = bucket(cs.smask.shape[2], 4)
    mask = np.asarray(cs.mask)
    fdt = np.asarray(cs.basis).dtype
    nodes = pad_slots(np.where(mask, np.asarray(cs.nodes), n_pad), cs, n_pad)
    C, M = nodes.shape
    sizes = slot_sizes(cs)
    return ColouredStars(
        nodes=to_device(nodes, np.int32),
        mask=to_device(pad_slots(mask, cs, False)),
        star=to_device(pad_slots(cs.star, cs, 0, k_pad), np.int32),
        smask=to_device(pad_slots(cs.smask, cs, False, k_pad, False)),
        basis=to_device(pad_slots(cs.basis, cs, 0.0), fdt),
        dims=to_device(pad_slots(cs.dims, cs, 0), np.int32),
        plane=to_device(pad_slots(cs.plane, cs, 0.0), fdt),
        **no_extra_slots((C, M), fdt),
        n_interior=sizes[0],
        n_surface=sizes[1],
        n_edge=sizes[2],
    )


def padded_sweeps(points, conn, cs: ColouredStars, cons: Constraints, multiple: int = 1):
    """The arguments of a compiled colour-sweep loop (the Laplacians', local CI's) padded to their size class
    (`jaxci.optim._buckets`): node coordinates (padding nodes at the origin, CORNER nodes of the padded
    `Constraints`, referenced by no real element), elements (repeats of element 0 with weight 0; a multiple of
    `multiple`, the device count of a sharded run), colours and slots (`pad_stars`). Hexahedral meshes only.

    **Returns:** ``(x, conn, cs, cons, weight, n_colours)``, device arrays; `n_colours` the real colour count
    (the loops skip the padded ones)."""
    x = np.asarray(points)
    n_pad = bucket(x.shape[0] + 1)
    hexes = np.asarray(conn).T
    c, w = padded_connectivity(hexes, bucket(len(hexes), multiple=multiple))
    return (to_device(pad_rows(x, n_pad, 0.0)), to_device(c, hexes.dtype), pad_stars(cs, n_pad),
            pad_constraints(cons, n_pad), to_device(w, x.dtype), to_device(np.int32(cs.nodes.shape[0])))


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


def onto_plane(xp, y, plane):
    """``(foot, inside)``: the orthogonal projection of points `y` ``(..., 3)`` onto their planes `plane`
    ``(..., 7)`` (origin, unit normal, radius: `planar_rings`), and whether it falls inside 0.999 of the disk the
    node's ring of faces covers, where it is the exact nearest point of the patch (no search needed). `xp`:
    `jax.numpy` or `numpy`."""
    o, nrm, r = plane[..., :3], plane[..., 3:6], plane[..., 6]
    foot = y - nrm * xp.sum((y - o) * nrm, axis=-1, keepdims=True)
    return foot, xp.sum((foot - o) ** 2, axis=-1) < (0.999 * r) ** 2


def project_trials(cons: Constraints, cs_i: ColouredStars, trials):
    """Project trial positions of shape ``(M, S, 3)`` of the nodes of one colour onto their constraints.

    Interior slots are returned unchanged. Surface slots whose ring is planar and whose trials all stay inside
    the disk their ring covers (`planar_rings`) take the orthogonal projection onto the plane, which is then the
    exact nearest point of the patch; otherwise (one `lax.cond` per colour) every boundary slot goes through
    `jaxci.geometry.projection.project_nodes` (nearest point of its patch or curve).
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
        flat, inside = onto_plane(jnp, part, cs_i.plane[a:b, None])
        ok = jnp.all(inside | ~cs_i.mask[a:b, None])
        proj = jax.lax.cond(ok, lambda: flat, full)
    elif b - a:
        flat, inside = onto_plane(jnp, part[: b - a], cs_i.plane[a:b, None])
        ok = jnp.all(inside | ~cs_i.mask[a:b, None])
        edge_idx = jnp.broadcast_to(jnp.minimum(cs_i.nodes[b:], n - 1)[:, None], (M - b, S)).reshape(-1)

        def shortcut():
            pe = project_nodes(cons, edge_idx, part[b - a:].reshape(-1, 3)).reshape(M - b, S, 3)
            return jnp.concatenate([flat, pe], axis=0)

        proj = jax.lax.cond(ok, shortcut, full)
    else:
        proj = full()
    return jnp.concatenate([trials[:a], proj], axis=0)
