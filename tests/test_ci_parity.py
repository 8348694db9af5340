"""Cohort Intelligence step by step on both engines: fed the same uniforms (the counter stream of
`jaxci.optim._draws`, ``stream="counter"``), the host engine (numpy and C) and the JAX engine take the same steps
and give the same mesh to 1e-9 in float64, for local CI (colour sweeps, pattern and Anderson moves) and for global
CI (the paper's), on a perturbed box and on a real mesh (Mesquite's block with an internal bias)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import MESQUITE

from jaxci import native
from jaxci.interface import engine
from jaxci.interface.methods import build_problem, free_scale, global_parametrisation
from jaxci.io import read_mesh
from jaxci.mesh.generate import paper_case
from jaxci.optim import _draws
from jaxci.optim._moves import coloured_stars
from jaxci.optim.ci import global_ci, local_ci
from jaxci.optim.ci_params import CIParams
from jaxci.optim.host_global import global_ci_np
from jaxci.optim.host_local import local_ci_np
from jaxci.optim.parametrisation import free_lengths
from jaxci.runtime._lazy import enable_x64

BIAS = MESQUITE / "1000hex-block-internal-bias.vtk"

pytestmark = pytest.mark.skipif(not native.AVAILABLE, reason="the host engine's CI needs the C extension "
                                "(jaxci._ckernels), which this install lacks")


def test_the_counter_stream_draws_the_same_numbers_with_numpy_and_jax():
    words = _draws.seed_words(11)
    with enable_x64():
        assert np.array_equal(words, np.asarray(jax.random.key_data(jax.random.key(11, impl="rbg")))[:2])
        h = _draws.path(words, (3, np.arange(5)[:, None], 2), np)
        hj = _draws.path(jax.numpy.asarray(words), (3, jax.numpy.arange(5)[:, None], 2), jax.numpy)
        assert np.array_equal(h, np.asarray(hj))
        for dtype in (np.float64, np.float32):
            u = _draws.uniforms(h, np.arange(7), dtype, np)
            assert u.dtype == dtype and u.shape == (5, 7) and 0 <= u.min() and u.max() < 1
            assert np.array_equal(u, np.asarray(_draws.uniforms(hj, jax.numpy.arange(7), dtype, jax.numpy)))
    big = _draws.uniforms(_draws.path(words, (np.arange(2000)[:, None],), np), np.arange(100), np.float64, np)
    assert abs(big.mean() - 0.5) < 0.005 and abs(big.var() * 12 - 1) < 0.01  # uniform, not merely in range


def _meshes():
    return [pytest.param(lambda: paper_case("cube27", seed=1), id="box"),
            pytest.param(lambda: read_mesh(BIAS), id="bias-block", marks=pytest.mark.shared)]


def _problems(mesh):
    host = build_problem(mesh, dtype=np.float64, plan=engine.host_plan())
    with enable_x64():
        return host, build_problem(mesh, dtype=np.float64)


@pytest.mark.parametrize("make", _meshes())
def test_global_ci_takes_the_same_steps_on_both_engines(make):
    mesh = make()
    p = CIParams.for_method("ci-global", attempts=150, init_width=0.01)  # 0.03: no trial betters the bias block
    host, dev = _problems(mesh)
    xh, ah, hh = global_ci_np(host.x0, mesh.hexes, host.cons, free_lengths(mesh, host.cons), p, 3,
                              host.info.topology.faces, stream="counter")
    with enable_x64():
        xj, aj, hj = global_ci(jax.random.key(3, impl="rbg"), global_parametrisation(dev), dev.conn, free_scale(dev),
                               p, stream="counter")
        xj = np.asarray(xj)
    assert ah == aj and hh["best"][-1] < 0.9 * hh["best"][0]  # it moved the mesh, the same attempts
    np.testing.assert_allclose(hj["best"], hh["best"], rtol=1e-9)
    np.testing.assert_allclose(xj, xh, rtol=0, atol=1e-9)
    other, _, _ = global_ci_np(host.x0, mesh.hexes, host.cons, free_lengths(mesh, host.cons), p, 4,
                               host.info.topology.faces, stream="counter")
    assert np.abs(other - xh).max() > 1e-6  # another seed, other numbers: the agreement is not trivial


@pytest.mark.parametrize("make", _meshes())
def test_local_ci_takes_the_same_steps_on_both_engines(make):
    mesh = make()
    p = CIParams(max_sweeps=4, tol=0.0, atol=0.0)
    host, dev = _problems(mesh)
    faces = host.info.topology.faces
    xh, sh, hh = local_ci_np(host.x0, mesh.hexes, host.cons, host.colour, faces, p, 5, stream="counter")
    with enable_x64():
        cs = coloured_stars(mesh.hexes, dev.cons, dev.colour, faces, dev.table)
        xj, sj, hj = local_ci(jax.random.key(5, impl="rbg"), dev.x0, dev.conn, cs, dev.cons, p, stream="counter")
        xj = np.asarray(xj)
    assert sh == sj == 4 and hh["objective"][-1] < 0.5 * hh["objective"][0]
    np.testing.assert_array_equal(hj["moved"], hh["moved"])
    np.testing.assert_allclose(hj["objective"], hh["objective"], rtol=1e-9)
    np.testing.assert_allclose(xj, xh, rtol=0, atol=1e-9)
