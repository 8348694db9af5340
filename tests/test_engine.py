"""One engine decision per run (`jaxci.interface.engine`): the plan's rules, that every stage and every report follows
and states it, the batched seeds of global CI, and that both engines reach the same optimum on the same meshes."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import MESQUITE, PEERS, fail_seed_method

from jaxci import native
from jaxci.cli import main
from jaxci.errors import ConfigError, MeshError
from jaxci.interface import engine
from jaxci.interface.seeds import smooth_seeds
from jaxci.interface.smooth import smooth
from jaxci.io import read_mesh, write_mesh
from jaxci.mesh.generate import paper_case, perturb_box

PAVE3 = MESQUITE / "pave3.e.vtk"
TANGLED = [PEERS / "cube9_pert.vtk", MESQUITE / "hex_5_tangled.vtk"]


def _mixed():
    """A 2x2x2 box with one hexahedron split into two wedges (a hex-dominant mesh)."""
    m = perturb_box(2, 2, 2, amplitude=0.1, seed=0)
    hexes = np.asarray(m.hexes)
    h = hexes[0]
    wedges = np.array([[h[0], h[1], h[3], h[4], h[5], h[7]], [h[1], h[2], h[3], h[5], h[6], h[7]]])
    from jaxci.mesh import CellBlock, HexMesh

    return HexMesh(m.points, (CellBlock("hexahedron", hexes[1:]), CellBlock("wedge", wedges)))


def _tangled(mesh):
    """`mesh` (a unit cube) with one interior node pushed through the opposite faces of its cells: inverted
    elements, untangled first."""
    pts = np.array(mesh.points)
    inner = np.flatnonzero(np.all((pts > 0.01) & (pts < 0.99), axis=1))[0]
    pts[inner] += 0.9
    return mesh.with_points(pts)


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
    assert engine.resolve_plan(box, "lbfgs", {}).engine == "host"  # numpy's kernels without the C ones
    assert engine.resolve_plan(box, "lbfgs", {}, device="gpu").device == "gpu"
    assert engine.resolve_plan(box, "lbfgs", {}, engine="jax").device == "gpu"


def test_auto_keeps_the_host_up_to_its_limit_and_no_further(monkeypatch):
    """The host engine's size limits (`engine.host_limit`, and the untangling stage's own where it runs first) are
    inclusive: a mesh of exactly the limit stays on the host, one more cell goes to the JAX engine, saying why."""
    from jaxci.optim import host

    box = perturb_box(2, 2, 2, amplitude=0.1, seed=0)
    n = box.n_hexes
    assert engine.host_limit("lbfgs", True) == host.HOST_MAX and engine.host_limit("ci", False) == 0
    monkeypatch.setattr(engine, "host_limit", lambda method, native: n)
    assert engine.resolve_plan(box, "lbfgs", {}).engine == "host"
    monkeypatch.setattr(engine, "host_limit", lambda method, native: n - 1)
    plan = engine.resolve_plan(box, "lbfgs", {})
    assert plan.engine == "jax" and f"{n} cells > the host engine's {n - 1} for lbfgs" in plan.reason
    monkeypatch.setattr(engine, "host_limit", lambda method, native: 10**9)
    monkeypatch.setattr(host, "UNTANGLE_HOST_MAX", n - 1)
    assert engine.resolve_plan(box, "lbfgs", {}).engine == "host"
    assert engine.resolve_plan(box, "lbfgs", {}, untangling=True).engine == "jax"
    monkeypatch.setattr(host, "UNTANGLE_HOST_MAX", n)
    assert engine.resolve_plan(box, "lbfgs", {}, untangling=True).engine == "host"


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


@pytest.mark.skipif(not native.AVAILABLE or native.ffi_api_version() is None, reason="no FFI handler built")
def test_a_handler_built_for_another_ffi_api_is_refused_and_the_plan_says_so(monkeypatch):
    """The version check runs at registration: a running jaxlib whose header speaks another major version refuses
    the handler (nothing registered), `refusal` says why, and a JAX plan on the CPU names XLA's kernel with a note."""
    from jaxci.metrics import native_grad

    built = native.ffi_api_version()
    monkeypatch.setattr(native_grad, "_header_version", lambda: (built[0] + 1, 0))
    monkeypatch.setattr(native_grad, "_registered", functools.cache(native_grad._registered.__wrapped__))
    monkeypatch.setattr(native_grad, "_REFUSALS", [])
    assert not native_grad.available("cpu")
    assert f"built against XLA FFI API {built[0]}.{built[1]}" in native_grad.refusal()
    plan = engine.resolve_plan(perturb_box(2, 2, 2, amplitude=0.1, seed=0), "lbfgs", {}, engine="jax")
    assert plan.kernel == "XLA" and plan.threads is not None
    assert any("FFI handler was not registered" in n and "rebuild" in n for n in plan.notes), plan.notes


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


@pytest.mark.parametrize("asked", ["host", "jax"])
def test_every_stage_runs_on_the_plans_engine_inside_its_context(asked, monkeypatch):
    """A tangled mesh smoothed by L-BFGS with presmoothing: the untangling, the set-up, the smart-Laplace sweeps and
    the solver each run on the engine of the plan (not by their own size rules: this mesh is small enough for the
    host), inside the plan's context (`Plan.context`: the device of the JAX engine), the shape improvement in the
    plan's dtype."""
    import jax

    if asked == "host" and not native.AVAILABLE:
        pytest.skip("the host's presmoothing needs the C kernels")
    gradient = importlib.import_module("jaxci.optim.gradient")
    host_local = importlib.import_module("jaxci.optim.host_local")
    laplace = importlib.import_module("jaxci.optim.laplace")
    untangle = importlib.import_module("jaxci.optim.untangle")
    inside, ran = [], []
    plan_context = engine.Plan.context

    @contextlib.contextmanager
    def context(self):
        inside.append(self.engine)
        try:
            with plan_context(self):
                yield
        finally:
            inside.pop()

    def spy(stage, fn, where):
        def run(*args, **kwargs):
            x64 = bool(jax.config.jax_enable_x64)
            out = fn(*args, **kwargs)
            engine_of = where(out, *args, **kwargs)
            if engine_of is not None:
                ran.append((stage, engine_of, tuple(inside), x64))
            return out
        return run

    monkeypatch.setattr(engine.Plan, "context", context)
    from jaxci.interface import smooth as smooth_module
    monkeypatch.setattr(smooth_module, "build_problem", spy("setup", smooth_module.build_problem,
                                                            lambda out, *a, plan, **kw: plan.engine))
    monkeypatch.setattr(untangle, "untangle_stage", spy(
        "untangle", untangle.untangle_stage,
        lambda out, mesh, info, p, **kw: "host" if untangle.on_host(mesh, p) else "jax"))
    monkeypatch.setattr(host_local, "laplace_np", spy(
        "presmooth", host_local.laplace_np, lambda out, *a, smart=False, **kw: "host" if smart else None))
    monkeypatch.setattr(laplace, "run_laplace", spy("presmooth", laplace.run_laplace, lambda out, *a, **kw: "jax"))
    monkeypatch.setattr(gradient, "use_host", spy("solve", gradient.use_host,
                                                  lambda out, *a, **kw: "host" if out else "jax"))
    dtype = "float32" if asked == "jax" else "float64"
    res = smooth(_tangled(paper_case("cube27", seed=0)), "lbfgs", presmooth=2, engine=asked, dtype=dtype)
    assert (res.plan.engine, res.plan.dtype) == (asked, "float64" if asked == "host" else dtype)
    assert res.after.inverted_elements == 0 and res.history["presmooth"] == 2
    assert any("untangling:" in n for n in res.notes)
    assert {stage for stage, *_ in ran} == {"untangle", "setup", "presmooth", "solve"}, ran
    assert all(e == asked and ctx and ctx[-1] == asked for _, e, ctx, _ in ran), ran
    if asked == "jax":  # the shape improvement in the plan's dtype (the untangling is float64 on either engine)
        assert all(x64 == (dtype == "float64") for stage, *_, x64 in ran if stage != "untangle"), ran


def test_a_jax_plan_on_the_cpu_moves_jax_off_an_accelerator(monkeypatch):
    """A machine whose JAX defaults to an accelerator (simulated), asked for device 'cpu': the JAX engine's
    context makes JAX's default device a CPU one; where the default platform is the plan's, and on the host
    engine, the context changes nothing."""
    import jax
    import jax.numpy as jnp

    plan = engine.Plan("jax", "cpu", "test CPU", 1, "float32", "XLA", 2, "test")
    assert jax.config.jax_default_device is None
    with plan.context(), engine.host_plan().context():
        assert jax.config.jax_default_device is None
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    with plan.context():
        assert jax.config.jax_default_device == jax.local_devices(backend="cpu")[0]
        assert next(iter(jnp.ones(3).devices())).platform == "cpu"
    with engine.host_plan().context():
        assert jax.config.jax_default_device is None
    assert jax.config.jax_default_device is None


def test_a_jax_plan_on_the_cpu_of_an_accelerator_machine_runs_the_kernel_it_names(monkeypatch):
    import jax

    from jaxci.metrics import native_grad

    box = perturb_box(3, 4, 2, amplitude=0.2, seed=5)  # a shape no other test here compiles
    calls = []
    terms = native_grad.terms_and_grad
    monkeypatch.setattr(native_grad, "terms_and_grad", lambda *a, **k: calls.append(1) or terms(*a, **k))
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # a GPU machine (simulated)
    res = smooth(box, "lbfgs", engine="jax", device="cpu")
    if res.plan.kernel != "FFI":
        pytest.skip("no FFI handler on this build")
    assert calls, "the plan names the FFI kernel, but XLA's ran"


@pytest.mark.slow
def test_without_the_c_extension_the_plan_names_what_ran(tmp_path):
    script = (
        "import jaxci\nfrom jaxci.mesh.generate import perturb_box\nm = perturb_box(3, 3, 3, amplitude=0.2, seed=0)\n"
        "for method in ('lbfgs', 'ci'):\n"
        "    r = jaxci.smooth(m, method, max_sweeps=2) if method == 'ci' else jaxci.smooth(m, method)\n"
        "    print(method, r.plan.engine, r.plan.kernel, any('C kernels' in n for n in r.notes))\n")
    env = {**os.environ, "JAXCI_NATIVE": "0"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[:2] == ["lbfgs host numpy True", "ci jax XLA True"]


@pytest.mark.slow
def test_without_the_c_extension_the_host_engines_default_pipeline_runs_or_is_refused():
    script = (
        "import jaxci, jaxci.interface.methods\nfrom jaxci.errors import ConfigError\n"
        "from jaxci.mesh.generate import perturb_box\n"
        "jaxci.interface.methods.AUTO_PRESMOOTH_FROM = 1  # the size rule, on a small mesh\n"
        "try:\n    r = jaxci.smooth(perturb_box(3, 3, 3, amplitude=0.2, seed=0), engine='host')\n"
        "    print('ok', r.plan.engine, r.plan.kernel, r.after.inverted_elements)\n"
        "except ConfigError as e:\n    print('refused', e)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "JAXCI_NATIVE": "0"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith(("ok host numpy 0", "refused engine 'host' cannot run this")), out.stdout


# ------------------------------------------------------------------------------------------ batched seeds
@pytest.mark.codegen
def test_seeds_of_global_ci_run_as_one_program_with_the_meshes_of_one_by_one():
    """Every seed's mesh, history and attempts are those it gets alone, also where the seeds stop at different
    attempts (saturation: `tol`, `patience`), so that the ones that stopped must stay frozen while the others go on;
    each seed's time is its own phases, the batch's time shared out."""
    seeds = list(range(engine.BATCH_SEEDS_FROM))
    meshes = [paper_case("cube27", seed=s) for s in seeds]
    kw = {"attempts": 40, "tol": 0.05, "patience": 3}
    t0 = time.perf_counter()
    batched = smooth_seeds(meshes, "ci-global", seeds, **kw)
    elapsed = time.perf_counter() - t0
    assert all(r.plan.engine == "jax" and r.params["batched_seeds"] == len(seeds) for r in batched)
    assert all(any("one batched program" in n for n in r.notes) for r in batched)
    stops = [r.iterations for r in batched]
    assert len(set(stops)) > 1 and max(stops) < kw["attempts"], stops  # by construction: frozen seeds
    for m, s, b in zip(meshes, seeds, batched, strict=True):
        alone = smooth(m, "ci-global", seed=s, engine="jax", **kw)
        np.testing.assert_array_equal(alone.mesh.points, b.mesh.points)
        assert alone.history["objective"] == b.history["objective"] and alone.iterations == b.iterations
        assert alone.history["worst"] == b.history["worst"]
    assert len({r.after.objective for r in batched}) == len(seeds)  # distinct seeds, distinct meshes
    for r in batched:  # its own phases (not the other seeds' validation and set-up): the batch's time shared out
        own = sum(v["seconds"] for k, v in r.phases.items() if k not in ("total", "validate"))
        assert r.wall_time == pytest.approx(own, abs=1e-3)
    assert sum(r.phases["smooth"]["seconds"] for r in batched) <= elapsed
    assert sum(r.wall_time for r in batched) <= elapsed


def test_seeds_of_another_connectivity_do_not_join_the_batch():
    """Three seeds on the JAX engine: two of one connectivity run as one program; the third, the same cube with its
    nodes numbered otherwise (the same shapes), runs alone and gets its own mesh."""
    a, b = paper_case("cube27", seed=0), paper_case("cube27", seed=1)
    perm = np.random.default_rng(0).permutation(a.n_nodes)  # node i becomes node perm[i]
    from jaxci.mesh import CellBlock, HexMesh

    c = HexMesh(np.asarray(a.points)[np.argsort(perm)], (CellBlock("hexahedron", perm[np.asarray(a.hexes)]),))
    res = smooth_seeds([a, b, c], "ci-global", [0, 1, 2], engine="jax", attempts=15)
    assert [r.params.get("batched_seeds") for r in res] == [2, 2, None]
    alone = smooth(c, "ci-global", seed=2, engine="jax", attempts=15)
    np.testing.assert_array_equal(alone.mesh.points, res[2].mesh.points)


@pytest.mark.skipif(not native.AVAILABLE, reason="global CI on the host engine needs the C kernels")
def test_seeds_that_run_one_after_the_other_each_report_their_own_time():
    seeds = [0, 1, 2]
    meshes = [paper_case("cube27", seed=s) for s in seeds]
    t0 = time.perf_counter()
    res = smooth_seeds(meshes, "ci-global", seeds, attempts=200, engine="host")
    elapsed = time.perf_counter() - t0
    assert not any(r.params.get("batched_seeds") for r in res)
    assert sum(r.wall_time for r in res) <= elapsed, [r.wall_time for r in res]


@pytest.mark.skipif(not native.AVAILABLE, reason="global CI on the host engine needs the C kernels")
def test_an_error_in_one_seeds_method_is_that_seeds_result(monkeypatch):
    fail_seed_method(monkeypatch, 1, MeshError("seed 1 failed in its method"))
    res = smooth_seeds([paper_case("cube27", seed=s) for s in range(3)], "ci-global", [0, 1, 2], errors="return",
                       attempts=10, engine="host")
    assert [type(r).__name__ for r in res] == ["SmoothResult", "MeshError", "SmoothResult"]


@pytest.mark.codegen
def test_a_seed_batched_with_one_whose_trials_leave_their_flat_regions_gets_its_own_numbers():
    import jax
    from scipy.spatial.transform import Rotation

    from jaxci.interface.methods import build_problem, free_scale, global_parametrisation, method_params
    from jaxci.optim.global_ci import global_ci_batched

    rot = Rotation.from_euler("xyz", [0.3, 0.7, 1.1]).as_matrix()
    m0 = paper_case("cube27", seed=0)
    pts = np.array(m0.points)
    face = np.flatnonzero((pts[:, 0] == 0) & np.all((pts[:, 1:] > 0.01) & (pts[:, 1:] < 0.99), axis=1))[0]
    pts[face, 1] = 0.002  # a surface node at 0.002 from its face's edge: a tiny flat region, left at once
    meshes = [m.with_points(np.asarray(m.points) @ rot.T) for m in (m0, m0.with_points(pts))]
    p = method_params("ci-global", {"attempts": 5})
    plan = engine.resolve_plan(meshes[0], "ci-global", {}, engine="jax")
    probs = [build_problem(m, dtype=np.float32, plan=plan) for m in meshes]
    pars, scales = [global_parametrisation(q) for q in probs], [free_scale(q) for q in probs]
    keys = [jax.random.key(s, impl="rbg") for s in (0, 1)]
    alone = global_ci_batched(keys[:1], pars[:1], probs[0].conn, scales[:1], p)[0]
    both = global_ci_batched(keys, pars, probs[0].conn, scales, p)[0]
    np.testing.assert_array_equal(alone[2]["objective"], both[2]["objective"])


def test_a_seed_that_cannot_join_the_batch_runs_alone_and_errors_can_be_returned():
    n = engine.BATCH_SEEDS_FROM
    meshes = [paper_case("cube27", seed=s) for s in range(n)]
    meshes[-1] = _tangled(meshes[-1])
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


@pytest.mark.shared
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


@pytest.mark.shared
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


def test_plan_is_a_frozen_record():
    plan = engine.host_plan()
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.engine = "jax"
    assert plan.to_dict()["name"] == "host" and plan.backend == "numpy"


def test_the_polish_on_the_host_beside_the_jax_engine_is_in_the_plan():
    """The default pipeline's worst-element polish always runs on the host: on the JAX engine the plan says so."""
    from jaxci.interface.smooth import POLISH_ON_HOST

    box = perturb_box(3, 3, 3, amplitude=0.3, seed=2)
    assert POLISH_ON_HOST in smooth(box, engine="jax").plan.notes
    assert POLISH_ON_HOST not in smooth(box, "lbfgs", engine="jax").plan.notes  # plain L-BFGS: no polish
    assert POLISH_ON_HOST not in smooth(box).plan.notes  # the host engine: every stage there
