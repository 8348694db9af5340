"""Gradient baselines (optimistix): back to the ideal grid, exact gradients, safety, least-squares size limit.

Compilation dominates the cost here (4-10 s per solver and mesh shape on 2 cores), so the tests share a few
mesh shapes (the 3^3 box with a sliding boundary for most solvers) and the more expensive combinations are
marked ``slow``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxci import native
from jaxci.errors import ConfigError
from jaxci.geometry.boundary import INTERIOR
from jaxci.geometry.projection import params_to_points, points_to_params
from jaxci.interface.smooth import build_problem, smooth
from jaxci.mesh.generate import box, perturb_box
from jaxci.metrics.hexahedron import objective_and_grad, objective_t, objective_terms_and_grad, transposed
from jaxci.optim._solve import make_solver as _solver
from jaxci.optim._solve import solve_loop
from jaxci.optim.gradient import GradientParams, make_parametrisation, minimise
from jaxci.optim.solver_objective import solver_args


def grid_error(mesh_out, n: int) -> float:
    """Largest node distance to the ideal n^3 grid of the unit cube, in units of h = 1/n."""
    return float(np.abs(np.asarray(mesh_out.points) - box(n).points).max() * n)


@pytest.mark.parametrize("method,n,which,fix", [
    ("lbfgs", 9, "interior", True),  # the 729-element cube, boundary fixed
    ("lbfgs", 5, "sliding", False),  # 5^3: shares its compiled solver with test_untangle's hex_5_tangled
    ("bfgs", 3, "sliding", False),
    ("cg", 3, "sliding", False),
    pytest.param("lbfgs", 3, "interior", True, marks=pytest.mark.slow),
    pytest.param("bfgs", 3, "interior", True, marks=pytest.mark.slow),
    pytest.param("cg", 9, "sliding", False, marks=pytest.mark.slow),
])
def test_perturbed_cube_returns_to_the_grid(method, n, which, fix):
    mesh = perturb_box(n, amplitude=0.3, seed=4, which=which)
    res = smooth(mesh, method, dtype="float64", fix_boundary=fix, ktol=0.0)  # to convergence, not to kappa/3 1+1e-6
    assert res.history["solver_result"] == "successful"
    assert res.after.max_condition <= 1 + 1e-6
    assert grid_error(res.mesh, n) <= 1e-5
    hist = np.asarray(res.history["objective"])
    assert len(hist) == res.iterations + 1 and hist[0] == pytest.approx(res.before.objective)
    assert np.all(np.diff(hist) <= 1e-12 * hist[0])  # line-search methods: F never rises
    assert np.asarray(res.history["max_condition"])[0] == pytest.approx(res.before.max_condition)


@pytest.mark.parametrize("method", ["lm", "gauss-newton"])
def test_least_squares_return_to_the_grid(method):
    mesh = perturb_box(3, amplitude=0.3, seed=4, which="sliding")
    res = smooth(mesh, method, dtype="float64", ktol=0.0)  # to convergence
    assert res.after.max_condition <= 1 + 1e-6
    assert grid_error(res.mesh, 3) <= 1e-5


@pytest.mark.parametrize("backend", ["numpy", "jax"])
def test_ktol_stops_once_every_corner_is_ideal_within_it(backend):
    """max kappa/3 <= 1 + ktol is the global minimum to within ktol: the solver stops there (host and compiled
    loop), on the first accepted step that reaches it; ktol=0 runs on to the Cauchy test."""
    mesh = perturb_box(5, amplitude=0.3, seed=4, which="sliding")
    full = smooth(mesh, "lbfgs", dtype="float64", backend=backend, ktol=0.0)
    k_full = np.asarray(full.history["max_condition"])
    ktol = 1e-4
    first = int(np.argmax(k_full <= 1 + ktol))
    assert 0 < first < full.iterations - 5  # the full run goes well past the first step within ktol
    res = smooth(mesh, "lbfgs", dtype="float64", backend=backend, ktol=ktol)
    assert res.iterations == first
    assert res.after.max_condition <= 1 + ktol
    np.testing.assert_array_equal(np.asarray(res.history["max_condition"]), k_full[: first + 1])


def test_least_squares_refuse_large_meshes():
    mesh = perturb_box(9, amplitude=0.1)  # 2400 free coordinates
    with pytest.raises(ConfigError, match="dense Jacobian.*max_free=1000"):
        smooth(mesh, "lm")


@pytest.mark.slow
def test_plain_gauss_newton_inverts_and_falls_back_to_the_best_valid_iterate():
    mesh = perturb_box(3, amplitude=0.3, seed=4, which="sliding")
    res = smooth(mesh, "gauss-newton", dtype="float64", gn_search="none", residual="kappa")
    # the full Gauss-Newton step inverts elements; the NaN state is caught and the input (the only valid
    # iterate) comes back, unchanged
    assert res.history["solver_result"] != "successful"
    assert res.after.inverted_elements == 0
    assert res.after.objective == pytest.approx(res.before.objective)


@pytest.mark.slow
def test_loop_matches_optx_minimise():
    """Our recording loop makes the same calls as optx.minimise: same steps, same iterate."""
    mesh = perturb_box(3, amplitude=0.3, seed=4, which="interior")
    pr = build_problem(mesh, dtype=np.float64, fix_boundary=True)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0)
    p = GradientParams(ktol=0.0)  # optx.minimise has only its own termination
    fn, args = solver_args("lbfgs", par, pr.conn, p)
    v0 = jnp.zeros(par.n_free)
    y, steps, result, hf, _ = solve_loop(_solver("lbfgs", p), fn, v0, args, 2000)
    sol = optx.minimise(fn, _solver("lbfgs", p), v0, args, has_aux=True, max_steps=2000, throw=False)
    assert int(steps) == int(sol.stats["num_steps"])
    assert sol.result == optx.RESULTS.successful and result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(y), np.asarray(sol.value), rtol=0, atol=1e-12)
    # optx.minimise's aux lags one accepted step; the loop records F of the returned iterate itself
    assert float(hf[int(steps)]) == pytest.approx(float(fn(sol.value, args)[1][0]), rel=1e-6, abs=1e-15)


def test_parametrisation_shortcut_equals_projection():
    mesh = perturb_box(3, amplitude=0.2, seed=1, which="sliding")
    pr = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0)
    assert par.shortcut  # planar faces, straight edges
    v = 0.2 * jax.random.normal(jax.random.key(0), (par.n_free,), jnp.float64)
    points = jax.jit(lambda p, u: p.points(u))
    x = points(par, v)
    np.testing.assert_allclose(np.asarray(x), np.asarray(params_to_points(pr.cons, par.scale * v, pr.x0)),
                               atol=1e-12)
    np.testing.assert_allclose(np.asarray(points_to_params(pr.cons, x, par.x0) / par.scale), np.asarray(v),
                               atol=1e-12)
    big = points(par, 20.0 * v)  # far outside the flat regions: the projection runs
    exact = np.asarray(params_to_points(pr.cons, par.scale * 20.0 * v, pr.x0))
    np.testing.assert_allclose(np.asarray(big), exact, atol=1e-12)
    # outside jit (numpy, what minimise returns) and the reach of the flat regions agree with it
    assert par.reach(v) < 1.0 < par.reach(20.0 * v)
    np.testing.assert_allclose(np.asarray(par.final_points(v)), np.asarray(x), atol=1e-12)
    np.testing.assert_allclose(np.asarray(par.final_points(20.0 * v)), exact, atol=1e-12)
    # strict: no projection; outside a flat region every coordinate is NaN (a rejected trial)
    strict = dataclasses.replace(par, strict=True)
    np.testing.assert_allclose(np.asarray(points(strict, v)), np.asarray(x), atol=0)
    assert bool(jnp.all(jnp.isnan(points(strict, 20.0 * v))))


def test_flat_regions_of_a_rotated_box_in_float32():
    """Planes and lines that are not axis-aligned are flat too when the constraints and the start are float32
    (their rounding made every such region fail a 1e-12 test: no shortcut, no strict run)."""
    c, s_ = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c, -s_], [0, s_, c]])
    mesh = perturb_box(4, amplitude=0.3, seed=1, which="sliding")
    mesh = mesh.with_points(mesh.points @ rot.T + 0.123)
    pr = build_problem(mesh, dtype=np.float32)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0)
    assert par.shortcut
    res = smooth(mesh, "lbfgs")
    assert res.after.max_condition < 1.0001 and res.after.inverted_elements == 0
    back = (res.mesh.points - 0.123) @ rot  # in the box's own frame: boundary nodes still on its faces
    on = res.node_class != INTERIOR
    assert np.all(np.min(np.abs(np.stack([back[on], back[on] - 1.0])), axis=0).min(axis=1) < 1e-9)


def test_strict_run_continues_with_the_projection_near_a_flat_region_edge(monkeypatch):
    import jaxci.optim.gradient as G
    import jaxci.optim.lbfgs as L

    mesh = perturb_box(3, amplitude=0.3, seed=2, which="sliding")
    pr = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0)
    seen = []

    loop = L.lbfgs_loop

    def spy(objective, args, *rest, **kw):
        seen.append(args[0].strict)
        return loop(objective, args, *rest, **kw)

    monkeypatch.setattr(L, "lbfgs_loop", spy)
    # the compiled loop; no early stop: the reach test decides
    p = GradientParams(restart_tol=0.0, ktol=0.0, backend="jax")
    x1, _, _, _ = minimise("lbfgs", par, pr.conn, p)
    assert seen and all(seen)  # a box: no node near the edge of its flat region, every run (restarts too) strict
    seen.clear()
    monkeypatch.setattr(G, "FLAT_REACH", 1e-9)  # any boundary move counts as near the edge of its region
    x2, _, h2, _ = minimise("lbfgs", par, pr.conn, p)
    assert seen[:2] == [True, False] and len(h2["restarts"]) >= 1  # on from there with the projection
    f = [float(objective_t(jnp.asarray(x), pr.conn)) for x in (x1, x2)]
    assert f[1] <= f[0] + 1e-12 and f[1] < 1e-6 * float(objective_t(pr.x0, pr.conn))


@pytest.mark.parametrize("backend", [pytest.param("numpy", marks=pytest.mark.skipif(
    not native.AVAILABLE, reason="the host's sweeps are the C kernels")), "jax"])
def test_presmooth_runs_smart_laplace_sweeps_first(backend):
    """On the host (the sweeps in numpy and C, `laplace_np`) and compiled alike."""
    mesh = perturb_box(4, amplitude=0.3, seed=3, which="sliding")
    plain = smooth(mesh, "lbfgs", dtype="float64", backend=backend)
    res = smooth(mesh, "lbfgs", dtype="float64", presmooth=2, backend=backend)
    lap = smooth(mesh, "smart-laplace", dtype="float64", max_sweeps=2, backend=backend)
    h = res.history
    assert h["presmooth"] == 2 and res.params["presmooth"] == 2
    # the history starts with the smart Laplacian's sweeps, then the solver's steps
    np.testing.assert_allclose(h["objective"][:3], lap.history["objective"], rtol=1e-9)
    assert len(h["objective"]) == res.iterations + 1
    assert res.after.inverted_elements == 0 and res.after.objective <= lap.after.objective
    assert res.after.max_condition == pytest.approx(plain.after.max_condition, abs=1e-4)
    with pytest.raises(ConfigError, match="presmooth"):
        smooth(mesh, "lbfgs", presmooth=-1)


def test_a_start_outside_a_flat_region_is_not_run_strict():
    """An edge node moved by the presmooth beyond its flat interval (centred on the original point): the strict
    run would start at a NaN point; it is skipped and every recorded F is finite."""
    mesh = box(3)
    p = mesh.points.copy()
    p[1, 0] = 0.08  # an edge node, close to the corner at 0
    mesh = mesh.with_points(p)
    res = smooth(mesh, "lbfgs", presmooth=1)
    assert np.all(np.isfinite(res.history["objective"]))
    assert res.iterations < 25 and res.after.max_condition < 1.0001


def test_closed_form_gradient_matches_autodiff_and_finite_differences():
    mesh = perturb_box(3, amplitude=0.3, seed=4, which="sliding")
    x = jnp.asarray(mesh.points, jnp.float64)
    conn = transposed(mesh.hexes)
    f, g = objective_and_grad(x, conn)
    f_ad, g_ad = jax.value_and_grad(objective_t)(x, conn)
    assert float(f) == pytest.approx(float(f_ad), rel=1e-12)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_ad), rtol=1e-10, atol=1e-12 * float(jnp.abs(g_ad).max()))
    rng = np.random.default_rng(0)
    d = jnp.asarray(rng.standard_normal(x.shape))
    eps = 1e-6
    fd = (float(objective_t(x + eps * d, conn)) - float(objective_t(x - eps * d, conn))) / (2 * eps)
    assert float(jnp.sum(g * d)) == pytest.approx(fd, rel=1e-6)
    # an inverted corner: F is inf and its gradient leaves that corner out
    bad = x.at[13].set(x[13] + 2.0)
    fb, gb = objective_and_grad(bad, conn)
    assert np.isinf(float(fb)) and bool(jnp.all(jnp.isfinite(gb)))


@pytest.mark.parametrize("block", [7, 16, 64, 125, 1000])
@pytest.mark.parametrize("weighted", [False, True])
def test_blocked_gradient_equals_the_whole_mesh_at_once(block, weighted):
    """`objective_terms_and_grad` over element blocks (blocks of 7, 16, 64 do not divide the 125 elements; 125
    and more: the whole mesh at once) gives F, max kappa/3 and the gradient of the unblocked kernel, padding
    elements (weight 0) and an inverted corner included."""
    mesh = perturb_box(5, amplitude=0.3, seed=2)
    x = jnp.asarray(mesh.points, jnp.float64)
    hexes = np.concatenate([mesh.hexes, np.zeros((3, 8), np.int64)]) if weighted else mesh.hexes
    conn = transposed(hexes)
    weight = jnp.asarray(np.r_[np.ones(mesh.n_hexes), np.zeros(3)]) if weighted else None
    fn = jax.jit(objective_terms_and_grad, static_argnums=(3, 4))
    f0, k0, g0 = fn(x, conn, weight, None, 0)
    f1, k1, g1 = fn(x, conn, weight, None, block)
    assert float(f1) == pytest.approx(float(f0), rel=1e-12) and float(k1) == pytest.approx(float(k0), rel=1e-12)
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=1e-10, atol=1e-12 * float(jnp.abs(g0).max()))
    bad = x.at[20].set(x[20] + 2.0)  # inverted corners: F and the max are inf, the gradient leaves them out
    fb0, kb0, gb0 = fn(bad, conn, weight, None, 0)
    fb1, kb1, gb1 = fn(bad, conn, weight, None, block)
    assert np.isinf(float(fb1)) and np.isinf(float(kb1)) and np.isinf(float(fb0))
    np.testing.assert_allclose(np.asarray(gb1), np.asarray(gb0), rtol=1e-10, atol=1e-12 * float(jnp.abs(gb0).max()))


@pytest.mark.slow
def test_closed_form_gradient_drives_the_solver():
    mesh = perturb_box(3, amplitude=0.3, seed=4, which="interior")
    pr = build_problem(mesh, dtype=np.float64, fix_boundary=True)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0)
    x_ad, it_ad, _, _ = minimise("lbfgs", par, pr.conn, GradientParams(gradient="autodiff"))
    x_cf, it_cf, _, _ = minimise("lbfgs", par, pr.conn, GradientParams())  # closed form: the default
    assert it_cf == it_ad
    np.testing.assert_allclose(np.asarray(x_cf), np.asarray(x_ad), atol=1e-9)


@pytest.mark.parametrize("kw,match", [
    (dict(max_steps=0), "max_steps"), (dict(rtol=-1), "rtol"), (dict(rtol=0, atol=0), "rtol"),
    (dict(cg_method="newton"), "cg_method"), (dict(history_length=0), "history_length"),
    (dict(gradient="numeric"), "gradient"), (dict(residual="log"), "residual"), (dict(bogus=1), "bogus"),
])
def test_bad_parameters(kw, match):
    with pytest.raises(ConfigError, match=match):
        smooth(perturb_box(2, amplitude=0.1), "lbfgs", **kw)


@settings(max_examples=3, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), amplitude=st.floats(0.05, 0.45))
def test_no_method_raises_f_or_inverts(seed, amplitude):
    """From a valid start no method raises F or inverts a corner by itself (smooth's fallback never fires)."""
    mesh = perturb_box(3, amplitude=amplitude, seed=seed, which="sliding")
    for method in ("bfgs", "cg", "smart-laplace"):
        res = smooth(mesh, method, dtype="float64")
        notes = [n for n in res.notes if "C kernels of jaxci.native are not built" not in n]  # a build without C
        assert notes == [], (method, res.notes)
        assert res.after.inverted_elements == 0
        assert res.after.objective <= res.before.objective


@pytest.mark.parametrize("method", ["lbfgs", "cg"])
def test_max_move_caps_every_trial_and_saves_line_search_trials(method):
    """No free coordinate moves more than `max_move` local edge lengths in one step (so the first trial of a mesh
    with a nearly flat corner is not a huge raw-gradient step that the line search halves dozens of times)."""
    mesh = perturb_box(5, amplitude=0.45, seed=3)
    pr = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0)
    with jax.enable_x64(True):
        x1, it1, h1, _ = minimise(method, par, pr.conn, GradientParams(max_steps=1, max_move=0.1, restarts=0))
        v1 = np.asarray(points_to_params(pr.cons, x1, par.x0) / par.scale)
        assert np.abs(v1).max() <= 0.1 + 1e-9
        capped = minimise(method, par, pr.conn, GradientParams(max_move=0.5))
        free = minimise(method, par, pr.conn, GradientParams(max_move=0.0))
    assert capped[2]["max_condition"][-1] < 1.001 and free[2]["max_condition"][-1] < 1.001
    rejected = [int((np.diff(h["objective"]) == 0).sum()) for h in (capped[2], free[2])]
    assert rejected[0] < rejected[1]


def test_the_lbfgs_memory_is_halved_on_large_host_problems_only_where_not_given():
    """`history_pairs`: 10 pairs by default, 5 on the host engine from `HISTORY_F16_FROM` unknowns (13 MB less at
    216,000 hexahedra), the JAX engine's 10 at any size, and a given `history_length` as given everywhere."""
    from jaxci.optim.gradient_params import history_pairs
    from jaxci.optim.host import HISTORY_F16_FROM, LARGE_HISTORY

    p = GradientParams()
    assert p.history_length is None and LARGE_HISTORY == 5
    assert history_pairs(p, HISTORY_F16_FROM - 1) == 10 and history_pairs(p, HISTORY_F16_FROM) == 5
    assert history_pairs(p) == 10
    given = GradientParams(history_length=10)
    assert history_pairs(given, 10 * HISTORY_F16_FROM) == history_pairs(given) == 10
