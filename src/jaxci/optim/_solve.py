"""optimistix's minimisation loop, recorded step by step, and a step cap for its quasi-Newton descents.

Shared by the gradient baselines (`jaxci.optim.gradient`) and the untangler (`jaxci.optim.untangle`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

#: Consecutive rejected trials after which `_solve` stops a solver whose steps are capped (`max_move`): the
#: trial is then below 2^-20 of `max_move`; in float32 that is F's rounding noise at the optimum (measured: 28
#: rejected trials ended every L-BFGS run at 30^3 after it had converged, each a full objective and gradient
#: evaluation). Uncapped solvers (and LM, Gauss-Newton) get `MAX_REJECTED_UNCAPPED`: their first raw-gradient
#: trial can be 2^35 times too long.
MAX_REJECTED = 20
MAX_REJECTED_UNCAPPED = 64


@eqx.filter_jit
def _solve(solver, fn, y0, args, max_steps: int, limit=None, max_rejected: int = MAX_REJECTED_UNCAPPED):
    """optimistix's iteration (init, step, terminate in a bounded loop), recording per step what `fn` reports.

    `fn(y, args)` returns ``(value, (f, k, stop))``: the solver minimises `value`; `f` (tracked: the best
    valid iterate is the one with the lowest finite `f`) and `k` are recorded per step; the loop also ends
    once `stop` is True at an accepted iterate, and after `max_rejected` (static) consecutive trials that leave
    the accepted iterate unchanged.

    `max_steps` (static) sizes the history; `limit` (traced, <= max_steps, default max_steps) ends the loop.

    Returns ``(y_best, steps, result, hist_f, hist_k)``.
    """
    limit = jnp.int32(max_steps) if limit is None else jnp.minimum(jnp.asarray(limit, jnp.int32), max_steps)
    tags = frozenset()
    options = {}
    f_struct, aux_struct = jax.eval_shape(lambda: fn(y0, args))
    state = solver.init(fn, y0, args, options, f_struct, aux_struct, tags)
    dyn0, static = eqx.partition(state, eqx.is_array)
    _, (f0, k0, stop0) = fn(y0, args)
    dtype = f0.dtype
    hf = jnp.full((max_steps + 1,), jnp.nan, dtype).at[0].set(f0)
    hk = jnp.full((max_steps + 1,), jnp.nan, dtype).at[0].set(k0)
    ok = optx.RESULTS.successful

    def cond(carry):
        _, step, _, stop, _, _, _, _, _, _ = carry
        return (step < limit) & ~stop

    def body(carry):
        y, step, dyn, _, _, y_best, f_best, hf, hk, rejected = carry
        st = eqx.combine(static, dyn)
        y, st, _ = solver.step(fn, y, args, options, st, tags)
        terminate, result = solver.terminate(fn, y, args, options, st, tags)
        f, k, stop = st.aux  # reported for the accepted iterate y
        finite_y = jnp.all(jnp.isfinite(y))
        result = optx.RESULTS.where(finite_y, result, optx.RESULTS.nonfinite)
        step = step + 1
        rejected = jnp.where(f == hf[step - 1], rejected + 1, 0)
        hf, hk = hf.at[step].set(f), hk.at[step].set(k)
        better = finite_y & jnp.isfinite(f) & (f <= f_best)
        y_best = jnp.where(better, y, y_best)
        f_best = jnp.where(better, f, f_best)
        stop = terminate | (result != ok) | (stop & finite_y & jnp.isfinite(f)) | (rejected >= max_rejected)
        dyn2, _ = eqx.partition(st, eqx.is_array)
        return y, step, dyn2, stop, result, y_best, f_best, hf, hk, rejected

    carry = (y0, jnp.int32(0), dyn0, stop0, ok, y0, f0, hf, hk, jnp.int32(0))
    _, steps, _, stop, result, y_best, _, hf, hk, _ = jax.lax.while_loop(cond, body, carry)
    result = optx.RESULTS.where((result == ok) & ~stop, optx.RESULTS.nonlinear_max_steps_reached, result)
    return y_best, steps, result, hf, hk


class _CappedDescent(optx.AbstractDescent):
    """A descent whose step is at most `cap` in the max norm at step size 1 (then scaled by the step size).

    The unknowns are in units of the local edge length, so no node moves more than `cap` edge lengths per trial.
    Without it, the first quasi-Newton step (identity Hessian: the raw gradient, huge where one corner is nearly
    flat) overshoots by orders of magnitude and the line search halves it ~35 times, one full objective and
    gradient evaluation each (measured: 35 of 76 L-BFGS steps at 30^3, amplitude 0.3).
    """

    inner: optx.AbstractDescent
    cap: float

    def init(self, y, f_info_struct):
        return self.inner.init(y, f_info_struct)

    def query(self, y, f_info, state):
        return self.inner.query(y, f_info, state)

    def step(self, step_size, state):
        d, result = self.inner.step(jnp.ones_like(step_size), state)
        big = optx.max_norm(d)
        k = step_size * jnp.minimum(1.0, self.cap / jnp.maximum(big, jnp.finfo(big.dtype).tiny))
        return jax.tree.map(lambda t: k.astype(t.dtype) * t, d), result
