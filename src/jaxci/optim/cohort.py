"""The learning attempt's pieces both forms of Cohort Intelligence share, on both engines: the follow step of a
cohort and global CI's attempt and saturation (written once over the array module: `jaxci.optim.global_ci` calls
them with `jax.numpy` in `jax.lax` loops, `jaxci.optim.host_global` with numpy, a seed axis of size 1); and the
split of `jaxci.optim.ci_params.CIParams` into what fixes shapes (static under `jax.jit`) and what does not.

Local CI's cohort runs in C on the host (`jaxci.native.ci_visit`: the threaded per-node loop, where numpy's
per-attempt overhead on a handful of numbers per node would cost more than the arithmetic); it follows the same
rule (`follow`) and is checked against the compiled one step by step (`tests/test_ci_parity.py`).
"""

from __future__ import annotations

import typing

from ..runtime._lazy import jnp
from . import _draws
from .ci_params import CIParams


class StaticParams(typing.NamedTuple):
    """The hyperparameters that fix array shapes: static under jit (one compile each). `attempts` and `max_sweeps`
    are the capacities of the histories (`capacity`); the counts themselves are traced (``d["attempts"]``,
    ``d["max_sweeps"]``), so that runs of other counts within one capacity share a program."""

    cohort: int
    variations: int
    attempts: int
    max_sweeps: int
    pattern: bool
    anderson: int


def capacity(n: int) -> int:
    """A history's length for `n` steps: the power of two at least `n`, at least 16 (a program for each)."""
    return max(16, 1 << (int(n) - 1).bit_length())


def split_params(p: CIParams, dtype) -> tuple[StaticParams, dict]:
    """Static part and traced part of `p`: changing the counts within their capacity, the reduction, widths or
    tolerances does not recompile."""
    s = StaticParams(int(p.cohort), int(p.variations), capacity(p.attempts), capacity(p.max_sweeps),
                     bool(p.pattern), int(p.anderson))
    d = {k: jnp.asarray(getattr(p, k), dtype) for k in
         ("reduction", "delta", "stage_switch", "init_width", "min_width", "tol", "atol", "ftol", "ktol")}
    d.update({k: jnp.asarray(int(getattr(p, k)), jnp.int32) for k in ("attempts", "max_sweeps", "patience")})
    return s, d


def follow(g, delta, roulette, u, xp):
    """The candidate each candidate of a cohort follows, ``(..., C)``: by roulette on 1/(g + delta) (an inverted
    candidate, g = inf, has probability 0), the wheel turned by the uniforms `u` ``(..., C)`` in [0, 1) (the
    first candidate whose cumulative weight exceeds ``u`` times the total), or the best where `roulette` is
    False. `g` ``(..., C)`` >= 0, the behaviours. `xp`: the array module."""
    C = g.shape[-1]
    cum = xp.cumsum(1.0 / (g + delta), axis=-1)
    draw = u * cum[..., -1:]
    rou = xp.minimum(xp.sum(draw[..., :, None] >= cum[..., None, :], axis=-1), C - 1)
    best = xp.broadcast_to(xp.argmin(g, axis=-1)[..., None], g.shape)
    return xp.where(roulette, rou, best)


def trials(centre, rows, u, w, t: int, xp):
    """Global CI's trial meshes at `rows` ``(..., R)`` (row ``r = c t + j``: candidate c's j-th variation) of the
    followed candidates `centre` ``(..., C, n_free)``: ``centre[c] + (u - 0.5) w``, `u` ``(..., R, n_free)`` the
    rows' uniforms in [0, 1), `w` ``(..., n_free)`` the attempt's interval widths. `xp`: the array module."""
    return xp.take_along_axis(centre, (rows // t)[..., None], axis=-2) + (u - 0.5) * w[..., None, :]


def counter_follow(words, a, C: int, dtype, xp):
    """Global CI's roulette uniforms ``(C,)`` of attempt `a` in the counter stream (`jaxci.optim._draws`, at
    ``(a, 0)`` under the seed `words`): what both engines draw with ``stream="counter"``. `xp`: the array module."""
    return _draws.uniforms(_draws.path(words, (a, 0), xp), xp.arange(C), dtype, xp)


def counter_rows(words, a, rows, n: int, dtype, xp):
    """Global CI's uniforms ``(R, n)`` of attempt `a`'s trial rows `rows` ``(R,)`` in the counter stream (at
    ``(a, 1, r)`` per row r): what both engines draw with ``stream="counter"``. `xp`: the array module."""
    return _draws.uniforms(_draws.path(words, (a, 1, rows[:, None]), xp), xp.arange(n)[None], dtype, xp)


def learning_attempt(cand, fc, kc, chosen, evaluate, winners, t: int, xp):
    """One learning attempt of global CI's cohorts, B seeds at once (the host: B = 1): each candidate moves to
    the best of its t trials where that lowers its behaviour (greedy).

    **Arguments:** `cand` ``(B, C, n_free)`` the candidates, `fc`, `kc` ``(B, C)`` their F and max kappa/3,
    `chosen` ``(B, C)`` whom each follows (`follow`); `evaluate(centre)` -> ``(F, max kappa/3)`` ``(B, C t)`` of
    the trials of the followed candidates `centre` ``(B, C, n_free)`` (`trials` at every row); `winners(centre,
    rows)` -> ``(B, C, n_free)`` the trials at `rows` ``(B, C)`` (`trials` again: the engines draw, evaluate and
    keep the trials their own way, on one device or sharded). `xp`: the array module.

    **Returns:** ``(cand, fc, kc)`` after the attempt.
    """
    B, C = fc.shape
    centre = xp.take_along_axis(cand, chosen[..., None], axis=1)
    ft, kt = (v.reshape(B, C, t) for v in evaluate(centre))
    j = xp.argmin(ft, axis=-1)
    fb = xp.take_along_axis(ft, j[..., None], axis=-1)[..., 0]
    kb = xp.take_along_axis(kt, j[..., None], axis=-1)[..., 0]
    better = fb < fc
    won = winners(centre, xp.arange(C) * t + j)
    return xp.where(better[..., None], won, cand), xp.where(better, fb, fc), xp.where(better, kb, kc)


def calm_after(fc, best_before, calm, tol, ftol, xp):
    """Global CI's saturation count ``(B,)`` after an attempt: `calm` + 1 where every behaviour `fc` ``(B, C)`` is
    within ``tol max(best, ftol)`` of the best and the best fell by no more than that since `best_before`
    ``(B,)``, else 0 (the run stops once it reaches ``patience``). `xp`: the array module."""
    best = xp.min(fc, axis=-1)
    scale = tol * xp.maximum(best, ftol)
    still = (xp.max(fc, axis=-1) - best <= scale) & (best_before - best <= scale)
    return xp.where(still, calm + 1, 0)
