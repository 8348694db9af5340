"""Truncated Newton on the host engine (`jaxci.optim.newton`, ``GradientParams(solver="newton")``): its CG, its
Hessian-vector products, and the solver's guarantees (F lowered, no inverted element, the boundary kept, the stops)."""

import numpy as np
import pytest
from helpers import wavy_annulus

from jaxci import smooth
from jaxci.errors import ConfigError
from jaxci.geometry.projection import project_np
from jaxci.interface.smooth import build_problem
from jaxci.mesh.generate import perturb_box
from jaxci.metrics.report import quality_report
from jaxci.optim.gradient import GradientParams
from jaxci.optim.host import HostObjective
from jaxci.optim.newton import FD_STEP, newton_cg, pcg
from jaxci.optim.parametrisation import make_parametrisation


def _objective(mesh, **kw):
    pr = build_problem(mesh, dtype=np.float64, **kw)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0, dtype=np.float64)
    return pr, par, HostObjective(par, np.ascontiguousarray(mesh.hexes.T), 1.0, keep_raw=True)


def _on_the_boundary(mesh, res) -> None:
    """Every boundary node of `res`'s mesh on the original boundary of `mesh`, its corner nodes where they were."""
    pr = build_problem(mesh, dtype=np.float64)
    x = np.asarray(res.mesh.points)
    np.testing.assert_allclose(project_np(pr.cons, x), x, atol=1e-9)
    corners = np.asarray(pr.cons.corner_nodes)
    np.testing.assert_array_equal(x[corners], np.asarray(mesh.points)[corners])


def test_pcg_solves_an_spd_system_and_stops_at_negative_curvature():
    """On ``H d = -g`` with H SPD, CG with a Jacobi preconditioner reaches the tolerance in at most n products;
    with an indefinite H whose first direction has negative curvature it returns ``-M g`` (a descent direction)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((30, 30))
    h = a @ a.T / 30 + np.eye(30)  # condition ~ 10: CG in exact arithmetic needs n products at most
    g = rng.standard_normal(30)
    inv = 1.0 / np.diag(h)
    d, n, why = pcg(lambda p: h @ p, lambda r: inv * r, g, 1e-10, 100)
    assert why == "converged" and n <= 30
    np.testing.assert_allclose(h @ d, -g, atol=1e-8)
    d, n, why = pcg(lambda p: -p, None, g, 1e-10, 100)
    assert (why, n) == ("curvature", 1) and g @ d < 0
    d, n, why = pcg(lambda p: h @ p, None, g, 0.0, 3)
    assert (why, n) == ("max_iter", 3) and g @ d < 0


@pytest.mark.parametrize("mesh", [perturb_box(4, amplitude=0.2, seed=1), wavy_annulus(24, 3, 3)],
                         ids=["box", "annulus"])
def test_hessian_vector_product_matches_central_differences_of_the_gradient(mesh):
    """`HostObjective.hvp` (a forward difference of the kernel's gradient, the projection linearised) against a
    central difference of the objective's own gradient, with a step small enough that no boundary node changes
    triangle; and the product is symmetric (u.Hv = v.Hu)."""
    _, par, fun = _objective(mesh)
    rng = np.random.default_rng(2)
    y = 0.01 * rng.standard_normal(par.n_free)
    _, g, _, _ = fun(y)
    assert g is not None
    fun.accept()
    u, v = rng.standard_normal(par.n_free), rng.standard_normal(par.n_free)
    hv = fun.hvp(v, FD_STEP)
    eps = 1e-5
    ref = (fun(y + eps * v)[1] - fun(y - eps * v)[1]) / (2 * eps)
    fun(y)
    fun.accept()
    assert np.linalg.norm(hv - ref) <= 1e-3 * np.linalg.norm(ref)
    hu = fun.hvp(u, FD_STEP)
    assert abs(u @ hv - v @ hu) <= 1e-4 * abs(u @ hv)


def test_newton_lowers_f_keeps_the_mesh_valid_and_the_boundary_on_its_walls():
    """On a wavy annulus (nodes sliding on curved walls): F falls at every accepted step, no element inverts, every
    boundary node lies on the original boundary and the corner nodes stay put; far fewer Newton iterations than
    L-BFGS takes steps."""
    mesh = wavy_annulus(24, 3, 3)
    ref = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False)
    res = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False, solver="newton")
    f = np.asarray(res.history["objective"])
    assert np.all(np.isfinite(f)) and np.all(np.diff(f) <= 0)
    assert res.after.inverted_elements == 0 and res.after.objective < res.before.objective
    assert res.after.objective <= ref.after.objective * (1 + 1e-2)  # a minimum as low, to 1%: 0.5011 / 0.5001
    assert res.history["newton_iterations"] < ref.iterations / 3  # 24 against 97 (2026-11-30)
    _on_the_boundary(mesh, res)


def test_an_inverting_newton_step_is_rejected():
    """Products a hundredth of the Hessian's make Newton steps a hundred times too long, and a cap of 5 edge lengths
    lets them invert elements: those trials are rejected (F = inf) and never accepted; the result is valid."""
    mesh = perturb_box(4, amplitude=0.3, seed=2)
    _, par, fun = _objective(mesh)
    calls = []

    def spy(v):
        out = fun(v)
        calls.append(out[0])
        return out

    def weak(p, step):
        hp = fun.hvp(p, step)
        return None if hp is None else 0.01 * hp

    spy.accept, spy.hvp = fun.accept, weak
    y, steps, result, hf, hk, outer = newton_cg(spy, np.zeros(par.n_free), limit=400, max_rejected=20, rtol=1e-8,
                                                atol=1e-8, cap=5.0, ftol=0.0, done=lambda f, k: k <= 1 + 1e-6)
    assert np.isinf(calls).any()
    assert np.all(np.isfinite(hf)) and np.all(np.diff(hf) <= 0)
    assert quality_report(mesh, fun.points(y)).inverted_elements == 0
    assert len(hf) == steps + 1 and result == "successful" and hk[-1] <= 1 + 1e-6


def test_the_stops():
    """ktol: a perturbed box (sliding boundary) stops at max kappa/3 <= 1 + ktol; ftol: at the first accepted
    iterate with F <= ftol; the step limit counts every gradient evaluation, products included."""
    mesh = perturb_box(5, amplitude=0.2, seed=4)
    res = smooth(mesh, method="lbfgs", dtype="float64", solver="newton", ktol=1e-4)
    assert res.after.max_condition <= 1 + 1e-4 and res.history["solver_result"] == "successful"
    f0 = res.before.objective
    res = smooth(mesh, method="lbfgs", dtype="float64", solver="newton", ftol=0.5 * f0, restarts=0)
    f = np.asarray(res.history["objective"])
    assert f[-1] <= 0.5 * f0 and np.sum(f <= 0.5 * f0) == 1
    res = smooth(mesh, method="lbfgs", dtype="float64", solver="newton", max_steps=7, keep_worst=False)
    assert res.iterations == 7 and len(res.history["objective"]) == 8


def test_newton_is_refused_for_other_methods_and_sharded_runs():
    with pytest.raises(ConfigError, match="solver"):
        GradientParams(solver="trust-region")
    with pytest.raises(ConfigError, match="solver='newton'"):
        smooth(perturb_box(3), method="cg", solver="newton")
    with pytest.raises(ConfigError, match="sharded"):
        smooth(perturb_box(3), method="lbfgs", solver="newton", devices=1)


def test_the_damping_and_forcing_rules_are_one_definition_for_both_engines():
    """`forcing`, `curvature_scale` and `damping` give the same numbers over numpy (`newton_cg`) and jax.numpy
    (`newton_loop`)."""
    import jax.numpy as jnp

    from jaxci.optim.newton import MU_MIN, curvature_scale, damping, forcing

    for mu in (0.0, 0.5 * MU_MIN, MU_MIN, 3.0):
        for rejected in (0, 1, 2, 5):
            assert float(damping(mu, rejected)) == float(damping(jnp.float64(mu), jnp.int32(rejected), jnp))
    assert float(damping(1.0, 0)) == 0.25 and float(damping(0.0, 1)) == 4 * MU_MIN and float(damping(0.0, 9)) == 0.64
    assert float(damping(0.2 * MU_MIN, 0)) == 0.0  # below MU_MIN / MU_FACTOR: off
    for gn in (0.0, 1e-3, 0.5, 4.0):
        assert float(forcing(gn, 2.0)) == float(forcing(jnp.float64(gn), 2.0, jnp))
    assert float(forcing(4.0, 2.0)) == 0.5
    for php, pdp in ((2.0, 4.0), (-1.0, 4.0), (1.0, 0.0)):
        assert float(curvature_scale(php, pdp)) == float(curvature_scale(jnp.float64(php), jnp.float64(pdp), jnp))


@pytest.mark.parametrize("mesh, kw", [(perturb_box(4, amplitude=0.2, seed=1), {}),
                                      (wavy_annulus(24, 3, 3), {"fix_boundary": True})], ids=["box", "annulus"])
def test_the_jax_engines_product_is_the_hosts(mesh, kw):
    """`hessian_closed` (the JAX engine's product) and `HostObjective.hvp` (the host's) are one definition: the
    same forward difference with the boundary held, to 1e-6, on a box whose boundary nodes slide on its walls and
    on an annulus with its boundary fixed. (On a curved wall the two engines' projections may hold a node near a
    triangle's edge to different triangles, both exact.)"""
    import jax.numpy as jnp

    from jaxci.optim.solver_objective import hessian_closed

    pr, par, fun = _objective(mesh, **kw)
    rng = np.random.default_rng(3)
    y = 0.01 * rng.standard_normal(par.n_free)
    _, g, _, _ = fun(y)
    fun.accept()
    v = rng.standard_normal(par.n_free)
    host = fun.hvp(v, FD_STEP)
    conn = jnp.asarray(np.ascontiguousarray(pr.mesh.hexes.T))
    product = hessian_closed(jnp.asarray(y), (par, jnp.float64(1.0), None, None), conn, None)
    np.testing.assert_allclose(np.asarray(product(jnp.asarray(v))), host, rtol=0, atol=1e-6 * np.abs(host).max())
    assert not np.asarray(product(jnp.zeros(par.n_free))).any()


def test_newton_on_the_jax_engine():
    """``engine="jax"``, ``solver="newton"`` (`newton_loop`): on a wavy annulus F falls at every accepted step to
    within 0.1% of the host Newton's, no element inverts, every boundary node lies on the original boundary, in a
    quarter of L-BFGS's steps in Newton iterations; the step limit counts every gradient evaluation; `newton_after`
    runs the JAX L-BFGS first and leaves its result alone where it ends sooner."""
    mesh = wavy_annulus(24, 3, 3)
    kw = dict(method="lbfgs", dtype="float64", keep_worst=False)
    host = smooth(mesh, solver="newton", **kw)
    lbfgs = smooth(mesh, engine="jax", **kw)
    res = smooth(mesh, engine="jax", solver="newton", **kw)
    f = np.asarray(res.history["objective"])
    assert np.all(np.isfinite(f)) and np.all(np.diff(f) <= 0) and len(f) == res.iterations + 1
    assert res.after.inverted_elements == 0 and res.history["solver_result"] == "successful"
    assert res.after.objective <= host.after.objective * (1 + 1e-3)
    assert res.history["newton_iterations"] < lbfgs.iterations / 4
    _on_the_boundary(mesh, res)
    capped = smooth(mesh, engine="jax", solver="newton", max_steps=7, **kw)
    assert capped.iterations == 7 and len(capped.history["objective"]) == 8
    first = smooth(mesh, engine="jax", solver="newton", newton_after=10_000, **kw)
    np.testing.assert_array_equal(first.mesh.points, lbfgs.mesh.points)
    assert first.history["newton_iterations"] == 0


def test_newton_after_runs_lbfgs_first():
    """``newton_after=N``: a run that L-BFGS ends within N steps is L-BFGS's to the last bit (no Newton iteration);
    one that goes on switches to Newton at step N (a start in ``restarts``) and ends no worse than Newton alone."""
    box = perturb_box(4, amplitude=0.2, seed=1)
    ref = smooth(box, method="lbfgs", dtype="float64", keep_worst=False)
    run = smooth(box, method="lbfgs", dtype="float64", keep_worst=False, solver="newton", newton_after=10_000)
    np.testing.assert_array_equal(run.mesh.points, ref.mesh.points)
    assert run.history["newton_iterations"] == 0 and run.iterations == ref.iterations
    assert run.params["solver"] == "lbfgs"  # the solver that ran
    mesh = wavy_annulus(24, 3, 3)
    run = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False, solver="newton", newton_after=20)
    assert 20 in list(run.history["restarts"]) and run.history["newton_iterations"] > 0
    assert run.params["solver"] == "newton"
    f = np.asarray(run.history["objective"])
    assert np.all(np.diff(f) <= 0) and run.after.inverted_elements == 0


def test_bench_solvers_script_writes_its_table_and_json(tmp_path):
    """scripts/bench_solvers.py on a small box: a row per solver (plain and in the default pipeline) with its
    iterations, gradient evaluations and element quality, in the table and the JSON."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    from jaxci import write_mesh

    root = Path(__file__).resolve().parents[1]
    mesh = tmp_path / "box.vtk"
    write_mesh(perturb_box(3, amplitude=0.2, seed=0), mesh)
    out = tmp_path / "out.json"
    env = {**os.environ, "PYTHONPATH": str(root / "src")}
    p = subprocess.run([sys.executable, str(root / "scripts" / "bench_solvers.py"), "--meshes", str(mesh),
                        "--solvers", "lbfgs", "auto/newton:cg_max=5", "--out", str(out)], capture_output=True,
                       text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [r["solver"] for r in rows] == ["lbfgs", "auto/newton:cg_max=5"] and "auto/newton:cg_max=5" in p.stdout
    assert all(r["grad_evals"] >= r["outer"] > 0 and r["worst"] >= 1.0 for r in rows)


def test_the_cli_names_the_solver(tmp_path, capsys):
    """``jaxci smooth --param solver=newton`` says in its summary that truncated Newton ran."""
    from jaxci.cli import main
    from jaxci.io import write_mesh

    src, out = tmp_path / "box.vtk", tmp_path / "out.vtk"
    write_mesh(perturb_box(3, amplitude=0.3, seed=1), str(src))
    assert main(["smooth", str(src), str(out), "--method", "lbfgs", "--param", "solver=newton"]) == 0
    assert "after (lbfgs, truncated Newton," in capsys.readouterr().out


def test_the_auto_solver_is_newton_where_its_preconditioner_is_built():
    """``solver="auto"``: truncated Newton on the JAX engine with M (the mesh on the host, one device), L-BFGS on the
    host engine and without M (``precondition="none"``); the result names the solver that ran. The default pipeline
    asks for it on the JAX engine; on the host it asks for Newton after `AUTO_NEWTON_AFTER` L-BFGS steps, which
    this box does not reach: its note says which, the result that L-BFGS ran."""
    from jaxci.interface.methods import AUTO_NEWTON_AFTER

    box = perturb_box(4, amplitude=0.3, seed=5)
    kw = dict(method="lbfgs", dtype="float64", solver="auto")
    assert smooth(box, engine="jax", **kw).params["solver"] == "newton"
    assert smooth(box, engine="jax", precondition="none", **kw).params["solver"] == "lbfgs"
    assert smooth(box, engine="host", **kw).params["solver"] == "lbfgs"
    jax_auto, host_auto = smooth(box, engine="jax"), smooth(box, engine="host")
    assert jax_auto.params["solver"] == "newton" and "truncated Newton" in jax_auto.notes[0]
    assert host_auto.params["solver"] == "lbfgs"
    assert f"(auto): L-BFGS on F (truncated Newton from its step {AUTO_NEWTON_AFTER})" in host_auto.notes[0]
    assert jax_auto.after.inverted_elements == 0 and jax_auto.after.max_condition < quality_report(box).max_condition
