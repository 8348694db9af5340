"""Truncated Newton (line-search Newton-CG) on the host: fewer iterations than L-BFGS, each dearer.

An outer iteration at the iterate ``v`` (gradient ``g`` of the scaled objective ``s F``) solves the Newton system
``H d = -g`` approximately by preconditioned conjugate gradients (`pcg`) and searches along ``d`` as the host
L-BFGS does (the trial capped at ``max_move`` in the max norm, the backtracking Armijo search of
`jaxci.optim.lbfgs`, an inverted element is F = inf and so a rejected trial). ``H`` is never formed: each
Hessian-vector product is a forward difference of the closed-form gradient (`hvp`: ``(g(v + h p) - g(v)) / h``,
one gradient evaluation, the C kernel of `jaxci.native`; `jaxci.optim.host.HostObjective.hvp` holds the boundary
nodes on the triangles of the iterate's projection, whose kinks a plain difference would pick up).

- **Forcing term**: CG stops once ``|r| <= eta |g|`` with ``eta = min(ETA_MAX, sqrt(|g| / |g_0|))`` (Eisenstat-
  Walker's choice 2 in the ratio to the first gradient: the objective's scale is the mesh's), or after `cg_max`
  products, or at a direction of non-positive curvature (then the CG iterate so far, or ``-M g`` at the first
  product: always a descent direction, ``M`` being symmetric positive definite).
- **Damping**: CG runs on ``H + mu c D`` (``D`` the diagonal of the Laplacian that ``M`` inverts, else I; ``c``
  the curvature ``p.Hp / p.Dp`` of the iteration's first product, so ``mu`` has no units): ``mu`` starts at 0, is
  divided by `MU_FACTOR` after a full step and multiplied by it per halving of a backtracked one (from `MU_MIN`),
  a Levenberg-Marquardt rule in place of a trust region. Undamped, the 1610-hex cylinder O-grid took 1213 gradient
  evaluations (the line search halving the step up to 14 times an iteration), damped 181.
- **Preconditioner** ``M``: the two-level Laplacian of `jaxci.optim.coarse` from the first step
  (``GradientParams.precondition`` ``"auto"`` or ``"coarse"``) or none (``"none"``), fixed for the run.
- **Stops**, the host L-BFGS's: F <= ftol, ``done(F, k)`` (max kappa/3 <= 1 + ktol), the Cauchy test of an
  accepted step (`jaxci.optim.lbfgs.converged`), `max_rejected` consecutive rejected trials, the step limit; and
  the Cauchy test's objective half alone (an outer iteration that lowers ``s F`` by less than ``atol + rtol |s
  F|``): along a wall the nodes keep sliding by more than the step half allows while F no longer changes (the
  small tet-to-hex sphere, before the damping, `cg_max` 50: the 2000-step limit without it, 787 steps with it, F
  within 2e-6). Every
  gradient evaluation is a step (a product as much as a trial), so the limit and the histories count the real
  cost.

Measured against L-BFGS on the real-mesh corpus, alone and in the default pipeline: docs/results/bench_solvers.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..runtime.phases import stepper
from .host import amax, dot
from .lbfgs import DECREASE, armijo, cap_factor, converged

#: CG products per outer iteration at most, and the largest forcing term.
CG_MAX = 20
ETA_MAX = 0.5
#: The damping ``mu``: its least value once on, and its factor per line search (down after a full step, up per
#: halving of the step, at most three).
MU_MIN, MU_FACTOR = 1e-2, 4.0
#: The forward-difference step of a Hessian-vector product, in the unknowns' units (local edge lengths), for the
#: largest entry of the direction.
FD_STEP = 1e-6


def pcg(hvp: Callable, precond: Callable | None, g, tol: float, max_iter: int):
    """Approximately solve ``H d = -g`` by preconditioned CG from ``d = 0``: ``(d, products, reason)``.

    `hvp(p)` returns ``H p`` or None (not computable: treated as negative curvature); `precond(r)` ``M r`` (None:
    the identity). Stops at ``|r| <= tol`` (``"converged"``), after `max_iter` products (``"max_iter"``), or
    when ``p.Hp <= 0`` (``"curvature"``; at the first product ``d = -M g``, a descent direction).
    """
    def vdot(a, b):
        return float(np.einsum("i,i->", a, b))

    def m(r):
        return r if precond is None else precond(r)

    r = g
    z = m(r)
    p = -z
    rz = vdot(r, z)
    d = np.zeros_like(g)
    for j in range(max_iter):
        hp = hvp(p)
        php = None if hp is None else vdot(p, hp)
        if php is None or not php > 1e-14 * vdot(p, p):
            return (p if j == 0 else d), j + 1, "curvature"
        a = rz / php
        d = d + a * p
        r = r + a * hp
        if float(np.sqrt(vdot(r, r))) <= tol:
            return d, j + 1, "converged"
        z = m(r)
        rz_new = vdot(r, z)
        p = -z + (rz_new / rz) * p
        rz = rz_new
    return d, max_iter, "max_iter"


def hvp(fun: Callable, y: np.ndarray, g: np.ndarray, p: np.ndarray, step: float = FD_STEP):
    """``H p`` at the accepted iterate `y` (gradient `g`) by a forward difference of the gradient, one evaluation:
    `fun`'s own ``fun.hvp(p, step)`` where it has one (`jaxci.optim.host.HostObjective.hvp`: the boundary's
    projection linearised), else ``(grad(y + h p) - g) / h`` (the evaluation not accepted); None where the step
    inverts an element."""
    if hasattr(fun, "hvp"):
        return fun.hvp(p, step)
    size = amax(p)
    if size == 0:
        return np.zeros_like(p)
    h = step / size
    _, g_h, _, _ = fun(y + h * p)
    if g_h is None:
        return None
    g_h -= g
    g_h *= 1.0 / h
    return g_h


def newton_cg(fun: Callable, y0: np.ndarray, *, limit: int, max_rejected: int, rtol: float, atol: float,
              cap: float, ftol: float, done: Callable | None = None, precond: Callable | None = None,
              cg_max: int = CG_MAX):
    """Minimise `fun` (``value, grad, F, k = fun(y)``, a `jaxci.optim.host.HostObjective`) from `y0` by truncated
    Newton (the module docstring). Arguments as `jaxci.optim.host.lbfgs` (no deadline; its steps reported as stage
    ``"Newton-CG"``; `precond`: a function returning the fixed preconditioner ``M``, called once at the start; None:
    the identity), plus `cg_max` products per outer iteration.

    **Returns:** ``(y_best, steps, result, hist_f, hist_k, outer)``: as `jaxci.optim.host.lbfgs` (steps: gradient
    evaluations, products and trials alike; histories one entry per step, F and max kappa/3 of the accepted
    iterate), and the outer (Newton) iterations.
    """
    def finished(f, k):
        return f <= ftol or (done is not None and bool(done(f, k)))

    if hasattr(fun, "keep_raw"):  # `jaxci.optim.host.HostObjective`: its `hvp` needs the raw node gradient
        fun.keep_raw = True
    y = np.array(y0, dtype=np.float64)
    value, g, f, k = fun(y)
    accept = getattr(fun, "accept", lambda: None)
    hf, hk = [f], [k]
    if g is None:
        return y, 0, "nonfinite", np.asarray(hf), np.asarray(hk), 0
    accept()
    m = precond() if precond is not None else None
    steps, outer, result = 0, 0, "nonlinear_max_steps_reached"
    stop = finished(f, k)
    g0 = float(np.sqrt(dot(g, g))) or 1.0
    tick = stepper("Newton-CG")

    def small(change, v):  # below the Cauchy test's tolerance on the objective
        return abs(change) < atol + rtol * abs(v)

    def record():
        hf.append(f)
        hk.append(k)
        if tick is not None:
            tick(steps, f, k)

    # the damping: products of H + mu c D, D the Laplacian's diagonal (M's, else I) and c the curvature p.Hp / p.Dp
    # of the iteration's first product, mu raised after a line search that backtracked and lowered after a full step
    diag = 1.0 / m.inv_diag if m is not None and hasattr(m, "inv_diag") else np.ones_like(y)
    mu, c = 0.0, None

    def product(p):
        nonlocal steps, c
        if steps >= limit:
            return None
        out = hvp(fun, y, g, p)
        steps += 1
        record()
        if out is not None:
            if c is None:
                php, pdp = dot(p, out), dot(p, diag * p)
                c = php / pdp if php > 0 and pdp > 0 else 0.0
            if mu > 0 and c > 0:
                out = out + (mu * c) * (diag * p)
        return out

    while not stop and steps < limit:
        gn = float(np.sqrt(dot(g, g)))
        eta = min(ETA_MAX, float(np.sqrt(gn / g0)))
        c = None
        d, _, _ = pcg(product, m, g, eta * gn, cg_max)
        if not dot(g, d) < 0:  # rounding, or a product past the limit at the first one: steepest descent
            d = -g if m is None else -m(g)
        d = d * float(cap_factor(amax(d), cap or 0.0))
        slope = dot(g, d)
        outer += 1
        alpha, rejected = 1.0, 0
        while steps < limit:
            y_try = y + alpha * d
            v_try, g_try, f_try, k_try = fun(y_try)
            steps += 1
            if g_try is not None and armijo(v_try, value, alpha, slope):
                # the Cauchy test, or its objective half alone: a Newton iteration that gains less is the last
                done_here = bool(converged(amax(y_try - y), amax(y_try), v_try, value, rtol, atol)) or small(
                    value - v_try, v_try)
                y, value, g, f, k = y_try, v_try, g_try, f_try, k_try
                accept()
                record()
                mu = mu / MU_FACTOR if rejected == 0 else max(mu, MU_MIN) * MU_FACTOR ** min(rejected, 3)
                mu = 0.0 if mu < MU_MIN / MU_FACTOR else mu
                if done_here:
                    result, stop = "successful", True
                stop = stop or finished(f, k)
                break
            record()
            alpha *= DECREASE
            rejected += 1
            if rejected >= max_rejected:
                stop = True
                break
    if stop and result == "nonlinear_max_steps_reached":
        result = "successful"
    return y, steps, result, np.asarray(hf, np.float64), np.asarray(hk, np.float64), outer
