"""L-BFGS: its rules written once for every loop, and the JAX engine's compiled loop (one device or sharded).

**The rules** (`SLOPE`, `DECREASE`, `cap_factor`, `armijo`, `converged`, `curvature_ok`), over the array module
(numpy floats or jax.numpy arrays), are those of every L-BFGS loop jaxci runs: the host engine's
(`jaxci.optim.host.lbfgs`, also the untangler's rounds on the host), the JAX engine's (`lbfgs_loop`, one device or
sharded) and the compiled untangler's (`jaxci.optim._untangle_loop`). An iteration: the two-loop L-BFGS direction
(initial inverse Hessian ``s.y / y.y`` I of the newest pair; a pair whose curvature is not clearly positive,
`curvature_ok`, is not stored; the memory forgotten when the direction is not one of descent), each trial capped at
``max_move`` in the max norm (`cap_factor`), a backtracking Armijo search (`armijo`: slope `SLOPE`, the step times
`DECREASE` on rejection, step 1 again after an accepted one), the Cauchy stop at accepted iterates (`converged`: the
largest change of an unknown below ``atol + rtol`` times the largest unknown, AND the change of the objective below
``atol + rtol |f|``; or a change of the objective below ``rtol |f|`` at `SETTLED_RUN` accepted steps in a row, where
the iterate drifts along a valley of F), the stop at ``F <= ftol`` or max kappa/3 <= 1 + ktol, `max_rejected`
consecutive rejections and the step limit. Every objective evaluation is a step. (optimistix's Cauchy test takes the
ratio per unknown; jaxci's unknowns start at 0 in units of the local edge length, where that ratio would ask every
unknown, even one that barely moves, to settle to ``atol``.) Two copies of the loop stay, for their loop primitive
and memory: the host's runs in Python with the C two-loop recursion and an optional coarse preconditioner;
`lbfgs_loop` is one `jax.lax.while_loop` whose recursion runs on Gram matrices (below).

**`lbfgs_loop`** runs the JAX engine's L-BFGS (`jaxci.optim.gradient.minimise`, ``"lbfgs"``): on one device
(``mesh`` None) as one compiled program, or inside one `jax.shard_map` over the devices of a
`jax.sharding.Mesh`, where:

- the elements (the connectivity and weights, sharded by `jaxci.optim.sharding.place_problem`) are split: each
  device evaluates F, its max and its gradient over its own elements, and ONE all-reduce per trial gives every
  device the whole mesh's (`jaxci.optim.sharding.local_terms_and_grad`);
- the L-BFGS memory, ``m`` pairs ``(s, y)`` stored as one ``(2m, n/D)`` block per device (its share of the free
  coordinates), is split too. The two-loop recursion needs, at each accepted step, the dot products of the new
  pair and of the gradient with the memory: each device takes them over its share and ONE all-reduce of ``6m +
  5`` numbers sums them; the recursion then runs on ``m x m`` Gram matrices kept up to date (``S^T Y``, ``Y^T
  Y``), the same arithmetic as the two-loop recursion on vectors (each ``s_i . q`` and ``y_i . r`` expanded into
  those dots), and each device forms its share of the direction, which one all-gather assembles.

The iterate, the gradient and the trial direction (``n`` numbers each) are kept whole on every device (the
objective needs every node on every device anyway). So an accepted step has three exchanges and a rejected one
one, and the ``4 m n`` of vector work of a two-loop recursion is divided by the device count (optimistix's
L-BFGS repeated it on every device: docs/sharding.md measured that repeated work at 2.3x a single device's on four
forced CPU devices). On one device the exchanges are absent and the program is the same.
"""

from __future__ import annotations

import numpy as np

from ..runtime._lazy import jax, jit, jnp
from ..runtime.transfer import program

#: Armijo slope and step factor on rejection (optimistix's `BacktrackingArmijo` defaults).
SLOPE = 0.1
DECREASE = 0.5
#: An accepted step size at or below this (8 cuts of `DECREASE`) whose objective change is within the Cauchy
#: test's stops the loop (`converged`).
STUCK_STEP = DECREASE ** 8
#: Accepted steps in a row whose objective changed by less than rtol of it (`calm_steps`) that stop
#: the loop whatever their size (`converged`): the iterate drifts along a valley where F barely changes, as an O-grid
#: cylinder's turns about its axis once its boundary nodes may slide on (`jaxci.geometry.anchors`): L-BFGS went on
#: for 510 steps there, for 1.2e-5 of F (2026-11-30).
SETTLED_RUN = 10

#: Result codes of `lbfgs_loop`, as the host path names them (`jaxci.optim.host.lbfgs`).
RESULTS = ("successful", "nonlinear_max_steps_reached", "nonfinite")


def cap_factor(biggest, cap, xp=np):
    """The factor that scales a trial direction whose largest entry (max norm) is `biggest` so that no unknown
    moves more than `cap` at step size 1 (1 where it does not, or where `cap` is 0: no cap)."""
    return xp.where((cap > 0) & (biggest > cap), cap / xp.where(biggest > 0, biggest, 1.0), 1.0)


def armijo(v_try, value, alpha, slope):
    """Whether a trial of objective `v_try` at step size `alpha` along a direction of slope `slope` (``g . d``)
    from an iterate of objective `value` passes the Armijo test: a decrease of at least `SLOPE` of the linear
    model's (a NaN `v_try` fails it; the loops also refuse a trial whose objective or gradient is not finite)."""
    return v_try <= value + SLOPE * alpha * slope


def converged(s_max, y_max, v_new, v_old, rtol, atol, alpha=1.0, calm=0):
    """The Cauchy stop at an accepted iterate: the objective's change below ``atol + rtol |v_new|`` (`settled`),
    and the step's largest change of an unknown `s_max` below ``atol + rtol y_max`` (the largest unknown) or the
    step accepted at a size `alpha` of at most `STUCK_STEP` (the line search had to cut the model's step 8 times:
    the objective has a kink along it, as where boundary nodes cross the edges of the boundary's triangles, and
    further steps would only be shorter); or `calm` (the accepted steps in a row whose objective changed by less
    than ``rtol`` of it, this one included: `calm_steps`) at least `SETTLED_RUN`, whatever their size."""
    return ((((s_max < atol + rtol * y_max) | (alpha <= STUCK_STEP)) & settled(v_new, v_old, rtol, atol))
            | (calm >= SETTLED_RUN))


def calm_steps(calm, v_new, v_old, rtol, xp=np):
    """The accepted steps in a row whose objective changed by less than ``rtol |v_new|``, after one from `v_old` to
    `v_new` (`calm` before it): `settled` without its absolute part, which near an objective of 0 (a mesh that
    reaches the ideal) holds while the iterate still converges."""
    return xp.where(abs(v_new - v_old) < rtol * abs(v_new), calm + 1, 0)


def settled(v_new, v_old, rtol, atol):
    """The Cauchy test's objective half: the change from `v_old` to `v_new` below ``atol + rtol |v_new|``
    (truncated Newton also stops on it alone, `jaxci.optim.newton`)."""
    return abs(v_new - v_old) < atol + rtol * abs(v_new)


def curvature_ok(sy, ss, yy, xp=np):
    """Whether a pair ``(s, y)`` enters the memory: its curvature ``s.y`` clearly positive, ``s.y > 1e-12 |s||y|``
    (from the dots ``s.y``, ``s.s``, ``y.y``; no overflow of ``ss * yy``)."""
    return sy > 1e-12 * xp.sqrt(ss) * xp.sqrt(yy)


def result_name(code) -> str:
    """The name of a result code of `lbfgs_loop`."""
    return RESULTS[int(np.asarray(code))]


def _two_loop_coefficients(SY, YY, a, b, age):
    """The two-loop recursion on the Gram matrices: ``(c, e, gamma)`` with ``H g = gamma g + S^T c + Y^T e``.

    **Arguments:** `SY` ``(m, m)``: ``s_i . y_j``; `YY` ``(m, m)``: ``y_i . y_j``; `a`, `b` ``(m,)``: ``s_i . g``,
    ``y_i . g``; `age` ``(m,)`` int32: each slot's push number (-1: empty). Slots in any order (chronology from
    `age`); empty slots get 0. `gamma`, the initial inverse Hessian's scale, is ``s.y / y.y`` of the newest pair
    (1 with no pair), as in `jaxci.optim.host`.

    The first loop (newest pair first) ``alpha_i = rho_i s_i . q`` with ``q = g - sum_{j newer} alpha_j y_j``,
    i.e. ``rho_i (a_i - sum_j alpha_j SY_ij)`` over the pairs done so far; then ``r = gamma q`` and the second loop
    (oldest first) ``beta_i = rho_i y_i . (r + sum_{j older} (alpha_j - beta_j) s_j)``, i.e. ``rho_i (gamma (b_i -
    (YY alpha)_i) + sum_j c_j SY_ji)`` with ``c_j = alpha_j - beta_j``. Then ``H g = gamma (g - Y^T alpha) + S^T
    c``.
    """
    m = age.shape[0]
    valid = age >= 0
    both = valid[:, None] & valid[None, :]  # an empty slot's stale entries, even inf, never reach a sum
    SY, YY = jnp.where(both, SY, 0.0), jnp.where(both, YY, 0.0)
    a, b = jnp.where(valid, a, 0.0), jnp.where(valid, b, 0.0)
    order = jnp.argsort(jnp.where(valid, age, jnp.iinfo(age.dtype).max))  # oldest first, empty slots last
    count = jnp.sum(valid)
    diag = jnp.diagonal(SY)
    rho = jnp.where(valid, 1.0 / jnp.where(valid, diag, 1.0), 0.0)
    newest = order[jnp.maximum(count - 1, 0)]
    gamma = jnp.where(count > 0, diag[newest] / jnp.where(count > 0, YY[newest, newest], 1.0), 1.0)

    def first(t, alpha):
        pos = m - 1 - t  # newest first
        i = order[pos]
        val = rho[i] * (a[i] - jnp.dot(SY[i], alpha))
        return alpha.at[i].set(jnp.where(pos < count, val, 0.0))

    alpha = jax.lax.fori_loop(0, m, first, jnp.zeros_like(a))
    yr = gamma * (b - YY @ alpha)  # y_i . r

    def second(pos, c):
        i = order[pos]
        beta = rho[i] * (yr[i] + jnp.dot(SY[:, i], c))
        return c.at[i].set(jnp.where(pos < count, alpha[i] - beta, 0.0))

    c = jax.lax.fori_loop(0, m, second, jnp.zeros_like(a))
    return c, -gamma * alpha, gamma


def _amax(a):
    return jnp.max(jnp.abs(a), initial=0.0)


def value_and_grad(v, args, conn, weight, n_dev: int, platform: str):
    """The objective of `lbfgs_loop` for hexahedral meshes, run inside its `jax.shard_map`: ``(s F, its gradient
    in v, F, max kappa/3)`` at the free coordinates `v` ``(n,)`` (whole on every device), from this device's
    elements `conn`, `weight` and one exchange (`jaxci.optim.sharding.local_terms_and_grad`); the chain rule
    through ``par.points`` (lift and projection) on every device. `args`: ``(par, s)``, the
    `jaxci.optim.parametrisation.Parametrisation` and the objective's scale
    (`jaxci.optim.solver_objective.solver_args`); `n_dev`, `platform`: the devices'."""
    from .sharding import local_terms_and_grad

    par, s = args
    x, pull = jax.vjp(par.points, v)
    f, k, gx = local_terms_and_grad(x, conn, weight, n_dev, platform)
    (gv,) = pull(gx.astype(x.dtype))
    return s * f, s * gv, f, k


@program
@jit(static_argnames=("objective", "static", "mesh", "max_steps", "history", "max_rejected"))
def lbfgs_loop(objective, args, conn, weight, y0, consts, limit, *, static: tuple = (), mesh=None, max_steps: int,
               history: int, max_rejected: int):
    """Minimise `objective` from `y0` on one device (`mesh` None) or sharded over `mesh`.

    **Arguments:**

    - `objective` (static): ``objective(v, args, conn, weight, n_dev, platform, *static) -> (value, gradient, F,
      k)`` at a whole vector `v` ``(n,)``; sharded, it is called inside `jax.shard_map` with this device's `conn`
      and `weight` (and makes any exchange it needs). The loop minimises `value`, records F and k, and stops once
      ``F <= ftol`` or ``k <= 1 + ktol``. For meshes: `value_and_grad` (sharded; value ``s F``, k the max
      kappa/3), `jaxci.optim.solver_objective.value_and_grad_closed` (one device).
    - `args`: a pytree of (replicated) arrays for `objective` (for `value_and_grad`: ``(par, s)``).
    - `conn` ``(8, N)``, `weight` ``(N,)``: the hexahedra and their weights (0: padding), sharded along N over
      `mesh` (`jaxci.optim.sharding.place_problem`).
    - `y0` ``(n,)``: the start (replicated); n need not be a multiple of the device count.
    - `consts` ``(5,)``: ``ftol, 1 + ktol, rtol, atol, cap`` (cap 0: trials not capped), traced.
    - `limit`: the most steps (traced, at most `max_steps`).
    - `static`: hashable values passed on to `objective`; `mesh`, `max_steps` (the history's length), `history`
      (the pairs m), `max_rejected`: static.

    **Returns:** ``(y, steps, result, hist_f, hist_k)``: the last accepted iterate (the lowest F: every accepted
    step lowers it), the steps taken, a code of `RESULTS`, and F and max kappa/3 of the accepted iterate after
    each step (entry 0: `y0`; NaN after the last step).
    """
    from jax.sharding import PartitionSpec as P

    from .sharding import AXIS

    n_dev = 1 if mesh is None else int(mesh.devices.size)
    n = int(y0.shape[0])
    n_loc = -(-n // n_dev)
    m = int(history)
    platform = jax.default_backend() if mesh is None else mesh.devices.flat[0].platform
    if mesh is None:  # no exchanges
        def psum(x):
            return x

        def share(v):
            return v

        def gather(d):
            return d
    else:
        def psum(x):
            return jax.lax.psum(x, AXIS)

        def share(v):  # this device's slice of a whole vector, padded to n_loc * n_dev
            return jax.lax.dynamic_slice(jnp.pad(v, (0, n_loc * n_dev - n)), (jax.lax.axis_index(AXIS) * n_loc,),
                                         (n_loc,))

        def gather(d):
            return jax.lax.all_gather(d, AXIS, tiled=True)[:n]

    def fn(v, args, conn, weight):
        return objective(v, args, conn, weight, n_dev, platform, *static)

    def local(args, conn, weight, y0, consts, limit):
        ftol, kstop, rtol, atol, cap = (consts[i] for i in range(5))
        dtype = y0.dtype

        def capped(d):
            return d * cap_factor(_amax(d), cap, jnp)

        def finished(f, k):  # the stops at an accepted iterate besides the Cauchy test
            return (f <= ftol) | (k <= kstop)

        value, g, f, k = fn(y0, args, conn, weight)
        ok = jnp.isfinite(value)
        trial = capped(-g)
        hf = jnp.full((max_steps + 1,), jnp.nan, dtype).at[0].set(f)
        hk = jnp.full((max_steps + 1,), jnp.nan, dtype).at[0].set(k)
        mem = dict(W=jnp.zeros((2 * m, n_loc), dtype), SY=jnp.zeros((m, m), dtype), YY=jnp.zeros((m, m), dtype),
                   age=jnp.full((m,), -1, jnp.int32), count=jnp.int32(0))
        it = dict(y=y0, g=g, value=value, f=f, k=k, trial=trial, slope=jnp.dot(g, trial), alpha=jnp.ones((), dtype),
                  rejected=jnp.int32(0), calm=jnp.int32(0), steps=jnp.int32(0), stop=~ok | finished(f, k),
                  hf=hf, hk=hk, mem=mem)

        def accepted(it, y_try, v_try, g_try, f_try, k_try):
            mem = it["mem"]
            ds, dg = y_try - it["y"], g_try - it["g"]  # the new pair
            calm = calm_steps(it["calm"], v_try, it["value"], rtol, jnp)
            done = converged(_amax(ds), _amax(y_try), v_try, it["value"], rtol, atol, it["alpha"], calm)
            s_l, y_l, g_l = share(ds), share(dg), share(g_try)
            W = mem["W"]
            # every dot the update and the recursion need, over this device's share, in ONE all-reduce
            # (2m, 3): S.s, S.y, S.g over Y.s, Y.y, Y.g (S.s unused: one pass over the block all the same); full
            # float32 precision on GPUs, whose default matmul rounds the inputs (5e-6 relative error measured)
            dots = jnp.matmul(W, jnp.stack([s_l, y_l, g_l], axis=1), precision=jax.lax.Precision.HIGHEST)
            pair = jnp.stack([jnp.dot(s_l, y_l), jnp.dot(s_l, s_l), jnp.dot(y_l, y_l), jnp.dot(s_l, g_l),
                              jnp.dot(y_l, g_l)])
            tot = psum(jnp.concatenate([dots.reshape(-1), pair]))
            dots, (sy, ss, yy, sg, yg) = tot[:6 * m].reshape(2 * m, 3), (tot[6 * m + i] for i in range(5))
            push = curvature_ok(sy, ss, yy, jnp)
            j = mem["count"] % m
            SY = jnp.where(push, mem["SY"].at[j, :].set(dots[m:, 0]).at[:, j].set(dots[:m, 1]).at[j, j].set(sy),
                           mem["SY"])
            YY = jnp.where(push, mem["YY"].at[j, :].set(dots[m:, 1]).at[:, j].set(dots[m:, 1]).at[j, j].set(yy),
                           mem["YY"])
            age = jnp.where(push, mem["age"].at[j].set(mem["count"]), mem["age"])
            W = W.at[j].set(jnp.where(push, s_l, W[j])).at[m + j].set(jnp.where(push, y_l, W[m + j]))
            a = jnp.where(push, dots[:m, 2].at[j].set(sg), dots[:m, 2])
            b = jnp.where(push, dots[m:, 2].at[j].set(yg), dots[m:, 2])
            c, e, gamma = _two_loop_coefficients(SY, YY, a, b, age)
            d_l = -(gamma * g_l + jnp.matmul(jnp.concatenate([c, e]), W, precision=jax.lax.Precision.HIGHEST))
            d = gather(d_l)
            descent = jnp.dot(g_try, d) < 0  # else: the memory forgotten, the steepest descent
            d = jnp.where(descent, d, -g_try)
            age = jnp.where(descent, age, -1)
            count = jnp.where(descent, mem["count"] + push.astype(jnp.int32), 0)
            trial = capped(d)
            return dict(it, y=y_try, g=g_try, value=v_try, f=f_try, k=k_try, trial=trial,
                        slope=jnp.dot(g_try, trial), alpha=jnp.ones((), dtype), rejected=jnp.int32(0),
                        calm=calm.astype(jnp.int32), stop=done | finished(f_try, k_try),
                        mem=dict(W=W, SY=SY, YY=YY, age=age, count=count))

        def rejected(it, *_):
            r = it["rejected"] + 1
            return dict(it, alpha=it["alpha"] * DECREASE, rejected=r, stop=r >= max_rejected)

        def body(it):
            y_try = it["y"] + it["alpha"] * it["trial"]
            v_try, g_try, f_try, k_try = fn(y_try, args, conn, weight)
            ok = jnp.isfinite(v_try) & armijo(v_try, it["value"], it["alpha"], it["slope"])
            it = jax.lax.cond(ok, accepted, rejected, it, y_try, v_try, g_try, f_try, k_try)
            steps = it["steps"] + 1
            return dict(it, steps=steps, hf=it["hf"].at[steps].set(it["f"]), hk=it["hk"].at[steps].set(it["k"]))

        it = jax.lax.while_loop(lambda it: ~it["stop"] & (it["steps"] < limit), body, it)
        code = jnp.where(~ok, 2, jnp.where(it["stop"], 0, 1)).astype(jnp.int32)
        return it["y"], it["steps"], code, it["hf"], it["hk"]

    limit = jnp.minimum(jnp.asarray(limit, jnp.int32), max_steps)
    if mesh is None:
        return local(args, conn, weight, y0, consts, limit)
    run = jax.shard_map(local, mesh=mesh, in_specs=(P(), P(None, AXIS), P(AXIS), P(), P(), P()),
                        out_specs=(P(), P(), P(), P(), P()), check_vma=False)
    return run(args, conn, weight, y0, consts, limit)
