"""One engine decision per run (`jaxci.engine`): the plan's rules, that every stage and every report follows and
states it, the batched seeds of global CI, and that both engines reach the same optimum on the same meshes."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxci import engine, native
from jaxci.cli import main
from jaxci.errors import ConfigError
from jaxci.generate import paper_case, perturb_box
from jaxci.io import read_mesh, write_mesh
from jaxci.smooth import smooth, smooth_seeds

SHARED = Path(__file__).resolve().parents[2] / "shared"
PAVE3 = SHARED / "data" / "mesquite" / "pave3.e.vtk"
TANGLED = [SHARED / "peers" / "cube9_pert.vtk", SHARED / "data" / "mesquite" / "hex_5_tangled.vtk"]
needs_shared = pytest.mark.skipif(not PAVE3.exists(), reason="../shared/data is not beside the repository")


def _mixed():
    """A 2x2x2 box with one hexahedron split into two wedges (a hex-dominant mesh)."""
    m = perturb_box(2, 2, 2, amplitude=0.1, seed=0)
    hexes = np.asarray(m.hexes)
    h = hexes[0]
    wedges = np.array([[h[0], h[1], h[3], h[4], h[5], h[7]], [h[1], h[2], h[3], h[5], h[6], h[7]]])
    from jaxci.mesh import CellBlock, HexMesh

    return HexMesh(m.points, (CellBlock("hexahedron", hexes[1:]), CellBlock("wedge", wedges)))


# ------------------------------------------------------------------------------------------------ the rules
def test_auto_picks_the_host_where_it_runs_every_stage_and_jax_elsewhere():
    box = perturb_box(3, 3, 3, amplitude=0.2, seed=0)
    plan = engine.resolve_plan(box, "lbfgs", {})
    assert (plan.engine, plan.device, plan.dtype) == ("host", "cpu", "float64")
    assert plan.kernel == ("C" if native.AVAILABLE else "numpy")
    bfgs = engine.resolve_plan(box, "bfgs", {}, dtype="float64")
    assert (bfgs.engine, bfgs.dtype) == ("jax", "float64") and "no host implementation" in bfgs.reason
    # a mixed mesh: L-BFGS on the host (C kernels); with presmoothing, or tangled, every stage on the JAX engine
    mixed = _mixed()
    if native.AVAILABLE:
        assert engine.resolve_plan(mixed, "lbfgs", {}).engine == "host"
    assert engine.resolve_plan(mixed, "lbfgs", {"presmooth": 3}).engine == "jax"
    assert engine.resolve_plan(mixed, "lbfgs", {}, untangling=True).engine == "jax"
    # global CI: one seed on the host, from BATCH_SEEDS_FROM seeds batched on the JAX engine
    assert engine.resolve_plan(box, "ci-global", {}).engine == ("host" if native.AVAILABLE else "jax")
    many = engine.resolve_plan(box, "ci-global", {}, seeds=engine.BATCH_SEEDS_FROM)
    assert many.engine == "jax" and "batched" in many.reason


def test_requests_that_cannot_be_honoured_are_one_clear_error():
    box = perturb_box(2, 2, 2, amplitude=0.1, seed=0)
    with pytest.raises(ConfigError, match="engine 'host' cannot run this: method 'bfgs' has no host"):
        smooth(box, "bfgs", engine="host")
    with pytest.raises(ConfigError, match="engine requests disagree"):
        smooth(box, "lbfgs", engine="jax", backend="numpy")
    with pytest.raises(ConfigError, match="engine must be one of"):
        smooth(box, "lbfgs", engine="gpu")
    with pytest.raises(ConfigError, match="device must be one of"):
        smooth(box, "lbfgs", device="tpu0")
    if engine.accelerator() is None:
        with pytest.raises(ConfigError, match="device 'gpu' asked for, but"):
            smooth(box, "lbfgs", device="gpu")
    with pytest.raises(ConfigError, match="engine 'host' runs on the CPU"):
        engine.resolve_plan(box, "lbfgs", {}, engine="host", device="gpu")


def test_an_accelerator_takes_large_meshes_under_auto(monkeypatch):
    """With an accelerator visible (simulated), ``auto`` runs the JAX engine on it from ACCELERATOR_FROM cells
    and when device 'gpu' is asked for, the host engine below it, and the CPU when device 'cpu' is asked for."""
    monkeypatch.setattr(engine, "accelerator", lambda: ("gpu", "Simulated GPU"))
    box = perturb_box(2, 2, 2, amplitude=0.1, seed=0)
    monkeypatch.setattr(engine, "ACCELERATOR_FROM", box.n_hexes)
    plan = engine.resolve_plan(box, "lbfgs", {})
    assert (plan.engine, plan.device, plan.device_kind, plan.threads) == ("jax", "gpu", "Simulated GPU", None)
    assert plan.kernel == "XLA" and "accelerator is visible" in plan.reason
    assert engine.resolve_plan(box, "lbfgs", {}, device="cpu").device == "cpu"
    monkeypatch.setattr(engine, "ACCELERATOR_FROM", box.n_hexes + 1)
    assert engine.resolve_plan(box, "lbfgs", {}).engine == ("host" if native.AVAILABLE else "jax")
    assert engine.resolve_plan(box, "lbfgs", {}, device="gpu").device == "gpu"
    assert engine.resolve_plan(box, "lbfgs", {}, engine="jax").device == "gpu"


def test_the_ffi_handler_is_checked_against_the_running_jaxlib():
    from jaxci.metrics import native_grad

    assert native_grad.check_version((0, 3), (0, 3)) == ""
    assert native_grad.check_version((0, 3), (0, 4)) == ""
    assert "rebuild" in native_grad.check_version((0, 4), (0, 3))
    assert "rebuild" in native_grad.check_version((1, 0), (0, 9))
    assert "without XLA's FFI header" in native_grad.check_version(None, (0, 3))
    if native.AVAILABLE and native.ffi_api_version() is not None:
        assert native_grad.available("cpu"), native_grad.refusal()
        assert native_grad.check_version(native.ffi_api_version(), native_grad._header_version()) == ""


# ----------------------------------------------------------------------------------- every run says what ran
def test_every_result_and_report_names_the_engine(tmp_path, capsys):
    box = perturb_box(3, 3, 3, amplitude=0.2, seed=1)
    res = smooth(box, "lbfgs", engine="jax", dtype="float64")
    assert res.plan.engine == "jax" and res.params["backend"] == "jax" and res.params["dtype"] == "float64"
    assert res.summary()["engine"] == res.plan.to_dict()
    assert smooth(box, "lbfgs").params["dtype"] == "float64" or not native.AVAILABLE  # the host's dtype
    src, out = tmp_path / "in.vtu", tmp_path / "out.vtu"
    write_mesh(box, src)
    assert main(["smooth", str(src), str(out), "--engine", "jax", "--json", "-v"]) == 0
    printed = capsys.readouterr()
    e = json.loads(printed.out)["engine"]
    assert {k: e[k] for k in ("name", "device", "dtype")} == {"name": "jax", "device": "cpu", "dtype": "float32"}
    assert e["kernel"] in ("XLA", "FFI") and "jaxci: engine    ... jax engine:" in printed.err
    assert main(["smooth", str(src), str(out), "--engine", "host", "--force"]) == 0
    assert "engine: host engine:" in capsys.readouterr().out


def test_a_mixed_mesh_runs_every_stage_on_one_engine():
    """Presmoothing on a mixed mesh ran compiled in float32, then the numpy L-BFGS: now one engine for both."""
    res = smooth(_mixed(), "lbfgs", presmooth=2)
    assert res.plan.engine == "jax" and res.params["backend"] == "jax" and res.history["presmooth"] == 2


@pytest.mark.slow
def test_without_the_c_extension_the_plan_names_what_ran(tmp_path):
    script = (
        "import jaxci\nfrom jaxci.generate import perturb_box\nm = perturb_box(3, 3, 3, amplitude=0.2, seed=0)\n"
        "for method in ('lbfgs', 'ci'):\n"
        "    r = jaxci.smooth(m, method, max_sweeps=2) if method == 'ci' else jaxci.smooth(m, method)\n"
        "    print(method, r.plan.engine, r.plan.kernel, any('C kernels' in n for n in r.notes))\n")
    env = {**os.environ, "JAXCI_NATIVE": "0"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[:2] == ["lbfgs host numpy True", "ci jax XLA True"]


# ------------------------------------------------------------------------------------------ batched seeds
def test_seeds_of_global_ci_run_as_one_program_with_the_meshes_of_one_by_one():
    seeds = list(range(engine.BATCH_SEEDS_FROM))
    meshes = [paper_case("cube27", seed=s) for s in seeds]
    batched = smooth_seeds(meshes, "ci-global", seeds, attempts=40)
    assert all(r.plan.engine == "jax" and r.params["batched_seeds"] == len(seeds) for r in batched)
    assert all(any("one batched program" in n for n in r.notes) for r in batched)
    for m, s, b in zip(meshes, seeds, batched, strict=True):
        alone = smooth(m, "ci-global", seed=s, attempts=40, engine="jax")
        np.testing.assert_array_equal(alone.mesh.points, b.mesh.points)
        assert alone.history["objective"] == b.history["objective"] and alone.iterations == b.iterations
    assert len({r.after.objective for r in batched}) == len(seeds)  # distinct seeds, distinct meshes


def test_a_seed_that_cannot_join_the_batch_runs_alone_and_errors_can_be_returned():
    n = engine.BATCH_SEEDS_FROM
    meshes = [paper_case("cube27", seed=s) for s in range(n)]
    pts = np.array(meshes[-1].points)
    inner = np.flatnonzero(np.all((pts > 0.01) & (pts < 0.99), axis=1))[0]
    pts[inner] += 0.9  # through the opposite face of its cells: inverted elements, untangled first
    meshes[-1] = meshes[-1].with_points(pts)
    res = smooth_seeds(meshes, "ci-global", list(range(n)), attempts=20)
    assert [r.params.get("batched_seeds") for r in res[:-1]] == [n - 1] * (n - 1)
    assert "batched_seeds" not in res[-1].params and any("untangling" in note for note in res[-1].notes)
    assert res[-1].plan.engine == ("host" if native.AVAILABLE else "jax")  # auto: the host for one seed
    out = smooth_seeds(meshes[:2], "ci-global", [0, 1], errors="return", attempts=10, cohort=0)
    assert all(isinstance(e, ConfigError) for e in out)
    with pytest.raises(ConfigError):
        smooth_seeds(meshes[:1], "ci-global", [0], attempts=10, cohort=0)


def test_jaxci_run_batches_the_seeds_of_global_ci(tmp_path):
    from jaxci.experiments.runner import load_config, run_experiment

    n = engine.BATCH_SEEDS_FROM
    text = (f"mesh: {{generate: {{case: cube27}}}}\nmethods:\n  - {{name: G, method: ci-global, params: "
            f"{{attempts: 30}}}}\nruns: {n}\nfigures: false\nwrite_meshes: false\n")
    cfg = tmp_path / "exp.yaml"
    cfg.write_text(text)
    res = run_experiment(load_config(cfg), tmp_path / "out")
    runs = res.summary["runs"]
    assert [r["seed"] for r in runs] == list(range(n)) and all(r["status"] == "ok" for r in runs)
    assert all(r["engine"]["name"] == "jax" and "batched" in r["engine"]["reason"] for r in runs)
    for r in runs:
        alone = smooth(paper_case("cube27", seed=r["seed"]), "ci-global", seed=r["seed"], attempts=30, engine="jax")
        assert r["after"]["objective"] == alone.after.objective
    cfg.write_text(text + "batch_seeds: false\n")
    one = run_experiment(load_config(cfg), tmp_path / "out2")
    want = "host" if native.AVAILABLE else "jax"
    assert all(r["engine"]["name"] == want for r in one.summary["runs"])


# --------------------------------------------------------------------------- both engines, the same optimum
def _both(mesh, method, **kw):
    return {e: smooth(mesh, method, engine=e, dtype="float64", **kw) for e in ("host", "jax")}


def _same_optimum(runs, rtol=1e-6):
    h, j = runs["host"], runs["jax"]
    assert h.plan.engine == "host" and j.plan.engine == "jax"
    assert h.after.inverted_elements == j.after.inverted_elements == 0
    assert abs(h.after.objective - j.after.objective) <= rtol * abs(h.after.objective), (h.after.objective,
                                                                                         j.after.objective)


pytestmark_native = pytest.mark.skipif(not native.AVAILABLE, reason="the host's local methods need the C "
                                       "kernels")
TIGHT = {"rtol": 1e-12, "atol": 1e-12, "max_steps": 5000, "precondition": "none"}


@needs_shared
@pytestmark_native
@pytest.mark.parametrize("method, params", [("lbfgs", TIGHT), ("laplace", {"tol": 1e-10, "max_sweeps": 5000}),
                                            ("smart-laplace", {"tol": 1e-10, "max_sweeps": 5000})])
def test_both_engines_reach_the_same_optimum_on_a_paved_mesh(method, params):
    """pave3 (1791 hexahedra, Mesquite's) with its boundary fixed: the optimum of F is far from ideal (F 0.41)."""
    _same_optimum(_both(read_mesh(PAVE3), method, fix_boundary=True, **params))


@pytestmark_native
@pytest.mark.parametrize("method, params", [("lbfgs", TIGHT), ("smart-laplace", {"tol": 1e-10, "max_sweeps": 5000})])
def test_both_engines_reach_the_same_optimum_with_sliding_flat_walls(method, params):
    """A perturbed box whose boundary nodes slide on its faces, with interior nodes held where the perturbation put
    them (so that the optimum is not the ideal grid)."""
    box = perturb_box(5, 5, 4, amplitude=0.3, seed=3)
    _same_optimum(_both(box, method, fixed_nodes=[43, 50, 64, 72], **params))


@needs_shared
@pytest.mark.parametrize("path", TANGLED, ids=lambda p: p.name)
def test_both_engines_untangle_to_the_same_mesh(path):
    from jaxci.geometry.boundary import classify_boundary
    from jaxci.optim.untangle import UntangleParams, untangle_stage

    mesh = read_mesh(path)
    info = classify_boundary(mesh)
    x = {b: untangle_stage(mesh, info, UntangleParams(backend=b))[0] for b in ("numpy", "jax")}
    np.testing.assert_allclose(x["numpy"], x["jax"], atol=1e-12)
    res = _both(mesh, "lbfgs", **TIGHT)
    assert all(r.after.inverted_elements == 0 and r.after.max_condition <= 1 + 1e-6 for r in res.values())


@pytestmark_native
@pytest.mark.parametrize("method, params", [("ci", {"max_sweeps": 30}), ("ci-global", {"attempts": 300})])
def test_cohort_methods_reach_statistically_the_same_quality(method, params):
    """The engines draw different random numbers (numpy's PCG64, JAX's keys), so their meshes differ; over
    seeds their final F agree: each seed improves F by more than half, and the engines' mean F are within 25%."""
    seeds = [0, 1, 2, 3]
    f = {}
    for e in ("host", "jax"):
        runs = [smooth(paper_case("cube27", seed=s), method, seed=s, engine=e, dtype="float64", **params)
                for s in seeds]
        assert all(r.after.objective < 0.5 * r.before.objective and r.after.inverted_elements == 0 for r in runs)
        f[e] = np.mean([r.after.objective for r in runs])
    assert abs(f["host"] - f["jax"]) <= 0.25 * max(f.values()), f


def test_plan_is_a_frozen_record():
    plan = engine.host_plan()
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.engine = "jax"
    assert plan.to_dict()["name"] == "host" and plan.backend == "numpy"
