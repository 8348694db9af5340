"""The benchmark scripts end to end on tiny meshes: they measure, write their JSON, and fail clearly."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from jaxci import native

ROOT = Path(__file__).resolve().parents[1]


def _bench(tmp_path, *args):
    out = tmp_path / "bench.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "benchmark.py"), "--sizes", "3", "--methods",
                        "lbfgs", "--out", str(out), *args], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout, json.loads(out.read_text())


@pytest.mark.slow
def test_benchmark_measures_and_writes_json(tmp_path):
    stdout, data = _bench(tmp_path, "--params", '{"presmooth": 1}', "--repeats", "2", "--engines", "jax")
    (row,) = data["rows"]
    assert row["hexes"] == 27 and row["engine"]["name"] == "jax" and row["engine"]["device"] == "cpu"
    assert row["params"] == {"presmooth": 1, "engine": "jax", "device": "auto"}
    assert row["after_max_condition"] <= 1.0001 and row["inverted_after"] == 0 and row["repeats"] == 2
    for key in ("to_1.01", "to_1.0001"):  # iterations from the history, then re-timed with that cap
        assert row[key]["iterations"] >= 1 and row[key]["seconds"] > 0 and row[key]["reached"] <= float(key[3:])
    assert row["cold_s"] > 0 and row["warm_s"] > 0 and row["objective_mcorners_per_s"] > 0
    assert len(row["history_max_condition"]) == row["iterations"] + 1
    assert "wrote" in stdout


def test_benchmark_puts_both_engines_side_by_side(tmp_path):
    _, data = _bench(tmp_path, "--full-upto", "2")
    host, jax_row = data["rows"]
    assert data["engines"] == ["host", "jax"] and data["command"] and data["date"]
    assert (host["engine"]["name"], jax_row["engine"]["name"]) == ("host", "jax")
    assert host["engine"]["dtype"] == "float64" and jax_row["engine"]["dtype"] == "float32"
    assert host["objective_mcorners_per_s"] is None and jax_row["objective_mcorners_per_s"] > 0
    for r in (host, jax_row):
        assert r["after_max_condition"] <= 1.0001 and r["cold_s"] > 0


@pytest.mark.slow
def test_benchmark_runs_each_device_count_sharded(tmp_path):
    """``--devices 2``: the child gets 2 forced CPU devices and runs sharded; the row says so, with its peak."""
    _, data = _bench(tmp_path, "--devices", "2", "--full-upto", "2")  # one cold run per row
    (row,) = data["rows"]
    assert data["devices"] == [2] and row["devices"] == 2  # the host engine does not shard: its row is not run
    assert row["params"] == {"devices": 2, "engine": "jax", "device": "auto"} and row["engine"]["devices"] == 2
    assert row["after_max_condition"] <= 1.0001 and row["inverted_after"] == 0
    assert row["peak_rss_mb"] > 0 and row["peak_rss_bytes_per_hex"] == pytest.approx(row["peak_rss_mb"] * 2**20 / 27)
    if sys.platform.startswith("linux"):  # XLA:CPU's pool: at least one thread per device
        assert row["xla_cpu_threads"] >= 2 and row["cpus"] >= 1


def test_benchmark_without_the_device_asked_for_says_so(tmp_path):
    import jax

    if jax.devices()[0].platform != "cpu":
        pytest.skip("a GPU is present")
    stdout, data = _bench(tmp_path, "--device", "gpu", "--engines", "jax")
    assert "FAILED: error: device 'gpu' asked for, but" in stdout
    assert "device 'gpu' asked for" in data["rows"][0]["error"]


@pytest.mark.slow
def test_bench_gpu_runs_every_section_at_small_sizes_on_a_cpu(tmp_path):
    """scripts/bench_gpu.py, ready for a GPU: with --small on this CPU every default section runs and writes its
    JSON (the largest box, the accelerator's own, is skipped without one): the kernel forms, the JAX engine cold
    then warm with its phases' device and host seconds and bytes, the engines side by side."""
    out = tmp_path / "gpu.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_gpu.py"), "--small", "--engines-sizes", "6",
                        "--out", str(out)], capture_output=True, text=True, timeout=900)  # one size: 3 runs, not 6
    assert p.returncode == 0, p.stderr[-2000:]
    d = json.loads(out.read_text())
    assert d["environment"]["default_backend"] in ("cpu", "gpu", "tpu") and d["commit"] is not None
    for section in ("kernels", "smooth", "engines"):
        rows = d[section]
        assert rows and not any("skipped" in r or "error" in r for r in rows), (section, rows)
    forms = {r["kernel"] for r in d["kernels"][0]["rows"]}
    assert {"scatter", "gather", "segment"} <= forms and all(r["corners_per_s"] > 0 for r in d["kernels"][0]["rows"])
    cold, warm, host = d["smooth"]
    assert (cold["process"], warm["process"], host["engine"]["name"]) == ("cold", "warm", "host")
    assert warm["phases"]["total"]["compiled"] == warm["phases"]["total"]["cache_hits"]  # nothing compiled anew
    assert warm["phases"]["total"]["compile_seconds"] < cold["phases"]["total"]["compile_seconds"]
    for r in (cold, warm):
        assert "upload" in r["phases"] and 0 < r["host_share"] < 1 and r["h2d_per_mesh"] > 0.5
        assert r["max_condition"] == pytest.approx(warm["max_condition"], rel=1e-9)
    assert {(r["engine_asked"], r["process"]) for r in d["engines"]} == {("jax", "cold"), ("jax", "warm"),
                                                                        ("host", "-")}
    assert {r["engine"]["name"] for r in d["engines"]} == {"host", "jax"}
    assert "F + gradient" in p.stdout and "targets" in p.stdout


def test_bench_gpu_compares_the_jax_engines_solvers(tmp_path):
    """scripts/bench_gpu.py --sections solvers: ``jaxci smooth --engine jax --method lbfgs`` with each solver in a
    fresh process on a curved annulus: its steps, the objective and the worst corner after."""
    out = tmp_path / "gpu.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_gpu.py"), "--small", "--sections", "solvers",
                        "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    rows = json.loads(out.read_text())["solvers"]
    assert [r["solver"] for r in rows] == ["lbfgs", "newton"] and not any("error" in r for r in rows), rows
    assert all(r["engine"]["name"] == "jax" and r["iterations"] > 0 and r["process_wall_s"] > 0 for r in rows)
    assert rows[1]["objective"] <= rows[0]["objective"] * 1.01 and rows[1]["max_condition"] < 2


def test_bench_memory_measures_the_peak_of_a_fresh_jaxci_process(tmp_path):
    """scripts/bench_memory.py on a small box: `jaxci smooth` in a fresh process, its peak memory (more than the
    interpreter's own), seconds and bytes per hexahedron, the engine and the result, in its table and JSON."""
    from jaxci.io import write_mesh
    from jaxci.mesh.generate import perturb_box

    box, out = tmp_path / "box.vtk", tmp_path / "mem.json"
    write_mesh(perturb_box(6, amplitude=0.3, seed=1), str(box))
    stages = ["--stages"] if sys.platform == "linux" else []  # (the kernel's per-process high-water mark, reset)
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_memory.py"), "--mesh", str(box), "--out",
                        str(out), *stages], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    d = json.loads(out.read_text())
    row = d["rows"]["jaxci"]
    if stages:  # the peak of each phase, from another process: read, the smoothing and the writing among them
        assert {"read", "smooth", "write"} <= set(row["stages_kb"]), row["stages_kb"]
        assert all(10_000 < kb < 2_000_000 for kb in row["stages_kb"].values()) and "peak MB by phase" in p.stdout
    assert d["hexahedra"] == 216 and row["status"] == 0 and "jaxci smooth" in p.stdout + row["command"]
    assert 20 < row["peak_mb"] < 2000 and row["peak_kb"] == pytest.approx(row["peak_mb"] * 1024, abs=60)
    assert row["bytes_per_hex"] == round(row["peak_kb"] * 1024 / 216) and row["wall_s"] > 0 and row["cpu_s"] > 0
    assert row["engine"]["name"] == "host" and row["after"]["inverted_elements"] == 0
    assert "peak MB" in p.stdout and "msqshape" not in d["rows"] and d["bytecode"] == "compiled (compileall)"


def test_bench_host_prep_times_the_phases_and_the_host_functions(tmp_path):
    out = tmp_path / "prep.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_host_prep.py"), "--hexes", "1000", "--engine",
                        "host", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    d = json.loads(out.read_text())
    assert d["hexes"] == 1000 and d["engine"]["name"] == "host" and d["wall_s"] > 0
    assert {"validate", "report", "setup", "smooth", "checks"} <= set(d["phases"])
    # the functions every run calls were found in the profile (a renamed one would read 0)
    for name in ("quality_report", "classify_boundary", "build_constraints", "check_volume", "worst_elements"):
        assert d["functions"][name] > 0, name
    assert "classify_boundary" in p.stdout


def test_bench_device_memory_measures_both_programs(tmp_path):
    out = tmp_path / "mem.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_device_memory.py"), "--hexes", "1000", "--out",
                        str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    d = json.loads(out.read_text())
    assert d["hexes"] == 1000 and d["engine"]["name"] == "jax"
    rows = d["bytes_per_hex"]
    assert set(rows) == {"presmoothing", "lbfgs"}
    for row in rows.values():  # the coordinates and connectivity at least (float32 points, int32 hexahedra)
        assert row["live"] > 32 and row["arguments"] > 0 and row["peak_estimate"] >= row["live"]




@pytest.mark.shared
def test_compare_methods_corpus_reports_before_and_after_per_method(tmp_path):
    """``compare_methods.py --corpus`` on two tiny Mesquite meshes (one tangled): every row has before AND after
    max and mean kappa/3, and a capped CI says so (no gmsh needed)."""
    out = tmp_path / "cmp"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "compare_methods.py"), "--corpus", "--meshes",
                        "hexes_4by2by2", "hex_5_tangled", "--methods", "lbfgs", "lbfgs-pmean", "ci",
                        "--ci-max-sweeps", "3", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    data = json.loads(out.with_suffix(".json").read_text())
    rows = {(r["mesh"], r["method"]): r for r in data["results"]}
    assert set(rows) == {(m, k) for m in ("hexes_4by2by2", "hex_5_tangled") for k in ("lbfgs", "lbfgs-pmean", "ci")}
    for (mesh, method), r in rows.items():
        assert r["status"] == "ok", r
        for when in ("before", "after"):
            for key in ("max_condition", "mean_condition", "inverted_elements"):
                assert r[when][key] is not None, (mesh, method, when, key)
        assert r["after"]["max_condition"] <= r["before"]["max_condition"] + 1e-9
        assert 1.0 <= r["after"]["mean_condition"] <= r["after"]["max_condition"] + 1e-9
        assert r["after"]["inverted_elements"] == 0 and r["iterations"] >= 1 and r["wall_s"] > 0
    assert rows["hex_5_tangled", "lbfgs"]["before"]["inverted_elements"] > 0  # untangled first
    assert rows["hexes_4by2by2", "lbfgs-pmean"]["method_params"]["objective"] == "pmean"
    ci = rows["hexes_4by2by2", "ci"]
    assert ci["method_params"]["max_sweeps"] == 3 and ci["capped"] and ci["iterations"] == 3
    md = out.with_suffix(".md").read_text()
    assert "max k/3 before" in md and "mean k/3 after" in md and "stopped at cap (max_sweeps=3)" in md


@pytest.mark.shared
@pytest.mark.skipif(not native.AVAILABLE, reason="needs the C kernels (jaxci.native)")
def test_bench_local_ci_times_ci_to_its_target_against_lbfgs(tmp_path):
    """``bench_local_ci.py`` on a 4^3 box and Mesquite's 4x2x2 hexes: per mesh L-BFGS's time and result, CI's
    run, the first sweep at the target (box: max kappa/3 1.0001; mesh: F within 1% of L-BFGS's), CI's time to
    it and the ratio, in the JSON."""
    out = tmp_path / "ci.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_local_ci.py"), "--boxes", "4", "--meshes",
                        "hexes_4by2by2", "--repeats", "1", "--out", str(out)], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    box, mesh = json.loads(out.read_text())["rows"]
    assert box["box"] and box["hexes"] == 64 and not mesh["box"]
    for r in (box, mesh):
        c = r["ci"]
        assert r["lbfgs"]["seconds"] > 0 and c["target_sweep"] is not None and c["seconds_to_target"] > 0
        assert c["ratio"] == pytest.approx(c["seconds_to_target"] / r["lbfgs"]["seconds"])
    assert box["ci"]["max_at_target"] <= 1.0001 and box["lbfgs"]["seconds_to_target"] > 0
    assert mesh["ci"]["F_at_target"] <= 1.01 * mesh["lbfgs"]["F"]


def test_bench_kernel_times_every_kernel_form(tmp_path):
    """scripts/bench_kernel.py --small: a row per kernel form and dtype with its corners/s, the incidences'
    build for the gather and segment forms, the C kernel's row where it is built; the JSON says where it ran."""
    out = tmp_path / "kernel.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_kernel.py"), "--small", "--out", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    d = json.loads(out.read_text())
    assert d["commit"] and d["date"] and "bench_kernel.py --small" in d["command"] and d["machine"]["cpus"] >= 1
    from jaxci.metrics import native_grad

    kernels = {"scatter", "gather", "segment"} | ({"ffi"} if native_grad.available("cpu") else set())
    assert {(r["kernel"], r["dtype"]) for r in d["rows"]} == {(k, t) for k in kernels for t in ("float32", "float64")}
    for r in d["rows"]:
        assert r["hexes"] == 1000 and len(r["times"]) == 3 and r["corners_per_s"] == pytest.approx(8000 / r["seconds"])
        assert (r["incidence_warm_s"] is not None) == (r["kernel"] in ("gather", "segment"))
    assert "M corners/s" in p.stdout and "segment" in p.stdout


@pytest.mark.slow
def test_bench_compile_measures_cold_and_warm_processes(tmp_path):
    """scripts/bench_compile.py --small: the CLI and the library on a 4^3 box, cold then warm, each a fresh
    process: the warm ones load every program's executable (nothing compiled, nothing looked up in JAX's own
    cache), and the JSON is stamped."""
    out = tmp_path / "compile.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_compile.py"), "--small", "--out", str(out)],
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-2000:]
    data = json.loads(out.read_text())
    assert data["date"] and data["command"] and data["machine"]["cpus"] and "commit" in data
    assert [(r["hexes"], r["way"]) for r in data["rows"]] == [(64, "cli"), (64, "library")]
    for row in data["rows"]:
        cold, warm = row["cold"], row["warm"]
        assert cold["compiled"] > cold["cache_hits"] and warm["compiled"] == warm["cache_hits"] == 0, row
        assert warm["compile_seconds"] < cold["compile_seconds"] and warm["max_condition"] == cold["max_condition"]
    lib = data["rows"][1]["warm"]
    assert lib["exported_programs"]["loaded"] >= 1 and lib["exported_programs"]["exported"] == 0
    assert set(lib["split"]) >= {"trace", "lower", "backend", "exported"}
    assert "library  warm" in p.stdout
