"""The paper's global Cohort Intelligence on the JAX engine, batched: every candidate of every seed in one program.

Each candidate is a whole mesh, a point of the free coordinates u (`jaxci.geometry.projection`'s layout,
``(n_free,)``); its behaviour is F (Eq. 3.1). A learning attempt of a cohort of C candidates draws t trial
meshes per candidate; all ``C t`` of them are lifted to node coordinates at once (``x0 + B u``,
`jaxci.optim.parametrisation.Parametrisation.lift`), projected onto the original boundary only where one of them
has a boundary node outside the flat region around it (one `jax.lax.cond` for the whole batch: on a box, never),
and evaluated `batch` meshes at a time (`jax.vmap` inside `jax.lax.map`; `candidate_batch` picks it per
platform, measured: docs/engines.md).

Several seeds (B runs: `global_ci_batched`) are one program too: the candidates, trials, histories and stops
carry a leading seed axis, so one compilation and one launch run them all, and every seed's run is the one it
would make alone (same key, same arithmetic; a seed that stopped is frozen while the others go on). Each seed may
have its own mesh (the paper's cubes are perturbed by the seed) as long as the meshes share connectivity and
boundary classes (`stackable`).

The iteration (`jaxci.optim.ci`'s module docstring has the algorithm): follow by roulette on
``1 / (F - 0 + delta)`` for the first ``stage_switch`` share of the attempts, then the best; each candidate's t
trials are uniform in its interval, ``init_width * h * reduction^(a+1)`` wide per coordinate (h the local edge
length); greedy replacement; saturation (every behaviour within ``tol`` of the best, and the best not improved by
more, for `patience` attempts) or ``F <= ftol`` stops a seed, else ``attempts`` do.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.projection import params_to_points, project
from ..metrics.objective import ExtraCells, no_extra, objective_and_max
from ..runtime.transfer import program
from . import _draws
from .cohort import calm_after, counter_follow, counter_rows, follow, learning_attempt, split_params, trials
from .parametrisation import Parametrisation


def candidate_batch(platform: str, n_trials: int) -> int:
    """Trial meshes evaluated at once on `platform`: all of an attempt's (`n_trials`, every seed's) on an
    accelerator, one `jax.vmap` (H200, cube729, 1000 attempts: 30 seeds in 0.26 s warm, 8.5 ms a seed); one at a
    time on a CPU, where batches of 5 or 25 were no faster (2-core CPU, cube729: 1.5-1.9 s for every batch size,
    within the machine's noise) and hold more memory (docs/engines.md)."""
    return n_trials if platform != "cpu" else 1


def _threefry(key):
    """`key` (any implementation) as a threefry key made from its first two words: threefry splits and draws
    are the same for one key alone and for a batch of keys under `jax.vmap` ("rbg" ones are not)."""
    return jax.random.wrap_key_data(_draws.key_words(key), impl="threefry2x32")


def _row_uniforms(key, a, rows, n: int, dtype, stream: str):
    """The uniforms ``(R, n)`` in [0, 1) of attempt `a`'s trial rows `rows` ``(R,)`` (row ``r = c t + j``:
    candidate c's j-th variation): ``"native"``, a threefry draw from the attempt's `key` folded with `r`;
    ``"counter"``, `jaxci.optim.cohort.counter_rows` under the seed words `key` ``(2,)`` (what the host draws
    there). Either way the numbers of one row do not depend on the other rows drawn with them (unlike "rbg" draws
    under `jax.vmap`): a device draws its own rows only, and a seed its own, the numbers of one device and of one
    seed alone."""
    if stream == "counter":
        return counter_rows(key, a, rows, n, dtype, jnp)
    key = _threefry(key)
    return jax.vmap(lambda r: jax.random.uniform(jax.random.fold_in(key, r), (n,), dtype))(rows)


def _follow_uniforms(key, a, C: int, dtype, stream: str):
    """The uniforms ``(C,)`` of attempt `a`'s roulette (`_row_uniforms`' streams; the counter's:
    `jaxci.optim.cohort.counter_follow`)."""
    if stream == "counter":
        return counter_follow(key, a, C, dtype, jnp)
    return jax.random.uniform(key, (C,), dtype)


def _points(par: Parametrisation, U):
    """Node coordinates ``(B, R, n, 3)`` of the free coordinates `U` ``(B, R, n_free)`` of seeds whose
    parametrisations `par` are stacked (leading axis B): lifted, and each mesh with a moving boundary node outside
    its flat region projected onto its seed's original boundary (the others as lifted: the projection of a point
    of a flat region is itself only to rounding, so a mesh's numbers must not depend on the meshes evaluated with
    it). The search runs only where some mesh of the batch needs it (one `jax.lax.cond`)."""
    X = jax.vmap(lambda p, Ub: jax.vmap(p.lift)(Ub))(par, U)
    if not par.shortcut:
        return jax.vmap(lambda p, Xb: project(p.cons, Xb))(par, X)
    inside = jax.vmap(lambda p, Xb: jax.vmap(p.inside)(Xb))(par, X)  # (B, R)

    def projected(X):
        P = jax.vmap(lambda p, Xb: project(p.cons, Xb))(par, X)
        return jnp.where(inside[:, :, None, None], X, P)

    return jax.lax.cond(jnp.all(inside), lambda X: X, projected, X)


def _behaviours(par: Parametrisation, U, conn, extra: ExtraCells, batch: int):
    """F and max kappa/3 ``(B, R)`` of the trial meshes `U` ``(B, R, n_free)``, `batch` meshes at a time."""
    X = _points(par, U)
    B, R = X.shape[:2]
    flat = X.reshape(B * R, *X.shape[2:])
    size = max(1, min(int(batch), B * R))
    pad = -(B * R) % size
    if pad:
        flat = jnp.concatenate([flat, jnp.broadcast_to(flat[:1], (pad, *flat.shape[1:]))])
    one = jax.vmap(lambda x: objective_and_max(x, conn, extra))
    f, k = jax.lax.map(one, flat.reshape(-1, size, *flat.shape[1:]))
    return f.reshape(-1)[: B * R].reshape(B, R), k.reshape(-1)[: B * R].reshape(B, R)


def _rows(keys, a, rows, centre, w, t: int, stream: str):
    """The trial meshes ``(B, R, n_free)`` of every seed at `rows` ``(B, R)`` (`jaxci.optim.cohort.trials`, drawn
    by `_row_uniforms` from each seed's `keys`)."""
    nf = centre.shape[-1]
    u = jax.vmap(lambda k, ab, r: _row_uniforms(k, ab, r, nf, centre.dtype, stream))(keys, a, rows)
    return trials(centre, rows, u, w, t, jnp)


def _attempt_behaviours(keys, a, centre, w, t: int, par, conn, extra, mesh, batch: int, stream: str):
    """``(F, max kappa/3)`` ``(B, C t)`` of the trial meshes of an attempt of every seed (`_rows` with each
    seed's key); with `mesh` (a `jax.sharding.Mesh`, one seed), the rows split over its devices (`jax.shard_map`,
    padded with copies of row 0 to a multiple of the device count), each device drawing and evaluating its own
    rows as one device would: the same numbers."""
    def rows_of(rows, keys, a, centre, w, par, conn, extra):
        U = _rows(keys, a, jnp.broadcast_to(rows, (keys.shape[0], rows.shape[0])), centre, w, t, stream)
        return _behaviours(par, U, conn, extra, batch)

    S = centre.shape[1] * t
    if mesh is None:
        return rows_of(jnp.arange(S), keys, a, centre, w, par, conn, extra)
    from jax.sharding import PartitionSpec as P

    from .sharding import AXIS

    rows = jnp.arange(S + (-S % mesh.devices.size)) % S
    f, k = jax.shard_map(rows_of, mesh=mesh, in_specs=(P(AXIS),) + (P(),) * 7,
                         out_specs=(P(None, AXIS), P(None, AXIS)))(rows, keys, a, centre, w, par, conn, extra)
    return f[:, :S], k[:, :S]


@program
@functools.partial(jax.jit, static_argnames=("s", "mesh", "batch", "stream"))
def _global_ci_run(keys, par: Parametrisation, conn, scale, s, d: dict, extra: ExtraCells, mesh=None,
                   batch: int = 1, stream: str = "native"):
    """Global CI of B seeds at once: `keys` ``(B,)``, `par` stacked parametrisations (leading axis B, unscaled:
    ``u`` in coordinates), `scale` ``(B, n_free)`` the local edge length per free coordinate; `s` the static
    hyperparameters (`jaxci.optim.cohort.StaticParams`), `d` the traced ones; `stream` the random numbers'
    (`_row_uniforms`). Returns the points ``(B, n, 3)``, the attempts ``(B,)`` and the histories
    ``(B, attempts + 1, 3)`` (best F, worst F, max kappa/3 of the best; NaN after a seed stopped)."""
    C, t, T = s.cohort, s.variations, d["attempts"]
    B, nf = scale.shape
    dtype = par.x0.dtype
    if stream == "counter":  # the seed words of each key, as the host's seed_words
        keys = jax.vmap(_draws.key_words)(keys)
    else:
        keys = jax.vmap(_threefry)(keys)  # draws that do not depend on the other seeds drawn with them
    f0, k0 = _behaviours(par, jnp.zeros((B, 1, nf), dtype), conn, extra, 1)
    f0, k0 = f0[:, 0], k0[:, 0]
    cand = jnp.zeros((B, C, nf), dtype)
    fc, kc = jnp.broadcast_to(f0[:, None], (B, C)), jnp.broadcast_to(k0[:, None], (B, C))
    hist = jnp.full((B, s.attempts + 1, 3), jnp.nan, dtype).at[:, 0].set(jnp.stack([f0, f0, k0], axis=-1))
    n_roulette = jnp.round(d["stage_switch"] * T)
    seeds = jnp.arange(B)

    def attempt(carry):
        keys, cand, fc, kc, a, hist, calm, done = carry
        if stream == "counter":
            kf = ku = keys
        else:
            split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
            keys, kf, ku = split[:, 0], split[:, 1], split[:, 2]
        u = jax.vmap(lambda k, ab: _follow_uniforms(k, ab, C, dtype, stream))(kf, a)
        chosen = follow(fc, d["delta"], (a < n_roulette)[:, None], u, jnp)  # (B, C)
        w = d["init_width"] * scale * (d["reduction"] ** (a + 1).astype(dtype))[:, None]  # (B, nf)
        new_cand, new_fc, new_kc = learning_attempt(
            cand, fc, kc, chosen,
            lambda centre: _attempt_behaviours(ku, a, centre, w, t, par, conn, extra, mesh, batch, stream),
            lambda centre, rows: _rows(ku, a, rows, centre, w, t, stream), t, jnp)
        new_a = a + 1
        best = jnp.min(new_fc, axis=-1)
        row = jnp.stack([best, jnp.max(new_fc, axis=-1), jnp.take_along_axis(
            new_kc, jnp.argmin(new_fc, axis=-1)[:, None], axis=-1)[:, 0]], axis=-1)
        new_calm = calm_after(new_fc, jnp.min(fc, axis=-1), calm, d["tol"], d["ftol"], jnp)
        stop = (new_calm >= d["patience"]) | (best <= d["ftol"]) | (new_a >= T)
        live = ~done  # a seed that stopped keeps its state
        keep = lambda new, old: jnp.where(live.reshape(-1, *([1] * (new.ndim - 1))), new, old)  # noqa: E731
        hist = hist.at[seeds, jnp.where(live, new_a, 0)].set(jnp.where(live[:, None], row, hist[seeds, 0]))
        return (keys, keep(new_cand, cand), keep(new_fc, fc), keep(new_kc, kc), keep(new_a, a), hist,
                keep(new_calm, calm), done | stop)

    def cond(carry):
        return ~jnp.all(carry[7])

    init = (keys, cand, fc, kc, jnp.zeros(B, jnp.int32), hist, jnp.zeros(B, jnp.int32), (f0 <= d["ftol"]) | (T <= 0))
    _, cand, fc, _, a, hist, _, _ = jax.lax.while_loop(cond, attempt, init)
    best = jnp.take_along_axis(cand, jnp.argmin(fc, axis=-1)[:, None, None], axis=1)[:, 0]  # (B, nf)
    x = jax.vmap(lambda p, u: params_to_points(p.cons, u, p.x0))(par, best)
    return x, a, hist


def stack(trees):
    """The pytrees `trees` (one per seed) stacked along a new leading axis (`stackable` must hold)."""
    return jax.tree.map(lambda *a: jnp.stack([jnp.asarray(v) for v in a]), *trees)


def stackable(trees) -> bool:
    """Whether the pytrees `trees` (per-seed parametrisations, scales) have the same structure, static fields and
    array shapes and dtypes, so that `stack` can run them as one batch."""
    first = jax.tree.structure(trees[0])
    shapes = [tuple((np.shape(v), str(getattr(v, "dtype", type(v).__name__))) for v in jax.tree.leaves(t))
              for t in trees]
    return all(jax.tree.structure(t) == first for t in trees) and all(s == shapes[0] for s in shapes)


def global_ci_batched(keys, pars, conn, scales, p, extra: ExtraCells | None = None, *, devices=None,
                      stream: str = "native"):
    """Run the paper's global CI for B seeds as one program (see the module docstring).

    **Arguments:**

    - `keys`: B `jax.random` keys, one per seed.
    - `pars`: B unscaled `jaxci.optim.parametrisation.Parametrisation` (``scaled=False``), one per seed's mesh
      (`stackable`).
    - `conn`: the transposed connectivity ``(8, N)`` the seeds share; `extra` their non-hexahedral cells.
    - `scales`: B arrays ``(n_free,)``, the local edge length per free coordinate of each seed's mesh.
    - `p`: `jaxci.optim.ci_params.CIParams`.
    - `devices` (keyword only): None, or a `jax.sharding.Mesh` (one seed only): the ``C t`` trial meshes of
      every attempt split over its devices.
    - `stream` (keyword only): ``"native"`` (`jax.random` from each key) or ``"counter"`` (`jaxci.optim._draws`
      under each key's words: the numbers `jaxci.optim.host_global.global_ci_np` draws for the same seed).

    **Returns:** a list of B ``(points, attempts, history)`` as `jaxci.optim.ci.global_ci` returns.
    """
    extra = no_extra() if extra is None else extra
    if devices is not None and len(pars) != 1:
        raise ValueError("global CI sharded over devices runs one seed at a time")
    platform = next(iter(jnp.asarray(pars[0].x0).devices())).platform
    batch = candidate_batch(platform, int(p.cohort) * int(p.variations) * len(pars))
    par = jax.tree.map(lambda v: jnp.asarray(v)[None], pars[0]) if len(pars) == 1 else stack(pars)
    static, traced = split_params(p, pars[0].x0.dtype)
    scale = jnp.stack([jnp.asarray(sc, pars[0].x0.dtype) for sc in scales])
    x, a, hist = _global_ci_run(jnp.stack(list(keys)), par, conn, scale, static, traced, extra, devices, int(batch),
                                 stream)
    a = np.asarray(a)
    hist = np.asarray(hist)
    out = []
    for b in range(len(pars)):
        h = hist[b, : int(a[b]) + 1]
        out.append((x[b], int(a[b]), {"objective": h[:, 0], "best": h[:, 0], "worst": h[:, 1],
                                      "max_condition": h[:, 2]}))
    return out
