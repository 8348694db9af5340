"""The two-level preconditioner of the host L-BFGS (`jaxci.optim.coarse`, ``precondition="coarse"``)."""

import numpy as np
import pytest
from helpers import wavy_annulus

from jaxci import native, smooth
from jaxci.errors import ConfigError
from jaxci.interface.engine import host_plan
from jaxci.interface.smooth import build_problem
from jaxci.mesh.generate import perturb_box
from jaxci.optim import coarse, host
from jaxci.optim.parametrisation import make_parametrisation


def _space(mesh, **kw):
    problem = build_problem(mesh, dtype=np.float64, plan=host_plan())
    par = make_parametrisation(problem.mesh, problem.info, problem.cons, dtype=np.float64)
    return par, coarse.build_coarse(par, {"hexahedron": mesh.hexes}, **kw)


def _dense(pc: coarse.CoarseSpace) -> np.ndarray:
    n = len(pc.inv_diag)
    z = np.zeros((n, len(pc.coarse_inv)))
    z[np.arange(n)[:, None], 3 * pc.block[:, None] + np.arange(3)] = pc.z
    return z @ pc.coarse_inv @ z.T + np.diag(pc.inv_diag)


@pytest.mark.parametrize("mesh", [wavy_annulus(16, 2, 2), perturb_box(4, amplitude=0.2, seed=3)],
                         ids=["annulus", "box"])
@pytest.mark.parametrize("use_c", [True, False])
def test_the_preconditioner_is_symmetric_positive_definite(mesh, use_c, monkeypatch):
    """M = Z P_c^-1 Z^T + D^-1 as applied (C and numpy) is the dense matrix, symmetric, with positive
    eigenvalues: L-BFGS with the initial inverse Hessian gamma M keeps its descent guarantee."""
    if use_c and not native.AVAILABLE:
        pytest.skip("the C kernels are not built")
    monkeypatch.setattr(native, "AVAILABLE", use_c)
    par, pc = _space(mesh)
    m = _dense(pc)
    rng = np.random.default_rng(0)
    q = rng.standard_normal(par.n_free)
    np.testing.assert_allclose(pc(q), m @ q, rtol=1e-12, atol=1e-12 * np.abs(m @ q).max())
    np.testing.assert_allclose(m, m.T, rtol=0, atol=1e-12 * np.abs(m).max())
    assert np.linalg.eigvalsh(m).min() > 0
    assert 0 < len(pc.coarse_inv) <= 3 * coarse.MAX_AGGREGATES and len(pc.coarse_inv) % 3 == 0


def test_the_coarse_matrix_and_diagonal_are_those_of_the_edge_laplacian():
    """Built independently here (dense): P = S B^T (L x I_3) B S over the free coordinates, L the Laplacian of the
    hexahedra's edges with weights 1 / length^2. The module's P_c (without its delta) is Z^T P Z, also though it
    leaves out the edges inside one aggregate between interior nodes, and its diagonal is diag(P)."""
    mesh = wavy_annulus(16, 2, 2)
    par, pc = _space(mesh, delta=1e-12)
    node, direction = coarse.free_directions(par)
    scale = np.asarray(par.scale)
    n, nf = mesh.n_nodes, par.n_free
    b = np.zeros((3 * n, nf))
    b[3 * node[:, None] + np.arange(3), np.arange(nf)[:, None]] = direction * scale[:, None]
    lap = np.zeros((n, n))
    x = np.asarray(mesh.points)
    edges = {tuple(sorted(e)) for h in mesh.hexes for e in h[[[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7],
                                                              [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]].tolist()}
    for i, j in edges:
        w = 1.0 / np.sum((x[i] - x[j]) ** 2)
        lap[i, i] += w
        lap[j, j] += w
        lap[i, j] -= w
        lap[j, i] -= w
    p = b.T @ np.kron(lap, np.eye(3)) @ b
    z = np.zeros((nf, len(pc.coarse_inv)))
    z[np.arange(nf)[:, None], 3 * pc.block[:, None] + np.arange(3)] = pc.z
    np.testing.assert_allclose(pc.inv_diag, 1.0 / np.diag(p), rtol=1e-12)
    built = np.linalg.inv(pc.coarse_inv)
    np.testing.assert_allclose(built, z.T @ p @ z, rtol=1e-6, atol=1e-8 * np.abs(built).max())


def test_aggregates_cover_every_node_within_the_budget():
    rng = np.random.default_rng(1)
    for points, most in ((rng.random((5000, 3)), 128), (rng.random((300, 3)) * [1, 1, 0], 16),
                         (np.zeros((5, 3)), 128)):
        agg = coarse.aggregates(points, 27, most)
        assert agg.shape == (len(points),) and agg.min() == 0
        k = int(agg.max()) + 1
        assert k <= most and np.array_equal(np.unique(agg), np.arange(k))  # numbered 0..k-1, none empty


@pytest.mark.parametrize("dtype", [np.float64, np.float16])
def test_the_c_two_loop_recursion_with_the_preconditioner_is_the_numpy_one(dtype, monkeypatch):
    if not native.AVAILABLE:
        pytest.skip("the C kernels are not built")
    par, pc = _space(wavy_annulus(16, 2, 2))
    n, rng = par.n_free, np.random.default_rng(2)
    monkeypatch.setattr(host, "HISTORY_F16_FROM", n if dtype == np.float16 else n + 1)
    mem = host._Memory(n, 5)
    assert mem.S.dtype == dtype
    mem.use(pc)
    g = rng.standard_normal(n)
    np.testing.assert_allclose(mem.direction(g), -pc(g), rtol=1e-12, atol=1e-12 * np.abs(pc(g)).max())  # no pairs
    for _ in range(7):  # more pairs than the memory holds: the ring buffer wraps
        s = rng.standard_normal(n)
        mem.push(mem.stored(s + 0.0), mem.stored(s + 0.2 * rng.standard_normal(n)))
    assert len(mem.order) == 5 and mem.gamma > 0
    g = rng.standard_normal(n)
    d_c = mem.direction(g)
    monkeypatch.setattr(native, "AVAILABLE", False)
    d_np = mem.direction(g)
    np.testing.assert_allclose(d_c, d_np, rtol=1e-10, atol=1e-12 * np.abs(d_np).max())
    assert g @ d_c < 0


def test_preconditioned_lbfgs_on_sliding_curved_walls():
    """The same optimum as plain L-BFGS (F to 1e-4), every node where it may be: no inverted element, the wall
    nodes on their cylinders and end planes."""
    mesh = wavy_annulus()
    plain = smooth(mesh, "lbfgs", precondition="none")
    pre = smooth(mesh, "lbfgs", precondition="coarse")
    assert pre.params["precondition"] == "coarse"
    # M was used from the first direction on: the second accepted iterate already differs
    assert not np.array_equal(pre.history["objective"][:5], plain.history["objective"][:5])
    assert pre.after.inverted_elements == 0
    assert pre.history["objective"][-1] <= plain.history["objective"][-1] * (1 + 1e-4)
    assert pre.history["objective"][-1] < 0.5 * pre.history["objective"][0]
    p0, p = np.asarray(mesh.points), np.asarray(pre.mesh.points)
    r0, r = np.hypot(p0[:, 0], p0[:, 1]), np.hypot(p[:, 0], p[:, 1])
    for wall in (0.5, 1.0):
        on = np.abs(r0 - wall) < 1e-9
        # on the wall's facets: between the circle and its chords (the input's wall nodes are at most 1.6 angular
        # spacings apart, so no chord comes nearer the axis than cos(1.6 pi / 32) of the radius)
        assert on.any() and np.all(r[on] <= wall + 1e-9) and np.all(r[on] >= wall * np.cos(1.6 * np.pi / 32) - 1e-9)
    for end in (0.0, 1.0):
        on = np.abs(p0[:, 2] - end) < 1e-12
        np.testing.assert_allclose(p[on, 2], end, atol=1e-9)


@pytest.mark.parametrize("kw", [dict(method="cg"), dict(method="lbfgs", backend="jax")])
def test_the_preconditioner_is_refused_off_the_host_lbfgs_and_newton(kw):
    with pytest.raises(ConfigError, match="precondition"):
        smooth(perturb_box(3, amplitude=0.2, seed=1), precondition="coarse", **kw)


def test_the_jax_engines_application_is_the_hosts():
    """`coarse.coarse_apply` over jax.numpy (the JAX engine's Newton) is M as the host applies it, and
    `CoarseSpace.padded` leaves a padding coordinate as it is and the real ones as before."""
    import jax.numpy as jnp

    par, pc = _space(wavy_annulus(16, 2, 2))
    q = np.random.default_rng(4).standard_normal(len(pc.inv_diag))
    dev = coarse.coarse_apply(tuple(jnp.asarray(a) for a in pc.arrays()), jnp.asarray(q), jnp)
    np.testing.assert_allclose(np.asarray(dev), pc(q), rtol=1e-12, atol=1e-12)
    n = len(q)
    index = np.arange(n) * 2 + 1  # the real coordinates at odd places of a vector twice as long
    qp = np.arange(2.0 * n)
    qp[index] = q
    out = coarse.coarse_apply(pc.padded(index, 2 * n).arrays(), qp)
    np.testing.assert_allclose(out[index], pc(q), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(out[::2], qp[::2])


@pytest.mark.parametrize("precondition", ["auto", "none"])
def test_newton_on_the_jax_engine_follows_the_hosts(precondition):
    """The JAX engine's truncated Newton on sliding curved walls, with M (``"auto"``: from its first step, as the
    host's) or without: within five Newton iterations of the host's run with the same preconditioner (26 and 29,
    18 and 20 measured), F within 1e-4 of it (the two engines hold the boundary nodes near a triangle's edge to
    different triangles)."""
    mesh = wavy_annulus(32, 3, 3)
    kw = dict(method="lbfgs", dtype="float64", keep_worst=False, solver="newton", precondition=precondition)
    host_run = smooth(mesh, **kw)
    jax_run = smooth(mesh, engine="jax", **kw)
    assert abs(jax_run.history["newton_iterations"] - host_run.history["newton_iterations"]) <= 5
    assert jax_run.after.objective == pytest.approx(host_run.after.objective, rel=1e-4)
    assert jax_run.after.inverted_elements == 0
