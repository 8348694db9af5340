"""An escape from a solver's poor minimum: local CI sweeps, then the solver again (``escape=N``; off by default).

F is not convex, and a gradient solver can end far above what node-by-node moves reach from the same start: a
minimum for small moves only. Mesquite's cub_fru (10,752 hexahedra) was the case: L-BFGS stopped at F 34.96 (max
kappa/3 51.0), where three sweeps of local CI lowered F by 55%. Its cause was not F: each boundary node projected
onto the cells around where it started, and the graded mesh's best shape has boundary nodes further away than that.
Now the candidate cells follow their nodes (`jaxci.geometry.anchors`), and the solver alone ends there at F 4.37
(`--method lbfgs`, max kappa/3 5.87, 2026-11-30), against the four escape rounds' 5.70. No mesh of the real-mesh
corpus needs the escape any more, and the default pipeline asks for none (`jaxci.interface.methods.AUTO_ESCAPE`).

`escape`: local CI sweeps (`jaxci.optim.host_local.local_ci_np`: every node tries a cohort of moves in its free
directions and keeps the best where its own elements get better: F never rises), at most `SWEEPS` (5), ending
after the first that lowers F by less than `GAIN` (1%). Where the first does, the solver's minimum stands, and that
sweep is the escape's whole cost (0.05 s at 2,000 hexahedra, 0.2-0.5 s at 25,000). Otherwise the solver again from
the sweeps' end, its result kept where F is lower, up to `GradientParams.escape` rounds.

The host engine's sweeps on hexahedral meshes (the C kernels of `jaxci.native`). Not on the JAX engine: its solve
is float32, and the sweeps' float64 points, rounded to it, can invert a near-flat corner (cub_fru, 2026-11-30: the
solve again started at an infinite F).
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
