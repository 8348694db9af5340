"""The numpy path's hexahedron kernels as fused C loops (`jaxci._ckernels`), with numpy's as the fallback.

`jaxci.optim.host` evaluates F with its gradient (and the untangling stage its energy with its gradient) a few
hundred times per run. Written with numpy, one evaluation is ~100 whole-array operations over every corner,
memory-bound: 20-30 ms at 27,000 hexahedra on the 2-core CPU. The C extension does the same arithmetic in one
loop over the elements, a corner's quantities in registers (measured 2026-11-24, 3c35738). It is
built at install time (`setup.py`, optional: without a C compiler the install succeeds and `AVAILABLE` is False,
so the numpy kernels run); ``JAXCI_NATIVE=0`` turns it off (for comparisons).

Arrays: float64 C-contiguous coordinates ``(n, 3)``; a connectivity (hexahedra, cells) int32 (`as_conn`: as
`jaxci.mesh.HexMesh` keeps it), other node indices int64.
"""

from __future__ import annotations

import os

import numpy as np

from .cells import KERNELS, ROTATE_TO_SLOT, load_c_kernels, pmean_weights
from .runtime.process import schedulable_cpus

_c = load_c_kernels()

#: Whether the C kernels are there (else the callers run their numpy kernels).
AVAILABLE = _c is not None

#: `jaxci.cells.ROTATE_TO_SLOT` as the star kernels take it (`local_sums`, `ci_visit`).
_ROTATE = np.ascontiguousarray(ROTATE_TO_SLOT, np.int64)


def _threads() -> int:
    """Threads per kernel call: ``JAXCI_THREADS``, else the CPUs this process may run on (at most 16). A call
    over fewer than 512 elements per thread uses fewer (`jaxci._ckernels`, whose threads are kept between
    calls); results are deterministic for a given number of threads (fixed ranges, fixed order of the sums)."""
    try:
        n = int(os.environ.get("JAXCI_THREADS", "0"))
    except ValueError:
        n = 0
    if n <= 0:
        n = schedulable_cpus()
    return max(1, min(n, 16))


#: Threads of the C kernels (`_threads`).
THREADS = _threads()


def _f8(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def _i4(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int32)


def _i8(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def as_conn(a) -> np.ndarray:
    """A connectivity as the C kernels take it: int32, C-contiguous (no copy where it is one already, as
    `jaxci.mesh.HexMesh.hexes` is); a wider array is checked to fit first."""
    a = np.asarray(a)
    if a.dtype != np.int32 and a.size and (a.max() > np.iinfo(np.int32).max or a.min() < 0):
        raise ValueError(f"node numbers up to {int(a.max())} do not fit the C kernels' int32 connectivity")
    return np.ascontiguousarray(a, dtype=np.int32)


def hex_terms_and_grad(points: np.ndarray, hexes: np.ndarray, power: float | None = None
                       ) -> tuple[float, float, np.ndarray]:
    """``(F, max kappa/3, dF/dx)`` of the hexahedra, as `jaxci.metrics.hexahedron.objective_terms_and_grad_np`.

    **Arguments:** `points` ``(n, 3)``; `hexes` ``(N, 8)`` (element-major: one element's nodes together);
    `power` p: the p-mean ``M_p`` of the corner excesses instead of their mean F (two passes: the terms, then
    the gradient weighted by ``(e_i / M_p)^(p - 1)``).

    **Returns:** F (``inf`` if a corner has det <= 0: the gradient then leaves those corners out), max kappa/3,
    and the gradient ``(n, 3)`` float64.
    """
    x, h = _f8(points), as_conn(hexes)
    if power is None:
        return _mean_terms_and_grad(x, h.shape[0], lambda w, g: _c.hex_condition(x, h, w, g, None, None, THREADS))
    grad = np.zeros_like(x)
    weight = _f_weight(h.shape[0])
    terms = np.empty((8, h.shape[0]))
    _c.hex_condition(x, h, 0.0, None, None, terms, THREADS)
    m, c = pmean_weights(np, terms - 1.0, None, float(power))
    if np.isfinite(m):
        _c.hex_condition(x, h, weight, grad, np.ascontiguousarray(c, dtype=np.float64), None, THREADS)
    return float(m), float(np.sqrt(np.max(terms, initial=0.0))), grad


def ffi_handler():
    """The C kernel of F and its gradient as an XLA FFI handler (a PyCapsule for `jax.ffi.register_ffi_target`;
    `jaxci.metrics.native_grad`); None where the extension was built without XLA's FFI header."""
    return _c.ffi_handler()


def ffi_api_version() -> tuple[int, int] | None:
    """``(major, minor)`` of the XLA FFI C API the handler was built against (the installed jaxlib's header at
    build time), or None (no extension, or no handler in it)."""
    if _c is None or not hasattr(_c, "ffi_api_version"):
        return None
    v = _c.ffi_api_version()
    return None if v is None else (int(v[0]), int(v[1]))


def corner_table(cells: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The corners of `cells` ``(N, k)`` as a flat table ``(4, n_corners N)`` int64 for `corner_condition`: row 0
    the corner's node, rows 1-3 the far ends of its columns (`corners`: rows ``[i, p, q, r]`` of
    `jaxci.cells.CORNERS`); corner j of cell e at ``j N + e``."""
    c = np.asarray(cells, dtype=np.int64)
    return np.ascontiguousarray(np.stack([c[:, corners[:, m]].T.ravel() for m in range(4)]))


class MixedKernel:
    """``(F, max kappa/3, dF/dx) = kernel(points)`` over every cell of a hex-dominant mesh (`jaxci.metrics.elements`'
    mixed objective: the mean over the corners of every hexahedron, wedge, pyramid and tetrahedron of
    ``(kappa/3)^2 - 1``, each relative to its type's ideal corner; ``inf`` if a corner, or one of the four
    tetrahedra of a pyramid, is inverted), for the numpy path of L-BFGS on mixed meshes.

    **Arguments:** `blocks`: cell type -> ``(N, k)`` cells (`jaxci.cells.element_blocks`). The hexahedra run
    through their own kernel; every other type through its `jaxci.cells.KERNELS` entry: its corner rows with its
    W^-1, and its barrier sub-tetrahedra (the pyramids'), whose det must stay > 0 and add no term.
    """

    def __init__(self, blocks: dict):
        self.hexes = as_conn(blocks.get("hexahedron", np.zeros((0, 8))))
        extra = {t: np.asarray(c, dtype=np.int64) for t, c in blocks.items() if t != "hexahedron" and len(c)}
        #: per type, its corners as a flat corner table with its W^-1 (objective terms)
        self.extra = [(corner_table(c, KERNELS[t].corners), _f8(KERNELS[t].winv)) for t, c in extra.items()]
        #: the barrier sub-tetrahedra of every type that has some, as one corner table (W = I): validity only
        self.barrier = np.concatenate([np.zeros((4, 0), np.int64)] + [
            corner_table(c, KERNELS[t].barrier) for t, c in extra.items() if len(KERNELS[t].barrier)], axis=1)
        self.n_corners = 8 * len(self.hexes) + sum(t.shape[1] for t, _ in self.extra)

    def __call__(self, points: np.ndarray) -> tuple[float, float, np.ndarray]:
        x = _f8(points)
        grad = np.zeros_like(x)
        n = max(self.n_corners, 1)
        weight = 2.0 / (9.0 * n)
        total, tmax, bad = _c.hex_condition(x, self.hexes, weight, grad, None, None, THREADS)
        for table, winv in self.extra:
            s, t, b = _c.corner_condition(x, table, winv, weight, grad, None, THREADS)
            total, tmax, bad = total + s, max(tmax, t), bad + b
        if self.barrier.shape[1]:
            bad += _c.corner_condition(x, self.barrier, _EYE, 0.0, None, None, THREADS)[2]
        if bad:
            return np.inf, np.inf, grad
        return total / n, float(np.sqrt(tmax)), grad


_EYE = np.eye(3)


def hex_sums(points: np.ndarray, hexes: np.ndarray) -> tuple[float, float, int]:
    """``(sum of (kappa/3)^2 - 1 over the valid corners, max (kappa/3)^2, inverted corners)`` of the hexahedra
    `hexes` ``(N, 8)`` at `points` ``(n, 3)``: one pass, no gradient."""
    return _c.hex_condition(_f8(points), as_conn(hexes), 0.0, None, None, None, THREADS)


def hex_objective(points: np.ndarray, hexes: np.ndarray) -> tuple[float, float]:
    """``(F, max kappa/3)`` of the hexahedra `hexes` ``(N, 8)`` at `points` ``(n, 3)`` (`hex_sums`; F is inf if a
    corner is inverted)."""
    total, tmax, bad = hex_sums(points, hexes)
    return (np.inf if bad else total / (8 * len(hexes))), float(np.sqrt(tmax))


def hex_corner_terms(points: np.ndarray, hexes: np.ndarray) -> tuple[np.ndarray, int]:
    """``(terms, inverted)``: (kappa/3)^2 of every corner of `hexes` ``(N, 8)`` as ``(8, N)`` float64 (corner i
    of hexahedron e at ``[i, e]``; ``inf`` where det <= 0) and the number of such corners."""
    h = as_conn(hexes)
    terms = np.empty((8, h.shape[0]))
    bad = _c.hex_condition(_f8(points), h, 0.0, None, None, terms, THREADS)[2]
    return terms, int(bad)


def hex_corner_measures(points: np.ndarray, hexes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(kappa3, sj)``: every corner's kappa/3 (``inf`` where det <= 0) and scaled Jacobian det / (|a| |b| |c|)
    (0 where an edge has length 0) of `hexes` ``(N, 8)``, each float64 ``(8, N)`` (corner i of hexahedron e at
    ``[i, e]``): `jaxci.metrics.elements`' per-corner measures in one threaded pass."""
    h = as_conn(hexes)
    terms, sj = np.empty((8, h.shape[0])), np.empty((8, h.shape[0]))
    _c.hex_condition(_f8(points), h, 0.0, None, None, terms, THREADS, sj)
    return np.sqrt(terms, out=terms), sj


def hex_penalty(points: np.ndarray, hexes: np.ndarray, level: float, mu: float, scale: float, cell_k: int = 0
                ) -> tuple[float, float, int, np.ndarray]:
    """The worst-element polish's penalised sum over the corners of `hexes` ``(N, 8)`` at `points` in one pass
    (`jaxci.optim.weighted.penalty_kernel`): ``(sum_i e_i + mu max(0, e_i - level)^2, max (kappa/3)^2, inverted
    corners, gradient)``, ``e_i = (kappa_i/3)^2 - 1``, the gradient ``(n, 3)`` that of the sum times `scale`
    (over the valid corners). `cell_k` > 0: each corner's ``e_i`` in the first sum is its cell's ``M - 1``, ``M``
    the cell's smooth max of its terms of power ``2^cell_k`` (`jaxci.optim.weighted.cell_measure`)."""
    x = _f8(points)
    grad = np.zeros_like(x)
    s, tmax, bad = _c.hex_condition(x, as_conn(hexes), 2.0 * float(scale) / 9.0, grad, None, None, THREADS, None,
                                    float(level), float(mu), int(cell_k))
    return float(s), float(tmax), int(bad), grad


def hex_weighted_grad(points: np.ndarray, hexes: np.ndarray, corner_weight: np.ndarray, scale: float,
                      grad: np.ndarray) -> None:
    """``grad += scale * sum_i corner_weight[i] d (kappa_i/3)^2 / dx`` over the valid corners of `hexes`
    ``(N, 8)``, `corner_weight` ``(8, N)`` (`hex_corner_terms`' layout), in place on `grad` float64 ``(n, 3)``."""
    _c.hex_condition(_f8(points), as_conn(hexes), 2.0 * float(scale) / 9.0, grad, _f8(corner_weight), None, THREADS)


def table_corner_terms(points: np.ndarray, table: np.ndarray, winv: np.ndarray) -> tuple[np.ndarray, int]:
    """``(terms, inverted)`` of the corners of a flat corner table `table` ``(4, C)`` (`corner_table`) with the
    type's W^-1 `winv`: (kappa/3)^2 of ``A W^-1`` per corner ``(C,)`` (``inf`` where det <= 0) and how many such."""
    terms = np.empty(table.shape[1])
    bad = _c.corner_condition(_f8(points), table, _f8(winv), 0.0, None, terms, THREADS)[2]
    return terms, int(bad)


def table_inverted(points: np.ndarray, table: np.ndarray) -> int:
    """How many of the tetrahedra of the corner table `table` ``(4, C)`` have det <= 0 (W = I: a barrier)."""
    return int(_c.corner_condition(_f8(points), table, _EYE, 0.0, None, None, THREADS)[2])


def near_project(x: np.ndarray, nodes: np.ndarray, active: np.ndarray, hint: np.ndarray, cand: np.ndarray,
                 table: np.ndarray, spheres: np.ndarray, kind: int, tol: float, bump: float) -> None:
    """`jaxci.geometry.near.NearProjector`'s search in C, in place: every node ``nodes[i]`` for ``i`` in `active`
    to the orthogonal projection onto its hint's cell (``cand[i, hint[i]]``) where that falls inside, else to
    the nearest point of its candidates (``hint[i]`` := the column); a candidate whose bounding sphere (`spheres`
    ``(nt, 4)``: centre, radius) comes nearer than the hint's projection is searched too. `kind` 0: triangles
    (`table` ``(nt, 19)``, C order: the transpose of `jaxci.geometry._closest`'s), 1: segments (``(nt, 8)``);
    `tol`, `bump` as `jaxci.geometry._closest`. `x` float64
    ``(n, 3)``, `cand` int32, the other index arrays int64. `THREADS` threads over the active nodes (each node's
    point and hint its own: `active` must not repeat a row, nor `nodes` a node; the same result on any count)."""
    _c.near_project(x, nodes, _i8(active), hint, cand, table, spheres, int(kind), float(tol), float(bump), THREADS)


def lbfgs_direction(g: np.ndarray, S: np.ndarray, Y: np.ndarray, rho: np.ndarray, order: np.ndarray,
                    out: np.ndarray, gamma: float = 1.0, precond=None, inv_scale: np.ndarray | None = None) -> None:
    """``out = -H g``: the L-BFGS two-loop recursion over the pairs ``(S[i], Y[i], rho[i])`` for ``i`` in `order`
    (oldest first; at most 64), in C (`jaxci.optim.host`'s memory). Float64 arrays (`S` and `Y` float64, or both
    float16 with `inv_scale` ``(2, m)``: the pair's vectors are ``S[i] * inv_scale[0, i]`` and ``Y[i] *
    inv_scale[1, i]``), `order` int64. The initial inverse Hessian is ``s.y / y.y`` I of the newest pair, or with
    `precond` (a `jaxci.optim.coarse.CoarseSpace`) ``gamma M``."""
    pc = (None,) * 4 if precond is None else (precond.block, precond.z, precond.coarse_inv, precond.inv_diag)
    _c.lbfgs_direction(g, S, Y, rho, order, out, float(gamma), *pc, inv_scale)


def half_dots(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """``(a.b, a.a, b.b)`` of two float16 vectors, summed in float64 (a pair of the host L-BFGS memory)."""
    return _c.half_dots(a, b)


def coarse_apply(q: np.ndarray, precond) -> np.ndarray:
    """``M q`` of a `jaxci.optim.coarse.CoarseSpace` `precond` for `q` ``(n,)`` (a new float64 array)."""
    out = np.empty(len(q))
    _c.coarse_apply(_f8(q), out, precond.block, precond.z, precond.coarse_inv, precond.inv_diag)
    return out


def untangle_energy(points: np.ndarray, hexes: np.ndarray, inv_len: np.ndarray, eps: float, theta: float,
                    grad: bool, per_node: float) -> tuple[float, float, np.ndarray | None]:
    """``(energy, min det J, gradient or None)`` of `jaxci.optim._untangle_loop.hex_kernel`: the sum of the
    corner energies divided by `per_node`, over the corners of `hexes` ``(N, 8)`` with one over each element's
    reference length `inv_len` ``(N,)`` (`hex_kernel`'s corner table would hold it 8 times). One pass over the
    elements, their eight corners side by side: half the time of a pass over the corner table."""
    x = _f8(points)
    g = np.zeros_like(x) if grad else None
    e, dmin = _c.untangle_energy(x, as_conn(hexes), _f8(inv_len), float(eps), float(theta), g, THREADS)
    if g is not None:
        g *= 1.0 / per_node
    return e / per_node, dmin, g


def local_sums(points: np.ndarray, hexes: np.ndarray, inc: np.ndarray, count: np.ndarray,
               trials: np.ndarray) -> np.ndarray:
    """`jaxci.optim._local.local_terms` in C: ``(M, S)`` sums of (kappa/3)^2 over the corners each node slot
    moves, its first ``count[m]`` star elements, the incidences ``inc[m]`` ``(M, K)`` into `hexes` ``(N, 8)``
    (``8 e + s``: `jaxci.optim._local.node_stars`), with the node at ``trials[m, s]`` ``(M, S, 3)``; inf where a
    corner has det <= 0. `THREADS` threads, each over its own node slots (the same numbers on any count)."""
    trials = _f8(trials)
    out = np.empty(trials.shape[:2])
    _c.local_sums(_f8(points), as_conn(hexes), _ROTATE, _i8(inc), _i8(count), trials, out, THREADS)
    return out


def ci_visit(x: np.ndarray, width: np.ndarray, nodes, hexes, inc, count, basis, free, plane, row, kind, hints,
             tables, p, seed: int, tol: float, bump: float, counter: bool = False) -> int:
    """One cohort run of local CI for every node of one colour, in C, in place on `x` ``(n, 3)`` and `width`
    ``(n,)`` (`jaxci.optim.host_local`; the algorithm of `jaxci.optim.ci`'s colour step): the nodes `nodes`
    ``(M,)`` with their stars as incidences `inc` ``(M, K)`` into `hexes` ``(N, 8)`` (as `local_sums`; the first
    ``count[m]`` real), move bases `basis`
    ``(M, 3, 3)``, free directions `free` ``(M, 3)`` (1 or 0), planar disks `plane` ``(M, 7)``, boundary kind
    `kind` ``(M,)`` (0 interior, 1 surface, 2 edge) and row `row` in the surface or edge list; `hints` the
    remembered cell columns of the surface and edge lists (int64, updated), `tables` their ``(cand, table,
    spheres)`` (`jaxci.geometry.near.NearProjector.native_tables`); `p` the `CIParams`; `seed` the random
    stream's; `counter`: draw from `jaxci.optim._draws`' counter stream instead, `seed` the visit's word (its path
    at the sweep and colour). Returns the number of nodes moved."""
    (cs, ts, ss), (ce, te, se) = tables
    return _c.ci_visit(x, width, nodes, _i8(inc), count, basis, free, plane, row, kind, hints[0], hints[1], cs, ts,
                       ss, ce, te, se, as_conn(hexes), _ROTATE, int(p.cohort), int(p.variations), int(p.attempts),
                       int(round(p.stage_switch * p.attempts)), float(p.reduction), float(p.delta),
                       float(p.init_width), float(p.min_width), float(tol), float(bump), int(seed), THREADS,
                       int(counter))


def layout(cons) -> tuple:
    """The free-coordinate layout of constraints `cons` (`jaxci.geometry.projection.Constraints`) as the C
    functions below take it: ``(interior (ni,), surface (ns,), basis (ns, 2, 3), edge (ne,), tangent (ne, 3))``,
    int32 / float64, contiguous (the constraints' own arrays where they are so; build it once per solve)."""
    return (_i4(cons.interior_nodes), _i4(cons.surface_nodes), _f8(cons.surface_basis), _i4(cons.edge_nodes),
            _f8(cons.edge_tangent))


def lift(x0: np.ndarray, scale: np.ndarray, v: np.ndarray, lay: tuple) -> np.ndarray:
    """``x0 + B (scale * v)`` (`jaxci.optim.parametrisation.lift_points` with numpy): a new float64 ``(n, 3)``;
    `lay` from `layout`, `x0` float64 ``(n, 3)``, `scale` and `v` ``(n_free,)``."""
    return lift_step(x0, scale, v, None, 1.0, lay)[0]


def lift_step(x0: np.ndarray, scale: np.ndarray, v: np.ndarray, d: np.ndarray | None, alpha: float, lay: tuple
              ) -> tuple[np.ndarray, int]:
    """`lift` of the trial point ``d * alpha + v`` (``(n_free,)`` float64 each) without making it: the same
    numbers as ``t = d * alpha; t += v; lift(x0, scale, t, lay)``. Returns ``(x, moved)``, `moved` the number of
    the trial point's entries that differ from `v`'s (`v` itself, and 0, without `d`)."""
    x = np.empty_like(x0)
    moved = _c.lift(x0, scale, _f8(v), *lay, x, None if d is None else _f8(d), float(alpha))
    return x, int(moved)


def lift_t(g: np.ndarray, scale: np.ndarray, lay: tuple, inplace: bool = False) -> np.ndarray:
    """``scale * B^T g`` (`jaxci.optim.parametrisation.lift_transpose_np`): ``(n_free,)`` float64 from the
    gradient `g` ``(n, 3)`` with respect to the node coordinates; `inplace` (g float64, contiguous, its interior
    nodes in ascending order): written over g's first ``n_free`` entries and returned as a view of them, the same
    numbers with no second vector (g is then spent)."""
    if inplace:
        out = g.reshape(-1)[: len(scale)]
        _c.lift_t(g, scale, *lay, out)
        return out
    out = np.empty_like(scale)
    _c.lift_t(_f8(g), scale, *lay, out)
    return out


def lift_slots(lay: tuple, n: int) -> np.ndarray:
    """Each node's first free coordinate in `lay`'s layout (3 per interior node, then 2 per surface node, then 1
    per edge node; -1: none), int32 ``(n,)``: the lifted points' source of `hex_terms_and_grad_lifted` and
    `lift_nodes`."""
    inter, surf, _, edge, _ = lay
    slot = np.full(n, -1, np.int32)
    slot[inter] = 3 * np.arange(len(inter))
    slot[surf] = 3 * len(inter) + 2 * np.arange(len(surf))
    slot[edge] = 3 * len(inter) + 2 * len(surf) + np.arange(len(edge))
    return slot


def _lifted(x0, scale, v, d, alpha, slot, lay) -> tuple:
    """`_c`'s lifted-source arguments."""
    return x0, scale, _f8(v), None if d is None else _f8(d), float(alpha), slot, lay[2], lay[4]


def lift_nodes(x0: np.ndarray, scale: np.ndarray, v: np.ndarray, d: np.ndarray | None, alpha: float,
               slot: np.ndarray, lay: tuple, nodes: np.ndarray) -> tuple[np.ndarray, int]:
    """The coordinates ``(k, 3)`` of `nodes` (int64 ``(k,)``) that `lift` (`lift_step` with `d`) would give, and
    the number of the trial point's entries that differ from `v`'s (0 without `d`); `slot` from `lift_slots`."""
    out = np.empty((len(nodes), 3))
    moved = _c.lift_nodes(*_lifted(x0, scale, v, d, alpha, slot, lay), nodes, out)
    return out, int(moved)


def hex_terms_and_grad_lifted(x0: np.ndarray, scale: np.ndarray, v: np.ndarray, d: np.ndarray | None, alpha: float,
                              slot: np.ndarray, lay: tuple, hexes: np.ndarray) -> tuple[float, float, np.ndarray]:
    """`hex_terms_and_grad` (F) of the points `lift` (`lift_step` with `d`) would give, each read from the free
    coordinates where a corner needs it: the same numbers, without an ``(n, 3)`` array of the points (5 MB at
    216,000 hexahedra while the kernel runs). `slot` from `lift_slots`, `hexes` ``(N, 8)``."""
    args = _lifted(x0, scale, v, d, alpha, slot, lay)
    return _mean_terms_and_grad(x0, hexes.shape[0],
                                lambda w, g: _c.hex_condition_lifted(*args, as_conn(hexes), w, g, THREADS))


def _f_weight(n_hex: int) -> float:
    """The C passes' gradient weight that makes the sum of the corners' term gradients F's: ``2 / (9 * 8 N)``."""
    return 2.0 / (9.0 * (8 * n_hex)) if n_hex else 0.0


def _mean_terms_and_grad(x: np.ndarray, n_hex: int, run) -> tuple[float, float, np.ndarray]:
    """F, max kappa/3 and dF/dx of `n_hex` hexahedra from ``(sum of (term - 1), max term, inverted corners) =
    run(weight, grad)``, a C pass that adds ``weight`` (`_f_weight`) times every corner's term gradient into
    `grad` (zeros like `x`)."""
    n_corners = 8 * n_hex
    grad = np.zeros_like(x)
    s, tmax, bad = run(_f_weight(n_hex), grad)
    f = np.inf if bad else (s / n_corners if n_corners else 0.0)
    return f, (np.inf if bad else float(np.sqrt(tmax))), grad


def flat_keep(x: np.ndarray, nodes: np.ndarray, origin: np.ndarray, r2: np.ndarray, keep: np.ndarray) -> int:
    """``keep[nodes[k]] = |x[nodes[k]] - origin[k]|^2 < r2[k]`` (boolean `keep` ``(n,)``, in place): which
    boundary nodes lie inside their flat regions; returns how many do not."""
    return _c.flat_keep(x, nodes, origin, r2, keep)


def pullback(g: np.ndarray, nodes: np.ndarray, hint: np.ndarray, keep: np.ndarray | None, cand: np.ndarray,
             table: np.ndarray, kind: int) -> None:
    """`jaxci.geometry.near.NearProjector.pullback` for one kind (0 surface nodes and their triangles, 1 edge
    nodes and their segments), in place on `g` float64 ``(n, 3)``: the arrays of the C search
    (`NearProjector`'s: `cand` int32), `keep` boolean ``(n,)`` or None."""
    _c.pullback(g, nodes, hint, keep, cand, table, int(kind))


def greedy_colour(cells: np.ndarray, n: int) -> np.ndarray:
    """The first-fit colouring of nodes ``0 .. n-1`` in index order through the cells `cells` ``(N, k)``
    (`jaxci.geometry.topology.colour_nodes`' colours, in one C pass): int32 ``(n,)``."""
    cells = as_conn(cells)
    out = np.empty(int(n), np.int64)
    _c.greedy_colour(cells, int(n), int(cells.shape[1]), out)
    return out.astype(np.int32)

