"""L-BFGS in numpy (`jaxci.optim.host`): same results as the compiled loop, validity by construction, boundary
kept on curved patches, nothing compiled on the user's path for a small mesh."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from jaxci import native
from jaxci.errors import ConfigError
from jaxci.geometry.near import NearProjector, project_near_np
from jaxci.geometry.projection import project_np
from jaxci.interface.smooth import build_problem, smooth
from jaxci.mesh import HexMesh
from jaxci.mesh.generate import perturb_box
from jaxci.mesh.shapes import annulus
from jaxci.metrics.hexahedron import objective_terms_and_grad, objective_terms_and_grad_np, transposed
from jaxci.metrics.report import quality_report
from jaxci.optim.gradient import GradientParams, minimise, use_host
from jaxci.optim.host import HOST_MAX, lbfgs
from jaxci.optim.parametrisation import make_parametrisation


def _wavy_annulus(seed: int = 0) -> HexMesh:
    """An annulus (curved inner and outer walls) with its interior and wall nodes moved off the ideal grid: the
    walls are moved along their own circles (and z), so the boundary stays the original cylinder."""
    m = annulus(16, 3, 3)
    p = np.array(m.points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    r, th = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0])
    inner = (r > 0.5 + 1e-9) & (r < 1 - 1e-9)
    r = np.where(inner, r + rng.uniform(-0.05, 0.05, len(r)), r)
    th = th + rng.uniform(-0.08, 0.08, len(r))
    z = p[:, 2]
    zin = (z > 1e-9) & (z < 1 - 1e-9)
    z = np.where(zin, z + rng.uniform(-0.08, 0.08, len(z)), z)
    q = np.stack([r * np.cos(th), r * np.sin(th), z], axis=1)
    return m.with_points(q)


def test_numpy_kernel_equals_the_compiled_one():
    m = perturb_box(5, amplitude=0.3, seed=1)
    with jax.enable_x64(True):
        fj, kj, gj = jax.jit(objective_terms_and_grad)(jax.numpy.asarray(m.points), transposed(m.hexes))
    fn, kn, gn = objective_terms_and_grad_np(np.asarray(m.points, np.float64), np.ascontiguousarray(m.hexes.T))
    assert fn == pytest.approx(float(fj), rel=1e-12) and kn == pytest.approx(float(kj), rel=1e-12)
    np.testing.assert_allclose(gn, np.asarray(gj), rtol=1e-10, atol=1e-12 * np.abs(gn).max())


@pytest.mark.parametrize("use_c", [True, False])
def test_near_projector_follows_a_moving_mesh_like_the_full_search(use_c, monkeypatch):
    """Small successive moves (a solver's iterates): the remembered triangle gives exactly the candidate search's
    point, also for a node inside its old triangle's prism but nearer another candidate (moved inward off the
    convex wall): kept on the old one, the projection jumped where the node left the prism. In C and numpy."""
    from jaxci import native

    if use_c and not native.AVAILABLE:
        pytest.skip("the C extension is not built")
    monkeypatch.setattr(native, "AVAILABLE", use_c)
    mesh = _wavy_annulus()
    pr = build_problem(mesh, dtype=np.float64)
    proj = NearProjector(pr.cons)
    rng = np.random.default_rng(3)
    x = np.array(mesh.points)
    for _ in range(6):
        x = x + 0.01 * rng.normal(size=x.shape)
        (a, hint), b = proj(x), project_near_np(pr.cons, x)
        proj.commit(hint)  # as a solver does on accepting the point
        np.testing.assert_allclose(a, b, atol=1e-12)
        np.testing.assert_allclose(project_np(pr.cons, a), a, atol=1e-9)  # on the original boundary
        x = a


@pytest.mark.parametrize("shape", ["box", "annulus"])
def test_numpy_lbfgs_reaches_the_compiled_result(shape):
    mesh = perturb_box(5, amplitude=0.3, seed=4) if shape == "box" else _wavy_annulus()
    out = {}
    for backend in ("numpy", "jax"):
        res = smooth(mesh, "lbfgs", dtype="float64", backend=backend, keep_worst=False)
        assert res.after.inverted_elements == 0
        hist = np.asarray(res.history["objective"])
        assert np.all(np.diff(hist) <= 1e-12 * hist[0])  # F never rises
        out[backend] = res
    f_np, f_jax = out["numpy"].after.objective, out["jax"].after.objective
    assert f_np <= f_jax * (1 + 1e-3) + 1e-9
    assert f_np < 0.5 * out["numpy"].before.objective
    if shape == "box":
        assert out["numpy"].after.max_condition <= 1 + 1e-6
    else:  # the walls stayed on their cylinders
        p = np.asarray(out["numpy"].mesh.points)
        r = np.hypot(p[:, 0], p[:, 1])
        wall = (np.abs(np.asarray(mesh.points)[:, :2]) ** 2).sum(1) ** 0.5
        on = np.isclose(wall, 0.5) | np.isclose(wall, 1.0)
        # the walls are polygons of 16 sides: a node on a wall stays between the chord and the circle
        assert np.all(np.abs(r[on] - wall[on]) <= 1 - np.cos(np.pi / 16) + 1e-9)


@pytest.mark.skipif(not native.AVAILABLE, reason="needs the C kernels (jaxci.native)")
def test_float16_lbfgs_memory_of_a_large_problem_reaches_the_same_mesh(monkeypatch):
    """From `HISTORY_F16_FROM` free coordinates the host L-BFGS keeps its pairs in float16 (a quarter of the
    memory, its largest part at 10^6 hexahedra): forced here on a small box, the run reaches the ideal grid as the
    float64 memory does, in about as many steps."""
    from jaxci.optim import host

    mesh = perturb_box(8, amplitude=0.3, seed=2)
    ref = smooth(mesh, "lbfgs", backend="numpy")
    made = []
    orig = host._Memory.__init__

    def spy(self, n, history):
        orig(self, n, history)
        made.append(self.S.dtype)

    monkeypatch.setattr(host._Memory, "__init__", spy)
    monkeypatch.setattr(host, "HISTORY_F16_FROM", 1)
    run = smooth(mesh, "lbfgs", backend="numpy")
    assert made and all(d == np.float16 for d in made)
    assert run.after.max_condition <= 1.0 + 1e-5 and ref.after.max_condition <= 1.0 + 1e-5
    assert run.after.inverted_elements == 0
    assert abs(run.iterations - ref.iterations) <= max(5, ref.iterations // 5)


def test_an_inverting_trial_is_rejected():
    """A quadratic-looking step that would invert elements: the line search shortens it, the mesh stays valid."""
    mesh = perturb_box(4, amplitude=0.3, seed=2)
    pr = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0, dtype=np.float64)
    from jaxci.optim.host import HostObjective

    fun = HostObjective(par, np.ascontiguousarray(mesh.hexes.T), 1.0)
    calls = []

    def spy(v):
        out = fun(v)
        calls.append(out[0])
        return out

    y, steps, result, hf, hk = lbfgs(spy, np.zeros(par.n_free), limit=200, max_rejected=20, rtol=1e-8, atol=1e-8,
                                     history=10, cap=5.0, ftol=0.0)  # a cap of 5 edge lengths: the first trials invert
    assert np.isinf(calls).any()  # some trials inverted elements ...
    assert np.all(np.isfinite(hf)) and np.all(np.diff(hf) <= 0)  # ... and were never accepted
    assert quality_report(mesh, fun.points(y)).inverted_elements == 0
    assert len(hf) == steps + 1 and result == "successful"


def test_backend_choice():
    box = perturb_box(3)
    assert use_host("lbfgs", GradientParams(), HOST_MAX)
    assert not use_host("lbfgs", GradientParams(), HOST_MAX + 1)
    assert use_host("lbfgs", GradientParams(backend="numpy"), 10 * HOST_MAX)
    assert not use_host("lbfgs", GradientParams(backend="jax"), 10)
    assert not use_host("cg", GradientParams(backend="numpy"), 10)
    with pytest.raises(ConfigError, match="backend"):
        GradientParams(backend="gpu")
    pr = build_problem(box, dtype=np.float64)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0, dtype=np.float64)
    _, _, hist, params = minimise("lbfgs", par, pr.conn, GradientParams(backend="numpy"))
    assert params["backend"] == "numpy" and hist["solver_result"] == "successful"


@pytest.mark.slow
def test_cli_small_mesh_compiles_nothing(tmp_path):
    """The user's path: `jaxci smooth` of a 1000-hex mesh, empty compile cache: no XLA compilation at all."""
    from jaxci.io import write_mesh

    write_mesh(perturb_box(10, amplitude=0.3, seed=1), str(tmp_path / "in.vtk"))
    env = dict(os.environ, JAXCI_CACHE_DIR=str(tmp_path / "cache"))
    p = subprocess.run([sys.executable, "-m", "jaxci", "smooth", str(tmp_path / "in.vtk"), str(tmp_path / "out.vtk"),
                        "--json"], env=env, capture_output=True, text=True, check=True)
    doc = json.loads(p.stdout)
    assert doc["phases"]["total"]["compiled"] == 0, doc["phases"]
    assert doc["after"]["max_condition"] <= 1.0001 and doc["after"]["inverted_elements"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("command", ["smooth", "quality"])
def test_cli_small_mesh_never_imports_jax(tmp_path, command):
    """`jaxci smooth` / `jaxci quality` of a tangled 1000-hex mesh run in numpy and C: JAX (0.4-0.5 s of import)
    is never imported, nor equinox, optimistix or jaxtyping, nor scipy.sparse or scipy.spatial (0.5 s)."""
    from jaxci.io import write_mesh

    mesh = perturb_box(10, amplitude=0.3, seed=1)
    x = np.array(mesh.points)
    x[mesh.hexes[555, 0]] = x[mesh.hexes[555, 6]] + 0.02  # an interior node past its cell: the untangling runs too
    write_mesh(mesh.with_points(x), str(tmp_path / "in.vtk"))
    args = [command, str(tmp_path / "in.vtk")] + ([str(tmp_path / "out.vtk")] if command == "smooth" else [])
    code = (f"import sys; from jaxci.cli import main; rc = main({args!r}); "
            "print(rc, sorted(m for m in ('jax', 'equinox', 'optimistix', 'jaxtyping', 'scipy.sparse', "
            "'scipy.spatial') if m in sys.modules))")
    env = dict(os.environ, JAXCI_CACHE_DIR=str(tmp_path / "cache"))
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert p.stdout.strip().splitlines()[-1] == "0 []", p.stdout + p.stderr
    if command == "smooth":
        assert "untangl" in p.stdout


def test_a_mesh_whose_nodes_are_all_fixed_returns_at_once_with_a_note():
    """A single hexahedron (every node a boundary corner): nothing can move, so no method runs and nothing
    compiles (it used to compile 45 small programs in the solver's set-up)."""
    from jaxci import smooth
    from jaxci.runtime.phases import compile_totals

    mesh = perturb_box(1, amplitude=0.0)
    mesh = mesh.with_points(mesh.points + np.array([[0.2, 0, 0]] + [[0, 0, 0]] * 7))
    before = compile_totals()["compiled"]
    res = smooth(mesh)
    assert compile_totals()["compiled"] == before
    assert res.iterations == 0 and np.array_equal(res.mesh.points, mesh.points)
    assert any("no node can move (all 8 nodes are fixed" in n for n in res.notes), res.notes


# ---------------------------------------------------------------------------------------------- p-mean objective
@pytest.mark.parametrize("power", [1.0, 2.0, 6.0])
def test_pmean_gradient_matches_finite_differences(power):
    m = perturb_box(4, amplitude=0.3, seed=1)
    x = np.asarray(m.points, np.float64)
    conn = np.ascontiguousarray(m.hexes.T)
    f, _, g = objective_terms_and_grad_np(x, conn, power)
    d = np.random.default_rng(0).normal(size=x.shape)
    h = 1e-7
    fd = (objective_terms_and_grad_np(x + h * d, conn, power)[0]
          - objective_terms_and_grad_np(x - h * d, conn, power)[0]) / (2 * h)
    assert fd == pytest.approx(float(np.sum(g * d)), rel=1e-5)
    if power == 1.0:  # M_1 is F
        assert f == pytest.approx(objective_terms_and_grad_np(x, conn)[0], rel=1e-12)
    with jax.enable_x64(True):  # the compiled kernel agrees
        fj, _, gj = jax.jit(objective_terms_and_grad, static_argnums=3)(jax.numpy.asarray(x), transposed(m.hexes),
                                                                        None, power)
    assert float(fj) == pytest.approx(f, rel=1e-10)
    np.testing.assert_allclose(np.asarray(gj), g, rtol=1e-8, atol=1e-10 * np.abs(g).max())


@pytest.mark.parametrize("backend", ["numpy", "jax"])
def test_pmean_pulls_the_worst_element_harder_than_the_mean(backend):
    """A perturbed box with its boundary fixed (no perfect mesh reachable): minimising F leaves max kappa/3 at
    2.58; the p-mean (p = 2) takes it to 2.33 at a small cost in the mean. Both keep every element valid, and
    each run's final check compares the objective it minimised."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    kw = dict(dtype="float64", backend=backend, keep_worst=False, fix_boundary=True)
    mean = smooth(mesh, "lbfgs", **kw)
    pm = smooth(mesh, "lbfgs", objective="pmean", **kw)
    from jaxci.metrics.hexahedron import pmean_objective

    assert mean.after.inverted_elements == pm.after.inverted_elements == 0
    assert pm.after.max_condition < mean.after.max_condition - 0.1
    assert pm.after.mean_condition < mean.after.mean_condition + 0.05
    assert (pmean_objective(pm.mesh.points, mesh.hexes, 2.0)
            < pmean_objective(mean.mesh.points, mesh.hexes, 2.0))
    assert pm.params["objective"] == "pmean" and pm.params["p"] == 2.0
    assert not any("rose" in n for n in pm.notes)  # F rose (0.199 -> 0.221), the p-mean fell: no false alarm


def test_pmean_refused_where_it_does_not_apply():
    mesh = perturb_box(3)
    with pytest.raises(ConfigError, match="pmean"):
        smooth(mesh, "smart-laplace", objective="pmean")
    with pytest.raises(ConfigError, match="closed"):
        GradientParams(objective="pmean", gradient="autodiff")
    with pytest.raises(ConfigError, match="p"):
        GradientParams(objective="pmean", p=0.5)
    with pytest.raises(ConfigError, match="pmean"):
        smooth(mesh, "lm", objective="pmean")


def test_cli_objective_flag(tmp_path):
    from jaxci.io import write_mesh

    write_mesh(perturb_box(4, amplitude=0.3, seed=1), str(tmp_path / "in.vtk"))
    base = [sys.executable, "-m", "jaxci", "smooth", str(tmp_path / "in.vtk"), str(tmp_path / "out.vtk"),
            "--fix-boundary", "--json", "--force", "--method", "lbfgs"]  # plain L-BFGS: the default polishes
    runs = {}
    for obj in ("mean", "pmean"):
        p = subprocess.run([*base, "--objective", obj], capture_output=True, text=True, check=True)
        runs[obj] = json.loads(p.stdout)
    assert runs["pmean"]["params"]["objective"] == "pmean"
    assert runs["pmean"]["after"]["max_condition"] < runs["mean"]["after"]["max_condition"] - 0.1
    bad = subprocess.run([*base, "--objective", "pmean", "--param", "objective=mean"], capture_output=True,
                         text=True)
    assert bad.returncode != 0 and "disagree" in bad.stderr and "Traceback" not in bad.stderr
    bad = subprocess.run([*base[:-2], "--objective", "pmean", "--method", "ci"], capture_output=True, text=True)
    assert bad.returncode != 0 and "gradient methods" in bad.stderr and "Traceback" not in bad.stderr


def test_near_projector_leaves_kept_nodes_alone():
    """Nodes marked `keep` (inside a flat part of the boundary) are neither moved nor pulled back; the others
    are projected as without it."""
    mesh = _wavy_annulus()
    pr = build_problem(mesh, dtype=np.float64)
    x = np.array(mesh.points) + 0.01 * np.random.default_rng(5).normal(size=mesh.points.shape)
    keep = np.zeros(mesh.n_nodes, bool)
    surf = np.asarray(pr.cons.surface_nodes)
    keep[surf[::2]] = True
    full, h_full = NearProjector(pr.cons)(x)
    part, h_part = NearProjector(pr.cons)(x, keep)
    np.testing.assert_array_equal(part[surf[::2]], x[surf[::2]])
    np.testing.assert_allclose(part[surf[1::2]], full[surf[1::2]], atol=1e-12)
    g = np.random.default_rng(6).normal(size=x.shape)
    proj = NearProjector(pr.cons)
    pulled = proj.pullback(g, h_part, keep)
    np.testing.assert_array_equal(pulled[surf[::2]], g[surf[::2]])
    np.testing.assert_allclose(pulled[surf[1::2]], proj.pullback(g, h_full)[surf[1::2]], atol=1e-12)



@pytest.mark.parametrize("use_c", [True, False])
def test_lifted_points_skip_the_corner_reset_only_where_it_changes_nothing(use_c, monkeypatch):
    """A solver's lifted points keep their CORNER nodes at the base's positions, so the projection need not put
    them back (`HostObjective` says so where the base holds them at their original ones): the same points and
    gradient as with the reset, on a box (8 corners), in a polish round on a curved annulus (its fixed nodes are
    corners) and from a base whose corner moved (then the reset runs)."""
    from jaxci.optim.host import HostObjective
    from jaxci.optim.polish import _Layout, _SubProblem

    if not use_c:
        monkeypatch.setattr(native, "AVAILABLE", False)
    cases = []
    box = perturb_box(5, amplitude=0.3, seed=2)
    pb = build_problem(box, dtype=np.float64)
    conn = np.ascontiguousarray(pb.mesh.hexes.T)
    corners = np.asarray(pb.cons.corner_nodes)
    assert len(corners) == 8
    cases.append((make_parametrisation(pb.mesh, pb.info, pb.cons, scaled=True), conn, True))
    moved = np.array(pb.mesh.points, np.float64)
    moved[corners[0]] += 1e-3
    cases.append((make_parametrisation(pb.mesh, pb.info, pb.cons, moved, scaled=True), conn, False))
    mesh = _wavy_annulus(3)
    pa = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pa.mesh, pa.info, pa.cons, scaled=True)
    free = np.zeros(mesh.n_nodes, bool)
    for nodes in (pa.cons.interior_nodes, pa.cons.surface_nodes, pa.cons.edge_nodes):
        free[np.asarray(nodes)] = True
    region = free & (np.arange(mesh.n_nodes) % 3 == 0)
    sub = _SubProblem({"hexahedron": np.asarray(mesh.hexes)}, pa.cons, _Layout(pa.cons, par, free), region,
                      np.asarray(pa.mesh.points, np.float64))
    assert len(np.asarray(sub.par.cons.corner_nodes)) > 100
    cases.append((sub.par, np.ascontiguousarray(sub.blocks["hexahedron"].T), True))
    rng = np.random.default_rng(7)
    for case_par, case_conn, placed in cases:
        fast = HostObjective(case_par, case_conn, 1.0)
        assert fast._corners_placed is placed
        ref = HostObjective(case_par, case_conn, 1.0)
        ref._corners_placed = False
        for _ in range(3):
            v = 0.3 * rng.normal(size=case_par.n_free)
            np.testing.assert_array_equal(fast.points(v), ref.points(v))
            np.testing.assert_array_equal(fast(v)[1], ref(v)[1])


def test_a_solve_inside_the_flat_regions_never_builds_the_projector(monkeypatch):
    """`HostObjective` makes its boundary projector on first use: a box's moving boundary nodes stay inside their
    flat regions, so a short step never builds it (its search tables were 6 MB at 216,000 hexahedra); a step that
    carries the boundary nodes out of their regions does, and projects them back onto the box."""
    from jaxci.optim.host import HostObjective

    mesh = perturb_box(5, amplitude=0.3, seed=3)
    pb = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pb.mesh, pb.info, pb.cons, scaled=True)
    fun = HostObjective(par, np.ascontiguousarray(pb.mesh.hexes.T), 1.0)
    v = 1e-3 * np.random.default_rng(8).normal(size=par.n_free)
    assert fun(v)[1] is not None
    assert "_project" not in vars(fun)
    far = fun.points(100.0 * np.ones(par.n_free))
    assert "_project" in vars(fun)
    # where F's kernel reads the lifted points itself (large meshes), the candidate triangles go until a search
    # needs them, then come back the same
    from jaxci.optim import host

    cand = np.array(pb.host_cons.surface_cand)
    monkeypatch.setattr(host, "LIFTED_FROM", 0)
    lean = HostObjective(make_parametrisation(pb.mesh, pb.info, pb.host_cons, scaled=True),
                         np.ascontiguousarray(pb.mesh.hexes.T), 1.0)
    assert lean._slots is not None and "surface_cand" not in vars(lean._cons)
    assert lean(v)[1] is not None and "surface_cand" not in vars(lean._cons)
    np.testing.assert_array_equal(lean.points(100.0 * np.ones(par.n_free)), far)
    np.testing.assert_array_equal(lean._cons.surface_cand, cand)
    bound = np.concatenate([np.asarray(pb.cons.surface_nodes), np.asarray(pb.cons.edge_nodes)])
    lo, hi = np.asarray(pb.mesh.points).min(axis=0), np.asarray(pb.mesh.points).max(axis=0)
    assert np.all(far[bound] >= lo - 1e-12) and np.all(far[bound] <= hi + 1e-12)


@pytest.mark.parametrize("shape", ["box", "annulus"])
def test_an_iterate_keeps_its_points_only_where_it_projected(shape):
    """`HostObjective` keeps an evaluation's points where it projected a node (the annulus) or for Newton's
    `hvp`; elsewhere (the box: every node inside its flat region) `points_of` lifts its `v` again, to the same
    numbers. L-BFGS from None starts at zeros: the same iterates, points and histories as from zeros."""
    from jaxci.optim.host import HostObjective

    mesh = perturb_box(5, amplitude=0.3, seed=3) if shape == "box" else annulus(n_r=3, n_theta=16, n_z=2)
    pb = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pb.mesh, pb.info, pb.cons, scaled=True)
    conn = np.ascontiguousarray(pb.mesh.hexes.T)
    v = 1e-3 * np.random.default_rng(8).normal(size=par.n_free)
    fun, kept = HostObjective(par, conn, 1.0), HostObjective(par, conn, 1.0, keep_raw=True)
    assert fun(v)[1] is not None
    fun.accept()
    kept(v)
    kept.accept()
    assert (fun.best[1] is None) == (shape == "box") and kept.best[1] is not None
    np.testing.assert_array_equal(fun.points_of(fun.best), kept.points_of(kept.best))
    kw = dict(limit=15, max_rejected=20, rtol=1e-9, atol=1e-9, history=10, cap=0.5, ftol=0.0, stage=None)
    runs = [(f, lbfgs(f, y0, **kw)) for f, y0 in ((HostObjective(par, conn, 1.0), None),
                                                   (HostObjective(par, conn, 1.0, keep_raw=True),
                                                    np.zeros(par.n_free)))]
    (f1, r1), (f2, r2) = runs
    assert r1[1] == r2[1] == 15
    for a, b in zip((r1[0], r1[3], r1[4], f1.points_of(f1.best)), (r2[0], r2[3], r2[4], f2.points_of(f2.best)),
                    strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("lifted", [False, True])
@pytest.mark.parametrize("shape", ["box", "annulus"])
def test_lbfgs_trials_without_their_points_made_take_the_same_steps(shape, lifted, monkeypatch):
    """`lbfgs` evaluates a `HostObjective`'s trial ``d * alpha + y`` without making it (`HostObjective.step`) and
    makes the accepted one in the direction's vector: the same iterates, histories and points as the same
    objective called at each trial made (a plain function), on a box (nothing projected) and an annulus, also
    with F's kernel reading the points from the free coordinates (`host.LIFTED_FROM`: where every moving boundary
    node may stay in its flat region, the box); a trial at step 0 is the accepted iterate's evaluation itself, as
    a call at it is."""
    from jaxci.optim import host
    from jaxci.optim.host import HostObjective

    mesh = perturb_box(5, amplitude=0.3, seed=3) if shape == "box" else annulus(n_r=3, n_theta=16, n_z=2)
    pb = build_problem(mesh, dtype=np.float64)
    par = make_parametrisation(pb.mesh, pb.info, pb.cons, scaled=True)
    conn = np.ascontiguousarray(pb.mesh.hexes.T)
    kw = dict(limit=25, max_rejected=20, rtol=1e-9, atol=1e-9, history=4, cap=0.5, ftol=0.0, stage=None)
    lazy, made = HostObjective(par, conn, 1.0), HostObjective(par, conn, 1.0)
    steps = []
    lazy_step = lazy.step
    lazy.step = lambda y, d, alpha: steps.append(alpha) or lazy_step(y, d, alpha)

    class Plain:  # `made` without `step`: every trial made before the call
        par = made.par

        def __call__(self, v):
            return made(v)

        def accept(self):
            made.accept()

    if lifted:  # the points read where the kernel needs them, not lifted into an array (large meshes)
        monkeypatch.setattr(host, "LIFTED_FROM", 0)
        lazy = HostObjective(par, conn, 1.0)
        lazy_step = lazy.step
        lazy.step = lambda y, d, alpha: steps.append(alpha) or lazy_step(y, d, alpha)
        assert (lazy._slots is not None) == par.shortcut
    r1, r2 = lbfgs(lazy, None, **kw), lbfgs(Plain(), None, **kw)
    assert r1[1] == r2[1] == len(steps) >= 20 and r1[2] == r2[2]
    for a, b in zip((r1[0], r1[3], r1[4], lazy.points_of(lazy.best)), (r2[0], r2[3], r2[4], made.points_of(made.best)),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    y = lazy.best[0]
    assert lazy_step(y, np.ones_like(y), 0.0) is lazy.best[2]


def test_pytrees_are_registered_when_jax_comes_after_jaxci():
    """A process that imports jaxci first (no JAX) and JAX later: Constraints, Parametrisation, ExtraCells and
    ColouredStars (registered by `_moves`) are JAX pytrees once JAX is imported (`jaxci.runtime._lazy`), and a jitted
    function takes numpy constraints moved to the device."""
    code = """
import sys
from jaxci.mesh.generate import perturb_box
from jaxci.geometry.boundary import classify_boundary
from jaxci.geometry.projection import build_constraints, project_np
from jaxci.optim.parametrisation import make_parametrisation
from jaxci.optim import _moves
import numpy as np
assert "jax" not in sys.modules
mesh = perturb_box(3, amplitude=0.2, seed=0)
info = classify_boundary(mesh)
cons = build_constraints(mesh, info, dtype=np.float64, device=False)
par = make_parametrisation(mesh, info, cons, dtype=np.float64)
assert "jax" not in sys.modules and isinstance(cons.x_orig, np.ndarray)
import jax
jax.config.update("jax_enable_x64", True)
from jaxci.metrics.objective import ExtraCells
fields = {f: np.zeros(1) for f in ("nodes", "mask", "star", "smask", "basis", "dims", "plane", "xnodes", "xwinv",
                                   "xweight", "xmask")}
assert len(jax.tree_util.tree_leaves(_moves.ColouredStars(**fields, n_interior=1, n_surface=0, n_edge=0))) == 11
from jaxci.geometry.projection import project
leaves = jax.tree_util.tree_leaves(cons)
assert len(leaves) == 16, len(leaves)
assert len(jax.tree_util.tree_leaves(par)) == 16 + 5
assert jax.tree_util.tree_structure(ExtraCells((), ())).num_leaves == 0
x = np.asarray(mesh.points) + 0.01
np.testing.assert_allclose(np.asarray(project(jax.device_put(cons), x)), project_np(cons, x), atol=1e-12)
print("ok")
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stdout + p.stderr


def test_host_path_keeps_fixed_nodes_bit_for_bit():
    """Corners of a box whose coordinates float32 cannot hold (scaled by 0.37, shifted by 0.1): the host solver
    works in float64 from the exact input, so nodes that cannot move keep their coordinates bit for bit, and the
    boundary nodes stay on the box's faces without a final k-d tree projection."""
    from jaxci.geometry.boundary import CORNER, classify_boundary

    mesh = perturb_box(6, amplitude=0.2, seed=1)
    mesh = mesh.with_points(np.asarray(mesh.points) * 0.37 + 0.1)
    res = smooth(mesh)
    assert res.after.max_condition < 1.0001
    x0, x = np.asarray(mesh.points), np.asarray(res.mesh.points)
    corner = np.asarray(classify_boundary(mesh).node_class) == CORNER
    assert corner.sum() == 8 and np.array_equal(x[corner], x0[corner])
    lo, hi = x0.min(axis=0), x0.max(axis=0)
    on_face = (np.isclose(x0, lo, atol=0, rtol=0) | np.isclose(x0, hi, atol=0, rtol=0))
    np.testing.assert_array_equal(x[on_face], x0[on_face])  # each boundary node keeps its face's coordinate
