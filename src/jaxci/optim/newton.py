"""Truncated Newton (line-search Newton-CG): fewer iterations than L-BFGS, each dearer. `newton_cg` runs it on the
host (numpy and the C kernels), `newton_loop` on the JAX engine (one compiled program, one device); their rules
are written once (`forcing`, `positive_curvature`, `curvature_scale`, `damping`, with `jaxci.optim.lbfgs`'s
search and stops) and their Hessian-vector products are the same difference (`newton_loop`'s docstring says
what differs). Two loops stay, for their loop primitive: a Python loop with early exits around the C kernel and
the host projector's remembered triangles, and `jax.lax.while_loop`s.

An outer iteration at the iterate ``v`` (gradient ``g`` of the scaled objective ``s F``) solves the Newton system
``H d = -g`` approximately by preconditioned conjugate gradients (`pcg`) and searches along ``d`` as the host
L-BFGS does (the trial capped at ``max_move`` in the max norm, the backtracking Armijo search of
`jaxci.optim.lbfgs`, an inverted element is F = inf and so a rejected trial). ``H`` is never formed: each
Hessian-vector product is a forward difference of the closed-form gradient (`jaxci.optim.host.HostObjective.hvp`:
``(g(v + h p) - g(v)) / h``, one gradient evaluation, the C kernel of `jaxci.native`, the boundary nodes held on the
triangles of the iterate's projection, whose kinks a plain difference would pick up).

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

from ..runtime._lazy import jax, jit, jnp
from ..runtime.phases import stepper
from ..runtime.transfer import program
from .coarse import coarse_apply
from .host import amax, dot
from .lbfgs import DECREASE, armijo, cap_factor, converged, settled

#: CG products per outer iteration at most, and the largest forcing term.
CG_MAX = 20
ETA_MAX = 0.5
#: The damping ``mu``: its least value once on, and its factor per line search (down after a full step, up per
#: halving of the step, at most three).
MU_MIN, MU_FACTOR = 1e-2, 4.0
#: The forward-difference step of a Hessian-vector product, in the unknowns' units (local edge lengths), for the
#: largest entry of the direction.
FD_STEP = 1e-6


def forcing(gn, g0, xp=np):
    """The forcing term ``eta = min(ETA_MAX, sqrt(|g| / |g_0|))`` of the gradient norm `gn` against the first's
    `g0`: CG stops at ``|r| <= eta |g|``."""
    return xp.minimum(ETA_MAX, xp.sqrt(gn / g0))


def positive_curvature(php, pp):
    """Whether a CG direction ``p`` has clearly positive curvature, ``p.Hp > 1e-14 p.p`` (a NaN fails)."""
    return php > 1e-14 * pp


def curvature_scale(php, pdp, xp=np):
    """The damping's scale ``c = p.Hp / p.Dp`` of an iteration's first product (0 where either is not positive)."""
    return xp.where((php > 0) & (pdp > 0), php / xp.where(pdp > 0, pdp, 1.0), 0.0)


def damping(mu, rejected, xp=np):
    """``mu`` after a line search that halved the step `rejected` times: divided by `MU_FACTOR` after a full step,
    else at least `MU_MIN` times `MU_FACTOR` per halving (at most three); 0 once below ``MU_MIN / MU_FACTOR``."""
    mu = xp.where(rejected == 0, mu / MU_FACTOR, xp.maximum(mu, MU_MIN) * MU_FACTOR ** xp.minimum(rejected, 3))
    return xp.where(mu < MU_MIN / MU_FACTOR, 0.0, mu)


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
        if php is None or not positive_curvature(php, vdot(p, p)):
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


def newton_cg(fun: Callable, y0: np.ndarray | None, *, limit: int, max_rejected: int, rtol: float, atol: float,
              cap: float, ftol: float, done: Callable | None = None, precond: Callable | None = None,
              cg_max: int = CG_MAX):
    """Minimise `fun` (``value, grad, F, k = fun(y)``, a `jaxci.optim.host.HostObjective`) from `y0` by truncated
    Newton (the module docstring). Arguments as `jaxci.optim.host.lbfgs` (`y0` None: zeros; no deadline; its steps
    reported as stage ``"Newton-CG"``; `precond`: a function returning the fixed preconditioner ``M``, called once at
    the start; None: the identity), plus `cg_max` products per outer iteration.

    **Returns:** ``(y_best, steps, result, hist_f, hist_k, outer)``: as `jaxci.optim.host.lbfgs` (steps: gradient
    evaluations, products and trials alike; histories one entry per step, F and max kappa/3 of the accepted
    iterate), and the outer (Newton) iterations.
    """
    def finished(f, k):
        return f <= ftol or (done is not None and bool(done(f, k)))

    if hasattr(fun, "keep_raw"):  # `jaxci.optim.host.HostObjective`: its `hvp` needs the raw node gradient
        fun.keep_raw = True
    y = np.zeros(fun.par.n_free) if y0 is None else np.array(y0, dtype=np.float64)
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
        out = fun.hvp(p, FD_STEP)  # H p at the accepted iterate; None where the step inverts an element
        steps += 1
        record()
        if out is not None:
            if c is None:
                c = float(curvature_scale(dot(p, out), dot(p, diag * p)))
            if mu > 0 and c > 0:
                out = out + (mu * c) * (diag * p)
        return out

    while not stop and steps < limit:
        gn = float(np.sqrt(dot(g, g)))
        eta = float(forcing(gn, g0))
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
                done_here = bool(converged(amax(y_try - y), amax(y_try), v_try, value, rtol, atol)) or bool(
                    settled(v_try, value, rtol, atol))
                y, value, g, f, k = y_try, v_try, g_try, f_try, k_try
                accept()
                record()
                mu = float(damping(mu, rejected))
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


@program
@jit(static_argnames=("objective", "hessian", "static", "max_steps", "max_rejected", "cg_max"))
def newton_loop(objective, hessian, args, conn, weight, y0, consts, limit, precond=None, *, static: tuple = (),
                max_steps: int, max_rejected: int, cg_max: int = CG_MAX):
    """Truncated Newton on the JAX engine, one device: `newton_cg`'s iteration as one compiled program.

    The same forcing term, damping, line search and stops as `newton_cg` (`forcing`, `positive_curvature`,
    `curvature_scale`, `damping`; `jaxci.optim.lbfgs`'s `armijo`, `cap_factor`, `converged`) and the same
    Hessian-vector product (`hessian`: a forward difference of the node gradient, the projection linearised at
    the iterate) and preconditioner (`precond`: the two-level M of `jaxci.optim.coarse`, built on the host, applied
    by `jaxci.optim.coarse.coarse_apply`; None: the identity, ``D = I`` in the damping). One thing differs, for the
    engine: the node gradient at the iterate, which the host keeps from its evaluation, is evaluated again once a
    Newton iteration (a step of its own). Each product and each trial is a step, as in `newton_cg`.

    **Arguments:** as `jaxci.optim.lbfgs.lbfgs_loop` on one device: `objective` (static) ``objective(v, args,
    conn, weight, 1, platform, *static) -> (value, gradient, F, k)``
    (`jaxci.optim.solver_objective.value_and_grad_closed`); `hessian` (static) ``hessian(v, args, conn, weight,
    *static, step=h) -> (p -> H p)`` (`jaxci.optim.solver_objective.hessian_closed`); `args`, `conn` ``(8, N)``,
    `weight` ``(N,)``, `y0` ``(n,)``, `consts` ``(5,)`` (``ftol, 1 + ktol, rtol, atol, cap``), `limit` (traced,
    at most `max_steps`); `precond`: None or `jaxci.optim.coarse.CoarseSpace.arrays` (device arrays over the
    vector `y0` is); `max_rejected` and `cg_max` (static) as `newton_cg`'s. The difference's step is `FD_STEP` in
    float64 and ``sqrt(eps)`` in float32.

    **Returns:** ``(y, steps, result, hist_f, hist_k, outer)``: those of `lbfgs_loop` and the Newton iterations.
    """
    platform = jax.default_backend()

    def fn(v):
        return objective(v, args, conn, weight, 1, platform, *static)

    ftol, kstop, rtol, atol, cap = (consts[i] for i in range(5))
    dtype = y0.dtype
    limit = jnp.minimum(jnp.asarray(limit, jnp.int32), max_steps)

    def norm(a):
        return jnp.sqrt(jnp.dot(a, a))

    def m(r):  # the preconditioner M
        return r if precond is None else coarse_apply(precond, r, jnp)

    diag = 1.0 if precond is None else 1.0 / precond[3]  # D: the Laplacian's diagonal that M inverts, else I

    def finished(f, k):
        return (f <= ftol) | (k <= kstop)

    def record(it, steps):  # F and k of the accepted iterate after step `steps`
        return dict(it, steps=steps, hf=it["hf"].at[steps].set(it["f"]), hk=it["hk"].at[steps].set(it["k"]))

    value, g, f, k = fn(y0)
    ok = jnp.isfinite(value)
    g0 = norm(g)
    g0 = jnp.where(g0 > 0, g0, 1.0)
    nan = jnp.full((max_steps + 1,), jnp.nan, dtype)
    it = dict(y=y0, g=g, value=value, f=f, k=k, mu=jnp.zeros((), dtype), steps=jnp.int32(0), outer=jnp.int32(0),
              stop=~ok | finished(f, k), hf=nan.at[0].set(f), hk=nan.at[0].set(k))

    def cg(it):
        """``(H + mu c D) d = -g`` by preconditioned CG from ``d = 0`` (`pcg`): the direction and the loop
        state."""
        y, g = it["y"], it["g"]
        gn = norm(g)
        tol = forcing(gn, g0, jnp) * gn
        step = max(FD_STEP, float(np.sqrt(np.finfo(dtype).eps)))
        hvp = hessian(y, args, conn, weight, *static, step=step)
        it = record(it, it["steps"] + 1)  # the node gradient at y

        def body(c):
            p = c["p"]
            hp = hvp(p)
            scale = jnp.where(c["j"] == 0, curvature_scale(jnp.dot(p, hp), jnp.dot(p, diag * p), jnp), c["scale"])
            hp = jnp.where((it["mu"] > 0) & (scale > 0), hp + (it["mu"] * scale) * (diag * p), hp)
            php = jnp.dot(p, hp)
            bad = ~positive_curvature(php, jnp.dot(p, p))
            a = c["rz"] / jnp.where(bad, 1.0, php)
            d = jnp.where(bad, jnp.where(c["j"] == 0, p, c["d"]), c["d"] + a * p)
            r = c["r"] + a * hp
            z = m(r)
            rz = jnp.dot(r, z)
            j = c["j"] + 1
            done = bad | (norm(r) <= tol) | (j >= cg_max) | (c["it"]["steps"] + 1 >= limit)
            return dict(c, d=d, r=r, p=-z + (rz / c["rz"]) * p, rz=rz, j=j, scale=scale, done=done,
                        it=record(c["it"], c["it"]["steps"] + 1))

        z = m(g)
        c = dict(d=jnp.zeros_like(g), r=g, p=-z, rz=jnp.dot(g, z), j=jnp.int32(0), scale=jnp.zeros((), dtype),
                 done=it["steps"] >= limit, it=it)
        c = jax.lax.while_loop(lambda c: ~c["done"], body, c)
        return c["d"], c["it"]

    def search(it, d):
        """The capped backtracking Armijo search along `d` (`newton_cg`'s), then the damping's update."""
        d = jnp.where(jnp.dot(it["g"], d) < 0, d, -m(it["g"]))  # rounding, or no product: steepest descent
        d = d * cap_factor(jnp.max(jnp.abs(d)), cap, jnp)
        slope = jnp.dot(it["g"], d)

        def body(s):
            it, alpha, rejected = s["it"], s["alpha"], s["rejected"]
            y_try = it["y"] + alpha * d
            v_try, g_try, f_try, k_try = fn(y_try)
            good = jnp.isfinite(v_try) & armijo(v_try, it["value"], alpha, slope)
            done_here = converged(jnp.max(jnp.abs(y_try - it["y"])), jnp.max(jnp.abs(y_try)), v_try, it["value"],
                                  rtol, atol) | settled(v_try, it["value"], rtol, atol)
            new = dict(it, y=y_try, g=g_try, value=v_try, f=f_try, k=k_try, mu=damping(it["mu"], rejected, jnp),
                       stop=done_here | finished(f_try, k_try))
            it = jax.tree.map(lambda a, b: jnp.where(good, a, b), new, it)
            rejected = jnp.where(good, rejected, rejected + 1)
            it = dict(it, stop=it["stop"] | (rejected >= max_rejected))
            return dict(it=record(it, it["steps"] + 1), alpha=jnp.where(good, alpha, alpha * DECREASE),
                        rejected=rejected, done=good)

        s = dict(it=it, alpha=jnp.ones((), dtype), rejected=jnp.int32(0), done=jnp.bool_(False))
        s = jax.lax.while_loop(lambda s: ~s["done"] & ~s["it"]["stop"] & (s["it"]["steps"] < limit), body, s)
        return s["it"]

    def outer(it):
        d, it = cg(it)
        it = search(dict(it, outer=it["outer"] + 1), d)
        return it

    it = jax.lax.while_loop(lambda it: ~it["stop"] & (it["steps"] < limit), outer, it)
    code = jnp.where(~ok, 2, jnp.where(it["stop"], 0, 1)).astype(jnp.int32)
    return it["y"], it["steps"], code, it["hf"], it["hk"], it["outer"]
