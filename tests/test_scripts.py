"""The benchmark script end to end on a tiny box: it measures, writes its JSON, and fails clearly."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bench(tmp_path, *args):
    out = tmp_path / "bench.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "benchmark.py"), "--sizes", "3", "--methods",
                        "lbfgs", "--out", str(out), *args], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout, json.loads(out.read_text())


@pytest.mark.slow
def test_benchmark_measures_and_writes_json(tmp_path):
    stdout, data = _bench(tmp_path, "--params", '{"presmooth": 1}')
    (row,) = data["rows"]
    assert row["hexes"] == 27 and row["backend"] == "cpu" and row["params"] == {"presmooth": 1}
    assert row["after_max_condition"] <= 1.0001 and row["inverted_after"] == 0
    for key in ("to_1.01", "to_1.0001"):  # iterations from the history, then re-timed with that cap
        assert row[key]["iterations"] >= 1 and row[key]["seconds"] > 0 and row[key]["reached"] <= float(key[3:])
    assert row["cold_s"] > 0 and row["warm_s"] > 0 and row["objective_mcorners_per_s"] > 0
    assert len(row["history_max_condition"]) == row["iterations"] + 1
    assert "wrote" in stdout


def test_benchmark_without_the_device_asked_for_says_so(tmp_path):
    import jax

    if jax.devices()[0].platform != "cpu":
        pytest.skip("a GPU is present")
    stdout, data = _bench(tmp_path, "--device", "gpu")
    assert "FAILED: error: device: gpu requested but JAX sees no GPU" in stdout
    assert "no GPU" in data["rows"][0]["error"]
