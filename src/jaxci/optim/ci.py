"""Cohort Intelligence (CI) smoothing: the batched local form (default) and the paper's global form.

The CI learning attempt (Kulkarni et al. 2013; ``shared/reference/cohort-intelligence.md``), for a cohort of
C candidates with behaviours f_c (minimised):

1. follow probabilities p_c = (1 / (g_c + delta)) / sum_k (1 / (g_k + delta)), with g_c = f_c - f_floor >= 0 the
   behaviour above its floor (0 at a perfect mesh, so plain 1/f would be undefined there; delta > 0 keeps the
   wheel defined: this is the documented choice);
2. each candidate picks a candidate to follow: by roulette wheel on p (the paper's stage 1), or the best one
   (stage 2, "follow best"); the first ``stage_switch`` fraction of the attempts use stage 1, the rest stage 2;
3. it centres its sampling interval on the followed candidate, shrunk by the reduction factor r each attempt;
4. it samples t variations uniformly in that interval (each projected onto the boundary constraints),
   evaluates them all at once, and keeps the best if it improves on its own behaviour (greedy CI);
5. it stops at saturation (every candidate's behaviour within `tol` of the best, and the best not improved by
   more than that, for `patience` consecutive attempts) or after `attempts` attempts.

**Local CI** (`local_ci`, beyond the paper, the one that scales): the nodes are coloured so that no two nodes of
a colour share an element. For one colour, EVERY node of the colour runs its own cohort of C candidate
positions at once, in its 3 (interior), 2 (surface) or 1 (edge) free coordinates; its behaviour is the local
objective (the mean of (kappa/3)^2 - 1 over the corners it moves). All nodes, candidates and variations are
one batched evaluation that computes only the corners a node touches. A node's best candidate replaces its
position only if it lowers the local objective and inverts no corner; since nodes of a colour share no
element, the mesh objective F decreases by the sum of the accepted decreases. Colours are swept in turn; each
node keeps an interval width adapted to its last move (a trust region). After each sweep a pattern move (Hooke
& Jeeves) tries the whole mesh further along the sweep's displacement D, ``x + a D`` for a few factors a, and
keeps the best if it lowers F without letting the worst corner's excess grow much (`_better`): node-by-node moves
remove long-wavelength error slowly (pave3 after untangling, 30 sweeps: F 10% above L-BFGS's without it, 5% with
it). Then Anderson acceleration over the last `anderson` sweeps (`jaxci.optim._anderson`: the combination of their
starts and displacements that best cancels the displacements, projected, taken on the same condition; pave3, 30
sweeps, 8 seeds, the default cohorts: F 1.6-2.6% above L-BFGS's without it, 0.0-0.4% with it). Sweeps stop when F
changes by less than `tol` relative plus `atol`, or F <= `ftol`, or max kappa/3 <= 1 + `ktol`, or after `max_sweeps`.

**Global CI** (`global_ci`, faithful to the paper; `jaxci.optim.global_ci`): each candidate is a whole mesh, a
point in the space of all free coordinates (`jaxci.geometry.projection`'s parametrisation), of shape
``(C, n_free)``; its behaviour is F (Eq. 3.1) evaluated for all C x t variations of an attempt in one batch, and
for several seeds at once (`jaxci.optim.global_ci.global_ci_batched`). Intervals are per coordinate, of initial
width ``init_width * h`` (h the local edge length).

Both run under one `jax.jit` with `jax.lax` loops, seeded by an explicit `jax.random` key: same key, same
result, bit for bit on CPU.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.projection import Constraints, project
from ..metrics.objective import ExtraCells, no_extra, objective_and_max
from ..runtime.transfer import program
from . import _draws
from ._anderson import anderson_point
from ._buckets import to_device
from ._local import gather_star
from ._moves import (
    ColouredStars,
    chunked_local_sum,
    colour_slice,
    local_count,
    local_scale,
    padded_sweeps,
    project_trials,
)
from .ci_params import (  # noqa: F401  (the parameters, re-exported: jaxci.optim.ci.CIParams is public)
    EXCESS_GROWTH,
    GLOBAL_DEFAULTS,
    PATTERN_FACTORS,
    CIParams,
    excess_within_bound,
    pattern_choice,
    sweep_done,
)
from .cohort import StaticParams, follow, split_params


# ------------------------------------------------------------------------------------------------ local CI
def _local_ci_colour(key, x, width, cs_i, cons: Constraints, s: StaticParams, d: dict, chunk: int,
                     stream: str = "native"):
    """One cohort run for every node of one colour. Returns new points, new widths, number of moved nodes.
    `key`: ``"native"`` `stream`, the colour's `jax.random` key; ``"counter"``, the visit's word (the path of
    `jaxci.optim._draws` at the sweep and the colour: each node then draws at (node, attempt, 0) for the roulette
    and (node, attempt, 1) for its trials, as `jaxci.native.ci_visit` does)."""
    nodes, mask, star, basis, dims = (cs_i.nodes, cs_i.mask, cs_i.star, cs_i.basis, cs_i.dims)
    M = nodes.shape[0]
    C, t, T = s.cohort, s.variations, d["attempts"]
    dtype = x.dtype
    E = gather_star(x, star)
    ncorner = jnp.maximum(local_count(cs_i), 1).astype(dtype)  # (M,)
    safe_nodes = jnp.minimum(nodes, x.shape[0] - 1)
    x0 = x[safe_nodes]  # (M, 3)
    w0 = width[safe_nodes]
    h = local_scale(x, cs_i, E)
    f0 = chunked_local_sum(x, cs_i, E, x0[:, None], chunk)[:, 0] / ncorner - 1.0  # (M,)
    dim_mask = (jnp.arange(3)[None, :] < dims[:, None]).astype(dtype)  # (M, 3)
    cand = jnp.broadcast_to(x0[:, None], (M, C, 3))
    fc = jnp.broadcast_to(f0[:, None], (M, C))
    n_roulette = jnp.round(d["stage_switch"] * T)

    def draws(key, a):  # the attempt's uniforms in [0, 1): the roulette's (M, C), the trials' (M, C, t, 3)
        if stream == "counter":
            h = _draws.mix(_draws.mix(key, nodes[:, None], jnp), a, jnp)
            return (key, _draws.uniforms(_draws.mix(h, 0, jnp), jnp.arange(C), dtype, jnp),
                    _draws.uniforms(_draws.mix(h, 1, jnp), jnp.arange(C * t * 3), dtype, jnp).reshape(M, C, t, 3))
        key, kf, ku = jax.random.split(key, 3)
        return key, jax.random.uniform(kf, (M, C), dtype), jax.random.uniform(ku, (M, C, t, 3), dtype)

    def attempt(a, carry):
        key, cand, fc = carry
        key, uf, ut = draws(key, a)
        chosen = follow(fc, d["delta"], a < n_roulette, uf, jnp)  # (M, C)
        centre = jnp.take_along_axis(cand, chosen[..., None], axis=1)  # (M, C, 3)
        w = w0 * d["reduction"] ** (a + 1).astype(dtype)  # (M,)
        u = (ut - 0.5) * (w[:, None, None, None] * dim_mask[:, None, None])
        step = jnp.einsum("mij,mctj->mcti", basis, u)
        trials = project_trials(cons, cs_i, (centre[:, :, None] + step).reshape(M, C * t, 3))
        ft = chunked_local_sum(x, cs_i, E, trials, chunk) / ncorner[:, None] - 1.0
        ft = ft.reshape(M, C, t)
        j = jnp.argmin(ft, axis=-1)  # (M, C)
        fb = jnp.take_along_axis(ft, j[..., None], axis=-1)[..., 0]
        yb = jnp.take_along_axis(trials.reshape(M, C, t, 3), j[..., None, None], axis=2)[:, :, 0]
        better = fb < fc
        return key, jnp.where(better[..., None], yb, cand), jnp.where(better, fb, fc)

    _, cand, fc = jax.lax.fori_loop(0, T, attempt, (key, cand, fc))
    c = jnp.argmin(fc, axis=-1)
    fbest = jnp.take_along_axis(fc, c[:, None], axis=-1)[:, 0]
    ybest = jnp.take_along_axis(cand, c[:, None, None], axis=1)[:, 0]
    accept = mask & (fbest < f0) & jnp.isfinite(fbest)
    new_pos = jnp.where(accept[:, None], ybest, x0)
    x = x.at[nodes].set(new_pos, mode="drop")
    move = jnp.linalg.norm(new_pos - x0, axis=-1)
    w_new = jnp.where(accept, 4.0 * move, 0.5 * w0)
    w_new = jnp.clip(w_new, d["min_width"] * h, d["init_width"] * h)
    width = width.at[nodes].set(w_new, mode="drop")
    return x, width, jnp.sum(accept, dtype=jnp.int32)


def _pattern_move(x, D, f, k, conn, cons: Constraints, extra: ExtraCells, weight=None):
    """``(x, f, k)`` after the pattern move: the ``project(x + a D)`` over `PATTERN_FACTORS` that
    `pattern_choice` picks (all six evaluated at once; an inverted corner makes F infinite: never taken), else
    `x`, `f`, `k` unchanged. `weight`: as in `jaxci.metrics.objective.objective_and_max`."""

    def trial(a):
        y = project(cons, x + a * D)
        return y, *objective_and_max(y, conn, extra, weight)

    factors = jnp.asarray(PATTERN_FACTORS, x.dtype)
    fy, ky = jax.lax.map(lambda a: trial(a)[1:], factors)
    best = pattern_choice(f, k, fy, ky, jnp)
    return _take_if_better(x, f, k, *trial(factors[jnp.maximum(best, 0)]))


def _better(f, k, fy, ky):
    """Whether a trial of F `fy` and max kappa/3 `ky` improves on `f`, `k`: F finite and lower, and the worst
    corner's excess ``ky - 1`` at most `EXCESS_GROWTH` times ``k - 1`` (the extrapolations, pattern and Anderson
    moves, must not trade the worst element for the mean)."""
    return jnp.isfinite(fy) & (fy < f) & excess_within_bound(k, ky)


def _take_if_better(x, f, k, y, fy, ky):
    """``(y, fy, ky)`` where it is `_better` than ``(x, f, k)``, else ``(x, f, k)``."""
    take = _better(f, k, fy, ky)
    return jnp.where(take, y, x), jnp.where(take, fy, f), jnp.where(take, ky, k)


def _anderson_move(x, f, k, starts, moves, valid, conn, cons: Constraints, extra: ExtraCells, weight=None):
    """``(x, f, k)`` after the Anderson step (`jaxci.optim._anderson.anderson_point` of the last sweeps' `starts`
    and `moves` ``(m, 3 n)``, `valid` of them real), projected, where it is `_better`."""
    y = project(cons, anderson_point(starts, moves, valid, jnp).reshape(x.shape))
    return _take_if_better(x, f, k, y, *objective_and_max(y, conn, extra, weight))


@program
@functools.partial(jax.jit, static_argnames=("s", "chunk", "stream"))
def _local_ci_run(key, x, conn, cs: ColouredStars, cons: Constraints, s: StaticParams, d: dict, chunk: int,
                  extra: ExtraCells, weight=None, n_colours=None, stream: str = "native"):
    """The sweeps under one jit. `weight` ``(N,)`` and `n_colours` (traced): for a problem padded to its size
    class, the element weights (0: padding) and the number of real colours (the padded ones are skipped).
    `stream`: the random numbers' (`local_ci`)."""
    n_colours = cs.nodes.shape[0] if n_colours is None else n_colours
    dtype = x.dtype
    # initial widths: init_width * local edge length of every node
    h_all = jnp.zeros(x.shape[0], dtype)

    def h_colour(i, h_all):
        cs_i = colour_slice(cs, i)
        return h_all.at[cs_i.nodes].set(local_scale(x, cs_i, gather_star(x, cs_i.star)), mode="drop")

    h_all = jax.lax.fori_loop(0, n_colours, h_colour, h_all)
    width = d["init_width"] * h_all
    f_init, k_init = objective_and_max(x, conn, extra, weight)
    hist_f = jnp.full((s.max_sweeps + 1,), jnp.nan, dtype).at[0].set(f_init)
    hist_k = jnp.full((s.max_sweeps + 1,), jnp.nan, dtype).at[0].set(k_init)
    hist_m = jnp.zeros((s.max_sweeps + 1,), jnp.int32)

    if stream == "counter":  # the key's seed words (jaxci.optim._draws.seed_words of the host's seed)
        key = _draws.key_words(key)

    def sweep(carry):
        key, x, width, it, f_prev, _, hf, hk, hm, starts, moves = carry
        if stream != "counter":
            key, ks = jax.random.split(key)

        def colour(i, c):
            x, width, moved = c
            visit = _draws.visit_word(key, it, i, jnp) if stream == "counter" else jax.random.fold_in(ks, i)
            x, width, m = _local_ci_colour(visit, x, width, colour_slice(cs, i), cons, s, d, chunk, stream)
            return x, width, moved + m

        x_start = x
        x, width, moved = jax.lax.fori_loop(0, n_colours, colour, (x, width, jnp.int32(0)))
        f, k = objective_and_max(x, conn, extra, weight)
        if s.anderson:  # the last sweeps, oldest first (this one last)
            starts = jnp.concatenate([starts[1:], x_start.reshape(1, -1)])
            moves = jnp.concatenate([moves[1:], (x - x_start).reshape(1, -1)])
        if s.pattern:
            x, f, k = _pattern_move(x, x - x_start, f, k, conn, cons, extra, weight)
        it = it + 1
        if s.anderson:
            x, f, k = _anderson_move(x, f, k, starts, moves, jnp.minimum(it, s.anderson), conn, cons, extra, weight)
        hf, hk, hm = hf.at[it].set(f), hk.at[it].set(k), hm.at[it].set(moved)
        done = sweep_done(f_prev, f, k, moved, d["ftol"], d["tol"], d["atol"], d["ktol"])
        return key, x, width, it, f, done, hf, hk, hm, starts, moves

    def cond(carry):
        it, done = carry[3], carry[5]
        return (it < d["max_sweeps"]) & ~done

    history = jnp.zeros((s.anderson, x.size), dtype)  # (0, 3 n) without Anderson acceleration
    init = (key, x, width, jnp.int32(0), f_init, (f_init <= d["ftol"]) | (k_init <= 1.0 + d["ktol"]), hist_f,
            hist_k, hist_m, history, history)
    _, x, _, it, _, _, hf, hk, hm, _, _ = jax.lax.while_loop(cond, sweep, init)
    return x, it, hf, hk, hm


def _auto_chunk(cs: ColouredStars, p: CIParams, budget: int = 4_000_000) -> int:
    """Trials evaluated at once per node so that one batch holds about `budget` corner evaluations."""
    M, K = cs.star.shape[1], cs.star.shape[2]
    return int(max(1, min(p.cohort * p.variations, budget // max(1, M * K * 4))))


def local_ci(key, points, conn, cs: ColouredStars, cons: Constraints, p: CIParams,
             extra: ExtraCells | None = None, *, devices=None, stream: str = "native"):
    """Run batched local CI from `points` ``(n, 3)``; `conn` is the ``(8, N)`` transposed connectivity, `extra`
    the non-hexahedral cells (`jaxci.metrics.objective.extra_cells`; default none), whose corners `cs` must hold too
    (`coloured_stars(..., table)`): F and the local objectives are then over every corner; `p` the `CIParams`.

    `devices` (keyword only): None (one device), or a `jax.sharding.Mesh` (hexahedral meshes): the problem is
    padded to its size class (`jaxci.optim._buckets`: nodes, elements with weight 0, colours and node slots), the
    elements (F, max kappa/3 and the pattern move) and the node slots of every colour (the cohorts: each device
    runs the cohorts of its share of a colour's nodes) sharded over it, the coordinates, widths and constraints
    replicated (`jaxci.optim.sharding.place_problem`). The random numbers are drawn for the padded slots, so any
    device count gives the same mesh (to float rounding), but not the unpadded run's.

    `stream` (keyword only): ``"native"`` (`jax.random` from `key`) or ``"counter"`` (`jaxci.optim._draws` under
    the key's words: the numbers `jaxci.optim.host_local.local_ci_np` draws with the same seed and stream).

    **Returns:** ``(points, sweeps, history)``: the smoothed coordinates ``(n, 3)``, the number of sweeps, and a
    dict of numpy arrays of length ``sweeps + 1`` (entry 0 = input): ``objective``, ``max_condition``,
    ``moved`` (nodes moved in the sweep).
    """
    extra = no_extra() if extra is None else extra
    static, traced = split_params(p, points.dtype)
    if devices is not None and not extra.types:
        from .sharding import place_problem

        n = int(points.shape[0])
        xp, c, cs_p, cons_p, w, n_col = padded_sweeps(points, conn, cs, cons, int(devices.devices.size))
        run_conn, weight, (xp, cons_p, n_col), cs_p = place_problem(c, w, (xp, cons_p, n_col), devices, cs_p)
        x, it, hf, hk, hm = _local_ci_run(key, xp, run_conn, cs_p, cons_p, static, traced, _auto_chunk(cs_p, p),
                                          extra, weight, n_col, stream)
        x = to_device(np.asarray(x)[:n])  # sliced on the host: no compilation
    else:
        x, it, hf, hk, hm = _local_ci_run(key, points, conn, cs, cons, static, traced, _auto_chunk(cs, p), extra,
                                          stream=stream)
    it = int(it)
    return x, it, {"objective": np.asarray(hf[: it + 1]), "max_condition": np.asarray(hk[: it + 1]),
                   "moved": np.asarray(hm[: it + 1])}


# ------------------------------------------------------------------------------------------------ global CI
def global_ci(key, par, conn, scale, p: CIParams, extra: ExtraCells | None = None, *, devices=None,
              stream: str = "native"):
    """Run the paper's global CI from ``par.x0`` (`jaxci.optim.global_ci`: one seed of the batched program).

    **Arguments:** `key` a `jax.random` key; `par` the unscaled `jaxci.optim.parametrisation.Parametrisation` of
    the mesh (``scaled=False``: the unknowns are coordinates); `conn` the transposed connectivity ``(8, N)``;
    `scale` the local edge length per free coordinate, shape ``(n_free,)``; `p` the `CIParams`; `extra` the
    non-hexahedral cells (default none): the behaviour is then F over every corner. `devices` (keyword only):
    None (one device), or a `jax.sharding.Mesh`: the C t trial meshes of every learning attempt are split over
    its devices (each evaluates whole meshes: the candidates, not the elements, are sharded), everything else
    replicated; the same numbers as on one device. `stream`: the random numbers', ``"native"`` or ``"counter"``
    (`jaxci.optim.global_ci.global_ci_batched`).

    **Returns:** ``(points, attempts, history)`` with history arrays ``objective`` and ``best`` (best behaviour
    F of the cohort), ``worst`` (worst behaviour), ``max_condition`` (of the best candidate), per learning
    attempt; entry 0 = input.
    """
    from .global_ci import global_ci_batched

    return global_ci_batched([key], [par], conn, [scale], p, extra, devices=devices, stream=stream)[0]
