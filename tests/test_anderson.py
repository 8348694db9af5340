"""Anderson acceleration of local CI's sweeps (`jaxci.optim._anderson`): what it computes, in numpy and JAX."""

from __future__ import annotations

import numpy as np
import pytest

from jaxci.optim._anderson import anderson_point


def _sweeps(m: int, n: int = 60, seed: int = 0):
    """m steps of the slow linear fixed-point map x -> M x + b (four eigenvalues, 0.5 to 0.99, like the
    long-wavelength modes a Gauss-Seidel sweep hardly damps): the starts and moves ``(m, n)`` and the fixed
    point."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    M = Q @ np.diag(np.repeat([0.5, 0.8, 0.95, 0.99], n // 4)) @ Q.T
    b = rng.normal(size=n)
    fixed = np.linalg.solve(np.eye(n) - M, b)
    x, starts, moves = np.zeros(n), [], []
    for _ in range(m):
        g = M @ x + b
        starts.append(x)
        moves.append(g - x)
        x = g
    return np.array(starts), np.array(moves), fixed


def test_anderson_point_lands_far_nearer_the_fixed_point_than_the_last_sweep():
    """Four slow modes: seven differences of eight sweeps span them, and the combination cancels them up to the
    regularisation (measured: 1% of the last sweep's error left; 0.1% with ten sweeps)."""
    starts, moves, fixed = _sweeps(8)
    last = starts[-1] + moves[-1]
    aa = anderson_point(starts, moves, 8, np)
    assert np.linalg.norm(last - fixed) > 0.3 * np.linalg.norm(fixed)
    assert np.linalg.norm(aa - fixed) < 0.02 * np.linalg.norm(last - fixed)


def test_anderson_point_ignores_the_rows_before_the_valid_ones_and_needs_two():
    starts, moves, _ = _sweeps(5)
    junk = np.full((3, starts.shape[1]), 1e6)
    padded_s, padded_m = np.concatenate([junk, starts]), np.concatenate([junk, moves])
    assert np.allclose(anderson_point(padded_s, padded_m, 5, np), anderson_point(starts, moves, 5, np), rtol=1e-9,
                       atol=1e-9)
    # one real sweep: its own result, whatever the rows before it hold
    assert np.array_equal(anderson_point(padded_s, padded_m, 1, np), starts[-1] + moves[-1])


def test_anderson_point_is_the_same_in_jax():
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    starts, moves, _ = _sweeps(6, seed=1)  # float64: tests/conftest.py enables x64
    got = np.asarray(jax.jit(lambda s, m, v: anderson_point(s, m, v, jnp))(starts, moves, 4))
    assert np.allclose(got, anderson_point(starts, moves, 4, np), rtol=1e-10, atol=1e-10)


def test_the_host_memory_gives_anderson_point_sweep_by_sweep():
    """`AndersonMemory` (local CI on the host: ring buffers and a Gram matrix extended by one row a sweep) gives
    `anderson_point` of the last m sweeps after every sweep, and nothing before the second."""
    from jaxci.optim._anderson import AndersonMemory

    starts, moves, _ = _sweeps(12, seed=2)
    for m in (1, 2, 3, 8):
        memory = AndersonMemory(m, starts.shape[1])
        for i in range(len(starts)):
            memory.push(starts[i], moves[i])
            got, lo = memory.point(), max(0, i + 1 - m)
            if min(i + 1, m) < 2:
                assert got is None
            else:
                want = anderson_point(starts[lo : i + 1], moves[lo : i + 1], min(i + 1, m), np)
                np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * np.abs(want).max())
