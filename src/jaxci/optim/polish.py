"""The worst-element polish: after L-BFGS on F, lower the worst element level by level, moving only the nodes of
the elements above the level, while F stays as low as the level allows.

A solver's acceptance checks, its time step and its conditioning depend on the WORST element, and F (the mean)
lets a few elements stay bad: on a tet-to-hex sphere L-BFGS on F leaves max kappa/3 2.99 where the p-mean
(p = 4) over the whole mesh reaches 2.19, at 1.7% of the mean element quality. The polish asks, level after
level, for the least F with every element below a level ``tau`` (a lexicographic goal: the worst element first,
then the mean): each round sets ``tau = 1 + gamma (w - 1)`` below the current worst ``w`` and minimises, with
the host L-BFGS (`jaxci.optim.host.lbfgs`, `ROUND_STEPS` steps) over the free nodes of the elements above ``tau``
(every other node fixed, so only the cells around them change),

    (sum_i e_i + MU sum_i max(0, e_i - e_tau)^2) / n_corners,   e_i = (kappa_i/3)^2 - 1,   e_tau = tau^2 - 1

(`jaxci.optim.weighted.penalty_kernel`: F's share of those corners with a quadratic penalty above the level).
A round is kept when the worst element went down, the mean element quality (the mean over the cells of each
cell's worst corner kappa/3, what VTK's per-element condition averages to) stays within `PolishParams.budget`
of the start's (and F at or below `PolishParams.f_limit` where one is given: `jaxci.smooth` gives none, its
final check keeps a result whose F rose above the input's only where the worst element fell,
`jaxci.metrics.guard.worst_first`); after a round that is not kept ``gamma`` moves towards 1 (a smaller
step). Where a round's last iterate is not kept (its worst element rose: the penalty traded it for many corners
above the level, or the mean went over the budget), the accepted iterate of the round's lowest worst corner is
tried in its place, and kept on the same terms, with the smaller step: measured on 13 meshes of the real-mesh
corpus (2026-11-29, in process), the worst element equal or lower on every one (the 25k cylinder 1.2110 ->
1.2103, the small sphere 1.9898 -> 1.9874, the small bracket 2.1567 -> 2.1508), the work within 3% or less.

Before its rounds, the polish lowers the mean element quality itself (its mean phase, `PolishParams.mean_steps`,
`GradientParams.polish_mean_steps`, 100 steps in the default pipeline; `_mean_phase`): the host L-BFGS over every
free node on the sum of each cell's smooth max of its corner terms (power 32, `MEAN_K`), the measure the mean
element quality takes, which F is not: at F's optimum the mean element is above what the nodes can reach (the
small tet-to-hex sphere of the real-mesh corpus 1.566 -> 1.514 in 25 steps, pave3 1.215 -> 1.203). It is kept
where the mean element fell and the worst did not rise; the rounds' budget stays the polish's start's, so what it
took off the mean is room for the worst element. The mean budget is what ends the rounds on most meshes (on pave3
every round not kept was over it; 2026-11-30), and the room moves the worst element down: measured cold on the 24
meshes of the real-mesh comparison (docs/results/bench_realmesh.md), 25 steps against none: the worst element
lower on 15 (pave3 1.9408 -> 1.8791, the small tet-to-hex sphere 1.9914 -> 1.9288, the 25,000-hexahedron bracket
2.1793 -> 2.1172), the same on 8, higher on one (the 25,000-hexahedron annulus 1.1945 -> 1.2047, within the spread
that rounding alone gives these runs), every mean within its bar. 100 steps against 25 (2026-12-01, in process,
23 meshes: Mesquite's pave1, pave2, pave3, pave_cyl and cub_fru, SfePy's matrix_fiber and acoustics, the ANSYS
rotor and 15 gmsh meshes of the real-mesh corpus, 1,610 to 26,744 hexahedra): the worst element lower on 17
(pave3 1.8779 -> 1.8356, the 25k bracket 2.1204 -> 2.0914, cub_fru 3.3432 -> 3.3084, the 25k annulus 1.2049 ->
1.1937, the 16,984 torus 1.8096 -> 1.7949, pave_cyl 1.2926 -> 1.2830), the same on 2 (the rotor and the 25k
cylinder, whose phase is not kept), higher on 4 by 0.02-0.12%, for about 10% more time (200 passes over every
cell); 50 steps raised it on 8 of the 23 (up to +0.73%), 200 on 2 of 14 and were slower.

The polish ends when the steps become negligible (``gamma > GAMMA_END``), the worst element is within
`MIN_EXCESS` of an ideal one, no node of it can move, or its work (kernel passes over cells) reaches
`PolishParams.work`.

Its work bound in the default pipeline is a fixed number of passes a cell (`GradientParams.polish_work`, 1000),
not the solve's steps: a solver that needs fewer steps (truncated Newton) would otherwise get a smaller polish.
Chosen by measurement (2026-11-29, docs/results/bench_solvers.md): unbounded, the polish ended by itself within
1000 passes a cell on every mesh of the real-mesh corpus and pave3 (160 to 1000, 0.2 to 5 s), after L-BFGS or
Newton; a bound of 500 would have left the 25k bracket after L-BFGS at 2.213 where it ends at 2.190.

Chosen by measurement (2026-11-27, in process on the real-mesh corpus of scripts/bench_realmesh.py; worst / mean
element): the descent run to its end reaches pave3 1.786 / 1.2420 from L-BFGS's 2.790 / 1.2159 (p-mean p = 4:
2.026 / 1.3151): the mean's cost is small for the first levels and steep near the best reachable worst element,
hence the budget. A p-mean (p = 16) over the same nodes instead of the penalty reached a similar worst element
at 3% of the mean (it pulls every corner of the region towards the max); the mean restored afterwards by the
penalty at the p-mean's level cost twice the time. The region without a ring of nodes around it and 50 steps a
round took a third of the time of one ring and 100 steps, with the same targets met (docs/results/bench_realmesh.md).

Runs on the host (numpy and the C kernels of `jaxci.native`) whatever the run's engine: each round is a small
sub-problem (the nodes near the worst elements, renumbered into a compact mesh of their cells) of a different
size, which a compiled program would have to be compiled for anew, costing seconds per round against
milliseconds of solving.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cells import element_blocks
from ..geometry.boundary import CORNER, EDGE, INTERIOR, SURFACE
from ..geometry.near import anchored, shared_tables
from ..geometry.projection import Constraints
from ..runtime.phases import stepper
from .host import HostObjective, lbfgs
from .parametrisation import Parametrisation
from .weighted import CellCorners, penalty_kernel

#: The first level's fraction of the worst element's excess (``tau = 1 + gamma (w - 1)``); after a round that
#: misses its level ``gamma <- sqrt(gamma)``, and the polish ends once ``gamma > GAMMA_END``.
GAMMA_START, GAMMA_END = 0.8, 0.995
#: Penalty weight of a corner excess above the level (relative to F's weight 1 per corner).
MU = 1000.0
#: Steps of one round's L-BFGS (a round need not converge: the next level starts from where it ended).
ROUND_STEPS = 50
#: Rounds at most.
MAX_ROUNDS = 40
#: A worst element within this of an ideal one (max kappa/3 <= 1 + MIN_EXCESS) is not polished.
MIN_EXCESS = 1e-3
#: The mean phase's cell measure: each cell's smooth max of its corner terms of power ``2^MEAN_K`` (32), the
#: measure the mean element quality takes (`jaxci.optim.weighted.cell_measure`).
MEAN_K = 5
#: The mean phase's stop (`jaxci.optim.lbfgs.converged` at this rtol and atol: 10 accepted steps in a row that
#: change its objective by less than this of it end it before its steps): where the phase stalls, its last steps
#: are time for nothing (the 24,225-hexahedron O-grid cylinder: 54 of 100 steps, a phase that is not kept there;
#: 2026-12-01, against a stop at 1e-9 on the 23 meshes of the docstring's measurement: the worst element the same
#: on 17, within -0.1% to +0.3% on the others: acoustics +0.2%, cub_fru +0.3%).
MEAN_RTOL = 1e-5
#: The mean phase also ends where, after this many accepted steps, the mean element has not fallen below the start's:
#: on a mesh whose mean F's optimum already holds the phase is not kept, and its steps over every cell were time
#: for nothing (the 24,225-hexahedron O-grid cylinder: 54 steps, 31% of its polish's work; after 15 its mean was
#: 0.01% above the start's). Measured (2026-12-01, in process) on the 23 meshes of the docstring's measurement:
#: the worst and the mean element unchanged on every one, the O-grid cylinder's polish 0.95-1.03 -> 0.61-0.79 s
#: (three runs of each, alternated); checked after 9 steps instead, the 1,610-hexahedron O-grid cylinder's phase
#: (whose mean fell by 0.03% in its 51 steps) ended too, its worst element 1.2536 -> 1.2597.
MEAN_CHECK = 15


@dataclasses.dataclass(frozen=True)
class Rest:
    """The cells the polish does not see (outside a window of the worst cells, `jaxci.optim.polish_window`): none
    of their nodes moves, so their figures stay as they are, and enter the polish's as these sums: `n_cells`,
    `n_corners`, `e_sum` (the sum of their corner excesses ``(kappa/3)^2 - 1``), `k_sum` and `k_max` (the sum and
    the max of each cell's worst corner kappa/3)."""

    n_cells: int = 0
    n_corners: int = 0
    e_sum: float = 0.0
    k_sum: float = 0.0
    k_max: float = 0.0


@dataclasses.dataclass(frozen=True)
class PolishParams:
    """`budget`: the most the mean element quality (the mean over the cells of each cell's worst corner kappa/3)
    may rise above the start's, as a fraction (default 0.01); `work`: the most kernel passes over cells, two per
    sub-problem step, checked before each round (None: no bound; `jaxci.optim.gradient.run_gradient` passes
    `GradientParams.polish_work` times the mesh's cells, 1000 by default, whatever the solver); `f_limit`: F
    (over every corner) must stay at or below this (default: no limit); `cell_k`: what a round keeps low besides
    the penalty (`jaxci.optim.weighted.penalty_kernel`): 0 (default) F's share of its corners, k > 0 each cell's
    smooth max of its corner terms of power 2^k (`GradientParams.polish_cell_power`); `mean_steps`: the steps of
    the mean phase before the rounds (0, the default: none; `GradientParams.polish_mean_steps`)."""

    budget: float = 0.01
    work: float | None = None
    f_limit: float = float("inf")
    cell_k: int = 0
    mean_steps: int = 0


def polish(mesh, cons: Constraints, par: Parametrisation, x: np.ndarray, p: PolishParams = PolishParams(),
           blocks: dict | None = None, rest: Rest | None = None):
    """Polish the worst elements of `mesh` at `x` (see the module docstring).

    **Arguments:** `mesh` the `HexMesh` (the geometry of `cons`; only read for `blocks` where they are not
    given); `cons` its numpy float64 `Constraints`; `par` a numpy `Parametrisation` of `cons` (its scales and
    flat regions are used, not its base); `x` float64 ``(n, 3)`` on the boundary; `p` the `PolishParams`;
    `blocks` the cells by type (default `jaxci.cells.element_blocks` of `mesh`); `rest`: the cells of the mesh
    that `blocks` leaves out, where `blocks`, `cons`, `par` and `x` are a window of it (the nodes of `blocks`
    that are also nodes of cells left out are fixed in `cons`): the worst cell, the mean and F are the whole
    mesh's.

    **Returns:** ``(x, report)``: the polished coordinates (a new array; `x` itself when nothing was kept) and a
    dict: ``rounds``, ``steps``, ``kept`` (rounds kept), ``worst`` and ``mean`` (before, after), ``objective``,
    ``max_condition``, ``element_mean`` and ``work`` (F, max kappa/3, the mean element and the kernel passes over
    cells so far, after each round), ``stopped`` (why it ended), ``limited`` (True where the worst element's
    nodes cannot move at all) and ``mean_phase`` (None without one, else its ``steps``, ``work``, ``kept`` and
    ``worst`` and ``mean`` before and after: `_mean_phase`).
    """
    with shared_tables():  # every round's projector on the mesh's boundary tables: their search data made once
        return _polish(mesh, cons, par, x, p, blocks, rest)


def _polish(mesh, cons: Constraints, par: Parametrisation, x: np.ndarray, p: PolishParams, blocks: dict | None,
            rest: Rest | None):
    blocks = element_blocks(mesh) if blocks is None else blocks
    blocks = {t: np.asarray(c) for t, c in blocks.items() if len(c)}  # (the mesh's int32: no copy)
    rest = Rest() if rest is None else rest
    x = np.array(x, dtype=np.float64)
    cells = CellCorners(blocks)
    terms = cells.terms_all(x)
    worst = cells.cell_worst(x, terms)
    order = list(worst)
    k = np.concatenate([worst[t] for t in order])
    offsets = dict(zip(order, np.cumsum([0] + [len(worst[t]) for t in order])[:-1].tolist(), strict=True))
    n_corners = cells.n_corners + rest.n_corners

    def figures(k):  # the worst cell and the mean cell of the whole mesh, the rest included
        return max(float(k.max()), rest.k_max), (float(k.sum()) + rest.k_sum) / (len(k) + rest.n_cells)

    w0, mean0 = figures(k)
    report = {"rounds": 0, "steps": 0, "kept": 0, "worst": [w0, w0], "mean": [mean0, mean0], "objective": [],
              "max_condition": [], "element_mean": [], "work": [], "stopped": "", "limited": False,
              "mean_phase": None}
    if not np.isfinite(w0) or w0 <= 1.0 + MIN_EXCESS:
        report["stopped"] = "inverted cells" if not np.isfinite(w0) else "worst element within 1e-3 of ideal"
        return x, report
    for t in terms:  # (in place, not before: the terms are not read again)
        t -= 1.0
    e_sum = float(sum(np.sum(t) for t in terms)) + rest.e_sum
    del terms
    # the sub-problems' candidate cells around the nodes' anchors at `x` (`jaxci.geometry.anchors`): the solver may
    # have moved a boundary node beyond its own ring (not where every moving boundary node is inside its flat
    # region: their projection is onto its plane)
    if not par.reach_of(x) < 1.0:
        cons = anchored(cons, x)
    free = np.zeros(len(x), bool)
    for nodes in (cons.interior_nodes, cons.surface_nodes, cons.edge_nodes):
        free[np.asarray(nodes)] = True
    layout = _Layout(cons, par, free)
    gamma, w, mean, work = GAMMA_START, w0, mean0, 0.0
    f_cap = p.f_limit * n_corners * (1.0 - 1e-9)

    def keep_first(sub: _SubProblem, candidates: list, ok) -> int | None:
        """The first of `candidates` (points of `sub`'s nodes) whose worst and mean element pass ``ok(w_new,
        mean_new)`` and whose F stays within `PolishParams.f_limit`, made the polish's points (its figures with
        it; only the cells of `sub` are measured again); its index, or None."""
        nonlocal k, w, mean, e_sum
        old_e = sum(np.sum(a - 1.0) for a in sub.cells.terms_all(x[sub.nodes]))
        for i, y_pts in enumerate(candidates):
            new_terms = sub.cells.terms_all(y_pts)
            new_worst = sub.cells.cell_worst(y_pts, new_terms)
            k_new = k.copy()
            for t, idx in sub.cell_index.items():
                k_new[offsets[t] + idx] = new_worst[t]
            w_new, mean_new = figures(k_new)
            e_new = e_sum + float(sum(np.sum(a - 1.0) for a in new_terms) - old_e)
            if ok(w_new, mean_new) and e_new <= f_cap:
                x[sub.nodes] = y_pts
                k, w, mean, e_sum = k_new, w_new, mean_new, e_new
                for t, idx in sub.cell_index.items():
                    worst[t][idx] = new_worst[t]
                return i
        return None

    if p.mean_steps > 0:  # the mean phase: where kept, the rounds start from there, their budget the start's mean
        sub = _SubProblem(blocks, cons, layout, free, x)
        fun, done = _mean_phase(sub, n_corners, p.mean_steps)
        kept = keep_first(sub, fun.candidates(), lambda w_new, mean_new: mean_new < mean0 and w_new <= w0)
        report["mean_phase"] = {"steps": done, "work": 2.0 * done * sub.n_cells, "kept": kept is not None,
                                "worst": [w0, w], "mean": [mean0, mean]}
        del sub, fun  # (the whole mesh's sub-problem, before the rounds make theirs)
    tick = stepper("worst-element polish", "round")
    while True:
        if report["rounds"] >= MAX_ROUNDS:
            report["stopped"] = f"{MAX_ROUNDS} rounds"
            break
        if gamma > GAMMA_END:
            report["stopped"] = "the worst element stopped improving"
            break
        if p.work is not None and work >= p.work:
            report["stopped"] = "its work bound (kernel passes over cells)"
            break
        level = 1.0 + gamma * (w - 1.0)
        region = np.zeros(len(x), bool)
        for t in order:
            above = worst[t] > level
            region[blocks[t][above].ravel()] = True
        region &= free
        if not region.any():
            report["stopped"] = "the nodes of the worst elements cannot move"
            report["limited"] = report["rounds"] == 0
            break
        sub = _SubProblem(blocks, cons, layout, region, x)
        # (its candidates are the anchored ones of `cons`: the round's small moves keep them, and its nodes, where
        # the solver left them, are at no corner of their cells, so that a projector that follows would make
        # the anchors' tables at every round for nothing: 12% of acoustics_mesh3d's run)
        fun, steps = _solve(sub, n_corners, level * level - 1.0, MU, p.cell_k, ROUND_STEPS, 1e-6)
        report["rounds"] += 1
        report["steps"] += int(steps)
        work += 2.0 * float(steps) * sub.n_cells  # two passes a step (the terms, then the weighted gradient)
        candidates = fun.candidates()
        if not candidates:  # no valid evaluation (cannot happen from a valid start): a smaller step
            gamma = gamma ** 0.5
            _record(report, e_sum / n_corners, w, mean, work)
            continue
        took = keep_first(sub, candidates, lambda w_new, mean_new: (w_new < w * (1.0 - 1e-4)
                                                                    and mean_new <= mean0 * (1.0 + p.budget)))
        if took is not None:
            report["kept"] += 1
        if took != 0:  # the last iterate no better, or too dear: a smaller step (after the lowest, or nothing, kept)
            gamma = gamma ** 0.5
        _record(report, e_sum / n_corners, w, mean, work)
        if tick is not None:
            tick(report["rounds"], e_sum / n_corners, w)
    report["worst"][1], report["mean"][1] = w, mean
    return x, report


def _mean_phase(sub: _SubProblem, n_corners: int, steps: int) -> tuple[_RoundObjective, int]:
    """The polish's mean phase on `sub` (every free node's cells): `steps` steps of the host L-BFGS on the sum of
    each cell's smooth max of its corner terms (`MEAN_K`), the measure the mean element quality takes. F, which the
    solver minimised, is not that measure: its optimum leaves the mean element above what the nodes can reach (the
    small tet-to-hex sphere of the real-mesh corpus: 1.566 -> 1.514 in 25 steps). The rounds' budget stays the
    polish's start's, so that what this phase takes off the mean is room for the worst element. It ends early where
    its mean element has not fallen below the start's after `MEAN_CHECK` accepted steps.

    **Returns:** ``(objective, steps)``: the `_RoundObjective` whose ``candidates()`` the polish keeps the first of
    where the mean element falls, the worst does not rise and F stays within its limit, and the steps taken."""
    def cell_sum(pts):  # the sum of the cells' worst corner kappa/3: n_cells times their mean element
        return float(sum(np.sum(a) for a in sub.cells.cell_worst(pts).values()))

    start = cell_sum(sub.par.x0)

    def stalled(fun: _RoundObjective):  # `lbfgs`' `done`: called at the start, then at each accepted iterate
        calls = 0

        def done(f, k):
            nonlocal calls
            calls += 1
            return calls == MEAN_CHECK + 1 and cell_sum(fun.points_of(fun.best)) >= start
        return done

    return _solve(sub, n_corners, np.inf, 0.0, MEAN_K, steps, MEAN_RTOL, stop=stalled)


def _solve(sub: _SubProblem, n_corners: int, level: float, mu: float, cell_k: int, steps: int,
           tol: float, stop=None) -> tuple[_RoundObjective, int]:
    """Up to `steps` steps of the host L-BFGS (its Cauchy stop at `tol`) from `sub`'s start on
    `jaxci.optim.weighted.penalty_kernel`'s objective (`level`, `mu`, `cell_k`): a round's solve, or the mean
    phase's (no level, no penalty). `stop` (optional): ``stop(objective)`` gives the solver's ``done(F, k)``
    (`jaxci.optim.host.lbfgs`), which may read the objective's accepted iterate. **Returns** ``(objective, steps
    taken)``: the `_RoundObjective`, whose ``candidates()`` the polish measures."""
    fun = _RoundObjective(sub.par, None, n_corners / 32.0,
                          kernel=penalty_kernel(sub.blocks, n_corners, level, mu, cell_k, sub.cells),
                          follow_anchors=False)
    _, done, _, _, _ = lbfgs(fun, np.zeros(sub.par.n_free), limit=steps, max_rejected=20, rtol=tol, atol=tol,
                             history=10, cap=0.5, ftol=0.0, done=None if stop is None else stop(fun))
    return fun, int(done)


def _record(report: dict, f: float, w: float, mean: float, work: float):
    """A round's figures in the polish's report: F, the worst and the mean element, the work so far."""
    for key, v in (("objective", f), ("max_condition", w), ("element_mean", mean), ("work", work)):
        report[key].append(v)


class _RoundObjective(HostObjective):
    """A round's `HostObjective` that also remembers, of the iterates the solver accepted, the one whose cells'
    worst corner is the lowest (the kernel's second figure): the candidates of the round's result."""

    def __post_init__(self):
        super().__post_init__()
        self._lowest = (np.inf, None)

    def accept(self) -> None:
        super().accept()
        if self._last[2][3] < self._lowest[0]:
            self._lowest = (self._last[2][3], self._last[:2])  # (v, points): `points_of` reads no more

    def candidates(self) -> list[np.ndarray]:
        """The points of the last accepted iterate, then (where another) those of the lowest worst corner."""
        last, lowest = self.best, self._lowest[1]
        if last is not None and lowest is not None and lowest[0] is last[0]:  # one evaluation (each has its own v)
            lowest = None
        return [self.points_of(e) for e in (last, lowest) if e is not None]


class _Layout:
    """Where each node's free coordinates sit in the full vector of `cons` (3 per interior node, 2 per surface
    node, 1 per edge node, in that order) and its flat region in `par`: for cutting sub-problems out of it."""

    def __init__(self, cons: Constraints, par: Parametrisation, free: np.ndarray):
        inter, surf, edge = (np.asarray(a, np.int64) for a in (cons.interior_nodes, cons.surface_nodes,
                                                                 cons.edge_nodes))
        n = len(free)
        self.start = np.full(n, -1, np.int64)
        self.start[inter] = 3 * np.arange(len(inter))
        self.start[surf] = 3 * len(inter) + 2 * np.arange(len(surf))
        self.start[edge] = 3 * len(inter) + 2 * len(surf) + np.arange(len(edge))
        self.scale = np.asarray(par.scale, np.float64)
        flat = np.asarray(par.flat_nodes, np.int64)
        self.flat_row = np.full(n, -1, np.int64)
        self.flat_row[flat] = np.arange(len(flat))
        self.flat_origin = np.asarray(par.flat_origin, np.float64)
        self.flat_radius = np.asarray(par.flat_radius, np.float64)


class _SubProblem:
    """The cells with a node in `region` as a compact mesh: their nodes (`nodes`, renumbered ``0 .. m-1``), the
    cells by type in that numbering (`blocks`) and their indices in the mesh's (`cell_index`), and the
    `Parametrisation` that moves the nodes of `region` (every other node of these cells fixed) from `x`."""

    def __init__(self, blocks: dict, cons: Constraints, layout: _Layout, region: np.ndarray, x: np.ndarray):
        touched = {t: np.flatnonzero(region[c].any(axis=1)) for t, c in blocks.items()}
        self.cell_index = {t: i for t, i in touched.items() if len(i)}
        used = np.zeros(len(region), bool)
        for t, i in self.cell_index.items():
            used[blocks[t][i].ravel()] = True
        self.nodes = np.flatnonzero(used)
        # int32, as the kernels take a connectivity (`jaxci.native.as_conn`): an int64 one would be copied by
        # `cells`
        renum = np.full(len(region), -1, np.int32)
        renum[self.nodes] = np.arange(len(self.nodes), dtype=np.int32)
        self.blocks = {t: renum[blocks[t][i]] for t, i in self.cell_index.items()}
        self.n_cells = sum(len(i) for i in self.cell_index.values())
        #: the corners of `blocks`, made once: for the round's penalty kernel, `keep_first` and the mean phase's check
        self.cells = CellCorners(self.blocks)
        # the nodes of `region` keep their class, free coordinates, scales and flat regions; the others are fixed
        nodes = self.nodes
        sub, groups = sub_constraints(x[nodes], np.asarray(cons.node_class)[nodes], region[nodes],
                                      np.asarray(cons.group)[nodes], np.asarray(cons.row)[nodes], cons)
        self.par = sub_parametrisation(sub, groups, x[nodes], layout.start[nodes], layout.flat_row[nodes],
                                       lambda coords, rows: (layout.scale[coords], layout.flat_origin[rows],
                                                             layout.flat_radius[rows]))


def sub_parametrisation(sub: Constraints, groups: dict, xs: np.ndarray, start: np.ndarray, flat_row: np.ndarray,
                        gather) -> Parametrisation:
    """The numpy float64 `Parametrisation` of a compact sub-problem (`sub_constraints`' `sub` and `groups`, its
    nodes at `xs`), its free coordinates in the same layout (interior 3 each, surface 2, edge 1): each node's
    scales and flat region are the whole problem's, read by ``gather(coords, rows) -> (scale, origin, radius)``
    at its first free coordinate `start` and its flat region's row `flat_row` (-1: none, radius 0)."""
    coords = np.concatenate([(start[groups[INTERIOR]][:, None] + np.arange(3)).ravel(),
                             (start[groups[SURFACE]][:, None] + np.arange(2)).ravel(), start[groups[EDGE]]])
    flat_nodes = np.concatenate([groups[SURFACE], groups[EDGE]])
    rows = flat_row[flat_nodes]
    scale, origin, radius = gather(coords, np.maximum(rows, 0))
    radius = np.where(rows >= 0, radius, 0.0).astype(np.float64)
    return Parametrisation(
        cons=sub,
        x0=np.ascontiguousarray(xs, np.float64),
        scale=np.ascontiguousarray(scale, np.float64),
        flat_nodes=flat_nodes.astype(np.int32),
        flat_origin=np.ascontiguousarray(np.where(rows[:, None] >= 0, origin, xs[flat_nodes]), np.float64),
        flat_radius=radius,
        shortcut=bool(len(flat_nodes)) and bool(np.all(radius > 0)),
    )


def sub_constraints(xs: np.ndarray, cls: np.ndarray, moving: np.ndarray, group: np.ndarray, row: np.ndarray,
                    tables) -> tuple[Constraints, dict]:
    """The `Constraints` of a compact sub-problem on k nodes and its nodes by class (class -> indices, ``0 .. k-1``).

    `xs` ``(k, 3)`` the nodes' coordinates; `cls`, `group`, `row` ``(k,)`` their class, group and row in `tables`
    (numpy float64 `Constraints`, or `jaxci.geometry.tables.BoundaryTables`: the surface and edge rows, triangles
    and segments the sub-problem takes); the nodes not `moving` become corners, fixed at `xs`."""
    sub_cls = np.where(moving, cls, CORNER).astype(np.int32)
    groups = {c: np.flatnonzero(sub_cls == c) for c in (INTERIOR, SURFACE, EDGE, CORNER)}
    s_rows, e_rows = row[groups[SURFACE]], row[groups[EDGE]]
    row_new = np.zeros(len(sub_cls), np.int32)
    row_new[groups[SURFACE]] = np.arange(len(s_rows))
    row_new[groups[EDGE]] = np.arange(len(e_rows))
    f64 = np.float64
    s_cand, e_cand = np.asarray(tables.surface_cand), np.asarray(tables.edge_cand)
    sub = Constraints(
        x_orig=np.ascontiguousarray(xs, f64),
        node_class=sub_cls,
        group=np.where((sub_cls == SURFACE) | (sub_cls == EDGE), group, -1).astype(np.int32),
        row=row_new,
        interior_nodes=groups[INTERIOR].astype(np.int32),
        surface_nodes=groups[SURFACE].astype(np.int32),
        edge_nodes=groups[EDGE].astype(np.int32),
        corner_nodes=groups[CORNER].astype(np.int32),
        surface_basis=np.asarray(tables.surface_basis, f64)[s_rows],
        edge_tangent=np.asarray(tables.edge_tangent, f64)[e_rows],
        surface_cand=s_cand[s_rows] if len(s_rows) else s_cand[:1],
        edge_cand=e_cand[e_rows] if len(e_rows) else e_cand[:1],
        triangles=np.asarray(tables.triangles, f64),
        triangle_patch=np.asarray(tables.triangle_patch),
        segments=np.asarray(tables.segments, f64),
        segment_curve=np.asarray(tables.segment_curve),
    )
    return sub, groups
