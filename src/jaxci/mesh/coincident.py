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
    p = to_unit(np.asarray(points)[idx], unit_frame(np.asarray(points)[idx]))
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
    uint64 keys and sorted once): a point looks into its own cell, and into a neighbouring cell only where it
    lies within `r` of the face, edge or corner they share (with the 13 lexicographically positive offsets, so
    every pair of cells is seen once); candidates are then checked by distance. O(m log m) plus the candidates:
    what scipy's ``cKDTree.query_pairs`` gives, without importing scipy.spatial (0.3-0.5 s of a command's
    start)."""
    p = np.asarray(p, dtype=np.float64)
    m = len(p)
    if r > 0:
        lo = p.min(axis=0)
        extent = float((p.max(axis=0) - lo).max())
        h = max(r, extent / max(m, 1) ** (1 / 3) / 2)
        local = (p - lo) / h
        cell = np.floor(local).astype(np.int64)
        frac = (local - cell) * h  # position inside the cell
        reach = r * (1 + 1e-6)  # rounding of `frac` must not hide a pair: more candidates, each checked
        near = np.stack([frac <= reach, h - frac <= reach], axis=0)  # (2, m, 3): near the low / high face
    else:  # equal rows: the cell of a point is the rank of each of its coordinates
        cell = np.stack([np.unique(p[:, d], return_inverse=True)[1].ravel() for d in range(3)], axis=1)
        near = None
    with np.errstate(over="ignore"):
        keys = (cell.astype(np.uint64) * _HASH).sum(axis=1, dtype=np.uint64)
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        found = []
        for d in (np.zeros(3, np.int64), *(_HALF if near is not None else ())):
            who = np.arange(m)
            for a in range(3):
                if d[a]:
                    who = who[near[int(d[a] > 0), who, a]]
            q = ((cell[who] + d).astype(np.uint64) * _HASH).sum(axis=1, dtype=np.uint64)
            first, last = np.searchsorted(sorted_keys, q, "left"), np.searchsorted(sorted_keys, q, "right")
            count = last - first
            i = np.repeat(who, count)
            j = order[np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count - first, count)]
            close = (i != j) & (np.sum((p[i] - p[j]) ** 2, axis=1) <= r * r)
            found.append(np.stack([i[close], j[close]], axis=1))
    pairs = np.sort(np.concatenate(found), axis=1)
    key = np.unique(pairs[:, 0] * m + pairs[:, 1])
    return np.stack([key // max(m, 1), key % max(m, 1)], axis=1)
