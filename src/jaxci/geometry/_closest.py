"""Closest points on triangles and segments: the kernels of `jaxci.geometry.projection` (numpy and JAX alike).

Vectors are tuples of 3 arrays (structure of arrays: XLA:CPU is many times faster on scalar component arrays
than on ``(..., 3)`` axes) and every function takes the array module `xp` (numpy or jax.numpy). The geometry
is packed into tables with one row per precomputed quantity and one column per triangle or segment, gathered
per candidate with 1-D gathers. See `jaxci.geometry.projection` for the method.
"""

from __future__ import annotations

import functools

import numpy as np


def _dot3(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _sub3(u, v):
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


def _axpy3(a, x, y):
    """a x + y for a scalar array a and 3-vectors x, y."""
    return (a * x[0] + y[0], a * x[1] + y[1], a * x[2] + y[2])


def _where3(xp, c, u, v):
    return (xp.where(c, u[0], v[0]), xp.where(c, u[1], v[1]), xp.where(c, u[2], v[2]))


@functools.cache
def inside_tolerance(dtype) -> float:
    """Relative tolerance of the inside tests (cached: the projection asks for it twice a solver step)."""
    return 256.0 * float(np.finfo(np.dtype(dtype)).eps)


@functools.cache
def segment_bump(dtype) -> float:
    """Score penalty of a segment point, times the squared size of its cell: an inside projection onto a
    triangle (or segment) wins unless the other point is nearer by more than rounding noise."""
    return (64.0 * float(np.finfo(np.dtype(dtype)).eps)) ** 2


# Rows of the packed triangle table (one column per triangle (c, a, b) of a boundary face, in `CELL_ORDER`; c its
# centroid, a and b consecutive corners; the 4 triangles of face f are columns 4 f .. 4 f + 3; a boundary triangle
# is the face [a, b, c, c], see `triangle_table`).
# Everything that depends on the original geometry only is precomputed: the kernel has no division or root.
TC = 0  # centroid c (x y z)
_TE1 = 3  # spoke e1 = a - c
_TE2 = 6  # spoke e2 = b - c
TN = 9  # unit normal
_TG = 12  # (g22, g12, g11) / |e1 x e2|^2, g the Gram matrix of (e1, e2)
_TOK = 15  # 1.0 for a non-degenerate triangle
_TIS = 16  # 1 / |e1|^2 (0 for a zero-length spoke)
_TID = 17  # 1 / |b - a|^2 (0 for a zero-length side)
_TL2 = 18  # squared size of the quad (its longest spoke), scales the segment penalty
TRI_ROWS = 19
# Rows of the packed segment table: start a, direction d = b - a, 1 / |d|^2 (0 if degenerate), |d|^2.
_SA, SD, _SI, _SL2 = 0, 3, 6, 7
SEG_ROWS = 8
#: The tables' memory order: Fortran, each cell's numbers together. The C search reads a cell's quantities from 3
#: cache lines instead of 19 rows apart (`jaxci.native.near_project` takes the transpose, the same memory): the local
#: CI sweeps of Mesquite's cub_fru, whose every trial searches its node's candidates, 26% faster (2026-11-30). numpy's
#: and JAX's code index the rows as before.
CELL_ORDER = "F"


def _segment_point(x, a, d, t, penalty):
    """Point a + t d, and its squared distance to x plus `penalty`."""
    p = _axpy3(t, d, a)
    v = _sub3(x, p)
    return p, _dot3(v, v) + penalty


def _keep_better(xp, best, new):
    """The candidate (point, score) with the lower score; `best` wins ties."""
    take = new[1] < best[1]
    return _where3(xp, take, new[0], best[0]), xp.where(take, new[1], best[1])


def closest_on_triangles(xp, x, t, tol):
    """Nearest points of `x` on triangles given by the 19 rows `t` of the triangle table, broadcast together.

    The candidates are the orthogonal projection onto the triangle if it falls inside, the nearest point of the
    spoke c-a and that of the side a-b (the other spoke is the next triangle's). Returns (point as 3 arrays,
    score), the score being the squared distance plus, for spoke and side points, a rounding-level penalty.
    """
    penalty = segment_bump(t[_TL2].dtype) * t[_TL2]
    c, e1, e2 = (tuple(t[k : k + 3]) for k in (TC, _TE1, _TE2))
    p, h, inside, w, d1 = plane_point(x, t, tol)
    best = (p, xp.where(inside, h * h, xp.inf))
    best = _keep_better(xp, best, _segment_point(x, c, e1, xp.clip(d1 * t[_TIS], 0, 1), penalty))
    side = _sub3(e2, e1)
    u = _dot3(_sub3(w, e1), side) * t[_TID]
    return _keep_better(xp, best, _segment_point(x, _axpy3(1.0, e1, c), side, xp.clip(u, 0, 1), penalty))


def plane_point(x, t, tol):
    """The orthogonal projection of `x` onto the planes of triangles `t`: ``(point, signed distance h, inside,
    x - c, (x - c) . e1)``; `inside` where it falls inside the triangle (within `tol`)."""
    c, e1, e2, un = (tuple(t[k : k + 3]) for k in (TC, _TE1, _TE2, TN))
    g22, g12, g11 = t[_TG], t[_TG + 1], t[_TG + 2]
    w = _sub3(x, c)
    d1, d2 = _dot3(w, e1), _dot3(w, e2)
    s = g22 * d1 - g12 * d2  # barycentric coordinates of the projection of x along e1 and e2
    r = g11 * d2 - g12 * d1
    inside = (t[_TOK] > 0) & (s >= -tol) & (r >= -tol) & (s + r <= 1 + tol)
    h = _dot3(w, un)
    return _axpy3(-h, un, x), h, inside, w, d1


def line_point(x, t, tol):
    """The orthogonal projection of `x` onto the lines of segments `t`: ``(point, inside)``."""
    a, d, inv = tuple(t[_SA : _SA + 3]), tuple(t[SD : SD + 3]), t[_SI]
    s = _dot3(_sub3(x, a), d) * inv
    return _axpy3(s, d, a), (inv > 0) & (s >= -tol) & (s <= 1 + tol)


def closest_on_segments(xp, x, t, tol):
    """Nearest points of `x` on segments given by the 8 rows `t` of the segment table; as for triangles (a
    point projecting inside the segment scores its squared distance, a clamped end point gets the penalty)."""
    a, d, inv = tuple(t[_SA : _SA + 3]), tuple(t[SD : SD + 3]), t[_SI]
    s = _dot3(_sub3(x, a), d) * inv
    inside = (inv > 0) & (s >= -tol) & (s <= 1 + tol)
    p, d2 = _segment_point(x, a, d, xp.where(inside, s, xp.clip(s, 0, 1)), 0)
    return p, xp.where(inside, d2, d2 + segment_bump(t[_SL2].dtype) * t[_SL2])


def triangle_table(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The packed triangle table of the faces `faces` (F, 4): shape (19, 4 F), float64, in `CELL_ORDER`.

    A face ``[a, b, c, c]`` is a triangle: its centre is its centroid (a + b + c) / 3, and its 4 triangles are
    (centre, a, b), (centre, b, c), a degenerate one (centre, c, c) (never an inside projection; its spoke lies
    in the face) and (centre, c, a): together exactly the triangle.
    """
    pc = points[faces]  # (F, 4, 3)
    tri = faces[:, 3] == faces[:, 2]
    centre = pc.mean(axis=1)
    if tri.any():
        centre[tri] = pc[tri, :3].mean(axis=1)
    c = np.repeat(centre, 4, axis=0)
    e1 = pc.reshape(-1, 3) - c
    e2 = np.roll(pc, -1, axis=1).reshape(-1, 3) - c
    n = np.cross(e1, e2)
    nn = (n * n).sum(1)
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    ok = nn > 1e-24 * g11 * g22
    inv = np.divide(1.0, nn, out=np.zeros_like(nn), where=ok)
    ll = ((e2 - e1) ** 2).sum(1)
    out = np.zeros((TRI_ROWS, len(c)), dtype=np.float64, order=CELL_ORDER)
    out[TC : TC + 3], out[_TE1 : _TE1 + 3], out[_TE2 : _TE2 + 3] = c.T, e1.T, e2.T
    # n / |n|: exactly +-1 along an axis for an axis-aligned triangle (sqrt(x^2) == |x| in IEEE arithmetic)
    out[TN : TN + 3] = np.divide(n, np.sqrt(nn)[:, None], out=np.zeros_like(n), where=ok[:, None]).T
    out[_TG], out[_TG + 1], out[_TG + 2] = g22 * inv, g12 * inv, g11 * inv
    out[_TOK] = ok
    out[_TIS] = np.divide(1.0, g11, out=np.zeros_like(g11), where=g11 > 0)
    out[_TID] = np.divide(1.0, ll, out=np.zeros_like(ll), where=ll > 0)
    out[_TL2] = np.repeat(((pc - centre[:, None, :]) ** 2).sum(2).max(axis=1), 4)
    return out


def cell_corners(table: np.ndarray, cells: np.ndarray, kind: int) -> tuple:
    """``(a, b, size2)`` of the columns `cells` (any shape) of a packed table: each cell's two corners ``(3,
    *cells.shape)`` and its squared size: a triangle's (c, a, b) of a face and the face's `_TL2` (kind 0), a
    segment's ends and its squared length (kind 1)."""
    if kind == 0:
        c = table[TC : TC + 3][:, cells]
        return c + table[_TE1 : _TE1 + 3][:, cells], c + table[_TE2 : _TE2 + 3][:, cells], table[_TL2][cells]
    a = table[_SA : _SA + 3][:, cells]
    return a, a + table[SD : SD + 3][:, cells], table[_SL2][cells]


def segment_table(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The packed segment table of `edges` (S, 2): shape (8, S), float64, in `CELL_ORDER`."""
    a, d = points[edges[:, 0]], points[edges[:, 1]] - points[edges[:, 0]]
    ll = (d * d).sum(1)
    out = np.zeros((SEG_ROWS, len(edges)), dtype=np.float64, order=CELL_ORDER)
    out[_SA : _SA + 3], out[SD : SD + 3] = a.T, d.T
    out[_SI] = np.divide(1.0, ll, out=np.zeros_like(ll), where=ll > 0)
    out[_SL2] = ll
    return out


def nearest_candidates(xp, x, table, cand, closest, tol):
    """Nearest candidate points: `x` (..., m, 3), candidate columns `cand` (m, K) of `table` -> (..., m, 3).

    `closest` is `closest_on_triangles` or `closest_on_segments`, `tol` the inside tolerance (`inside_tolerance`).
    """
    rows = candidate_rows(table, cand)
    xs = tuple(x[..., j][..., None] for j in range(3))  # each (..., m, 1)
    p, score = closest(xp, xs, rows, tol)
    k = xp.argmin(score, axis=-1)[..., None]
    return xp.stack([xp.take_along_axis(pj, k, axis=-1)[..., 0] for pj in p], axis=-1)


def candidate_rows(table, cand) -> list:
    """The rows of `table` gathered at the candidates `cand` (m, K): a list of (m, K) arrays (kept between
    projections by `jaxci.geometry.near.NearProjector` where numpy searches: the gather was a third of a
    projection)."""
    return [table[j][cand] for j in range(table.shape[0])]  # 1-D gathers, each (m, K)


def triangle_centres(t: np.ndarray):
    c, e1, e2 = t[TC : TC + 3].T, t[_TE1 : _TE1 + 3].T, t[_TE2 : _TE2 + 3].T
    centre = c + (e1 + e2) / 3.0
    return centre, np.max([np.linalg.norm(v - centre, axis=1) for v in (c, c + e1, c + e2)], axis=0)


def segment_centres(t: np.ndarray):
    d = t[SD : SD + 3].T
    return t[_SA : _SA + 3].T + 0.5 * d, 0.5 * np.linalg.norm(d, axis=1)
