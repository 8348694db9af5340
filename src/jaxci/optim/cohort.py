"""The learning attempt's pieces both forms of Cohort Intelligence share on the JAX engine (`jaxci.optim.ci`'s local
CI, `jaxci.optim.global_ci`): the split of `jaxci.optim.ci_params.CIParams` into what fixes shapes (static under
`jax.jit`) and what does not, and the follow step of the cohort."""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp

from .ci_params import CIParams


class StaticParams(typing.NamedTuple):
    """The hyperparameters that fix array shapes or loop bounds: static under jit (one compile each)."""

    cohort: int
    variations: int
    attempts: int
    max_sweeps: int
    patience: int
    pattern: bool
    anderson: int


def split_params(p: CIParams, dtype) -> tuple[StaticParams, dict]:
    """Static part and traced part of `p`: changing reduction, widths or tolerances does not recompile."""
    s = StaticParams(int(p.cohort), int(p.variations), int(p.attempts), int(p.max_sweeps), int(p.patience),
                bool(p.pattern), int(p.anderson))
    d = {k: jnp.asarray(getattr(p, k), dtype) for k in
         ("reduction", "delta", "stage_switch", "init_width", "min_width", "tol", "atol", "ftol", "ktol")}
    return s, d


def follow(key, g, delta, roulette):
    """Index each candidate follows: roulette on 1/(g + delta), or the best. `g` has shape ``(..., C)``, >= 0."""
    logits = -jnp.log(g + delta)  # g = inf (an inverted candidate) -> probability 0
    wheel = jnp.broadcast_to(logits[..., None, :], (*g.shape, g.shape[-1]))
    rou = jax.random.categorical(key, wheel, axis=-1)
    best = jnp.broadcast_to(jnp.argmin(g, axis=-1)[..., None], g.shape)
    return jnp.where(roulette, rou, best)
