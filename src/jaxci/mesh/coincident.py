"""Coincident nodes: distinct nodes at one point (closer than a fraction of the bounding-box diagonal), as an
unmerged interface leaves them, found in O(n log n) with a hashed grid (numpy only).

`coincident_pairs` gives the pairs of coincident nodes of a point array of shape ``(n, 3)`` (`HexMesh` notes them
on construction, `merge_coincident` merges them); `close_pairs` the pairs of rows within a distance, the search
beneath it.
"""

from __future__ import annotations

import numpy as np

from ..errors import MeshError
from .frame import to_unit, unit_frame
from .sorting import position_bits, sort_positions

#: Two distinct nodes closer than this fraction of the bounding-box diagonal are coincident (`coincident_pairs`):
#: an unmerged interface, two parts meshed apart and written into one file.
COINCIDENT_TOLERANCE = 1e-9


def coincident_pairs(points: np.ndarray, nodes: np.ndarray | None = None,
                     tol: float = COINCIDENT_TOLERANCE) -> np.ndarray:
    """Pairs of distinct nodes closer than `tol` times the bounding-box diagonal of `points`.

    **Arguments:** `points` of shape ``(n, 3)``; `nodes` the node indices to consider (default all); `tol` the
    relative tolerance (>= 0; 0: exactly equal coordinates).

    **Returns:** an int64 array of shape ``(k, 2)``, each row ``i < j``, sorted. O(n log n) (`close_pairs`).
    """
    if not (isinstance(tol, (int, float, np.floating)) and not isinstance(tol, bool) and 0 <= tol < 1):
        raise MeshError(f"coincident-node tolerance must be a number in [0, 1) (a fraction of the bounding-box "
                        f"diagonal), got {tol!r}")
    idx = np.arange(len(points)) if nodes is None else np.asarray(nodes, dtype=np.int64)
    if len(idx) < 2:
        return np.zeros((0, 2), np.int64)
    p = np.asarray(points)[idx]
    p = to_unit(p, unit_frame(p))
    diag = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    if diag > 0:
        pairs = close_pairs(p, tol * diag)
    else:  # every node at one point: a chain joins them all (not every pair)
        pairs = np.stack([np.arange(len(idx) - 1), np.arange(1, len(idx))], axis=1)
    pairs = np.sort(idx[np.asarray(pairs, dtype=np.int64).reshape(-1, 2)], axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def coincident_groups(n: int, pairs: np.ndarray) -> np.ndarray:
    """Each of the `n` nodes' group representative: the lowest-numbered node of its group of coincident nodes
    (`pairs` ``(k, 2)`` joined transitively), itself for a node in no pair; int64 ``(n,)``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    g = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    rep = np.full(comp.max() + 1, n, dtype=np.int64)
    np.minimum.at(rep, comp, np.arange(n))
    return rep[comp]


#: Multipliers that hash a grid cell's three integer coordinates into one uint64 key (large odd constants).
_HASH = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 1], dtype=np.uint64)
#: The grid-cell offsets that see every pair of neighbouring cells once: the 13 lexicographically positive ones.
_HALF = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)])


def close_pairs(p: np.ndarray, r: float) -> np.ndarray:
    """Index pairs ``(i, j)``, ``i < j``, of the rows of `p` ``(m, 3)`` at Euclidean distance at most `r` (>= 0;
    0: equal rows), as an int64 array ``(k, 2)`` in no particular order.

    A uniform grid of cells no smaller than `r` and about one point each (their integer coordinates hashed to
    uint64 keys): a point looks into its own cell, and into a neighbouring cell only where it lies within `r` of
    the face, edge or corner they share (with the 13 lexicographically positive offsets, so every pair of cells is
    seen once); candidates are then checked by distance. O(m log m) plus the candidates: what scipy's
    ``cKDTree.query_pairs`` gives, without importing scipy.spatial (0.3-0.5 s of a command's start).

    The keys are sorted as one ``np.sort`` of words holding the key's leading bits above the point's index
    (`jaxci.mesh.sorting.sort_positions`: an argsort at the cost of a sort); a cell's points are then a run of
    equal words (and equal keys: a run can hold other cells' points too, which the keys tell apart), so only
    points in runs of two or more, and points near a side of their cell, look for partners."""
    p = np.asarray(p, dtype=np.float64)
    m = len(p)
    if r > 0:
        lo = p.min(axis=0)
        extent = float((p.max(axis=0) - lo).max())
        h = max(r, extent / max(m, 1) ** (1 / 3) / 2)
        local = p - lo
        local /= h
        whole = np.floor(local)
        cell = whole.astype(np.int64)
        frac = local  # position inside the cell
        frac -= whole
        frac *= h
        del whole
        reach = r * (1 + 1e-6)  # rounding of `frac` must not hide a pair: more candidates, each checked
        low, high = frac <= reach, h - frac <= reach  # (m, 3): near the low / high face
        del frac
        anywhere = low | high
        side = np.flatnonzero(anywhere[:, 0] | anywhere[:, 1] | anywhere[:, 2])  # the points near a side
        near = np.stack([low[side], high[side]], axis=0)  # (2, len(side), 3)
        del low, high, anywhere
    else:  # equal rows: the cell of a point is the rank of each of its coordinates
        cell = np.stack([np.unique(p[:, d], return_inverse=True)[1].ravel() for d in range(3)], axis=1)
        near = side = None
    keys = _cell_keys(cell)
    bits = position_bits(m)
    word = _lead(keys, bits)
    word <<= np.uint64(bits)
    order, word = sort_positions(word, bits)  # runs of equal words: of equal keys' leading bits
    run = np.flatnonzero(np.diff(word, prepend=~word[:1], append=~word[-1:]) != 0) if m else np.zeros(1, np.int64)
    length = np.diff(run)
    multi = length > 1
    found = [_pairs_in_runs(run[:-1][multi], length[multi], order, keys, p, r)]
    if near is not None and len(side):
        for d in _HALF:
            sel = np.arange(len(side))
            for a in range(3):
                if d[a]:
                    sel = sel[near[int(d[a] > 0), sel, a]]
            who = side[sel]
            q = _cell_keys(cell[who] + d)
            lead = _lead(q, bits)
            first, last = np.searchsorted(word, lead, "left"), np.searchsorted(word, lead, "right")
            found.append(_candidates(who, q, first, last - first, order, keys, p, r))
    pairs = np.sort(np.concatenate(found), axis=1)
    key = np.unique(pairs[:, 0] * m + pairs[:, 1])
    return np.stack([key // max(m, 1), key % max(m, 1)], axis=1)


def _cell_keys(cell: np.ndarray) -> np.ndarray:
    """The uint64 hash keys of integer grid cells ``(k, 3)`` (`_HASH`, wrapping)."""
    c = np.ascontiguousarray(cell, dtype=np.int64).view(np.uint64)  # negative: wrapped, as astype does
    with np.errstate(over="ignore"):
        keys = c[:, 0] * _HASH[0]
        keys += c[:, 1] * _HASH[1]
        keys += c[:, 2]
    return keys


def _lead(keys: np.ndarray, bits: int) -> np.ndarray:
    """The leading ``64 - bits`` bits of the keys times an odd constant (which every bit of a key reaches; the
    last coordinate's, in the lowest bits of a key, would be lost otherwise), shifted down."""
    with np.errstate(over="ignore"):
        out = keys * np.uint64(0xBF58476D1CE4E5B9)
    out >>= np.uint64(bits)
    return out


def _pairs_in_runs(start: np.ndarray, length: np.ndarray, order, keys, p, r: float) -> np.ndarray:
    """`close_pairs`' pairs of points in one cell: the candidates of every point of the sorted runs
    ``order[start[k]:start[k] + length[k]]``."""
    who = order[np.repeat(start, length) + np.arange(int(length.sum())) - np.repeat(np.cumsum(length) - length, length)]
    return _candidates(who, keys[who], np.repeat(start, length), np.repeat(length, length), order, keys, p, r)


def _candidates(who, q, first, count, order, keys, p, r: float) -> np.ndarray:
    """The pairs ``(who[k], order[first[k] + t])``, ``0 <= t < count[k]``, of distinct points whose key is
    ``q[k]`` and whose distance is at most `r`, shape ``(c, 2)``."""
    i = np.repeat(who, count)
    j = order[np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count - first, count)]
    close = (i != j) & (keys[j] == np.repeat(q, count))
    i, j = i[close], j[close]
    close = np.sum((p[i] - p[j]) ** 2, axis=1) <= r * r
    return np.stack([i[close], j[close]], axis=1)
