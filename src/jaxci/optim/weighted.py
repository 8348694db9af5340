"""Host kernels of objectives that weigh every corner of every cell type: the p-mean (`pmean_kernel`) and the
worst-element polish's penalty (`penalty_kernel`), each ``kernel(points) -> (value, max kappa/3, gradient)`` as
`jaxci.optim.host.HostObjective` takes it.

Both are functions of the corner terms ``t_i = (kappa_i/3)^2`` of the cells (each relative to its type's ideal
corner, `jaxci.metrics.elements`), and their gradients are ``sum_i c_i d t_i / dx`` with per-corner weights ``c_i``:
two passes, the terms and then the weighted gradient. The hexahedra run through the C kernel of `jaxci.native`
(its corner weights); the wedges, pyramids and tetrahedra through their flat corner tables: the terms in C, the
weighted gradient in numpy (`_table_grad`: the C corner kernel takes one weight for all corners). Without the C
kernels everything is numpy. A pyramid's four Verdict tetrahedra are a validity barrier (no term), as in F.
"""

from __future__ import annotations

import numpy as np

from .. import native
from ..cells import CORNERS, KERNELS, pmean_weights

_EYE = np.eye(3)


def _cross(a, b) -> np.ndarray:
    """Column-wise cross products of ``(3, C)`` arrays."""
    return np.cross(np.asarray(a), np.asarray(b), axis=0)


def _corner_table(cells: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """`jaxci.native.corner_table` (numpy only): rows node, column ends; corner j of cell e at ``j N + e``."""
    c = np.asarray(cells, dtype=np.int64)
    return np.ascontiguousarray(np.stack([c[:, corners[:, m]].T.ravel() for m in range(4)]))


class CellCorners:
    """Every corner of a set of cells, as the weighted kernels take them.

    **Arguments:** `blocks`: cell type -> ``(N, k)`` cells (`jaxci.cells.element_blocks`' layout; types absent or
    empty are skipped).

    `terms` and `grad` work on a list of per-type arrays: first the hexahedra's ``(8, N)`` (when there are
    hexahedra), then each other type's ``(n_corners N,)`` in the order of `types`.
    """

    def __init__(self, blocks: dict):
        self.types = [t for t, c in blocks.items() if len(c)]
        self.counts = {t: len(blocks[t]) for t in self.types}
        c_hex = native.AVAILABLE and "hexahedron" in self.types
        self.hexes = native.as_conn(blocks["hexahedron"]) if c_hex else None
        #: per non-C type: (type, flat corner table (4, C), W^-1)
        self.tables = [(t, _corner_table(blocks[t], CORNERS[t]), np.asarray(KERNELS[t].winv, np.float64))
                       for t in self.types if not (c_hex and t == "hexahedron")]
        self.barrier = np.concatenate([np.zeros((4, 0), np.int64)] + [
            _corner_table(blocks[t], KERNELS[t].barrier) for t in self.types if len(KERNELS[t].barrier)], axis=1)
        self.n_corners = sum(len(blocks[t]) * KERNELS[t].n_corners for t in self.types)

    def terms(self, x: np.ndarray) -> list[np.ndarray] | None:
        """The corner terms (kappa/3)^2 at `x` ``(n, 3)`` per part, or None where a corner or a barrier
        tetrahedron is inverted."""
        out = []
        if self.hexes is not None:
            t, bad = native.hex_corner_terms(x, self.hexes)
            if bad:
                return None
            out.append(t)
        for _, table, winv in self.tables:
            if native.AVAILABLE:
                t, bad = native.table_corner_terms(x, table, winv)
            else:
                t = _table_terms(x, table, winv)
                bad = int(np.count_nonzero(~np.isfinite(t)))
            if bad:
                return None
            out.append(t)
        if self.barrier.shape[1]:
            bad = native.table_inverted(x, self.barrier) if native.AVAILABLE else int(
                np.count_nonzero(~np.isfinite(_table_terms(x, self.barrier, _EYE))))
            if bad:
                return None
        return out

    def grad(self, x: np.ndarray, weights: list[np.ndarray], scale: float) -> np.ndarray:
        """``scale * sum_i w_i d t_i / dx`` ``(n, 3)``, `weights` per part as `terms` gives the terms."""
        g = np.zeros_like(x)
        parts = iter(weights)
        if self.hexes is not None:
            native.hex_weighted_grad(x, self.hexes, next(parts), scale, g)
        for (_, table, winv), w in zip(self.tables, parts, strict=True):
            _table_grad(x, table, winv, scale * w, g)
        return g

    def cell_worst(self, x: np.ndarray, terms: list[np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """Per type, each cell's worst corner kappa/3 at `x` (``inf`` for an inverted one), float64 ``(N,)``."""
        out = {}
        parts = iter(self.terms_all(x) if terms is None else terms)
        if self.hexes is not None:
            out["hexahedron"] = np.sqrt(next(parts).max(axis=0))
        for (t, _, _), part in zip(self.tables, parts, strict=True):
            out[t] = np.sqrt(part.reshape(-1, self.counts[t]).max(axis=0))
        return out

    def terms_all(self, x: np.ndarray) -> list[np.ndarray]:
        """`terms` without the early return: inverted corners ``inf`` (the barrier is not looked at)."""
        out = []
        if self.hexes is not None:
            out.append(native.hex_corner_terms(x, self.hexes)[0])
        for _, table, winv in self.tables:
            out.append(native.table_corner_terms(x, table, winv)[0] if native.AVAILABLE
                       else _table_terms(x, table, winv))
        return out


def _table_columns(x: np.ndarray, table: np.ndarray, winv: np.ndarray):
    """The columns of ``J = A W^-1`` of every corner of `table`, each ``(3, C)`` (rows x, y, z)."""
    o = x[table[0]].T
    e = [x[table[m + 1]].T - o for m in range(3)]
    return [sum(e[m] * winv[m, c] for m in range(3) if winv[m, c] != 0.0) for c in range(3)]


def _table_terms(x: np.ndarray, table: np.ndarray, winv: np.ndarray) -> np.ndarray:
    """(kappa/3)^2 of ``A W^-1`` per corner of `table` in numpy (``inf`` where det <= 0)."""
    a, b, c = _table_columns(x, table, winv)
    u, v, w = _cross(b, c), _cross(c, a), _cross(a, b)
    det = a[0] * u[0] + a[1] * u[1] + a[2] * u[2]
    fro2 = sum(np.sum(m * m, axis=0) for m in (a, b, c))
    adj2 = sum(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] for m in (u, v, w))
    valid = det > 0
    safe = np.where(valid, det, 1.0)
    return np.where(valid, fro2 * adj2 / (9.0 * safe * safe), np.inf)


def _table_grad(x: np.ndarray, table: np.ndarray, winv: np.ndarray, w: np.ndarray, g: np.ndarray) -> None:
    """``g += sum_i w_i d t_i / dx`` over the valid corners of `table` (the closed form of
    `jaxci.metrics.hexahedron._node_grads` on the columns of ``A W^-1``, taken back through ``W^-1``)."""
    a, b, c = _table_columns(x, table, winv)
    u, v, ww = _cross(b, c), _cross(c, a), _cross(a, b)
    det = np.einsum("dc,dc->c", a, u)
    fro2 = np.einsum("dc,dc->c", a, a) + np.einsum("dc,dc->c", b, b) + np.einsum("dc,dc->c", c, c)
    adj2 = np.einsum("dc,dc->c", u, u) + np.einsum("dc,dc->c", v, v) + np.einsum("dc,dc->c", ww, ww)
    valid = det > 0
    idet = np.where(valid, 1.0 / np.where(valid, det, 1.0), 0.0)
    idet2 = idet * idet
    w2 = np.where(valid, w * (2.0 / 9.0), 0.0)  # as the C kernel's weight: ga below is (9/2) w2 d t / da
    p, q = w2 * adj2 * idet2, w2 * fro2 * idet2
    r = p * fro2 * idet
    ga = p * a + q * (_cross(v, c) + _cross(b, ww)) - r * u
    gb = p * b + q * (_cross(c, u) + _cross(ww, a)) - r * v
    gc = p * c + q * (_cross(u, b) + _cross(a, v)) - r * ww
    n = len(g)
    for m in range(3):  # d / d (column m of A) = sum_c d / d (column c of J) W^-1[m, c]
        gm = ga * winv[m, 0] + gb * winv[m, 1] + gc * winv[m, 2]
        for d in range(3):
            g[:, d] += np.bincount(table[m + 1], weights=gm[d], minlength=n)
            g[:, d] -= np.bincount(table[0], weights=gm[d], minlength=n)


def pmean_kernel(blocks: dict, power: float):
    """``kernel(x) -> (M_p, max kappa/3, dM_p/dx)``: the p-mean of the corner excesses ``e_i = t_i - 1`` over every
    corner of the cells `blocks` (`jaxci.metrics.hexahedron.pmean_objective` over every cell type; ``inf`` if
    a corner is inverted)."""
    cells = CellCorners(blocks)
    n = max(cells.n_corners, 1)

    def kernel(x):
        parts = cells.terms(x)
        if parts is None:
            return np.inf, np.inf, np.zeros_like(x)
        flat = np.concatenate([t.ravel() for t in parts])
        m, c = pmean_weights(np, flat - 1.0, None, float(power))
        kmax = float(np.sqrt(flat.max(initial=1.0)))
        if not np.isfinite(m) or m <= 0:
            return float(m), kmax, np.zeros_like(x)
        return float(m), kmax, cells.grad(x, _split_like(c, parts), 1.0 / n)

    return kernel


def cell_measure(t: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``(M, dM)`` of the corner terms `t` ``(c, N)`` of N cells of c corners each: every cell's smooth max of its
    terms ``M = t_max (mean_i (t_i / t_max)^P)^(1/P)``, ``P = 2^k`` (by squarings and square roots, as the C kernel
    of `jaxci.native.hex_penalty` computes it), shape ``(N,)``, and ``c dM / dt_i = (t_i / M)^(P - 1)``, shape
    ``(c, N)``. ``M`` lies between the mean and the max of the cell's terms, nearer the max as P grows."""
    top = t.max(axis=0)
    s = t / top
    for _ in range(k):
        s = s * s
    m = s.sum(axis=0) * (1.0 / t.shape[0])
    for _ in range(k):
        m = np.sqrt(m)
    m = top * m
    rel = t / m
    d = rel.copy()
    for _ in range(k):
        d = d * d
    return m, d / rel


def penalty_kernel(blocks: dict, n_norm: int, level: float, weight: float, cell_k: int = 0,
                   cells: CellCorners | None = None):
    """``kernel(x) -> (value, max kappa/3, gradient)`` of ``(sum_i e_i + weight * sum_i max(0, e_i - level)^2) /
    n_norm`` over the corners of the cells `blocks` (``e_i = t_i - 1``): F's share of these corners (`n_norm`: the
    corners of the whole mesh) with a quadratic penalty on every corner excess above `level` (the worst-element
    polish, `jaxci.optim.polish`); ``inf`` if a corner is inverted. `cell_k` > 0: each corner's ``e_i`` in the
    first sum is its cell's ``M - 1`` instead (`cell_measure` of power ``2^cell_k``: a smooth max of the cell's
    terms, so that the sum weighs each cell by its worst corners, as the mean element quality does). On hexahedra
    alone with the C kernels: terms and gradient in one pass (`jaxci.native.hex_penalty`), where the general path
    makes two (a third of the polish's time on a 25,000-hexahedron tet-to-hex bracket). `cells`: the
    `CellCorners` of `blocks` where the caller has them (else made here)."""
    cells = CellCorners(blocks) if cells is None else cells
    inv = 1.0 / max(int(n_norm), 1)
    if cells.hexes is not None and not cells.tables and not cells.barrier.shape[1]:  # hexahedra: one C pass
        hexes = cells.hexes

        def fused(x):
            total, tmax, bad, g = native.hex_penalty(x, hexes, level, weight, inv, cell_k)
            return (np.inf, np.inf, np.zeros_like(x)) if bad else (total * inv, float(np.sqrt(tmax)), g)

        return fused

    def kernel(x):
        parts = cells.terms(x)
        if parts is None:
            return np.inf, np.inf, np.zeros_like(x)
        total, weights, tmax = 0.0, [], 1.0
        for t, c in zip(parts, _corners_per_cell(cells), strict=True):
            e = t - 1.0
            over = np.maximum(e - level, 0.0)
            # einsum, not np.dot: BLAS's threads spin against other processes (`jaxci.optim.host.dot`)
            penalty = weight * float(np.einsum("i,i->", over.ravel(), over.ravel()))
            if cell_k:
                m, d = cell_measure(t.reshape(c, -1), cell_k)
                total += float(c * (m - 1.0).sum()) + penalty
                weights.append(d.reshape(t.shape) + 2.0 * weight * over)
            else:
                total += float(e.sum()) + penalty
                weights.append(1.0 + 2.0 * weight * over)
            tmax = max(tmax, float(t.max(initial=1.0)))
        return total * inv, float(np.sqrt(tmax)), cells.grad(x, weights, inv)

    return kernel


def _corners_per_cell(cells: CellCorners) -> list[int]:
    """The corners of one cell of each part of `CellCorners.terms`: the hexahedra's ``(8, N)`` first (where the C
    kernel runs), then each other type's flat ``(c N,)`` terms (corner j of cell e at ``j N + e``)."""
    out = [8] if cells.hexes is not None else []
    return out + [KERNELS[t].n_corners for t, _, _ in cells.tables]


def _split_like(flat: np.ndarray, parts: list[np.ndarray]) -> list[np.ndarray]:
    """`flat` cut into arrays of the shapes of `parts` (in order)."""
    ends = np.cumsum([0] + [t.size for t in parts])
    return [flat[a:b].reshape(t.shape) for a, b, t in zip(ends[:-1], ends[1:], parts, strict=True)]
