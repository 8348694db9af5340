"""Local CI on the host (`jaxci.optim.host_local`): the C local sums, the same algorithm as the compiled sweep,
nothing compiled or imported from JAX, the boundary kept."""

from __future__ import annotations

import functools
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import MESQUITE, spiked_sweep

import jaxci
from jaxci import native
from jaxci.errors import ConfigError
from jaxci.interface.engine import host_plan
from jaxci.interface.smooth import smooth
from jaxci.mesh.generate import perturb_box

pytestmark = pytest.mark.skipif(not native.AVAILABLE, reason="the C kernels are not built")


def test_local_sums_equal_the_local_terms_of_the_compiled_sweep(monkeypatch):
    """`native.local_sums` gives `jaxci.optim._local.local_terms` (float64) for trial positions of every node,
    inf exactly where a corner inverts (trials far enough to fold some elements); the same numbers on one thread
    and on three (a 9^3 box's 1,000 node slots: three ranges)."""
    import jax
    import jax.numpy as jnp

    from jaxci.optim._local import gather_star, local_terms, node_stars

    mesh = perturb_box(5, amplitude=0.3, seed=3)
    x, hexes = np.asarray(mesh.points), np.asarray(mesh.hexes)
    stars = node_stars(hexes, len(x))
    inc = node_stars(hexes, len(x), incidences=True).star
    trials = x[:, None] + np.random.default_rng(0).normal(size=(len(x), 7, 3)) * 0.06
    with jax.enable_x64(True):
        ref = np.asarray(local_terms(gather_star(jnp.asarray(x), jnp.asarray(stars.star)), jnp.asarray(stars.mask),
                                     jnp.asarray(trials)))
    got = native.local_sums(x, hexes, inc, stars.mask.sum(axis=1), trials)
    finite = np.isfinite(ref)
    assert 0.2 < finite.mean() < 0.95  # both kinds of trials are there
    assert np.array_equal(np.isfinite(got), finite)
    np.testing.assert_allclose(got[finite], ref[finite], rtol=1e-12)
    mesh = perturb_box(9, amplitude=0.3, seed=3)
    x, hexes = np.asarray(mesh.points), np.asarray(mesh.hexes)
    stars = node_stars(hexes, len(x), incidences=True)
    trials = x[:, None] + np.random.default_rng(1).normal(size=(len(x), 7, 3)) * 0.06
    runs = []
    for threads in (1, 3):
        monkeypatch.setattr(native, "THREADS", threads)
        runs.append(native.local_sums(x, hexes, stars.star, stars.mask.sum(axis=1), trials))
    assert np.array_equal(runs[0], runs[1]) and np.isfinite(runs[0]).any()


@pytest.mark.parametrize("block", [1, 7, 1 << 14])
def test_stars_in_blocks_and_of_some_rows_are_the_whole_stars(monkeypatch, block):
    """`node_stars` sorts the incidences `STAR_BLOCK` elements at a time: the same stars as one sort of every
    incidence (each node's elements in order); with `rows`, the rows of the whole stars for those nodes, in that
    order (`sweep_colours`' colours, made without the whole stars)."""
    from jaxci.optim import _local
    from jaxci.optim._local import node_stars

    mesh = perturb_box(6, amplitude=0.3, seed=2)
    hexes, n = mesh.hexes, mesh.n_nodes
    valence = np.bincount(hexes.ravel(), minlength=n)
    mask = np.arange(valence.max()) < valence[:, None]
    ref = np.zeros(mask.shape, np.int64)
    ref[mask] = np.argsort(hexes.ravel(), kind="stable")  # every incidence at once, grouped by node
    monkeypatch.setattr(_local, "STAR_BLOCK", block)
    whole = node_stars(hexes, n, incidences=True)
    np.testing.assert_array_equal(whole.star, ref)
    np.testing.assert_array_equal(whole.mask, mask)
    rows = np.random.default_rng(0).permutation(n)[: n // 3]
    some = node_stars(hexes, n, incidences=True, rows=rows)
    np.testing.assert_array_equal(some.star, ref[rows])
    np.testing.assert_array_equal(some.mask, mask[rows])
    np.testing.assert_array_equal(node_stars(hexes, n).star, node_stars(hexes.astype(np.int64), n).star)


@pytest.mark.shared
def test_star_incidences_are_the_relabelled_node_lists():
    """The host sweeps' stars are incidences (8 e + s, 8x less memory): `star_nodes` turns them into exactly the
    compiled path's relabelled node lists, real slots and mask the same, on a mesh with uneven valences."""
    from jaxci.optim._local import node_stars, star_nodes

    mesh = jaxci.read_mesh(str(MESQUITE / "pave3.e.vtk"))
    hexes = np.asarray(mesh.hexes)
    lists, inc = node_stars(hexes, mesh.n_nodes), node_stars(hexes, mesh.n_nodes, incidences=True)
    assert inc.star.shape == lists.mask.shape and np.array_equal(inc.mask, lists.mask)
    real = lists.mask
    assert np.array_equal(star_nodes(hexes, inc.star)[real], lists.star[real])


def test_local_sums_name_a_bad_incidence():
    """An incidence outside the elements or a count above K is an IndexError naming the kernel and the value,
    not a read out of bounds."""
    x, hexes = np.zeros((8, 3)), np.arange(8)[None]
    trials = np.zeros((1, 1, 3))
    with pytest.raises(IndexError, match="local_sums: incidence 8 out of range"):
        native.local_sums(x, hexes, np.array([[8]]), np.array([1]), trials)
    with pytest.raises(IndexError, match="local_sums: count 2 out of range"):
        native.local_sums(x, hexes, np.array([[0]]), np.array([2]), trials)


def test_host_and_compiled_local_ci_reach_the_same_optimum_in_as_many_sweeps():
    """The paper's 27-element cube, float64: the host sweep (numpy's random stream) and the compiled one (JAX's)
    both reach the ideal grid (F <= ftol) in about the same number of sweeps, F never rising."""
    mesh = jaxci.paper_case("cube27", seed=1)
    runs = {b: smooth(mesh, "ci", seed=0, dtype="float64", backend=b) for b in ("numpy", "jax")}
    for res in runs.values():
        assert res.after.max_condition < 1.0001 and res.after.inverted_elements == 0
        hist = np.asarray(res.history["objective"])
        assert np.all(np.diff(hist) <= 1e-12 * hist[0])
    assert abs(runs["numpy"].iterations - runs["jax"].iterations) <= 0.3 * runs["jax"].iterations
    assert runs["numpy"].params["backend"] == "numpy"


def test_host_local_ci_is_deterministic_per_seed():
    mesh = perturb_box(4, amplitude=0.3, seed=2)
    a, b, c = (smooth(mesh, "ci", seed=s, max_sweeps=5) for s in (7, 7, 8))
    assert np.array_equal(a.mesh.points, b.mesh.points)
    assert not np.array_equal(a.mesh.points, c.mesh.points)


def test_host_local_ci_keeps_corners_and_faces_exactly():
    """Sliding boundary of a perturbed box: corners bit for bit, every face node on its face plane to 1e-15."""
    mesh = perturb_box(6, amplitude=0.3, seed=0)
    res = smooth(mesh, "ci", max_sweeps=20)
    x0, x = np.asarray(mesh.points), np.asarray(res.mesh.points)
    for d in range(3):
        for side in (0.0, 1.0):
            on = x0[:, d] == side
            assert np.all(np.abs(x[on, d] - side) <= 1e-15)
    corners = np.all((x0 == 0) | (x0 == 1), axis=1)
    assert np.array_equal(x[corners], x0[corners])
    assert res.after.objective < 0.05 * res.before.objective and res.after.inverted_elements == 0


def test_backend_is_checked():
    with pytest.raises(ConfigError, match="backend"):
        smooth(perturb_box(2), "ci", backend="gpu")


@pytest.mark.slow
def test_cli_local_ci_on_a_small_mesh_never_imports_jax(tmp_path):
    """``jaxci smooth --method ci`` on a 1000-hex box runs in numpy and C: no JAX import, nothing compiled."""
    from jaxci.io import write_mesh

    write_mesh(perturb_box(10, amplitude=0.3, seed=1), str(tmp_path / "in.vtk"))
    args = ["smooth", str(tmp_path / "in.vtk"), str(tmp_path / "out.vtk"), "--method", "ci", "--param",
            "max_sweeps=10"]
    code = (f"import sys; from jaxci.cli import main; rc = main({args!r}); "
            "print(rc, sorted(m for m in ('jax', 'scipy.sparse', 'scipy.spatial') if m in sys.modules))")
    env = dict(os.environ, JAXCI_CACHE_DIR=str(tmp_path / "cache"))
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert p.stdout.strip().splitlines()[-1] == "0 []", p.stdout + p.stderr


def test_lbfgs_with_presmoothing_runs_on_the_host_without_jax():
    """L-BFGS after smart-Laplace sweeps (the default pipeline's recipe from 100,001 hexahedra) on a mesh the host
    takes: sweeps and solver in numpy and C, JAX never imported."""
    code = ("import sys; from jaxci.mesh.generate import perturb_box; from jaxci.interface.smooth import smooth; "
            "r = smooth(perturb_box(6, amplitude=0.3, seed=1), 'lbfgs', presmooth=2); "
            "print(r.history['presmooth'], r.after.max_condition < r.before.max_condition, 'jax' in sys.modules)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert p.stdout.strip().splitlines()[-1] == "2 True False", p.stdout + p.stderr


@pytest.mark.parametrize("method", ["laplace", "smart-laplace"])
def test_host_and_compiled_laplacians_agree(method):
    """The Laplacians on the host take the compiled sweeps' moves (no randomness): the same mesh after the same
    number of sweeps, to rounding (the compiled loop runs on the problem padded to its size class)."""
    mesh = jaxci.paper_case("cube64", seed=2)
    a, b = (smooth(mesh, method, dtype="float64", backend=be, max_sweeps=6) for be in ("numpy", "jax"))
    assert a.iterations == b.iterations == 6
    np.testing.assert_allclose(a.mesh.points, b.mesh.points, atol=1e-12)
    assert a.params["backend"] == "numpy"


def test_host_smart_laplace_keeps_a_curved_boundary_and_never_raises_f():
    from test_ci import boundary_error

    from jaxci.mesh.shapes import annulus

    mesh0 = annulus(16, 3, 2)
    rng = np.random.default_rng(1)
    x = np.array(mesh0.points)
    x += rng.uniform(-0.02, 0.02, x.shape)
    mesh = mesh0.with_points(x)
    res = smooth(mesh, "smart-laplace", untangle="never")
    hist = np.asarray(res.history["objective"])
    assert np.all(np.diff(hist) <= 1e-12 * hist[0]) and res.after.inverted_elements == 0
    assert boundary_error(mesh, res.mesh) < 1e-9


def test_host_and_compiled_global_ci_both_beat_the_papers_worst_on_cube27():
    """The paper's global CI with its defaults (1000 attempts) on the 27-element cube: the host loop
    (`jaxci.optim.host_global`) and the compiled one both end below the paper's worst max kappa/3 (1.0117,
    Table 3), the cohort's best never rising, and the host one keeps the faces exactly."""
    mesh = jaxci.paper_case("cube27", seed=4)
    for backend in ("numpy", "jax"):
        res = smooth(mesh, "ci-global", seed=1, dtype="float64", backend=backend)
        assert res.after.max_condition < 1.0117 and res.after.inverted_elements == 0
        assert np.all(np.diff(np.asarray(res.history["best"])) <= 0)
    res = smooth(mesh, "ci-global", seed=1, attempts=100)
    x0, x = np.asarray(mesh.points), np.asarray(res.mesh.points)
    for d in range(3):
        for side in (0.0, 1.0):
            on = x0[:, d] == side
            assert np.all(np.abs(x[on, d] - side) <= 1e-15)


def test_host_local_ci_gives_the_same_mesh_on_any_number_of_threads(monkeypatch):
    """`jaxci.native.ci_visit` splits a colour's nodes over threads, each node with its own random stream: one
    thread and three give the same mesh bit for bit."""
    mesh = perturb_box(7, amplitude=0.3, seed=5)
    runs = []
    for threads in (1, 3):
        monkeypatch.setattr(native, "THREADS", threads)
        runs.append(smooth(mesh, "ci", seed=3, max_sweeps=4).mesh.points)
    assert np.array_equal(runs[0], runs[1])


def test_host_local_length_is_the_mean_edge_length_at_the_node(monkeypatch):
    """The length scale of the host sweeps (CI's initial widths and width bounds, the Laplacians' stopping
    test) is `jaxci.optim._local.local_length`, the compiled path's: on a unit box of 4^3 cells, the spacing 0.25
    at every node (it was once sqrt(l1^2 + l2^2 + l3^2) / 3, 0.58 x the spacing); computed in blocks of nodes
    (`LENGTH_CHUNK`), the same numbers as at once on a perturbed box."""
    from jaxci.interface.methods import build_problem
    from jaxci.mesh.generate import box
    from jaxci.optim import host_local
    from jaxci.optim.host_local import _local_length, sweep_colours

    mesh = box(4, 4, 4)
    pb = build_problem(mesh, dtype=np.float64, plan=host_plan())
    for col in sweep_colours(mesh.hexes, pb.cons, pb.colour, pb.info.topology.faces):
        np.testing.assert_allclose(_local_length(np.asarray(mesh.points), mesh.hexes, col), 0.25, rtol=1e-12)
    mesh = perturb_box(5, amplitude=0.3, seed=1)
    pb = build_problem(mesh, dtype=np.float64, plan=host_plan())
    cols = sweep_colours(mesh.hexes, pb.cons, pb.colour, pb.info.topology.faces)
    whole = [_local_length(np.asarray(mesh.points), mesh.hexes, col) for col in cols]
    monkeypatch.setattr(host_local, "LENGTH_CHUNK", 3)
    for col, ref in zip(cols, whole, strict=True):
        np.testing.assert_array_equal(_local_length(np.asarray(mesh.points), mesh.hexes, col), ref)



@pytest.mark.parametrize("which", ["box", pytest.param("pave3", marks=pytest.mark.shared)])
def test_host_sweep_set_up_equals_its_reference(which):
    """The host sweeps' local lengths (measured on the real slots of the stars alone) are bit for bit the
    compiled path's formula over the gathered, padded stars (`_local.local_length`); the colours made with the
    planar rings the solve's parametrisation keeps (`flat_surface_rings`, as the escape passes them) equal those
    that make their own: on a perturbed box and on pave3 (paved: irregular stars, curved walls)."""
    from jaxci.interface.methods import build_problem
    from jaxci.io import read_mesh
    from jaxci.optim._local import gather_star, local_length, star_nodes
    from jaxci.optim.host_local import _local_length, sweep_colours
    from jaxci.optim.parametrisation import flat_surface_rings

    mesh = perturb_box(5, amplitude=0.3, seed=2) if which == "box" else read_mesh(str(MESQUITE / "pave3.e.vtk"))
    pb = build_problem(mesh, dtype=np.float64, plan=host_plan())
    faces = pb.info.topology.faces
    x = np.asarray(pb.mesh.points, np.float64)
    cols = sweep_colours(pb.mesh.hexes, pb.cons, pb.colour, faces)
    for col in cols:
        real = np.arange(col.inc.shape[1])[None] < col.count[:, None]
        ref = local_length(gather_star(x, star_nodes(pb.mesh.hexes, col.inc)), real, np)
        np.testing.assert_array_equal(_local_length(x, pb.mesh.hexes, col), ref)
    rings = flat_surface_rings(np.asarray(pb.cons.x_orig, np.float64), pb.info, pb.cons)
    given = sweep_colours(pb.mesh.hexes, pb.cons, pb.colour, faces, rings)
    assert any(len(c.surface_plane) for c in cols)
    for a, b in zip(cols, given, strict=True):
        np.testing.assert_array_equal(a.nodes, b.nodes)
        np.testing.assert_array_equal(a.surface_plane, b.surface_plane)

_BOX6 = perturb_box(6, amplitude=0.3, seed=4)


@functools.cache
def _box6_without_stops(backend: str):
    """Local CI on `_BOX6` without the atol and ktol stops (80 sweeps at most): the reference of the two tests
    below, run once per backend."""
    return smooth(_BOX6, "ci", seed=0, max_sweeps=80, backend=backend, ktol=0.0, atol=0.0)


def test_local_ci_stops_once_a_sweep_gains_less_than_atol():
    """A perturbed box approaches the ideal grid geometrically: with `tol` (relative) alone local CI swept on
    while F fell towards 0; `atol` stops it once a sweep lowers F by less than ``tol F + atol``, at max kappa/3
    <= 1.0001, in fewer sweeps than with ``atol=0``, on the host and compiled."""
    for backend in ("numpy", "jax"):
        stop = smooth(_BOX6, "ci", seed=0, max_sweeps=80, backend=backend, ktol=0.0)
        on = _box6_without_stops(backend)
        hist = np.asarray(stop.history["objective"])
        assert stop.params["atol"] == 1e-7
        assert stop.after.max_condition <= 1.0001 and stop.iterations < on.iterations, backend
        assert hist[-2] - hist[-1] <= 1e-6 * hist[-2] + 1e-7 and hist[-1] > 1e-10


@pytest.mark.parametrize("backend", ["numpy", "jax"])
def test_local_ci_stops_once_every_corner_is_ideal_within_ktol(backend):
    """max kappa/3 <= 1 + ktol (the global minimum within ktol) stops local CI after the first sweep that reaches
    it, on the host and compiled; the same sweeps as a run without it up to there."""
    full = _box6_without_stops(backend)
    k_full = np.asarray(full.history["max_condition"])
    ktol = 1e-3
    first = int(np.argmax(k_full <= 1 + ktol))
    assert 0 < first < full.iterations
    res = smooth(_BOX6, "ci", seed=0, max_sweeps=80, backend=backend, ktol=ktol, atol=0.0)
    assert res.iterations == first and res.after.max_condition <= 1 + ktol
    np.testing.assert_allclose(np.asarray(res.history["max_condition"]), k_full[: first + 1], rtol=1e-12)


@pytest.mark.shared
def test_local_ci_reaches_lbfgs_on_pave3_in_30_sweeps():
    """On pave3 (paved, unstructured, 106 inverted elements first untangled) 30 sweeps of local CI
    come within 1% of L-BFGS's final F; Anderson acceleration over the sweeps (`CIParams.anderson`) is what takes
    them there (measured over 8 seeds with the default cohorts: 0.0-0.4% above L-BFGS's F with it, 1.6-2.6%
    without)."""
    mesh = jaxci.read_mesh(str(MESQUITE / "pave3.e.vtk"))
    f_lbfgs = smooth(mesh, "lbfgs").after.objective
    runs = [smooth(mesh, "ci", seed=seed, max_sweeps=30) for seed in (0, 1)]
    for seed, r in enumerate(runs):
        assert r.iterations == 30 and r.after.inverted_elements == 0
        assert r.after.objective <= 1.01 * f_lbfgs, (seed, r.after.objective / f_lbfgs)
        assert np.all(np.diff(r.history["objective"]) <= 0)  # the accelerated step is taken only where F falls
    plain = smooth(mesh, "ci", seed=0, max_sweeps=30, anderson=0)
    assert plain.after.objective > runs[0].after.objective


def test_host_pattern_move_never_worsens_the_worst_corner():
    """On the host too (`_Sweeper.pattern`, the same condition as the compiled `jaxci.optim.ci._better`): along
    a sweep displacement whose lowest-F factor (4) makes the worst corner's excess more than `EXCESS_GROWTH` times
    worse, the factor 2 is taken, which lowers both F and max kappa/3."""
    from jaxci.interface.smooth import build_problem
    from jaxci.optim.ci_params import EXCESS_GROWTH, CIParams
    from jaxci.optim.host_local import _Sweeper

    mesh, D = spiked_sweep()
    pb = build_problem(mesh, dtype=np.float64, plan=host_plan())
    sw = _Sweeper(np.asarray(mesh.points), mesh.hexes, pb.cons, pb.colour, pb.info.topology.faces, CIParams())
    f, k = sw.objective(sw.x)
    f2, k2 = sw.objective(sw.x + 2 * D)
    f4, k4 = sw.objective(sw.x + 4 * D)
    assert f4 < f2 < f and k2 < k and k4 - 1 > EXCESS_GROWTH * (k - 1)
    np.testing.assert_allclose(sw.pattern(D, f, k), (f2, k2), rtol=1e-12)
    np.testing.assert_allclose(sw.x, np.asarray(mesh.points) + 2 * D, atol=1e-15)


def test_host_pattern_move_stops_at_the_first_factor_where_f_rises():
    """`_Sweeper.pattern` tries the factors in order and stops after the first whose F is not below its
    predecessor's: along the spiked sweep F falls at 1, 2, 4 and rises at 8, so 4 of the 6 factors are evaluated,
    and the choice is the one of all six (the factor 2, as the test above)."""
    from jaxci.interface.smooth import build_problem
    from jaxci.optim.ci_params import PATTERN_FACTORS, CIParams
    from jaxci.optim.host_local import _Sweeper

    mesh, D = spiked_sweep()
    pb = build_problem(mesh, dtype=np.float64, plan=host_plan())
    sw = _Sweeper(np.asarray(mesh.points), mesh.hexes, pb.cons, pb.colour, pb.info.topology.faces, CIParams())
    f, k = sw.objective(sw.x)
    along = [sw.objective(sw.x + a * D)[0] for a in PATTERN_FACTORS]
    assert len(PATTERN_FACTORS) == 6 and along[0] > along[1] > along[2] and not along[3] < along[2]
    calls = []
    evaluate = sw.objective
    sw.objective = lambda x: calls.append(1) or evaluate(x)
    sw.pattern(D, f, k)
    assert len(calls) == 4
    np.testing.assert_allclose(sw.x, np.asarray(mesh.points) + 2 * D, atol=1e-15)


def test_both_engines_pick_the_same_pattern_trial():
    """`pattern_choice`, the one rule of local CI's pattern move: numpy (the host, which stops evaluating at the
    first rise of F) and jax.numpy (the compiled sweep, all six trials at once) pick the trial that the
    sequential rule picks (the lowest F below the current one with the worst corner within bound, among the trials
    up to the first rise), on random F (NaN and inf among them) and max kappa/3."""
    import jax.numpy as jnp

    from jaxci.optim.ci_params import EXCESS_GROWTH, PATTERN_FACTORS, pattern_choice

    rng = np.random.default_rng(0)
    m = len(PATTERN_FACTORS)
    for t in range(500):
        f, k = 1.0, 1.5
        fy, ky = rng.uniform(0.5, 1.2, m), rng.uniform(1.2, 2.5, m)
        fy[rng.integers(m)] = (np.nan, np.inf, fy[0])[t % 3]
        want, low, previous = -1, f, f
        for i in range(m):  # in order, as the host evaluates them
            if fy[i] < low and ky[i] - 1 <= EXCESS_GROWTH * (k - 1):
                want, low = i, fy[i]
            if not fy[i] < previous:
                break
            previous = fy[i]
        got_np = int(pattern_choice(f, k, fy, ky, np))
        got_jax = int(pattern_choice(jnp.asarray(f), jnp.asarray(k), jnp.asarray(fy), jnp.asarray(ky), jnp))
        assert got_np == got_jax == want, (t, got_np, got_jax, want, fy, ky)


@pytest.mark.parametrize("which", ["box", "annulus"])
def test_host_colours_are_the_compiled_sweeps_slots(which):
    """The host sweep's colours (`host_local.sweep_colours`, made one at a time) hold what the compiled sweep's padded
    tables (`coloured_stars`) hold in their real slots, in the same order: the nodes by class, their incidences,
    bases, free directions and planar rings; on a box with sliding flat walls and on an annulus with curved ones."""
    from helpers import wavy_annulus

    from jaxci.interface.methods import build_problem
    from jaxci.optim import host_local
    from jaxci.optim._local import node_stars
    from jaxci.optim._moves import coloured_stars

    mesh = perturb_box(6, amplitude=0.3, seed=1) if which == "box" else wavy_annulus(16, 3, 3)
    pb = build_problem(mesh, dtype=np.float64)
    faces = pb.info.topology.faces
    got = host_local.sweep_colours(mesh.hexes, pb.cons, pb.colour, faces)
    cs = coloured_stars(mesh.hexes, pb.cons, pb.colour, faces, place=False)
    inc = node_stars(mesh.hexes, mesh.n_nodes, incidences=True).star
    mask = np.asarray(cs.mask)
    kept = [i for i in range(len(mask)) if mask[i].any()]
    assert [c.index for c in got] == kept and sum(len(c.nodes) for c in got) == int(mask.sum())
    assert any(c.b > c.a for c in got) and any(len(c.nodes) > c.b for c in got)  # surface and edge slots
    for c in got:
        real = mask[c.index]
        np.testing.assert_array_equal(c.nodes, np.asarray(cs.nodes)[c.index][real])
        np.testing.assert_array_equal(c.inc, inc[c.nodes])
        np.testing.assert_array_equal(c.count, np.asarray(cs.smask)[c.index][real].sum(axis=1))
        np.testing.assert_array_equal(c.basis, np.asarray(cs.basis, np.float64)[c.index][real])
        np.testing.assert_array_equal(c.plane, np.asarray(cs.plane, np.float64)[c.index][real])
        dims = np.asarray(cs.dims)[c.index][real]
        np.testing.assert_array_equal(c.free, (np.arange(3)[None] < dims[:, None]).astype(np.float64))
        assert (c.kind[: c.a] == 0).all() and (c.kind[c.a : c.b] == 1).all() and (c.kind[c.b :] == 2).all()
