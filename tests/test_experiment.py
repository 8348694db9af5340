"""Experiments from YAML: config validation (one-line errors with key and line), `jaxci run` end to end,
output files, determinism, refusal to overwrite, Ctrl-C."""

from __future__ import annotations

import importlib
import json
import os
import re
import shutil
from pathlib import Path

import meshio
import numpy as np
import pytest
import yaml
from helpers import CUBE27_EXPERIMENT, fail_seed_method, interrupted_on_call

from jaxci.cli import main
from jaxci.errors import ConfigError
from jaxci.experiments.runner import load_config

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted((REPO / "configs").glob("*.yaml"))

SMALL = "description: test config\n" + CUBE27_EXPERIMENT


def _write(folder: Path, text: str, name: str = "exp.yaml") -> Path:
    p = folder / name
    p.write_text(text)
    return p


def _run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _figures(summary: dict) -> dict:
    """summary.json without wall times: what must be identical between two runs of one config."""
    s = json.loads(json.dumps(summary))
    s.pop("elapsed")
    for r in s["runs"]:
        r.pop("wall_time")
    for a in s["aggregates"]:
        a.pop("median_wall_time")
    return s


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """The small config run once through the CLI; returns (config path, output folder)."""
    folder = tmp_path_factory.mktemp("small")
    cfg = _write(folder, SMALL)
    out = folder / "out"
    assert main(["run", str(cfg), "--out", str(out), "--quiet"]) == 0
    return cfg, out


# ------------------------------------------------------------------------------------------------ shipped configs
def test_configs_exist():
    names = {p.name for p in CONFIGS}
    for n in ("paper.yaml", "paper_quick.yaml", "cube27.yaml", "cube64.yaml", "cube729.yaml", "mesquite_block.yaml",
              "untangle.yaml", "scaling.yaml"):
        assert n in names


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.shared) if "/shared/" in p.read_text() else p
                                  for p in CONFIGS], ids=[p.name for p in CONFIGS])
def test_shipped_config_validates(path):  # a config naming a mesh of ../shared needs it
    exp = load_config(path)
    assert exp.meshes and exp.methods and exp.seeds
    assert exp.runs()


def test_paper_config_shape():
    exp = load_config(REPO / "configs" / "paper.yaml")
    assert len(exp.seeds) == 30
    assert {m.paper_case for m in exp.meshes} == {"cube27", "cube64", "cube729"}
    assert {"ci", "ci-global", "lbfgs", "cg", "smart-laplace"} <= {m.method for m in exp.methods}


def test_mesh_paths_resolve_against_config_folder(tmp_path):
    sub = tmp_path / "a" / "b"
    sub.mkdir(parents=True)
    from jaxci import box
    from jaxci.io import write_mesh

    write_mesh(box(2), tmp_path / "m.vtu")
    exp = load_config(_write(sub, "mesh: {file: ../../m.vtu}\nmethods: [{method: ci}]\n"))
    assert exp.meshes[0].path == (tmp_path / "m.vtu").resolve()
    assert exp.meshes[0].name == "m"


# ------------------------------------------------------------------------------------------------ end to end
def test_run_writes_everything(small_run):
    cfg, out = small_run
    for name in ("summary.json", "runs.csv", "history.json", "report.md"):
        assert (out / name).is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["partial"] is False
    assert len(summary["runs"]) == 2 and all(r["status"] == "ok" for r in summary["runs"])
    assert summary["versions"]["jax"] and summary["device"]["requested"] == "auto"
    assert summary["device"]["accelerator"] is None and summary["device"]["cpu"]
    # every run says what ran it: the engine's plan in summary.json, runs.csv and report.md
    assert all(r["engine"]["name"] in ("host", "jax") and r["engine"]["dtype"] for r in summary["runs"])
    assert summary["config"]["methods"][0]["params"] == {"max_sweeps": 3}
    agg = summary["aggregates"][0]
    kap = [r["after"]["max_condition"] for r in summary["runs"]]
    assert agg["worst_max_condition"] == max(kap) and agg["best_max_condition"] == min(kap)
    rows = (out / "runs.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("mesh,method,algorithm,seed,status,engine,device,dtype,kernel,")
    engine = summary["runs"][0]["engine"]
    assert rows[1].split(",")[5:9] == [engine["name"], engine["device"], engine["dtype"], engine["kernel"]]
    report = (out / "report.md").read_text()
    assert "Table 1" in report and "Table 2" in report and "Table 3" in report
    row = f"| CI local | {engine['name']} | {engine['device']} | {engine['dtype']} | {engine['kernel']} | 2 |"
    assert row in report
    assert "510.1303" in report and "0.001429" in report  # the paper's numbers beside ours


def test_vtu_fields(small_run):
    _, out = small_run
    vtus = sorted((out / "meshes").glob("*.vtu"))
    # write_meshes: only the first seed, plus its input mesh
    assert [p.name for p in vtus] == ["cube27_ci-local_seed0.vtu", "cube27_input_seed0.vtu"]
    m = meshio.read(out / "meshes" / "cube27_ci-local_seed0.vtu")
    assert {"element_condition", "scaled_jacobian"} <= set(m.cell_data)
    assert {"node_class", "displacement"} <= set(m.point_data)
    summary = json.loads((out / "summary.json").read_text())
    run0 = summary["runs"][0]
    assert np.max(m.cell_data["element_condition"][0]) == pytest.approx(run0["after"]["max_condition"], rel=1e-9)
    inp = meshio.read(out / "meshes" / "cube27_input_seed0.vtu")
    assert np.allclose(m.points - inp.points, m.point_data["displacement"])
    assert np.abs(m.point_data["displacement"]).max() > 0


def test_figures_from_run_data(small_run, tmp_path):
    cfg, out = small_run
    pngs = sorted((out / "figures").glob("*.png"))
    names = {p.name for p in pngs}
    assert {"convergence_cube27.png", "histogram_cube27.png", "surface_cube27_ci-local.png"} == names
    for p in pngs:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    history = json.loads((out / "history.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    for h, r in zip(history, summary["runs"], strict=True):
        assert (h["seed"], h["method"]) == (r["seed"], r["label"])
        assert h["objective"][0] == pytest.approx(r["before"]["objective"], rel=1e-4)
        assert len(h["objective"]) == r["iterations"] + 1
    # another first seed -> other figures
    other = _write(tmp_path, SMALL.replace("seeds: [0, 1]", "seeds: [1]"))
    assert main(["run", str(other), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    for name in names:
        assert (tmp_path / "o" / "figures" / name).read_bytes() != (out / "figures" / name).read_bytes()


def test_deterministic(small_run, tmp_path):
    cfg, out = small_run
    assert main(["run", str(cfg), "--out", str(tmp_path / "again"), "--quiet"]) == 0
    a = json.loads((out / "summary.json").read_text())
    b = json.loads((tmp_path / "again" / "summary.json").read_text())
    assert _figures(a) == _figures(b)
    assert (out / "history.json").read_text() == (tmp_path / "again" / "history.json").read_text()


def test_force_replaces_and_seeds_override(small_run, tmp_path, capsys):
    cfg, first = small_run
    out = tmp_path / "out"
    shutil.copytree(first, out)  # earlier results
    code, _, err = _run(["run", str(cfg), "--out", str(out), "--quiet"], capsys)
    assert code == 2 and "--force" in err
    code, _, _ = _run(["run", str(cfg), "--out", str(out), "--quiet", "--force", "--seeds", "1"], capsys)
    assert code == 0
    assert len(json.loads((out / "summary.json").read_text())["runs"]) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary folder left behind
    (out / "notes.txt").write_text("mine")  # a file jaxci did not write: never replaced, even with --force
    code, _, err = _run(["run", str(cfg), "--out", str(out), "--quiet", "--force"], capsys)
    assert code == 2 and "not a jaxci results folder" in err and "notes.txt" in err
    assert (out / "notes.txt").read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_keyboard_interrupt_writes_partial(tmp_path, monkeypatch, capsys):
    from jaxci.interface import smooth as smooth_module
    monkeypatch.setattr(smooth_module, "smooth", interrupted_on_call(smooth_module.smooth))
    cfg = _write(tmp_path, SMALL)
    code, _, err = _run(["run", str(cfg), "--out", str(tmp_path / "out"), "--quiet"], capsys)
    assert code == 130 and "partial" in err
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["partial"] is True and s["runs_done"] == 1 and s["runs_planned"] == 2
    assert "PARTIAL" in (tmp_path / "out" / "report.md").read_text()


def test_failed_run_recorded(tmp_path, monkeypatch, capsys):
    """A run that raises a JaxciError (e.g. an inverted mesh) is recorded as failed; the others go on; exit 1."""
    from jaxci.errors import InvertedMeshError
    from jaxci.interface import smooth as smooth_module
    real = smooth_module.smooth

    def failing(mesh, method, *, seed, **kw):
        if seed == 0:
            raise InvertedMeshError("the mesh has 3 inverted elements")
        if seed == 1:
            raise RuntimeError("a bug")
        return real(mesh, method, seed=seed, **kw)

    monkeypatch.setattr(smooth_module, "smooth", failing)
    cfg = _write(tmp_path, SMALL.replace("seeds: [0, 1]", "seeds: [0, 1, 2]") + "figures: false\nwrite_meshes: false\n")
    code, _, err = _run(["run", str(cfg), "--out", str(tmp_path / "out"), "--quiet"], capsys)
    assert code == 1 and "seed 0: the mesh has 3 inverted elements" in err
    assert "seed 1: internal error (RuntimeError: a bug)" in err
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert [r["status"] for r in s["runs"]] == ["failed", "failed", "ok"]
    assert s["aggregates"][0]["failed"] == 2 and s["aggregates"][0]["runs"] == 3
    # --debug: a bug is raised, not recorded, and nothing is written
    with pytest.raises(RuntimeError, match="a bug"):
        main(["--debug", "run", str(cfg), "--out", str(tmp_path / "dbg"), "--quiet"])
    assert not (tmp_path / "dbg").exists()
    assert "Failed runs" in (tmp_path / "out" / "report.md").read_text()
    assert not (tmp_path / "out" / "figures").exists() and not (tmp_path / "out" / "meshes").exists()


# ------------------------------------------------------------------------------------------------ bad configs
BAD = [
    # (name, yaml text or substitution, key expected in the message, YAML line or None)
    ("unknown top key", SMALL + "colour: red\n", "colour", 9),
    ("unknown nested key", SMALL.replace("    params:", "    paramz:"), "methods[0].paramz", 7),
    ("wrong type", SMALL.replace("seeds: [0, 1]", "seeds: 3"), "seeds", 8),
    ("wrong type str", SMALL.replace("seeds: [0, 1]", "runs: three"), "runs", 8),
    ("negative cohort", SMALL.replace("{max_sweeps: 3}", "{cohort: -3}"), "methods[0].params.cohort", 7),
    ("r = 1.5", SMALL.replace("{max_sweeps: 3}", "{reduction: 1.5}"), "methods[0].params.reduction", 7),
    ("unknown param", SMALL.replace("{max_sweeps: 3}", "{sweeps: 3}"), "methods[0].params.sweeps", 7),
    ("unknown method", SMALL.replace("method: ci", "method: simplex"), "methods[0].method", 6),
    ("missing mesh file", SMALL.replace("generate: {case: cube27}", "file: nowhere.vtk"), "mesh[0].file", 3),
    ("unknown case", SMALL.replace("cube27", "cube28"), "mesh[0].generate.case", 3),
    ("file and generate", SMALL.replace("generate:", "file: x.vtk\n  generate:"), "mesh[0]", 3),
    ("missing methods", "mesh: {generate: {case: cube27}}\n", "methods", 1),
    ("duplicate key", SMALL + "seeds: [3]\n", "seeds", 9),
    ("bad enum", SMALL + "dtype: float16\n", "dtype", 9),
    ("seeds and runs", SMALL + "runs: 4\n", None, 1),
    ("bad yaml", SMALL + "methods: [\n", None, None),
]


@pytest.mark.parametrize("name,text,key,line", BAD, ids=[b[0] for b in BAD])
def test_bad_config(tmp_path, capsys, name, text, key, line):
    cfg = _write(tmp_path, text)
    out = tmp_path / "out"
    code, stdout, err = _run(["run", str(cfg), "--out", str(out)], capsys)
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("jaxci: error: ")
    if key is not None:
        assert f": {key}: " in err, err
    if line is not None:
        assert f"exp.yaml:{line}:" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml"]  # nothing written


def test_unknown_method_lists_valid(tmp_path):
    from jaxci.interface.smooth import METHODS

    with pytest.raises(ConfigError, match=re.escape(", ".join(METHODS))):
        load_config(_write(tmp_path, SMALL.replace("method: ci", "method: simplex")))


def test_unwritable_output(tmp_path, capsys):
    cfg = _write(tmp_path, SMALL)
    (tmp_path / "file.txt").write_text("x")
    out = tmp_path / "file.txt" / "sub"  # a folder under a regular file: unwritable even for root
    code, _, err = _run(["run", str(cfg), "--out", str(out)], capsys)
    assert code == 2 and err.count("\n") == 1 and "--out" in err and "file.txt" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml", "file.txt"]
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            code, _, err = _run(["run", str(cfg), "--out", str(ro / "sub")], capsys)
            assert code == 2 and "--out" in err and list(ro.iterdir()) == []
        finally:
            ro.chmod(0o700)


def test_output_key_from_config(tmp_path, capsys):
    (tmp_path / "file.txt").write_text("x")
    cfg = _write(tmp_path, SMALL + f"output: {tmp_path / 'file.txt' / 'sub'}\n")
    code, _, err = _run(["run", str(cfg)], capsys)
    assert code == 2 and "exp.yaml:9: output" in err


def test_report_engines_table_has_one_row_per_engine_and_rule():
    """report.md's Engines table: one row per method and (engine, device and device count, dtype, kernel, rule),
    with the number of runs; the mesh size the rule was applied to is left out, runs without a plan are not rows."""
    from jaxci.experiments import report

    rule = "auto: the host engine is the fastest for ci on a CPU up to 250,000 cells"

    def plan(n, devices=1, name="host"):
        return {"name": name, "device": "cpu", "devices": devices, "dtype": "float64", "kernel": "C",
                "reason": f"{rule}; this mesh has {n}"}

    summary = {"methods": [{"name": "CI"}, {"name": "G"}],
               "runs": [{"label": "CI", "engine": plan(27)}, {"label": "CI", "engine": plan(729)},
                        {"label": "CI", "engine": plan(27, devices=4, name="jax")}, {"label": "CI", "engine": None},
                        {"label": "G", "engine": plan(64)}]}
    assert [ln for ln in report._engines(summary) if ln.startswith("| CI ") or ln.startswith("| G ")] == [
        f"| CI | host | cpu | float64 | C | 2 | {rule} |", f"| CI | jax | cpu x4 | float64 | C | 1 | {rule} |",
        f"| G | host | cpu | float64 | C | 1 | {rule} |"]


def test_summary_and_report_name_the_accelerator_jax_sees(tmp_path, monkeypatch):
    """summary.json's device: what was asked for, the accelerator JAX sees (simulated here) and the CPU; report.md
    says both."""
    from jaxci.experiments import report
    from jaxci.interface import engine

    monkeypatch.setattr(engine, "accelerator", lambda: ("gpu", "Simulated GPU"))
    exp = load_config(_write(tmp_path, SMALL + "device: cpu\n"))
    summary = report.build_summary(exp, [], partial=False, total_runs=0, elapsed=0.0)
    assert summary["device"] == {"requested": "cpu", "accelerator": {"platform": "gpu", "kind": "Simulated GPU"},
                                 "cpu": engine.cpu_model()}
    assert f"device asked for: cpu; machine: Simulated GPU (gpu) and {engine.cpu_model()};" in \
        report.render_report(summary)


@pytest.mark.skipif(not importlib.import_module("jaxci.native").AVAILABLE,
                    reason="global CI on the host engine needs the C kernels")
def test_an_internal_error_in_one_seed_fails_that_seed_only(tmp_path, monkeypatch):
    from jaxci.experiments.runner import run_experiment

    fail_seed_method(monkeypatch, 1, RuntimeError("a bug in seed 1's run"))
    text = ("mesh: {generate: {case: cube27}}\nmethods:\n  - {name: G, method: ci-global, engine: host, params: "
            "{attempts: 10}}\nruns: 3\nfigures: false\nwrite_meshes: false\n")
    res = run_experiment(load_config(_write(tmp_path, text)), tmp_path / "out")
    assert [r.status for r in res.records] == ["ok", "failed", "ok"], [(r.status, r.error) for r in res.records]
    assert "a bug in seed 1's run" in res.records[1].error


def test_gpu_absent(tmp_path, capsys):
    import jax

    if any(d.platform != "cpu" for d in jax.devices()):
        pytest.skip("an accelerator is present")
    cfg = _write(tmp_path, SMALL + "device: gpu\n")
    code, _, err = _run(["run", str(cfg), "--out", str(tmp_path / "out")], capsys)
    assert code == 2 and "device: gpu" in err and not (tmp_path / "out").exists()


def test_load_config_is_yaml_equivalent(tmp_path):
    """A config written from its own echo loads to the same settings (the echo is a valid config)."""
    exp = load_config(_write(tmp_path, SMALL))
    echo = exp.config.model_dump(mode="json", exclude_defaults=True)
    again = load_config(_write(tmp_path, yaml.safe_dump(echo), "echo.yaml"))
    assert again.config == exp.config


def test_stage1_is_prefix_of_stage2(tmp_path):
    """The report's Table 1 mapping: global CI with stage_switch 1.0 for A attempts is exactly the first A
    attempts of a run with 2A attempts and stage_switch 0.5 (same seed)."""
    from jaxci.experiments.runner import run_experiment

    glob_ = "init_width: 0.05, reduction: 0.99, cohort: 3, variations: 3"
    text = f"""\
mesh: {{generate: {{case: cube27}}}}
methods:
  - {{name: s1, method: ci-global, params: {{{glob_}, attempts: 20, stage_switch: 1.0}}}}
  - {{name: s2, method: ci-global, params: {{{glob_}, attempts: 40, stage_switch: 0.5}}}}
figures: false
write_meshes: false
report: {{table1: {{stage1: s1, stage2: s2}}}}
"""
    res = run_experiment(load_config(_write(tmp_path, text)), tmp_path / "out")
    h1, h2 = (r.history["objective"] for r in res.records)
    assert len(h1) == 21 and h1 == h2[:21] and h2[-1] <= h1[-1]
    report = (tmp_path / "out" / "report.md").read_text()
    assert "ours stage 1 (s1)" in report and "paper stage 2" in report


@pytest.mark.parametrize("entry, device, message", [
    ("{method: bfgs, engine: host}", "auto", r"methods\[0\]\.engine: engine 'host' cannot run method 'bfgs'"),
    ("{method: lbfgs, engine: host}", "gpu", r"methods\[0\]\.engine: engine 'host' runs on the CPU; device: gpu"),
    ("{method: lbfgs, engine: jax, params: {backend: numpy}}", "auto", r"methods\[0\]\.engine: engine requests "
                                                                        r"disagree"),
])
def test_an_engine_request_that_cannot_be_honoured_is_refused_at_its_line(tmp_path, entry, device, message):
    cfg = _write(tmp_path, f"mesh: {{generate: {{case: cube27}}}}\nmethods:\n  - {entry}\ndevice: {device}\n")
    with pytest.raises(ConfigError, match=r"exp\.yaml:3: " + message):
        load_config(cfg)
