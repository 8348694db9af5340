"""Every user input is checked where it enters: coincident nodes, extreme coordinates, method
parameters, seeds, memory, zero-volume meshes, wrong argument types, exact counts in messages."""

from __future__ import annotations

import json
import math
import time
import warnings

import meshio
import numpy as np
import pytest

import jaxci
from jaxci.cli import main
from jaxci.errors import ConfigError, InvertedMeshError, JaxciError, MeshError, UsageError
from jaxci.io import read_mesh, write_mesh
from jaxci.mesh import hex_mesh, merge_coincident
from jaxci.mesh.generate import box, perturb_box
from jaxci.metrics.report import quality_report


def split_box(n: int = 4, amplitude: float = 0.2, seed: int = 1, scale: float = 1.0, offset: float = 0.0):
    """A perturbed n^3 box cut at x = 1/2 into two parts that do not share their interface nodes: the nodes of
    the right part on the interface are copies, numbered after the box's nodes. Returns (mesh, pairs)."""
    m = perturb_box(n, amplitude=amplitude, seed=seed)
    grid = box(n).points
    hexes = m.hexes.copy()
    iface = np.flatnonzero(np.isclose(grid[:, 0], 0.5))
    copy = {int(k): m.n_nodes + i for i, k in enumerate(iface)}
    right = grid[hexes].mean(axis=1)[:, 0] > 0.5
    hexes[right] = np.vectorize(lambda k: copy.get(int(k), int(k)))(hexes[right])
    points = np.concatenate([m.points, m.points[iface]]) * scale + offset
    assert len(iface)
    return hex_mesh(points, hexes), np.stack([iface, np.arange(len(iface)) + m.n_nodes], axis=1)


def run_cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_error_line(code, err, match):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxci: error: "), err
    assert "Traceback" not in err and "internal error" not in err
    assert match in lines[0], lines[0]


# ------------------------------------------------------------------------------------------ coincident nodes
def test_coincident_nodes_noted_and_kept_coincident():
    mesh, pairs = split_box()
    note = [n for n in mesh.notes if "coincident" in n]
    assert len(note) == 1 and note[0].startswith(f"{len(pairs)} pairs of coincident nodes")
    assert f"first: nodes {pairs[0, 0]} and {pairs[0, 1]}" in note[0]
    np.testing.assert_array_equal(mesh.coincident_nodes(), pairs)
    res = jaxci.smooth(mesh, "smart-laplace", max_sweeps=20)
    p = res.mesh.points
    np.testing.assert_array_equal(p[pairs[:, 0]], p[pairs[:, 1]])  # exactly coincident
    assert res.after.objective < res.before.objective  # the rest was smoothed
    assert any(f"{2 * len(pairs)} coincident nodes in {len(pairs)} sets" in n for n in res.notes)


def test_coincidence_tolerance_is_relative():
    mesh, pairs = split_box(scale=1e-6, offset=1e3)  # tiny and far from the origin: still found
    np.testing.assert_array_equal(mesh.coincident_nodes(), pairs)
    m = perturb_box(2, amplitude=0.1)
    p = m.points.copy()
    p[13] = p[12] + 1e-6  # close, but 1e-6 of the diagonal is well above the 1e-9 tolerance
    assert not any("coincident" in n for n in hex_mesh(p, m.hexes).notes)


def test_merge_coincident():
    mesh, pairs = split_box(n=2)
    merged = merge_coincident(mesh)
    base = perturb_box(2, amplitude=0.2, seed=1)
    assert merged.n_nodes == base.n_nodes == mesh.n_nodes - len(pairs)
    np.testing.assert_array_equal(merged.hexes, base.hexes)  # the copies map back to the interface nodes
    np.testing.assert_array_equal(merged.points, base.points)
    assert merged.notes[-1].startswith(f"merged {len(pairs)} groups of coincident nodes")
    assert not len(merged.coincident_nodes())
    assert merge_coincident(base) is base
    res = jaxci.smooth(mesh, "smart-laplace", max_sweeps=5, merge_coincident=True)
    assert res.mesh.n_nodes == base.n_nodes and any(n.startswith("merged") for n in res.notes)


# ------------------------------------------------------------------------------------------ extreme coordinates
@pytest.mark.parametrize("scale", [1e300, 1e-300])
def test_scaled_box_reports_like_the_unit_box(scale):
    m = perturb_box(3, amplitude=0.3, seed=2)
    big = m.with_points(m.points * scale)
    assert big.notes == ()  # no false degenerate / inverted notes
    ref, rep = quality_report(m), quality_report(big)
    assert rep.inverted_corners == 0 and rep.inverted_elements == 0
    for key in ("max_condition", "mean_condition", "objective", "min_scaled_jacobian"):
        assert getattr(rep, key) == pytest.approx(getattr(ref, key), rel=1e-9)
    a = jaxci.smooth(m, "smart-laplace", dtype="float64", max_sweeps=5)
    b = jaxci.smooth(big, "smart-laplace", dtype="float64", max_sweeps=5)
    assert np.isfinite(b.mesh.points).all()
    np.testing.assert_allclose(b.mesh.points / scale, a.mesh.points, rtol=1e-9, atol=1e-12)
    assert b.after.max_condition == pytest.approx(a.after.max_condition, rel=1e-9)


def test_stray_node_refused_with_its_label():
    m = box(4)
    p = m.points.copy()
    p[37] = [1e300, 0.5, 0.5]
    with pytest.raises(MeshError, match=r"node 37 at .*times the median edge length"):
        hex_mesh(p, m.hexes)


def test_cli_quality_of_scaled_box(capsys, tmp_path):
    path = tmp_path / "big.vtk"
    m = box(3)
    write_mesh(m.with_points(m.points * 1e300), path)
    code, out, err = run_cli(capsys, "quality", path, "--json")
    assert code == 0, err
    d = json.loads(out, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert d["inverted_elements"] == 0 and d["max_condition"] == pytest.approx(1.0)


# ------------------------------------------------------------------------------------------ method parameters
@pytest.mark.parametrize("method,key,value", [
    ("ci", "cohort", "abc"), ("ci", "cohort", math.nan), ("ci", "cohort", True), ("ci", "init_width", "abc"),
    ("ci", "reduction", math.inf), ("ci-global", "attempts", 10**12), ("ci", "cohort", 10**6),
    ("lbfgs", "presmooth", "abc"), ("lbfgs", "max_steps", 10**12), ("lbfgs", "scaled", 1),
    ("cg", "cg_method", "newton"), ("lbfgs", "rtol", math.nan), ("laplace", "max_sweeps", 1.5),
    ("smart-laplace", "backtrack", 100),
])
def test_bad_method_parameter(method, key, value):
    with pytest.raises(ConfigError, match=rf"method '{method}': .* parameter {key} must be .*got {value!r}"):
        jaxci.smooth(box(2), method, **{key: value})


def test_unknown_parameter_lists_the_valid_ones():
    with pytest.raises(ConfigError, match=r"unknown parameter 'init_widht' of method 'ci'; valid: cohort, "):
        jaxci.smooth(box(2), "ci", init_widht=0.5)
    with pytest.raises(ConfigError, match=r"unknown parameter 'untangle_bogus' of the untangling stage; valid: "
                                          r"untangle_theta"):
        jaxci.smooth(box(2), "ci", untangle_bogus=1)


def test_integral_float_parameter_is_an_int():
    from jaxci.optim.ci import CIParams

    assert CIParams(cohort=6.0).cohort == 6 and isinstance(CIParams(cohort=6.0).cohort, int)


# ------------------------------------------------------------------------------------------ seeds
@pytest.mark.parametrize("seed", [2**32, 2**63, 99999999999999999999999, -1, 1.5, 1.0, "a", None, True])
def test_bad_seed(seed):
    with pytest.raises(ConfigError, match=r"seed must be an integer in \[0, 2\*\*32 - 1\]"):
        jaxci.smooth(box(2), "laplace", seed=seed)


def test_largest_seed_and_numpy_int_accepted():
    a = jaxci.smooth(perturb_box(2, amplitude=0.2), "ci", seed=2**32 - 1, max_sweeps=2)
    b = jaxci.smooth(perturb_box(2, amplitude=0.2), "ci", seed=np.uint32(2**32 - 1), max_sweeps=2)
    c = jaxci.smooth(perturb_box(2, amplitude=0.2), "ci", seed=0, max_sweeps=2)
    np.testing.assert_array_equal(a.mesh.points, b.mesh.points)
    assert not np.array_equal(a.mesh.points, c.mesh.points)
    with pytest.raises(ConfigError, match="seed"):
        perturb_box(2, seed=2**32)


# ------------------------------------------------------------------------------------------ memory, no volume
def test_huge_boxes_refused_before_allocating():
    t0 = time.perf_counter()
    for args in ((1000,), (10**9, 1, 1)):
        with pytest.raises(MeshError, match=r"1_000_000_000 hexahedra needs about .* of memory \(estimate\)"):
            box(*args)
        with pytest.raises(MeshError, match="estimate"):
            perturb_box(*args, amplitude=0.1)
    assert time.perf_counter() - t0 < 5


def test_smooth_refuses_what_does_not_fit(monkeypatch):
    import jaxci.runtime.memory

    monkeypatch.setattr(jaxci.runtime.memory, "available_bytes", lambda: 10**6)
    with pytest.raises(MeshError, match=r"smoothing 8 hexahedra in float64 needs about .* GB .* and 0.001 GB"):
        jaxci.smooth(box(2), "laplace", dtype="float64")


def test_the_memory_estimate_of_a_host_run_is_the_host_path_s(monkeypatch):
    """A run entirely on the host (numpy and C) is estimated with its own measured bytes per hexahedron and
    fixed part (no JAX runtime, no compilation): with 300 MB free, a small host run goes ahead and the same run
    compiled is refused."""
    import jaxci.runtime.memory

    assert jaxci.runtime.memory.smooth_bytes(10**6, host=True) < 0.6 * jaxci.runtime.memory.smooth_bytes(10**6)
    monkeypatch.setattr(jaxci.runtime.memory, "available_bytes", lambda: 300 * 2**20)
    assert jaxci.smooth(box(2), "lbfgs", dtype="float64").after.inverted_elements == 0
    with pytest.raises(MeshError, match=r"smoothing 8 hexahedra in float64 needs about .* GB"):
        jaxci.smooth(box(2), "lbfgs", dtype="float64", engine="jax")


def test_flat_mesh_refused_at_once():
    m = box(20, 20, 2)
    p = m.points.copy()
    p[:, 2] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        flat = hex_mesh(p, m.hexes)
    t0 = time.perf_counter()
    with pytest.raises(MeshError, match=r"lie in one plane .*no volume"):
        jaxci.smooth(flat)
    assert time.perf_counter() - t0 < 5


# ------------------------------------------------------------------------------------------ config (YAML)
@pytest.mark.parametrize("text,match", [
    ("mesh: {generate: {box: [1000, 1000, 1000]}}\nmethods: [{method: ci}]\n",
     "cfg.yaml:1: mesh[0]: mesh 'box1000x1000x1000': smoothing 1_000_000_000 elements"),
    ("mesh: {generate: {box: [1000000000, 1, 1]}}\nmethods: [{method: ci}]\n", "needs about"),
    ("mesh: {generate: {case: cube27}}\nmethods: [{method: ci}]\nseeds: [4294967296]\n", "seeds"),
    ("mesh: {generate: {case: cube27}}\nmethods: [{method: ci}]\nruns: 1000000000000\n", "runs"),
    ("mesh: {generate: {case: cube27}}\nmethods:\n  - {method: ci, params: {cohort: abc}}\n",
     "cfg.yaml:3: methods[0].params.cohort: CI parameter cohort must be an integer"),
    ("mesh: {generate: {case: cube27}}\nmethods:\n  - {method: ci-global, params: {init_width: abc}}\n",
     "init_width must be a finite number"),
])
def test_config_refusals(tmp_path, text, match):
    from jaxci.experiments.config import load_config

    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert match in str(e.value).replace(str(tmp_path) + "/", "")


# ------------------------------------------------------------------------------------------ argument types
@pytest.mark.parametrize("fn", [jaxci.smooth, jaxci.quality_report, jaxci.classify_boundary])
def test_wrong_mesh_types(fn, tmp_path):
    name = fn.__name__
    with pytest.raises(UsageError, match=rf"{name} expects a jaxci HexMesh, got an array of shape \(27, 3\); "
                                         r"build one .* jaxci.hex_mesh"):
        fn(box(2).points)
    with pytest.raises(UsageError, match=rf"{name} expects a jaxci HexMesh, got the path .*jaxci.read_mesh"):
        fn(tmp_path / "x.vtk")
    with pytest.raises(UsageError, match="got builtins.dict"):
        fn({})
    assert issubclass(UsageError, JaxciError) and issubclass(UsageError, TypeError)


def test_meshio_mesh_accepted():
    m = perturb_box(2, amplitude=0.2)
    mm = meshio.Mesh(m.points, [("hexahedron", m.hexes)])
    assert quality_report(mm).max_condition == pytest.approx(quality_report(m).max_condition)
    assert jaxci.smooth(mm, "smart-laplace", max_sweeps=3).after.objective < quality_report(m).objective


@pytest.mark.parametrize("kw,match", [
    (dict(fixed_sets="top"), "fixed_sets must be a list of node set names, got the string 'top'"),
    (dict(feature_angle="abc"), "feature_angle must be in degrees"),
    (dict(fix_boundary="yes"), "fix_boundary must be True or False"),
    (dict(dtype="float16"), "dtype must be one of"),
    (dict(untangle="sometimes"), "untangle must be one of"),
    (dict(fixed_nodes=["a"]), "fixed_nodes must be node indices"),
])
def test_bad_smooth_arguments(kw, match):
    with pytest.raises(JaxciError, match=match):
        jaxci.smooth(box(2), "laplace", **kw)


# ------------------------------------------------------------------------------------------ exact counts
def test_untangling_failure_counts_are_consistent():
    p = box(1).points.copy()
    p[6] = [0.2, 0.2, 0.2]  # node 6 pushed through the element: inverted; every node of one hex is a corner
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = hex_mesh(p, box(1).hexes)
    with pytest.raises(InvertedMeshError, match=r"untangling failed: 1 element is inverted after \d+ rounds \(1 was "
                                                r"in the input; .* of their 8 nodes are fixed"):
        jaxci.smooth(mesh, "laplace")


# ------------------------------------------------------------------------------------------ the CLI
@pytest.mark.parametrize("extra,match", [
    (["--method", "ci", "--param", "cohort=abc"], "method 'ci': CI parameter cohort must be an integer"),
    (["--method", "ci", "--param", "cohort=NaN"], "got nan"),
    (["--method", "lbfgs", "--param", "presmooth=abc"], "presmooth"),
    (["--method", "ci-global", "--param", "attempts=1000000000000"], "attempts"),
    (["--method", "ci", "--param", "init_width=abc"], "init_width must be a finite number"),
    (["--method", "ci", "--param", "bogus=1"], "unknown parameter 'bogus' of method 'ci'; valid: cohort"),
    (["--param", "cohort=4"], "unknown parameter 'cohort' of method 'lbfgs'; valid: max_steps"),
    (["--param", "cohort=4"], "(the default method, auto, runs lbfgs; --method picks another)"),
    (["--seed", "99999999999999999999999"], "seed must be an integer"),
    (["--seed", str(2**63)], "seed must be an integer"),
    (["--seed", "4294967296"], "seed must be an integer"),
])
def test_cli_usage_errors(capsys, tmp_path, extra, match):
    src = tmp_path / "in.vtk"
    write_mesh(box(2), src)
    code, out, err = run_cli(capsys, "smooth", src, tmp_path / "out.vtk", *extra)
    assert_one_error_line(code, err, match)
    assert not (tmp_path / "out.vtk").exists()


def test_cli_generate_refuses_a_huge_box(capsys, tmp_path):
    code, out, err = run_cli(capsys, "generate", "box", tmp_path / "g.vtk", "--n", "1000")
    assert_one_error_line(code, err, "needs about")
    code, out, err = run_cli(capsys, "generate", "box", tmp_path / "g.vtk", "--seed", "-1")
    assert_one_error_line(code, err, "seed must be an integer")


def test_cli_smooth_keeps_coincident_nodes(capsys, tmp_path):
    mesh, pairs = split_box(n=2)
    src = tmp_path / "dup.vtk"
    write_mesh(mesh, src)
    code, out, err = run_cli(capsys, "smooth", src, tmp_path / "out.vtk", "--method", "smart-laplace", "--json")
    assert code == 0, err
    assert any("coincident nodes in" in n and "move as one" in n for n in json.loads(out)["notes"])
    p = read_mesh(tmp_path / "out.vtk").points
    np.testing.assert_array_equal(p[pairs[:, 0]], p[pairs[:, 1]])


def test_the_memory_estimate_counts_each_ci_form_s_own_default_cohort():
    """`jaxci.runtime.memory.ci_trials` (the YAML configs' up-front check) takes each CI form's defaults from the same
    numbers as `CIParams.for_method`."""
    from jaxci.optim.ci_params import CIParams
    from jaxci.runtime.memory import CI_DEFAULT_TRIALS, ci_trials

    for method, (cohort, variations) in CI_DEFAULT_TRIALS.items():
        p = CIParams.for_method(method)
        assert (p.cohort, p.variations) == (cohort, variations)
        assert ci_trials(method, {}) == cohort * variations
    assert ci_trials("ci", {"cohort": 8}) == 8 * CI_DEFAULT_TRIALS["ci"][1]
    assert ci_trials("lbfgs", {"cohort": 8}) == 16


def test_the_host_memory_estimate_of_ci_is_ci_s_own():
    """CI on the host holds more than the default pipeline (Anderson's history, global CI's trial meshes): its
    estimate is its own, measured one, and grows with global CI's trials."""
    from jaxci.runtime.memory import smooth_bytes

    n = 10**5
    base = smooth_bytes(n, host=True)
    local = smooth_bytes(n, trials=9, host=True, method="ci")
    glob = smooth_bytes(n, trials=25, host=True, method="ci-global")
    assert base < local < glob
    assert smooth_bytes(n, trials=100, host=True, method="ci-global") > glob
    assert smooth_bytes(n, trials=100, host=True, method="lbfgs") == base
