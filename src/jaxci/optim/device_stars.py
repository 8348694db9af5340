"""The colour sweeps' data built on the device: what `jaxci.optim.laplace`'s compiled sweeps take, padded to
their size class, from the device's mesh (the JAX engine; hexahedral meshes on one device).

The host builds it in numpy (`jaxci.optim._moves.coloured_stars`, `pad_stars`,
`jaxci.optim.laplace.coloured_neighbours`): per node slot its star as 8 relabelled copies of its hexahedra
(64 indices a slot, 0.6 GB uploaded at 10^6 hexahedra). Here the stars are INCIDENCES (``8 e + s``: the slot's
node is local corner ``s`` of hexahedron ``e``, 8 indices a slot), relabelled inside the sweep from the
connectivity and a constant table (`jaxci.optim._local.star_coords`; ``lists=True`` relabels them once here
instead), and everything is built by programs on the device from:

- the points, the transposed connectivity ``(8, N)`` and the `Constraints` (device arrays);
- the node incidences and the colouring (`jaxci.geometry.device_colouring`: built here unless given);
- the boundary faces (host, O(boundary)): the planar rings of the surface nodes (`surface_planes`) are found on
  the host from the boundary nodes' coordinates alone and go up as one ``(n_surface, 7)`` table.

What comes down: the largest valence, the colour count (`jaxci.geometry.device_colouring`), then ONE small
array of the per-colour, per-class node counts and the largest number of edge neighbours (the static sizes of
the padded slots, `jaxci.optim._moves.padded_blocks`); and the boundary's O(boundary) arrays of the planes.

Given the same colouring, the slots hold the nodes, stars (as incidences), bases, planes and edge neighbours of
`coloured_stars` + `pad_stars` + `coloured_neighbours` (tests: the same sweeps, bit for bit): the sweeps'
result does not depend on the order of the slots within a colour, but they are kept in node order anyway.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cells import CORNER_NEIGHBOURS
from ..geometry.boundary import CORNER, EDGE, INTERIOR, SURFACE
from ..geometry.device_colouring import (
    PALETTE,
    WORD,
    Incidences,
    incidence_table,
    speculative_colouring,
    valence,
)
from ..geometry.projection import Constraints
from ..runtime._lazy import enable_x64, jax, jit, jnp
from ..runtime.transfer import program, to_device, to_host
from ._buckets import bucket, pad_connectivity, pad_rows, padded_constraints
from ._local import relabel
from ._moves import ColouredStars, no_extra_slots, padded_blocks, surface_rings, without_slack

#: Nodes per block of the edge-neighbour deduplication (`_edge_neighbours`: ``(block, 3K, 3K)`` comparisons).
NEIGHBOUR_BLOCK = 1 << 14

#: Nodes per block of the in-block ranks of `_group_positions`.
RANK_BLOCK = 32


@dataclasses.dataclass(frozen=True)
class SweepData:
    """The arguments of `jaxci.optim.laplace`'s compiled sweeps, padded to their size class, on the device.

    - `x` ``(n_pad, 3)`` points (padding at the origin), `conn` ``(8, N_pad)`` int32 (padding repeats element
      0), `weight` ``(N_pad,)`` (1 real, 0 padding), `cons` the padded `Constraints`;
    - `cs` the `ColouredStars` (``star``: incidences ``(C, M, K)``, or with ``lists`` the node lists
      ``(C, M, K, 8)``), `nbr`, `nmask` ``(C, M, Kn)`` the slots' edge neighbours;
    - `n_colours` the real row count (a device scalar: the loops skip the padded rows; a row is a colour, or part
      of one: `slot_layout`);
    - `n_nodes` the real node count (host int), `colours` the colour count (host int);
    - for `jaxci.optim.device_parametrisation`: `inc` the mesh's `Incidences` (unpadded), `view` the
      `BoundaryView` of the points the planes were found on and `planes` the planar rings of the surface nodes
      ``(n_surface, 7)`` (host, float64: `surface_planes`).
    """

    x: jax.Array
    conn: jax.Array
    cs: ColouredStars
    nbr: jax.Array
    nmask: jax.Array
    cons: Constraints
    weight: jax.Array
    n_colours: jax.Array
    n_nodes: int
    colours: int
    inc: Incidences
    view: BoundaryView
    planes: np.ndarray


def sweep_data(points, conn, cons: Constraints, faces: np.ndarray, *, colour=None, inc: Incidences | None = None,
               lists: bool = False, split: bool = True, plane_points=None, view: BoundaryView | None = None,
               planes: np.ndarray | None = None) -> SweepData:
    """Build the padded sweep data of a hexahedral mesh on the device.

    **Arguments:**

    - `points` ``(n, 3)`` (device, the run's dtype); `conn` ``(8, N)`` (device, int32 or int64); `cons` its
      `Constraints` (device arrays, unpadded); `faces` ``(n_faces, 4)`` the boundary faces (host,
      ``BoundaryInfo.topology.faces``).
    - `colour`: ``(colour, n_colours)``, a device colouring (no two nodes of one colour in a hexahedron) and
      its colour count; default the device's (`jaxci.geometry.device_colouring.colour_nodes_device`'s rounds).
    - `inc`: the mesh's `Incidences` if at hand (default: built).
    - `lists`: the stars as relabelled node lists ``(C, M, K, 8)`` (8x the memory; the sweep gathers no
      relabelling) instead of incidences.
    - `split`: a colour over several rows where one row a colour pads a tenth or more of the slots
      (`slot_layout`; False: one row a colour, `coloured_stars`' layout).
    - `plane_points`: the coordinates the planar rings are tested on (device ``(n, 3)``; default
      ``cons.x_orig``, as `coloured_stars` does).
    - `view`, `planes`: the `boundary_view` of those coordinates and its `surface_planes`, if at hand (default:
      found here).

    **Returns:** a `SweepData`.

    Programs: the valence (its largest value comes down) unless `inc` is given; the incidences, the colouring,
    the edge neighbours and the slot counts (one small array comes down: the static sizes); the boundary view
    (`boundary_view`: O(boundary) each way); the padded arrays.
    """
    n = int(points.shape[0])
    if inc is None:
        v, width = valence(conn, n)
        table = None
    else:
        v, width, table = inc.valence, inc.width, inc.table
    given = colour is not None
    n_words = 1
    while True:
        bound = int(colour[1]) if given else WORD * n_words
        table_, col, nbr_table, degree, counts, stats = _prepare(
            conn, v, table, cons.node_class, colour[0] if given else None, width=width, n_colours=bound,
            n_words=n_words)
        counts, stats = to_host((counts, stats))  # the one small array of static sizes
        n_col, kn = (int(a) for a in stats)
        if n_col <= bound:
            break
        n_words *= 2  # a node found every colour of the words taken
    inc = Incidences(table=table_, valence=v)
    counts = np.asarray(counts, np.int64)[:n_col]
    blocks, row_start, rows = slot_layout(counts[counts.sum(axis=1) > 0], split)
    if view is None:
        view = boundary_view(cons.x_orig if plane_points is None else plane_points, faces, cons)
    planes = surface_planes(view) if planes is None else planes
    x, c, cs, nbr, nmask, cons_p, w = _build(
        points, conn, inc, col, cons, to_device(planes, cons.x_orig.dtype), nbr_table, degree,
        to_device(row_start, np.int32), rows=bucket(rows), blocks=blocks, width=bucket(width, 4),
        nbr_width=bucket(max(kn, 1), 4), n_pad=bucket(n + 1),
        n_elements=bucket(int(conn.shape[1])), lists=bool(lists))
    cs = dataclasses.replace(cs, **no_extra_slots(cs.nodes.shape, cons.x_orig.dtype))
    return SweepData(x=x, conn=c, cs=cs, nbr=nbr, nmask=nmask, cons=cons_p, weight=w,
                     n_colours=to_device(np.int32(rows)), n_nodes=n, colours=len(row_start), inc=inc, view=view,
                     planes=planes)


def slot_layout(counts: np.ndarray, split: bool = True) -> tuple[tuple[int, int, int], np.ndarray, int]:
    """The slots of the colours of `counts` ``(C, 3)`` (movable interior, surface, edge nodes of each colour
    holding some): ``(blocks, row_start, rows)``, the padded interior / surface / edge blocks of a row
    (`jaxci.optim._moves.padded_blocks`), the first row of each colour and the row count.

    One row a colour (`coloured_stars`' layout), or with `split` on a large mesh (a class of nodes without slot
    slack: `jaxci.optim._moves.without_slack`), where blocks sized for 1/2, 1/3 or 1/4 of the largest colour
    save a tenth or more of the slots, each colour over the fewest rows of such blocks (the
    largest blocks within 5% of the fewest slots: fewer rows, fewer sequential steps): a row is a part of one
    colour, so its nodes still share no hexahedron. Colours of unequal sizes pad their rows up to the largest
    (the device's colouring at 10^6 hexahedra: 16 colours of 59,000 interior nodes and 4 of 1 to 20,000; 1.44 M
    slots in one row a colour, 1.29 M in 36 rows of halves).
    """
    counts = np.asarray(counts, np.int64).reshape(-1, 3)
    if not len(counts):
        return padded_blocks((0, 0, 0), [0, 0, 0], 1), np.zeros(1, np.int64), 1
    totals = [int(a) for a in counts.sum(axis=0)]
    options = []
    # small meshes keep one row a colour: their slots' slack lets meshes of a size class share the sweep loop
    for d in (1, 2, 3, 4) if split and without_slack(max(totals)) else (1,):
        sizes = tuple(-(-int(m) // d) for m in counts.max(axis=0))
        blocks = padded_blocks(sizes, totals, d * len(counts))
        per = np.ones(len(counts), np.int64)
        for j, b in enumerate(blocks):
            if b:
                per = np.maximum(per, -(-counts[:, j] // b))
        options.append((int(per.sum()) * sum(blocks), d, blocks, per))
    least = min(o[0] for o in options)
    # the fewest rows (sequential steps) within 5% of the least padding, if that saves a tenth of one a colour's
    _, _, blocks, per = next(o for o in options if o[0] <= 1.05 * least) if least <= 0.9 * options[0][0] \
        else options[0]
    return blocks, np.cumsum(per) - per, int(per.sum())


@program
@jit(static_argnames=("width", "n_colours", "n_words"))
def _prepare(conn, node_valence, table, node_class, colour, *, width: int, n_colours: int, n_words: int):
    """The incidence table (`table` if given), the colours (`colour` if given, else the device's), the edge
    neighbours ``(n, 3K)`` and degrees, and the static sizes: the movable nodes per colour and class
    ``(n_colours, 3)`` (interior, surface, edge) and ``[colour count, most edge neighbours of a node]``."""
    inc = Incidences(table=incidence_table(conn, node_valence, width) if table is None else table,
                     valence=node_valence)
    if colour is None:
        colour, count, _ = speculative_colouring(conn, inc, n_words, PALETTE)
    else:
        count = jnp.max(colour, initial=-1) + 1
    nbr, degree = _edge_neighbours(conn, inc)
    movable = (node_class != CORNER).astype(jnp.int32)
    counts = jnp.zeros((n_colours, 3), jnp.int32).at[colour, jnp.clip(node_class, 0, 2)].add(movable, mode="drop")
    return inc.table, colour, nbr, degree, counts, jnp.stack([count, jnp.max(degree, initial=0)]).astype(jnp.int32)


def _edge_neighbours(conn, inc: Incidences):
    """Every node's edge neighbours: ``(table, degree)``, the distinct nodes joined to it by a hexahedron edge
    in increasing order in the first `degree` entries of its row ``(n, 3K)`` (the rest: the node itself), as
    `jaxci.optim._local.edge_neighbours` lists them; from the 3 edge ends at each of its incidences, without a
    sort (comparisons within the row, in blocks of nodes)."""
    n, k = inc.table.shape
    width = 3 * k
    nb = jnp.asarray(CORNER_NEIGHBOURS, jnp.int32)[inc.table & 7]  # (n, K, 3)
    big = jnp.iinfo(jnp.int32).max
    cand = conn.reshape(-1).astype(jnp.int32)[nb * conn.shape[1] + (inc.table >> 3)[..., None]]
    cand = jnp.where(inc.mask()[..., None], cand, big).reshape(n, width)
    blocks = -(-n // NEIGHBOUR_BLOCK)
    pad = blocks * NEIGHBOUR_BLOCK - n
    cand = jnp.concatenate([cand, jnp.full((pad, width), big, jnp.int32)]).reshape(blocks, -1, width)
    own = jnp.arange(blocks * NEIGHBOUR_BLOCK, dtype=jnp.int32).reshape(blocks, -1)
    earlier = jnp.tril(jnp.ones((width, width), bool), -1)  # [j, i]: i before j

    def block(args):
        c, v = args
        first = (c < big) & ~jnp.any((c[:, :, None] == c[:, None, :]) & earlier, axis=2)
        rank = jnp.sum((c[:, None, :] < c[:, :, None]) & first[:, None, :], axis=2)  # distinct ones below
        out = jnp.broadcast_to(v[:, None], c.shape)
        rows = jnp.broadcast_to(jnp.arange(c.shape[0])[:, None], c.shape)
        out = out.at[rows, jnp.where(first, rank, width)].set(c, mode="drop")
        return out, jnp.sum(first, axis=1, dtype=jnp.int32)

    table, degree = jax.lax.map(block, (cand, own))
    return table.reshape(-1, width)[:n], degree.reshape(-1)[:n]


def _group_positions(group, valid, n_groups: int):
    """Each valid entry's position among the valid entries of its group (`group` ``(n,)`` int32 in
    ``[0, n_groups)``), in index order: counts per block of `RANK_BLOCK` entries (a scatter-add), their
    exclusive sums over the blocks, plus the rank within the block (comparisons). No sort."""
    n = group.shape[0]
    b = RANK_BLOCK
    blocks = -(-n // b)
    g = jnp.concatenate([jnp.where(valid, group, -1), jnp.full(blocks * b - n, -1, jnp.int32)]).reshape(blocks, b)
    before = jnp.tril(jnp.ones((b, b), bool), -1)  # [i, j]: j before i
    inner = jnp.sum((g[:, :, None] == g[:, None, :]) & before, axis=2)
    hist = jnp.zeros((blocks, n_groups), jnp.int32).at[jnp.arange(blocks)[:, None], g].add(
        (g >= 0).astype(jnp.int32), mode="drop")
    offset = jnp.cumsum(hist, axis=0) - hist  # (blocks, G) before each block
    pos = jnp.take_along_axis(offset, jnp.maximum(g, 0), axis=1) + inner
    return pos.reshape(-1)[:n]


@program
@jit(static_argnames=("rows", "blocks", "width", "nbr_width", "n_pad", "n_elements", "lists"))
def _build(points, conn, inc: Incidences, colour, cons: Constraints, planes, nbr_table, degree, row_start, *,
           rows: int, blocks: tuple, width: int, nbr_width: int, n_pad: int, n_elements: int, lists: bool):
    """The padded `SweepData` arrays: ``(x, conn, cs, nbr, nmask, cons, weight)``; the colours holding movable
    nodes, in increasing order, from rows `row_start` (`slot_layout`)."""
    n = points.shape[0]
    conn = conn.astype(jnp.int32)
    cls = cons.node_class
    movable = cls != CORNER
    kind = jnp.clip(cls, 0, 2)
    # each node's place among the movable nodes of its colour and class, in node order (colour values are below n)
    has = jnp.zeros(n + 1, bool).at[jnp.where(movable, colour, n)].set(True)[:n]
    rank = jnp.where(movable, (jnp.cumsum(has, dtype=jnp.int32) - 1)[colour], 0)
    pos = _group_positions(rank * 3 + kind, movable, row_start.shape[0] * 3)
    size = jnp.asarray([max(b, 1) for b in blocks], jnp.int32)[kind]
    row = row_start[rank] + pos // size
    slot = jnp.asarray(np.cumsum((0,) + tuple(blocks[:-1])), jnp.int32)[kind] + pos % size
    m = sum(blocks)
    nodes = jnp.full((rows, m), n_pad, jnp.int32).at[jnp.where(movable, row, rows), slot].set(
        jnp.arange(n, dtype=jnp.int32), mode="drop")
    mask = nodes < n_pad
    safe = jnp.minimum(nodes, n - 1)
    k = jnp.arange(width, dtype=jnp.int32)
    star = inc.table[safe[..., None], jnp.minimum(k, inc.width - 1)]  # (C, M, width)
    smask = (k < inc.valence[safe][..., None]) & mask[..., None]
    star = jnp.where(smask, star, star[..., :1])
    if lists:
        star = relabel(conn, star)
    c_safe, r_safe = cls[safe], cons.row[safe]
    dtype = cons.x_orig.dtype
    cs = ColouredStars(
        nodes=nodes,
        mask=mask,
        star=star,
        smask=smask,
        basis=_bases(cons, c_safe, r_safe, mask),
        dims=jnp.where(mask, jnp.asarray([3, 2, 1, 0], jnp.int32)[c_safe], 0),
        plane=jnp.where(((c_safe == SURFACE) & mask)[..., None], planes[jnp.clip(r_safe, 0, planes.shape[0] - 1)],
                        0.0).astype(dtype),
        xnodes=None,  # no other cells: their empty arrays are put there by `sweep_data` (`no_extra_slots`)
        xwinv=None,
        xweight=None,
        xmask=None,
        n_interior=blocks[0],
        n_surface=blocks[1],
        n_edge=blocks[2],
    )
    kn = jnp.arange(nbr_width, dtype=jnp.int32)
    nbr = nbr_table[safe[..., None], jnp.minimum(kn, nbr_table.shape[1] - 1)]
    nmask = (kn < degree[safe][..., None]) & mask[..., None]
    nbr = jnp.where(mask[..., None], nbr, 0)
    c, w = pad_connectivity(conn, n_elements, points.dtype)
    return (pad_rows(points, n_pad, 0.0), c, cs, nbr, nmask, padded_constraints(cons, n_pad), w)


def _bases(cons: Constraints, cls, row, mask):
    """The move bases ``(..., 3, 3)`` of nodes of classes `cls` at rows `row` of their class's tables
    (`jaxci.optim._moves.node_bases`, gathered for the slots), 0 where `mask` is False."""
    dtype = cons.x_orig.dtype
    ns, ne = cons.surface_basis.shape[0], cons.edge_tangent.shape[0]
    zero = jnp.zeros(cls.shape + (3,), dtype)
    sb = cons.surface_basis[jnp.clip(row, 0, max(ns - 1, 0))].astype(dtype) if ns else jnp.zeros(cls.shape + (2, 3),
                                                                                                    dtype)
    et = cons.edge_tangent[jnp.clip(row, 0, max(ne - 1, 0))].astype(dtype) if ne else zero
    surf, edge = (cls == SURFACE)[..., None], (cls == EDGE)[..., None]
    col0 = jnp.where(surf, sb[..., 0, :], jnp.where(edge, et, zero))
    col1 = jnp.where(surf, sb[..., 1, :], zero)
    B = jnp.stack([col0, col1, zero], axis=-1)  # columns = free directions
    B = jnp.where((cls == INTERIOR)[..., None, None], jnp.eye(3, dtype=dtype), B)
    return jnp.where(mask[..., None, None], B, 0.0)


@dataclasses.dataclass(frozen=True)
class BoundaryView:
    """What the host needs of the boundary for the flat regions (`surface_planes`,
    `jaxci.optim.parametrisation.flat_intervals`): O(boundary) arrays, numpy.

    - `nodes` ``(nb,)``: the nodes of the boundary faces, sorted; `points` ``(nb, 3)`` float64 their
      coordinates; `faces` ``(n_faces, 4)`` the boundary faces in positions into `nodes`;
    - `surf` ``(ns,)``, `edge` ``(ne,)``: the SURFACE and EDGE nodes (``cons.surface_nodes``, ``edge_nodes``),
      and `surf_at`, `edge_at` their positions in `nodes`; `ring` ``(ns, K)`` each surface node's ring faces
      (every 4th candidate triangle of ``cons.surface_cand`` divided by 4: its 4 triangles are consecutive).
    """

    nodes: np.ndarray
    points: np.ndarray
    faces: np.ndarray
    surf: np.ndarray
    edge: np.ndarray
    ring: np.ndarray

    @property
    def surf_at(self) -> np.ndarray:
        return np.searchsorted(self.nodes, self.surf)

    @property
    def edge_at(self) -> np.ndarray:
        return np.searchsorted(self.nodes, self.edge)

    def local(self, nodes: np.ndarray) -> np.ndarray:
        """Positions in `nodes` of boundary nodes `nodes` (any shape)."""
        return np.searchsorted(self.nodes, nodes)


def boundary_view(points, faces: np.ndarray, cons: Constraints) -> BoundaryView:
    """The `BoundaryView` of the boundary faces `faces` (host) with the coordinates of their nodes from the
    device `points` ``(n, 3)`` and the surface and edge nodes from `cons`: the node list goes up, the
    O(boundary) arrays come down (one program, one download)."""
    faces = np.asarray(faces, np.int64).reshape(-1, 4)
    nodes = np.unique(faces)
    ns, ne = int(cons.surface_nodes.shape[0]), int(cons.edge_nodes.shape[0])
    with enable_x64():  # float64 points come down as they are
        surf, edge, ring, xb = to_host(_boundary_arrays(cons.surface_nodes, cons.edge_nodes, cons.surface_cand,
                                                        points, to_device(nodes, np.int32), ns=ns, ne=ne))
    return BoundaryView(nodes=nodes, points=np.asarray(xb, np.float64), faces=np.searchsorted(nodes, faces),
                        surf=np.asarray(surf, np.int64), edge=np.asarray(edge, np.int64),
                        ring=np.asarray(ring, np.int64))


@program
@jit(static_argnames=("ns", "ne"))
def _boundary_arrays(surface_nodes, edge_nodes, surface_cand, points, nodes, ns: int, ne: int):
    """The surface and edge nodes, the surface nodes' ring faces ``(ns, K / 4)`` and the coordinates of
    `nodes`."""
    return surface_nodes[:ns], edge_nodes[:ne], surface_cand[:ns, ::4] // 4, points[nodes]


def surface_planes(view: BoundaryView, device: bool = False) -> np.ndarray:
    """`jaxci.optim._moves.planar_rings` of the surface nodes ``(n_surface, 7)`` (rows in
    ``cons.surface_nodes`` order; at least one row), float64 numpy, from a `BoundaryView` (O(boundary)). `device`:
    measured by a compiled program (the view's arrays up, the planes down), else in numpy."""
    if not len(view.surf) or not len(view.faces):
        return np.zeros((max(len(view.surf), 1), 7))
    if not device:
        return surface_rings(view.points, view.faces, view.surf_at, view.ring)
    with enable_x64():
        i32 = tuple(np.asarray(a, np.int32) for a in (view.faces, view.surf_at, view.ring))
        return np.asarray(to_host(_surface_rings(to_device(np.asarray(view.points, np.float64)), *to_device(i32))))


@program
@jit
def _surface_rings(points, faces, surf, ring):
    return surface_rings(points, faces, surf, ring, jnp)
