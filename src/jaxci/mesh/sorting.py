"""Sorting integer keys at the speed of numpy's vectorised sort of 64-bit words (numpy only).

numpy 2 sorts an array of 64-bit integers with x86-simd-sort (AVX-512 or AVX2), several times faster than
``np.argsort``, ``np.lexsort`` or ``np.sort(axis=1)``. `sort_positions` makes an argsort of such a sort: the key
in a word's high bits, the position in its low bits. `group_pairs` puts equal int64 key pairs together with it
(a hash of the pair, checked exactly), `sort4` sorts 4 columns elementwise by a sorting network.
`jaxci.geometry.topology` finds the boundary faces with them, `jaxci.mesh.coincident` the nodes of one grid cell;
`sorted_unique` is ``np.unique`` of integers by one sort.
"""

from __future__ import annotations

import numpy as np

#: The odd multipliers of `group_pairs`' hash of two int64 keys (`HASH_MIX`: the same, for the device's face keys,
#: `jaxci.geometry.device_topology`).
_MIX = HASH_MIX = (np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9))
#: `group_pairs` sorts in windows of about ``2**_WINDOW_BITS`` positions of close first keys.
_WINDOW_BITS = 16


def position_bits(m: int) -> int:
    """The number of low bits a word needs for a position in ``[0, m)`` (at least 1)."""
    return max((m - 1).bit_length(), 1)


def sort_positions(words: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Sort the uint64 `words`, whose low `bits` bits are zero, with their positions: an argsort by the high bits
    at the cost of one ``np.sort`` (positions in the low bits). `words` is overwritten.

    **Returns:** ``(order, lead)``: the positions in sorted order (int64, ties by position) and the sorted words'
    high bits shifted down (a view of `words`), both of shape ``(m,)``.
    """
    words |= np.arange(len(words), dtype=np.uint64)
    words.sort()
    order = (words & np.uint64((1 << bits) - 1)).view(np.int64)
    words >>= np.uint64(bits)
    return order, words


def group_pairs(k1: np.ndarray, k2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An order of the positions of the int64 key pairs ``(k1[j], k2[j])`` that puts equal pairs together, and
    where each group of equal pairs starts in it: ``(order, starts)``, int64 of shapes ``(m,)`` and
    ``(n_groups,)``.

    One `sort_positions` of words holding, above the position, a multiplicative hash of the pair and on top the
    leading bits of `k1`, so that the pairs come in windows of about 65,000 positions of close `k1` (faces with
    close lowest nodes: usually of close cells, whose keys are then read in cache). Equal pairs have equal words
    but for the position; the keys are then compared exactly, and the few runs of equal words that hold different
    pairs (a collision of the truncated hash) are ordered by ``np.lexsort`` of their keys. Groups come in no
    particular order."""
    k1, k2 = (np.ascontiguousarray(k, dtype=np.int64) for k in (k1, k2))  # viewed as uint64 words below
    m = len(k1)
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    bits = position_bits(m)
    lo = int(k1.min())
    span = int(k1.max()) - lo
    lead = min(max(bits - _WINDOW_BITS, 0), span.bit_length())  # leading bits of k1 - lo above the hash
    h = k1.view(np.uint64) * _MIX[0]
    h += k2.view(np.uint64)
    h *= _MIX[1]
    h >>= np.uint64(bits + lead)
    h <<= np.uint64(bits)
    if lead:
        top = (k1 - lo).view(np.uint64)
        top >>= np.uint64(span.bit_length() - lead)
        top <<= np.uint64(64 - lead)
        h |= top
        del top
    order, h = sort_positions(h, bits)
    first = _firsts(k1, k2, order)
    clash = first[1:] & (h[1:] == h[:-1])
    if clash.any():  # runs of one word with different keys: sort each run by its keys (runs are contiguous)
        run = np.zeros(m, dtype=np.int64)
        np.cumsum(h[1:] != h[:-1], out=run[1:])
        bad = np.zeros(int(run[-1]) + 1, dtype=bool)
        bad[run[1:][clash]] = True
        pos = np.flatnonzero(bad[run])
        at = order[pos]
        order[pos] = at[np.lexsort((k2[at], k1[at], run[pos]))]
        first = _firsts(k1, k2, order)
    return order, np.flatnonzero(first)


def _firsts(k1: np.ndarray, k2: np.ndarray, order: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """Where the key pairs in `order` change (True at 0): the keys gathered a block of `chunk` positions at a
    time, not all at once (two arrays of every key: 21 MB at 216,000 hexahedra)."""
    first = np.ones(len(order), dtype=bool)
    for lo in range(1, len(order), chunk):
        at = order[lo - 1:lo + chunk]
        a, b = k1[at], k2[at]
        first[lo:lo + chunk] = (a[1:] != a[:-1]) | (b[1:] != b[:-1])
    return first


def sort4(c: list) -> None:
    """Sort 4 equal-length arrays elementwise in place (``c[0] <= c[1] <= c[2] <= c[3]`` after), by the 5
    compare-exchanges of a sorting network on whole columns: 0.15 s for 6 M rows against 0.22 s for
    ``np.sort(axis=1)`` of the ``(m, 4)`` rows, which also need stacking. The list's entries are swapped for other
    arrays."""
    tmp = np.empty_like(c[0])
    for i, j in ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)):
        np.minimum(c[i], c[j], out=tmp)
        np.maximum(c[i], c[j], out=c[j])
        c[i], tmp = tmp, c[i]


def sorted_unique(a) -> np.ndarray:
    """The distinct values of an integer array (any shape), sorted: ``np.unique(a)`` by one ``np.sort`` (numpy 2's
    ``np.unique`` hashes integers: 39 ms against 5 ms for the 240,000 corners of a 100^3 box's boundary faces)."""
    s = np.sort(np.asarray(a).ravel())
    return s[np.concatenate([[True], s[1:] != s[:-1]])] if len(s) else s
