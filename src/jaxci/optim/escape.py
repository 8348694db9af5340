"""The default pipeline's escape from a solver's poor minimum: local CI sweeps, then the solver again.

F is not convex, and on a strongly graded mesh a gradient solver can end far above what node-by-node moves reach
from the same start: on Mesquite's cub_fru (10,752 hexahedra) L-BFGS and truncated Newton both stop at F 34.96
(max kappa/3 51.0), where three sweeps of local CI lower F by 55% (local CI alone from the input ends at F 5.21,
max kappa/3 14.3, in 27 s). The solver's end is a minimum for small moves only: a node moved by a good part of
its edge length (a cohort's trial) crosses the barrier a near-flat corner makes.

So, after the solve (`escape`): local CI sweeps (`jaxci.optim.host_local.local_ci_np`: every node tries a cohort
of moves in its free directions and keeps the best where its own elements get better: F never rises), at most
`SWEEPS` (5), ending after the first that lowers F by less than `GAIN` (1%). Where the first does, the solver's
minimum stands: on every other mesh of the real-mesh corpus the first sweep gains at most 0.4% (2026-11-30), and
that sweep is the escape's whole cost (0.05 s at 2,000 hexahedra, 0.2-0.5 s at 25,000). Otherwise the solver
again from the sweeps' end, its result kept where F is lower, up to `GradientParams.escape` rounds. On cub_fru,
the default pipeline with the polish after it: F 5.70, max kappa/3 11.96 in about 4 s cold (four rounds), where it ends
at max kappa/3 29.7 without them (``escape=0``; 2% and 3 sweeps: F 6.01, max kappa/3 14.4; 1% and 3 sweeps: 5.76
and 12.9).

The host engine's sweeps on hexahedral meshes (the C kernels of `jaxci.native`): the default pipeline asks for it
there (`jaxci.interface.methods.auto_pipeline`). Not on the JAX engine: its solve is float32, and the sweeps'
float64 points, rounded to it, can invert a near-flat corner (cub_fru, 2026-11-30: the solve again started at an
infinite F); its default pipeline presmooths (3 smart-Laplace sweeps before truncated Newton) and ends cub_fru's
solve at F 5.83 without it (worst element 15.3 after the polish, in 24 s on a 2-core CPU).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from . import _params as _p
from .ci_params import CIParams
from .host_local import local_ci_np, sweep_colours
from .parametrisation import flat_surface_rings, make_parametrisation

#: The least relative decrease of F by a sweep that goes on sweeping (by the first: that starts a round).
GAIN = 0.01
#: Most sweeps of a round.
SWEEPS = 5


def escape(problem, x: np.ndarray, f: float, rounds: int, solve: Callable):
    """Up to `rounds` rounds of local CI sweeps and `solve` from the solver's result `x` (float64 ``(n, 3)``, F
    `f`) on the host engine's `problem` (a `jaxci.interface.smooth.Problem`); `solve(x0)` runs the solver from the
    points `x0` (on the boundary) and returns ``(x, steps, hist, par)`` as `jaxci.optim.gradient.minimise` with
    its parametrisation. Round r's sweeps draw from seed r.

    **Returns:** ``(x, f, steps, hist, par, report)``: the points and F of the last round's solve (`x` and `f`
    where none ran), the sweeps and solver steps of the rounds run, their history (F and max kappa/3 after each
    sweep and step, concatenated; empty arrays where none ran), the last solve's parametrisation (None where none
    ran) and a report: ``rounds`` (solves run), ``sweeps`` (F before and after each round's first sweep) and
    ``objective`` (F before the first round and after the last).
    """
    mesh = problem.mesh
    cp = _p.make_params(CIParams, {"max_sweeps": SWEEPS, "tol": GAIN}, "ci")
    steps, par = 0, None
    hist = {"objective": np.zeros(0), "max_condition": np.zeros(0)}
    report = {"rounds": 0, "sweeps": [], "objective": [f, f]}
    faces = problem.info.topology.faces
    colours = None
    if rounds:  # for every round; the planar rings are the solve's parametrisation's (kept on `info`)
        rings = flat_surface_rings(np.asarray(problem.cons.x_orig, np.float64), problem.info, problem.cons)
        colours = sweep_colours(mesh.hexes, problem.cons, problem.colour, faces, rings)
    for r in range(rounds):
        xs, k, h = local_ci_np(x, mesh.hexes, problem.cons, problem.colour, faces, cp, seed=r, colours=colours)
        fs = np.asarray(h["objective"], np.float64)
        report["sweeps"].append((f, float(fs[min(k, 1)])))
        if not (k and fs[1] < (1.0 - GAIN) * f):
            break
        xn, n_steps, hn, par_n = solve(np.asarray(xs, np.float64))
        fn = float(np.asarray(hn["objective"], np.float64)[-1])
        steps += k + n_steps
        for key in hist:
            hist[key] = np.concatenate([hist[key], np.asarray(h[key], np.float64)[1: k + 1],
                                        np.asarray(hn[key], np.float64)[1:]])
        report["rounds"] += 1
        if not fn < f:
            break
        x, f, par = np.asarray(xn, np.float64), fn, par_n
        report["objective"][1] = f
    return x, f, steps, hist, par, report


def after_solve(problem, method: str, par, x, steps: int, hist: dict, p, minimise: Callable):
    """`escape` after the solve of `jaxci.optim.gradient.run_gradient` on the host engine (`minimise` its solver,
    `p` its `GradientParams`, `par` the solve's parametrisation): ``(x, steps, hist, par)`` with the rounds' sweeps
    and steps counted and appended to the history (``escape``: its report), and the parametrisation of the last
    round's solve (the polish's scales and flat regions). Nothing where the solve reached the ideal."""
    f, kmax = (float(np.asarray(hist[key], np.float64)[-1]) for key in ("objective", "max_condition"))
    if f <= p.ftol or kmax <= 1.0 + p.ktol:
        return x, steps, hist, par

    def solve(x0):  # (the sweeps' points are on the boundary: the C search of the solver's own projection)
        par_n = make_parametrisation(problem.mesh, problem.info, problem.cons, x0, scaled=p.scaled,
                                     dtype=problem.dtype)
        xn, k, hn, _ = minimise(method, par_n, problem.conn, p)
        return xn, k, hn, par_n

    x, _, k, h, par_n, report = escape(problem, np.asarray(x, np.float64), f, int(p.escape), solve)
    hist = {**hist, "escape": report}
    for key in ("objective", "max_condition"):
        hist[key] = np.concatenate([np.asarray(hist[key], np.float64), h[key]])
    return x, steps + k, hist, par if par_n is None else par_n
