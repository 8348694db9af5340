"""The worst-element polish of the default pipeline (jaxci.optim.polish), the per-corner weighted host kernels
(jaxci.optim.weighted) and the p-mean on meshes with wedges, pyramids and tetrahedra."""

from __future__ import annotations

import numpy as np
import pytest

from jaxci import native
from jaxci.cells import KERNELS, element_blocks
from jaxci.errors import ConfigError
from jaxci.geometry.boundary import classify_boundary
from jaxci.geometry.projection import build_constraints
from jaxci.geometry.topology import HEX_FACES
from jaxci.interface.smooth import smooth
from jaxci.mesh import CellBlock, HexMesh
from jaxci.mesh.generate import perturb_box
from jaxci.metrics.elements import checked_objective, mixed_objective
from jaxci.metrics.guard import cell_worst
from jaxci.optim import polish as polish_module
from jaxci.optim import weighted
from jaxci.optim.gradient_params import GradientParams
from jaxci.optim.parametrisation import make_parametrisation
from jaxci.optim.polish import PolishParams, _RoundObjective, polish


def all_types_box(seed: int = 1) -> HexMesh:
    """A perturbed 3^3 box: hexahedron 0 (a box corner) as 6 pyramids around a new centre node, the one on the
    face x = 0 split into 2 tetrahedra; the column of hexahedra 8, 17, 26 split into 2 wedges each."""
    m = perturb_box(3, amplitude=0.15, seed=seed)
    h, pts = m.hexes, m.points
    c = len(pts)
    pts = np.vstack([pts, pts[h[0]].mean(axis=0)])
    pyr = np.array([list(f[::-1]) + [c] for f in h[0][HEX_FACES]])
    a, b, cc, d, e = pyr[0]
    tet = np.array([[a, b, cc, e], [a, cc, d, e]])
    col = [8, 17, 26]
    w = np.concatenate([h[col][:, [0, 1, 2, 4, 5, 6]], h[col][:, [0, 2, 3, 4, 6, 7]]])
    return HexMesh(pts, (CellBlock("hexahedron", np.delete(h, [0, *col], axis=0)), CellBlock("wedge", w),
                         CellBlock("pyramid", pyr[1:]), CellBlock("tetra", tet)))


def element_stats(mesh, points) -> tuple[float, float]:
    """(worst, mean) over every cell of each cell's worst corner kappa/3 (VTK's per-element condition)."""
    k = np.concatenate(list(cell_worst(mesh, points).values()))
    return float(k.max()), float(k.mean())


@pytest.fixture(params=["C", "numpy"])
def kernels(request, monkeypatch):
    if request.param == "C" and not native.AVAILABLE:
        pytest.skip("the C kernels are not built")
    if request.param == "numpy":
        monkeypatch.setattr(native, "AVAILABLE", False)
    return request.param


def test_weighted_kernels_are_F_and_their_gradients_are_exact(kernels):
    mesh = all_types_box()
    blocks = element_blocks(mesh)
    assert set(blocks) == {"hexahedron", "wedge", "pyramid", "tetra"}
    x = np.array(mesh.points)
    cells = weighted.CellCorners(blocks)
    f, _, _ = weighted.penalty_kernel(blocks, cells.n_corners, np.inf, 0.0)(x)  # no penalty: F itself
    assert f == pytest.approx(float(mixed_objective(x, mesh)), rel=1e-12)
    d = np.random.default_rng(0).normal(size=x.shape)
    h = 1e-6
    for kernel in (weighted.pmean_kernel(blocks, 4.0), weighted.penalty_kernel(blocks, 100, 0.05, 50.0)):
        v, kmax, g = kernel(x)
        fd = (kernel(x + h * d)[0] - kernel(x - h * d)[0]) / (2 * h)
        assert fd == pytest.approx(float(np.sum(g * d)), rel=1e-6)
        assert kmax == pytest.approx(element_stats(mesh, x)[0], rel=1e-12)
    # the caller's CellCorners of the same blocks (the polish's sub-problem's): the same numbers, bit for bit
    given = weighted.penalty_kernel(blocks, 100, 0.05, 50.0, cells=cells)(x)
    made = weighted.penalty_kernel(blocks, 100, 0.05, 50.0)(x)
    assert given[:2] == made[:2] and np.array_equal(given[2], made[2])
    assert weighted.pmean_kernel(blocks, 4.0)(x)[0] == pytest.approx(checked_objective(mesh, 4.0)(x), rel=1e-12)
    worst = cells.cell_worst(x)
    ref = cell_worst(mesh, x)
    for t in blocks:
        np.testing.assert_allclose(worst[t], ref[t], rtol=1e-12)
    flat = x.copy()  # an inverted tetrahedron: inf, as F
    flat[blocks["tetra"][0, 3]] = x[blocks["tetra"][0, :3]].mean(axis=0) - 0.05 * (x[blocks["tetra"][0, 3]] -
                                                                                     x[blocks["tetra"][0, :3]].mean(0))
    assert weighted.pmean_kernel(blocks, 4.0)(flat)[0] == np.inf and cells.terms(flat) is None


def test_mixed_pmean_of_the_jax_engine_matches_the_host_kernel():
    import jax

    from jaxci.metrics.objective import extra_cells
    from jaxci.optim.solver_objective import mixed_pmean

    m = perturb_box(3, amplitude=0.2, seed=0)  # hexahedra and wedges: a small program to compile
    h, col = m.hexes, [4, 13, 22]
    w = np.concatenate([h[col][:, [0, 1, 2, 4, 5, 6]], h[col][:, [0, 2, 3, 4, 6, 7]]])
    mesh = HexMesh(m.points, (CellBlock("hexahedron", np.delete(h, col, axis=0)), CellBlock("wedge", w)))
    blocks = element_blocks(mesh)
    x = np.array(mesh.points)
    v, _, g = weighted.pmean_kernel(blocks, 3.0)(x)
    with jax.enable_x64(True):
        extra = extra_cells(mesh)
        conn = jax.numpy.asarray(np.ascontiguousarray(mesh.hexes.T))
        fn = jax.jit(jax.value_and_grad(lambda y: mixed_pmean(y, conn, extra, 3.0)[0]))
        vj, gj = fn(jax.numpy.asarray(x))
    assert float(vj) == pytest.approx(v, rel=1e-10)
    np.testing.assert_allclose(np.asarray(gj), g, rtol=1e-7, atol=1e-9 * np.abs(g).max())


def test_pmean_on_a_mixed_mesh_runs_on_the_host_and_lowers_the_pmean():
    mesh = all_types_box()
    mean = smooth(mesh, "lbfgs", keep_worst=False)
    pm = smooth(mesh, "lbfgs", objective="pmean", p=4, keep_worst=False)
    # the host engine (a mixed mesh's L-BFGS there needs the C kernels; without them the JAX engine)
    assert pm.plan.engine == ("host" if native.AVAILABLE else "jax") and pm.params["objective"] == "pmean"
    pmean = checked_objective(mesh, 4.0)
    assert pmean(pm.mesh.points) < pmean(mesh.points)
    assert pmean(pm.mesh.points) < pmean(mean.mesh.points)
    assert pm.after.overall["inverted"] == 0 and not any("returned" in n for n in pm.notes)


def test_default_polishes_the_worst_element_within_its_budget():
    """A perturbed box with its boundary fixed: F leaves worst kappa/3 2.58; the default's polish takes it below
    the p-mean's (p = 2: 2.33) while the mean element quality stays within 1% and F below the input's."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    plain = smooth(mesh, "lbfgs", fix_boundary=True)
    auto = smooth(mesh, fix_boundary=True)
    assert "polish" not in plain.history and plain.params["polish"] is False  # --method lbfgs stays plain
    assert auto.params["polish"] is True and "worst-element polish" in auto.params["pipeline"]
    w0, m0 = element_stats(mesh, plain.mesh.points)
    w1, m1 = element_stats(mesh, auto.mesh.points)
    assert w0 > 2.5 and w1 < 2.3
    assert m1 <= m0 * 1.01
    assert auto.after.objective < auto.before.objective
    rep = auto.history["polish"]
    assert rep["worst"][1] == pytest.approx(w1, rel=1e-9) and rep["kept"] >= 1
    assert len(auto.history["objective"]) == auto.iterations + 1
    # no mean budget: a round that raises the mean element quality is not kept
    none = smooth(mesh, fix_boundary=True, polish_budget=0.0)
    assert element_stats(mesh, none.mesh.points)[1] <= m0 * (1 + 1e-12)


def test_the_default_polish_work_bound_is_passes_a_cell_whatever_the_solver():
    """`polish_work`: kernel passes over the mesh's cells (1000 by default), not the solve's steps: a bound below one
    round's work stops either solver's polish after its first round; a negative one is refused."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    auto = smooth(mesh, fix_boundary=True)
    assert auto.params["polish_work"] == 1000.0
    rep = auto.history["polish"]
    assert len(rep["work"]) == len(rep["element_mean"]) == rep["rounds"] and rep["work"][-1] < 1000.0 * 64
    assert rep["element_mean"][-1] == pytest.approx(rep["mean"][1], rel=1e-12)
    for solver in ("lbfgs", "newton"):
        tiny = smooth(mesh, fix_boundary=True, solver=solver, polish_work=1e-9)
        assert tiny.history["polish"]["rounds"] == 1 and "work bound" in tiny.history["polish"]["stopped"]
    with pytest.raises(ConfigError, match="polish_work"):
        GradientParams(polish_work=-1.0)


def polish_setup(mesh, x, fixed=None):
    info = classify_boundary(mesh, fixed_nodes=fixed)
    cons = build_constraints(mesh, info, dtype=np.float64, device=False)
    return cons, make_parametrisation(mesh, info, cons, x)


def test_polish_bounds_and_limits():
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    x = np.array(smooth(mesh, "lbfgs", fix_boundary=True).mesh.points)
    cons, par = polish_setup(mesh, x, fixed=np.flatnonzero(np.abs(mesh.points - 0.5).max(axis=1) > 0.49))
    y, rep = polish(mesh, cons, par, x, PolishParams(work=0.0))  # no work allowed: nothing done
    assert rep["rounds"] == 0 and "work" in rep["stopped"] and np.array_equal(y, x)
    f0 = float(mixed_objective(x, mesh))
    y, rep = polish(mesh, cons, par, x, PolishParams(f_limit=f0))  # F may not rise at all
    assert rep["rounds"] >= 1 and float(mixed_objective(y, mesh)) <= f0
    # the worst element's nodes fixed: nothing can move it, and the report says so
    worst = int(np.argmax(cell_worst(mesh, x)["hexahedron"]))
    cons, par = polish_setup(mesh, x, fixed=mesh.hexes[worst])
    y, rep = polish(mesh, cons, par, x)
    assert rep["limited"] and rep["rounds"] == 0 and np.array_equal(y, x)


def test_a_round_offers_its_lowest_worst_iterate_after_its_last():
    """A polish round's result candidates: the last accepted iterate, then, where another, the accepted one whose
    worst corner is the lowest (tried where the last is not kept)."""
    mesh = perturb_box(3, amplitude=0.0)
    cons, par = polish_setup(mesh, np.array(mesh.points))
    fun = _RoundObjective(par, None, 1.0, kernel=weighted.penalty_kernel(element_blocks(mesh), 216, 0.01, 1000.0))
    v0 = np.zeros(par.n_free)
    fun(v0)
    fun.accept()
    [only] = fun.candidates()
    np.testing.assert_allclose(only, mesh.points, atol=1e-12)  # the ideal box: its own lowest
    v1 = 0.05 * np.random.default_rng(0).standard_normal(par.n_free)
    _, _, _, k1 = fun(v1)
    fun.accept()
    last, lowest = fun.candidates()
    assert k1 > 1.01
    np.testing.assert_allclose(last, fun.points(v1), atol=1e-12)
    np.testing.assert_allclose(lowest, mesh.points, atol=1e-12)


def test_default_trades_F_for_the_worst_element_at_an_optimum_of_F():
    """Input already at L-BFGS's optimum of F: the default's polish can lower the worst element only by raising
    F above the input's, and the worst-first order keeps that (with a note); plain L-BFGS and polish=False
    never return a higher F; the untangling path follows the same order."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    opt = mesh.with_points(smooth(mesh, "lbfgs", fix_boundary=True).mesh.points)
    w0, m0 = element_stats(opt, opt.points)
    f0 = float(mixed_objective(opt.points, opt))
    auto = smooth(opt, fix_boundary=True)
    w1, m1 = element_stats(opt, auto.mesh.points)
    f1 = float(mixed_objective(auto.mesh.points, opt))
    assert w1 < w0 * (1 - 1e-3) and f1 > f0 and m1 <= m0 * 1.01
    note = [n for n in auto.notes if n.startswith("F rose")]
    assert len(note) == 1 and f"{w1:.6g}" in note[0] and "the worst element first" in note[0]
    for kw in ({"method": "lbfgs"}, {"polish": False}):
        res = smooth(opt, fix_boundary=True, **kw)
        assert float(mixed_objective(res.mesh.points, opt)) <= f0
        assert not any(n.startswith("F rose") for n in res.notes)
    # the check after untangling, as if `opt` were the untangled start: the same order
    from jaxci.interface.invariants import enforce

    cons = build_constraints(opt, classify_boundary(opt, fix_boundary=True), dtype=np.float64, device=False)
    for worst_first in (True, False):
        y, notes = enforce(opt, cons, opt.points, auto.mesh.points, untangled=True, projected=True,
                           worst_first=worst_first)
        if worst_first:
            assert np.array_equal(y, auto.mesh.points) and notes[0].startswith("F rose")
        else:
            assert np.array_equal(y, opt.points) and "the untangled mesh is returned" in notes[0]


def test_worst_first_keeps_a_higher_F_only_where_the_worst_element_fell():
    from jaxci.interface.invariants import enforce
    from jaxci.metrics.guard import worst, worst_first

    mesh = perturb_box(3, amplitude=0.25, seed=2)
    better = np.array(smooth(mesh, "lbfgs", fix_boundary=True).mesh.points)
    start, x = better, np.array(mesh.points)  # x: the worse mesh, as if a method had made it
    fs, fx = float(mixed_objective(start, mesh)), float(mixed_objective(x, mesh))
    assert worst(mesh, x) > worst(mesh, start) and fx > fs
    assert worst_first(mesh, start, x, fs, fx) is None  # F and the worst both rose: refused
    # the same F rise with the worst element fallen: kept, and the note gives both figures
    note = worst_first(mesh, x, start, fx, fx * 1.01)
    assert note is not None and f"{worst(mesh, start):.6g}" in note and f"{worst(mesh, x):.6g}" in note
    assert worst_first(mesh, x, x, fx, fx * 1.01) is None  # the worst element unchanged: refused
    # the final check: the worse mesh is refused whatever the order, after untangling or not
    cons = build_constraints(mesh, classify_boundary(mesh, fix_boundary=True), dtype=np.float64, device=False)
    for order in (False, True):
        for untangled, what in ((True, "the untangled mesh"), (False, "the input")):
            y, notes = enforce(mesh, cons, start, x, untangled=untangled, projected=True, worst_first=order)
            assert np.array_equal(y, start) and notes == [f"the objective rose from {fs:.6g} to {fx:.6g}; {what} is "
                                                          f"returned"]


@pytest.mark.skipif(not native.AVAILABLE, reason="the fused penalty is a C kernel")
def test_the_fused_penalty_is_the_two_pass_one():
    """On hexahedra the polish's penalised objective is one C pass (`jaxci.native.hex_penalty`): the same value,
    worst corner and gradient as the terms, then the weighted gradient, of the general path; inf where a corner is
    inverted."""
    m = perturb_box(6, 5, 4, amplitude=0.35, seed=3)
    h, x = np.asarray(m.hexes), np.asarray(m.points, np.float64)
    level, mu, n_norm = 0.3, 1000.0, 1000
    t, bad = native.hex_corner_terms(x, h)
    e = t - 1.0
    over = np.maximum(e - level, 0.0)
    assert bad == 0 and over.any() and (over == 0).any()  # the penalty is active on some corners only
    g = np.zeros_like(x)
    native.hex_weighted_grad(x, h, 1.0 + 2.0 * mu * over, 1.0 / n_norm, g)
    value, kmax, grad = weighted.penalty_kernel({"hexahedron": h}, n_norm, level, mu)(x)
    assert value == pytest.approx((e.sum() + mu * np.sum(over * over)) / n_norm, rel=1e-13)
    assert kmax == np.sqrt(t.max()) and np.abs(grad - g).max() <= 1e-13 * np.abs(g).max()
    flipped = x.copy()
    flipped[h[0, 6]] = x[h[0, 0]] - 0.5 * (x[h[0, 6]] - x[h[0, 0]])  # through its own element: inverted
    assert weighted.penalty_kernel({"hexahedron": h}, n_norm, level, mu)(flipped)[0] == np.inf


def test_the_cell_measure_is_a_smooth_max_of_each_cells_terms(kernels):
    """`weighted.cell_measure`: between the mean and the max of each cell's terms, nearer the max as the power
    grows; the penalty kernel with it (every cell type, C and numpy) is each cell's share ``c (M - 1)`` plus the
    penalty, and its gradient is exact."""
    t = 1.0 + np.random.default_rng(2).random((8, 50)) ** 2
    m1, _ = weighted.cell_measure(t, 1)
    m5, d5 = weighted.cell_measure(t, 5)
    assert np.all(t.mean(axis=0) <= m1) and np.all(m1 <= m5) and np.all(m5 <= t.max(axis=0))
    h = 1e-7
    bump = np.zeros_like(t)
    bump[3, :] = h
    fd = (weighted.cell_measure(t + bump, 5)[0] - weighted.cell_measure(t - bump, 5)[0]) / (2 * h)
    np.testing.assert_allclose(8 * fd, d5[3], rtol=1e-6, atol=1e-7)  # c dM / dt_i = (t_i / M)^(P - 1)
    mesh = all_types_box()
    blocks = element_blocks(mesh)
    x = np.array(mesh.points)
    kernel = weighted.penalty_kernel(blocks, 100, 0.05, 50.0, 5)
    cells = weighted.CellCorners(blocks)
    parts = cells.terms(x)
    assert cells.types[0] == "hexahedron"  # (so the parts are in the order of the types, C kernel or not)
    corners = [KERNELS[t].n_corners for t in cells.types]
    expect = sum(c * float((weighted.cell_measure(p.reshape(c, -1), 5)[0] - 1.0).sum())
                 + 50.0 * float(np.sum(np.maximum(p - 1.0 - 0.05, 0.0) ** 2)) for p, c in zip(parts, corners,
                                                                                            strict=True)) / 100
    v, _, g = kernel(x)
    assert v == pytest.approx(expect, rel=1e-12)
    d = np.random.default_rng(0).normal(size=x.shape)
    fd = (kernel(x + 1e-6 * d)[0] - kernel(x - 1e-6 * d)[0]) / 2e-6
    assert fd == pytest.approx(float(np.sum(g * d)), rel=1e-6)


@pytest.mark.skipif(not native.AVAILABLE, reason="the fused penalty is a C kernel")
def test_the_fused_cell_measure_is_the_numpy_one(monkeypatch):
    m = perturb_box(6, 5, 4, amplitude=0.35, seed=3)
    h, x = np.asarray(m.hexes), np.asarray(m.points, np.float64)
    fused = weighted.penalty_kernel({"hexahedron": h}, 1000, 0.3, 1000.0, 5)(x)
    monkeypatch.setattr(native, "AVAILABLE", False)
    plain = weighted.penalty_kernel({"hexahedron": h}, 1000, 0.3, 1000.0, 5)(x)
    assert fused[0] == pytest.approx(plain[0], rel=1e-13) and fused[1] == pytest.approx(plain[1], rel=1e-14)
    assert np.abs(fused[2] - plain[2]).max() <= 1e-12 * np.abs(plain[2]).max()


def test_the_polish_with_the_cell_measure_keeps_its_guarantees():
    """``polish_cell_power``: a power of two (else a ConfigError naming it); with 32 the polish still lowers the
    worst element within its budget, as with F's sum."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    plain = smooth(mesh, "lbfgs", fix_boundary=True)
    cell = smooth(mesh, fix_boundary=True, polish_cell_power=32)
    w0, m0 = element_stats(mesh, plain.mesh.points)
    w1, m1 = element_stats(mesh, cell.mesh.points)
    assert w1 < w0 - 0.2 and m1 <= m0 * 1.01 and cell.params["polish_cell_power"] == 32
    with pytest.raises(ConfigError, match="polish_cell_power=3 must be a power of two"):
        smooth(mesh, polish_cell_power=3)


def test_the_mean_phase_lowers_the_mean_element_before_the_rounds():
    """`mean_steps`: the polish first lowers the mean element quality (L-BFGS on each cell's smooth max) and keeps
    that only where the mean fell and the worst did not rise; the rounds' budget stays the start's. Where the phase
    is not kept (F may not rise here, and it would), the result is the one without it, bit for bit."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    x = np.array(smooth(mesh, "lbfgs", fix_boundary=True).mesh.points)
    cons, par = polish_setup(mesh, x, fixed=np.flatnonzero(np.abs(mesh.points - 0.5).max(axis=1) > 0.49))
    w0, m0 = element_stats(mesh, x)
    y, rep = polish(mesh, cons, par, x, PolishParams(mean_steps=25))
    phase = rep["mean_phase"]
    assert phase["kept"] and 1 <= phase["steps"] <= 25 and phase["work"] > 0
    assert phase["mean"][0] == pytest.approx(m0, rel=1e-12) and phase["mean"][1] < m0
    assert phase["worst"][1] <= phase["worst"][0] == pytest.approx(w0, rel=1e-12)
    w1, m1 = element_stats(mesh, y)
    assert w1 == pytest.approx(rep["worst"][1], rel=1e-12) and w1 < w0 and m1 <= m0 * 1.01
    _, plain = polish(mesh, cons, par, x, PolishParams())
    assert plain["mean_phase"] is None
    # the phase ends where it stalls (`MEAN_RTOL`), not after all its steps
    _, long = polish(mesh, cons, par, x, PolishParams(mean_steps=1000))
    assert long["mean_phase"]["steps"] < 200
    f0 = float(mixed_objective(x, mesh))
    y1, rep1 = polish(mesh, cons, par, x, PolishParams(f_limit=f0, mean_steps=25))
    y0, _ = polish(mesh, cons, par, x, PolishParams(f_limit=f0))
    assert not rep1["mean_phase"]["kept"] and np.array_equal(y1, y0)


def test_the_mean_phase_ends_where_its_mean_has_not_fallen(monkeypatch):
    """`MEAN_CHECK`: after that many accepted steps the mean phase goes on only where the mean element has fallen
    below the start's. Where it has, the check changes nothing (the same points, bit for bit); where it has not
    (checked at the start itself, where it cannot have), the phase ends there, is not kept, and the polish is the
    one without a phase."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    x = np.array(smooth(mesh, "lbfgs", fix_boundary=True).mesh.points)
    cons, par = polish_setup(mesh, x, fixed=np.flatnonzero(np.abs(mesh.points - 0.5).max(axis=1) > 0.49))
    monkeypatch.setattr(polish_module, "MEAN_CHECK", 10**9)
    y_free, free = polish(mesh, cons, par, x, PolishParams(mean_steps=25))
    assert free["mean_phase"]["kept"] and free["mean_phase"]["steps"] > 3
    monkeypatch.setattr(polish_module, "MEAN_CHECK", 3)
    y3, rep3 = polish(mesh, cons, par, x, PolishParams(mean_steps=25))
    assert rep3["mean_phase"]["steps"] == free["mean_phase"]["steps"] and np.array_equal(y3, y_free)
    monkeypatch.setattr(polish_module, "MEAN_CHECK", 0)
    y0, rep0 = polish(mesh, cons, par, x, PolishParams(mean_steps=25))
    assert rep0["mean_phase"]["steps"] == 0 and not rep0["mean_phase"]["kept"]
    y_none, _ = polish(mesh, cons, par, x, PolishParams())
    assert np.array_equal(y0, y_none)


def test_the_default_polish_has_a_mean_phase():
    """The default pipeline's polish runs its mean phase (`polish_mean_steps`, 100); 0 turns it off; a negative
    count is refused by name."""
    mesh = perturb_box(4, amplitude=0.3, seed=1)
    auto = smooth(mesh, fix_boundary=True)
    assert auto.params["polish_mean_steps"] == 100 and auto.history["polish"]["mean_phase"]["steps"] >= 1
    off = smooth(mesh, fix_boundary=True, polish_mean_steps=0)
    assert off.history["polish"]["mean_phase"] is None
    with pytest.raises(ConfigError, match="polish_mean_steps"):
        GradientParams(polish_mean_steps=-1)
