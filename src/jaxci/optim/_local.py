"""Node stars: what the local (per-node, coloured) optimizers need to evaluate one node's move cheaply.

Moving node v changes only the corners of the elements around v. We relabel every element around v by a
rotation of the reference cube so that v sits in local slot 0 (`ROTATE_TO_SLOT`): the element is the same
right-handed hexahedron, its 8 corner condition numbers are the same set, and the corners whose matrix contains
node 0 are always corners 0, 1, 3 and 4 (`AFFECTED_CORNERS`). So a trial position of v costs 4 corner
evaluations per incident element, with static indices.

Nodes of one colour of a node colouring share no element, so all of them can move at once and the change of
the mesh objective is the sum of their local changes: a move accepted because it lowers its local sum lowers
the global objective F by exactly that amount.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cells import ROTATE_TO_SLOT, corner_invariants
from ..metrics.hexahedron import squared_condition_from_invariants
from ..runtime._lazy import jax, jnp

#: The corners whose matrix involves local node 0, and their (base, column nodes) in VTK convention.
AFFECTED_CORNERS = ((0, (1, 3, 4)), (1, (2, 0, 5)), (3, (0, 2, 7)), (4, (7, 5, 0)))


@dataclasses.dataclass(frozen=True)
class NodeStars:
    """Elements around each node, relabelled so that the node is local slot 0 (numpy, built once per mesh).

    - `star`: shape ``(n_nodes, K, 8)``, node indices of the K incident elements (padded rows repeat the node
      itself; `mask` marks the real ones); or ``(n_nodes, K)`` incidences (``node_stars(..., incidences=True)``).
    - `mask`: shape ``(n_nodes, K)`` bool.
    - `valence`: shape ``(n_nodes,)``, number of incident elements.
    """

    star: np.ndarray
    mask: np.ndarray
    valence: np.ndarray


def node_stars(hexes: np.ndarray, n_nodes: int, incidences: bool = False, rows: np.ndarray | None = None
               ) -> NodeStars:
    """Build `NodeStars` for `hexes` of shape ``(N, 8)`` (vectorised; K = the maximum valence; int32 indices while
    they fit: the star of a 100^3 box holds 64 M of them).

    `incidences` True: `star` holds the incidences ``(n_nodes, K)``, ``8 e + s`` for the node being local node
    ``s`` of element ``e`` (padding 0), 8x less memory than the node lists; `star_nodes` gives the node lists.
    `rows` (optional, with `incidences`; distinct nodes): the stars of these nodes alone, in this order, ``(len(rows),
    K)`` (`star` and `mask`): the rows ``[rows]`` of the whole stars, made without them
    (`jaxci.optim.host_local.sweep_colours`).
    """
    hexes = np.asarray(hexes)
    valence = np.bincount(hexes.ravel(), minlength=n_nodes)
    K = max(int(valence.max(initial=0)), 1)
    it = np.int32 if max(n_nodes * K, 8 * len(hexes)) < 2**31 else np.int64  # every index below fits
    if rows is None:
        rows = np.arange(n_nodes, dtype=it)
    rank = np.full(n_nodes, -1, it)  # each node's row, -1: none
    rank[rows] = np.arange(len(rows), dtype=it)
    mask = np.arange(K) < valence[rows][:, None]
    inc = np.zeros((len(rows), K), it)
    # the incidences of STAR_BLOCK elements at a time, sorted by row (stable: elements in order), each put after
    # the row's entries of the blocks before (one sort of every incidence held 20 MB of temporaries on cube60_pert's
    # 1.7 M incidences, these blocks 8 MB; tracemalloc)
    fill = np.zeros(len(rows), it)
    for lo in range(0, len(hexes), STAR_BLOCK):
        key = rank[hexes[lo:lo + STAR_BLOCK].ravel()]
        order = np.argsort(key, kind="stable")
        key = key[order]
        first = np.searchsorted(key, 0)  # the incidences of no row sort first (-1)
        order, key = order[first:], key[first:]
        run = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]])) if len(key) else np.zeros(0, np.intp)
        size = np.diff(np.append(run, len(key)))  # each run's length: a row's incidences in this block
        col = np.arange(len(key)) - np.repeat(run, size)  # the entry's place in its run
        inc[key, fill[key] + col] = order + 8 * lo
        fill[key[run]] += size.astype(it)
    if incidences:
        return NodeStars(star=inc, mask=mask, valence=valence)
    hexes = hexes.astype(it, copy=False)
    return NodeStars(star=star_nodes(hexes, inc, mask, np.arange(n_nodes, dtype=it)), mask=mask, valence=valence)


#: Elements per block of `node_stars`' sort (its temporaries: about 45 bytes an incidence, 6 MB a block).
STAR_BLOCK = 1 << 14


#: Incidences `star_nodes` relabels at a time: its index temporaries stay at a few MB and are reused, where
#: whole-array ones (1.5 GB at 10^6 elements) cost more in fresh pages than the gather itself.
STAR_CHUNK = 1 << 17


def star_nodes(hexes: np.ndarray, inc: np.ndarray, mask: np.ndarray | None = None,
               node: np.ndarray | None = None) -> np.ndarray:
    """The relabelled node lists ``inc.shape + (8,)`` of incidences `inc` (``node_stars(..., incidences=True)``):
    element ``inc // 8`` of `hexes` ``(N, 8)`` with its local node ``inc % 8`` moved to slot 0, in the dtype of
    `hexes`. With `mask` (bool, ``inc.shape``) and `node` (``inc.shape[:-1]``), the lists where `mask` is False
    (padding) repeat `node` of their row instead (`node_stars`' padding)."""
    flat = np.asarray(hexes).ravel()
    if not flat.size:  # no elements: every entry is padding (element 0 of a stand-in)
        flat = np.zeros(8, flat.dtype)
    inc = np.asarray(inc)
    out = np.empty(inc.shape + (8,), flat.dtype)
    src, dst = inc.reshape(-1), out.reshape(-1, 8)
    rot = ROTATE_TO_SLOT.astype(np.intp)
    for lo in range(0, len(src), STAR_CHUNK):
        i = src[lo : lo + STAR_CHUNK].astype(np.intp)
        slot = i & 7  # i % 8 (incidences are non-negative)
        idx = rot.take(slot, axis=0)  # (m, 8)
        slot ^= i  # i - i % 8: the element's first incidence
        idx += slot[:, None]
        np.take(flat, idx, mode="clip", out=dst[lo : lo + STAR_CHUNK])  # valid by construction: no bounds check
    if mask is not None:
        pad = ~np.asarray(mask)
        out[pad] = np.broadcast_to(np.asarray(node)[..., None], pad.shape)[pad][:, None]
    return out


def gather_star(points, star):
    """Coordinates of star nodes, structure of arrays: ``(X, Y, Z)`` each of shape ``star.shape``."""
    return tuple(points[:, d][star] for d in range(3))


def relabel(conn, inc):
    """The relabelled node lists ``inc.shape + (8,)`` of incidences `inc` (``8 e + s``, int32) on the device:
    hexahedron ``e`` of the transposed connectivity `conn` ``(8, N)`` with its local node ``s`` moved to slot 0
    (`star_nodes`' lists, gathered from `conn` and the constant `ROTATE_TO_SLOT`)."""
    rot = jnp.asarray(ROTATE_TO_SLOT, jnp.int32)[inc & 7]  # (..., 8) old local node of each new slot
    return conn.reshape(-1)[rot * conn.shape[1] + (inc >> 3)[..., None]]


def star_coords(points, conn, star):
    """`gather_star` of one colour's stars `star`: node lists ``(M, K, 8)``, or incidences ``(M, K)`` (the
    device-built stars of `jaxci.optim.device_stars`), relabelled here from `conn` ``(8, N)``; the number of
    axes tells them apart (static)."""
    return gather_star(points, star if star.ndim == 3 else relabel(conn, star))


def local_terms(E, smask, y):
    """Sum of (kappa/3)^2 over the corners around node slot 0 when the node is at `y`.

    **Arguments:**

    - `E`: ``(X, Y, Z)`` from `gather_star`, each of shape ``(M, K, 8)`` (current coordinates; slot 0 is ignored).
    - `smask`: shape ``(M, K)``, real incident elements.
    - `y`: trial positions of shape ``(M, S, 3)`` (S trials per node).

    **Returns:** shape ``(M, S)``: the local sum, ``inf`` where any affected corner has det <= 0.
    """
    X, Y, Z = (c[:, None] for c in E)  # (M, 1, K, 8)
    y0 = [y[..., d][..., None] for d in range(3)]  # (M, S, 1)

    def node(C, d, i):
        return y0[d] if i == 0 else C[..., i]

    total = 0.0
    for base, cols in AFFECTED_CORNERS:
        comps = []
        for j in cols:
            for d, C in enumerate((X, Y, Z)):
                comps.append(node(C, d, j) - node(C, d, base))
        term = squared_condition_from_invariants(*corner_invariants(*comps))  # (M, S, K)
        total = total + jnp.where(smask[:, None, :], term, 0.0)
    return jnp.sum(total, axis=-1)


def chunked(fn, y, chunk: int):
    """``fn(y)`` for trials `y` ``(M, S, 3)`` -> ``(M, S)``, evaluated `chunk` trials at a time (`jax.lax.map`)."""
    M, S, _ = y.shape
    if chunk >= S:
        return fn(y)
    n = -(-S // chunk)
    pad = n * chunk - S
    yp = jnp.concatenate([y, jnp.broadcast_to(y[:, :1], (M, pad, 3))], axis=1) if pad else y
    yc = jnp.moveaxis(yp.reshape(M, n, chunk, 3), 1, 0)
    out = jax.lax.map(fn, yc)  # (n, M, chunk)
    return jnp.moveaxis(out, 0, 1).reshape(M, n * chunk)[:, :S]


def local_length(E, smask, xp=jnp):
    """Mean length of the edges at slot 0 of the incident elements, shape ``(M,)`` (a local length scale);
    `xp`: `jax.numpy` (default) or `numpy` (the host sweeps of `jaxci.optim.host_local`)."""
    X, Y, Z = E
    tot = 0.0
    for j in (1, 3, 4):
        tot = tot + xp.sqrt((X[..., j] - X[..., 0]) ** 2 + (Y[..., j] - Y[..., 0]) ** 2 + (Z[..., j] - Z[..., 0]) ** 2)
    cnt = xp.maximum(xp.sum(smask, axis=-1), 1)
    return xp.sum(xp.where(smask, tot, 0.0), axis=-1) / (3.0 * cnt)


@dataclasses.dataclass(frozen=True)
class ColourBatches:
    """Movable nodes grouped by colour, padded to one size so every colour runs the same compiled code.

    - `nodes`: shape ``(n_colours, M)`` node indices; padded entries hold `n_nodes` (out of range: writes to
      them are dropped).
    - `mask`: shape ``(n_colours, M)`` bool, real entries.
    """

    nodes: np.ndarray
    mask: np.ndarray


def colour_batches(colour: np.ndarray, movable: np.ndarray, n_nodes: int, colours) -> ColourBatches:
    """Group `movable` nodes (bool, shape ``(n_nodes,)``) by `colour` (int per node) into `ColourBatches`, a row
    for each colour value of `colours`; M may be 0."""
    ids = np.flatnonzero(movable)
    cols = np.asarray(colour)[ids]
    groups = [ids[cols == c] for c in colours] or [np.zeros(0, np.int64)]
    M = max((len(g) for g in groups), default=0)
    nodes = np.full((len(groups), M), n_nodes, dtype=np.int64)
    mask = np.zeros((len(groups), M), bool)
    for i, g in enumerate(groups):
        nodes[i, : len(g)] = g
        mask[i, : len(g)] = True
    return ColourBatches(nodes=nodes, mask=mask)


#: The 12 edges of a hexahedron in VTK node order.
HEX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]], dtype=np.int64
)


#: Hexahedra per block of `edge_neighbours`' edge keys.
EDGE_CHUNK = 1 << 16


def _edge_keys(a: np.ndarray, b: np.ndarray, n, out: np.ndarray) -> None:
    """``min(a, b) * n + max(a, b)`` of the edges' ends `a`, `b` (`b` overwritten) into `out` (int64, as `n`)."""
    np.minimum(a, b, out=out)
    np.maximum(a, b, out=b)
    out *= n
    out += b


def edge_neighbours(hexes: np.ndarray, n_nodes: int, edges: np.ndarray | None = None,
                    dtype=np.int64) -> tuple[np.ndarray, np.ndarray]:
    """Nodes joined to each node by a hexahedron edge, each once, padded.

    **Arguments:** `hexes` of shape ``(N, 8)``; `n_nodes`; `edges`: optional node pairs ``(E, 2)`` of further
    cell edges (a mixed mesh's `jaxci.metrics.objective.edge_pairs`), joined to the hexahedron edges; `dtype`:
    the integer type of `nbr` (int32 holds any node number below 2^31: half the bytes).

    **Returns:** ``(nbr, mask)`` of shape ``(n_nodes, K)`` (K the largest number of edge neighbours; padding
    repeats the node itself and is False in `mask`).
    """
    hexes = np.asarray(hexes)  # (int32: the keys are made in int64, block by block)
    extra = np.zeros((0, 2), np.int64) if edges is None else np.asarray(edges, np.int64).reshape(-1, 2)
    n = np.int64(n_nodes)
    # each edge once: low * n + high, the 12 edges of each hexahedron in order (then the extra edges), made block
    # by block: the ends of every edge at once were two more arrays of the keys' size (41 MB at 216,000 hexahedra)
    und = np.empty(12 * len(hexes) + len(extra), np.int64)
    for lo in range(0, len(hexes), EDGE_CHUNK):
        block = hexes[lo : lo + EDGE_CHUNK]
        _edge_keys(np.take(block, HEX_EDGES[:, 0], axis=1).ravel(), np.take(block, HEX_EDGES[:, 1], axis=1).ravel(),
                   n, und[12 * lo : 12 * (lo + len(block))])
    _edge_keys(extra[:, 0].copy(), extra[:, 1].copy(), n, und[12 * len(hexes) :])
    und.sort()
    und = und[np.concatenate([[True], und[1:] != und[:-1]])] if len(und) else und
    # both directions, by (node, neighbour): the keys, then high * n + low made in the second half of their array
    # (the ends of every edge and the reversed keys as arrays of their own were 16 MB more, cube60_pert's untangling
    # peak)
    m = len(und)
    key = np.empty(2 * m, np.int64)
    key[:m] = und
    rev = np.remainder(und, n, out=key[m:])
    rev *= n
    for lo in range(0, m, 12 * EDGE_CHUNK):
        rev[lo : lo + 12 * EDGE_CHUNK] += und[lo : lo + 12 * EDGE_CHUNK] // n
    del und, rev
    key.sort()
    # each node's degree block by block, then the neighbours in the keys' own array (no two more of its size)
    deg = np.zeros(n_nodes, np.int64)
    for lo in range(0, len(key), 12 * EDGE_CHUNK):
        deg += np.bincount(key[lo : lo + 12 * EDGE_CHUNK] // n, minlength=n_nodes)
    dst = np.remainder(key, n, out=key)
    K = max(int(deg.max(initial=0)), 1)
    mask = np.arange(K) < deg[:, None]  # a node's neighbours, in order, fill the first `deg` entries of its row
    nbr = np.repeat(np.arange(n_nodes, dtype=dtype)[:, None], K, axis=1)
    nbr[mask] = dst
    return nbr, mask


def laplace_trials(x, x0, nbr, nmask, basis, n_steps: int, xp):
    """The (smart) Laplacian's trial points for the nodes of one colour, both engines (`jaxci.optim.laplace`,
    `jaxci.optim.host_local`), before their projection onto the boundary: each node's move towards the centroid of
    its edge neighbours `nbr` ``(M, K)`` (real where `nmask`) in `x` ``(n, 3)``, from its position `x0` ``(M, 3)``,
    restricted to its free directions `basis` ``(M, 3, 3)`` (columns; zero for none), and the fractions 1, 1/2,
    ... of it (`n_steps`): ``(M, n_steps, 3)``. `xp`: the array module."""
    w = nmask.astype(x.dtype)
    count = xp.maximum(xp.sum(w, axis=-1, keepdims=True), 1.0)
    centroid = xp.stack([xp.sum(x[:, c][nbr] * w, axis=-1) for c in range(3)], axis=-1) / count  # a column each
    d = xp.einsum("mij,mj->mi", basis, xp.einsum("mji,mj->mi", basis, centroid - x0))
    fractions = xp.asarray([0.5**k for k in range(n_steps)], x.dtype)
    return x0[:, None] + fractions[None, :, None] * d[:, None]


def longest_step(f0, ft, xp):
    """The smart Laplacian's choice for each node, both engines: ``(j, accept)``, the longest trial (the first
    of `ft` ``(M, S)``, the local objective at each trial, longest first) whose local objective is finite and
    below `f0` ``(M,)`` (the node's as it is), and whether there is one. `xp`: the array module."""
    ok = (ft < f0[:, None]) & xp.isfinite(ft)
    return xp.argmax(ok, axis=1), xp.any(ok, axis=1)
