"""Uniform random numbers both engines draw alike: a counter-based stream, written once over the array module.

Each engine has its own random stream for Cohort Intelligence: the JAX engine `jax.random` keys, the host numpy's
PCG64 (global CI) and one xoshiro256** stream per node in C (local CI). The same seed therefore gives different
meshes on the two engines, and their agreement can only be judged statistically. With ``stream="counter"`` both
engines draw every uniform from this stream instead: a number is a hash of the run's seed and of where it is
used (a path of counters: sweep, colour, node, learning attempt, what it draws; then its index), so each engine
computes the same numbers in any order, on any number of devices or threads, and the two engines' runs can be
compared step by step (`tests/test_ci_parity.py`: the same mesh to 1e-9 in float64).

The hash is MurmurHash3's 32-bit finaliser applied to the running word xor each counter times the golden ratio
(`mix`); a float64 uniform takes 53 bits from two such words, a float32 one 24 bits from one. All arithmetic is on
uint32 arrays (numpy and XLA both wrap it modulo 2^32). The C cohort of `jaxci.native.ci_visit` has its own copy
of `mix` (C cannot call this one); `tests/test_ci_parity.py` checks that the two give the same numbers.
"""

from __future__ import annotations

import numpy as np

GOLDEN = 0x9E3779B1  # 2^32 / golden ratio, odd
M1, M2 = 0x85EBCA6B, 0xC2B2AE35  # MurmurHash3's fmix32 multipliers


def mix(h, v, xp):
    """The running hash word `h` after the counter `v` (uint32 arrays or scalars, broadcast)."""
    u32 = xp.uint32
    with np.errstate(over="ignore"):  # numpy warns of the wrap-around on scalars; it is the arithmetic meant here
        h = xp.asarray(h, u32) ^ (xp.asarray(v, u32) * u32(GOLDEN))
        h = h ^ (h >> u32(16))
        h = h * u32(M1)
        h = h ^ (h >> u32(13))
        h = h * u32(M2)
        return h ^ (h >> u32(16))


def seed_words(seed: int) -> np.ndarray:
    """The two uint32 words of an integer seed (high, low): the key data of ``jax.random.key(seed)`` for a
    threefry key and ``0 <= seed < 2^32``, so a host run's seed and the JAX engine's key name the same stream."""
    seed = int(seed) % 2**64
    return np.array([seed >> 32, seed & 0xFFFFFFFF], np.uint32)


def key_words(key):
    """The two uint32 words of a `jax.random` key's data that `seed_words` gives for its seed (the first two: a
    threefry or "rbg" key made from a seed below 2^32); JAX arrays, under `jax.jit` too."""
    from ..runtime._lazy import jax, jnp

    return jax.random.key_data(key).ravel()[:2].astype(jnp.uint32)


def path(words, counters, xp):
    """The hash word of the stream at `counters` (a sequence of counters, each a uint32 array or scalar,
    broadcast) under the seed `words` ``(2,)``."""
    h = mix(mix(xp.uint32(0), words[0], xp), words[1], xp)
    for c in counters:
        h = mix(h, c, xp)
    return h


def visit_word(words, sweep, colour, xp):
    """Local CI's word of one colour's visit in sweep `sweep`: each node of it draws under
    ``mix(mix(word, node), attempt)`` (then 0 for its roulette, 1 for its trials), in the compiled sweep
    (`jaxci.optim.ci`) and in the C cohort (`jaxci.native.ci_visit`)."""
    return path(words, (sweep, colour), xp)


def uniforms(h, index, dtype, xp):
    """Uniforms in [0, 1) of the stream word `h` at the indices `index` (uint32, broadcast against `h`): float64
    from 53 bits of two words, float32 from 24 bits of one."""
    index = xp.asarray(index, xp.uint32)
    if np.dtype(dtype) == np.float64:
        a = mix(h, index * xp.uint32(2), xp) >> xp.uint32(5)
        b = mix(h, index * xp.uint32(2) + xp.uint32(1), xp) >> xp.uint32(6)
        return (a.astype(dtype) * 67108864.0 + b.astype(dtype)) * (1.0 / 9007199254740992.0)
    return (mix(h, index * xp.uint32(2), xp) >> xp.uint32(8)).astype(dtype) * np.float32(1.0 / 16777216.0)
