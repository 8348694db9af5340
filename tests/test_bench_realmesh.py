"""The real-mesh benchmark (scripts/bench_realmesh.py) and its corpus (scripts/realmesh_corpus.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import bench_realmesh as bench  # noqa: E402
import realmesh_corpus as corpus  # noqa: E402


@pytest.mark.shared
def test_cube_recipe_reproduces_the_peers_cube():
    path = corpus.PEERS / "cube9_pert.vtk"
    import meshio

    m = meshio.read(path)
    pts, hexes = corpus.perturbed_cube(9)
    np.testing.assert_array_equal(pts, m.points)
    np.testing.assert_array_equal(hexes, m.cells_dict["hexahedron"])


def _pairs(args):
    return sorted((f, tuple(float(x) for x in v.split(","))) for f, v in zip(args[::2], args[1::2], strict=True))


def test_box_domain_flags_of_the_unit_cube_are_msqshapes():
    from jaxci.mesh import hex_mesh

    pts, hexes = corpus.perturbed_cube(3)
    mesh = hex_mesh(pts, hexes)
    _, faces = bench.skin(mesh)
    box = bench.box_planes(pts, faces)
    assert box is not None and box["on"].sum() == 6 * 16  # 4 x 4 nodes in each face plane
    want = corpus.PEERS / "cube_domain_args.txt"
    if want.exists():
        assert _pairs(bench.box_domain_args(box)) == _pairs(want.read_text().split())
    moved = pts.copy()
    moved[0, 0] += 0.01  # node 0 (a corner) leaves x = 0
    assert bench.off_box(moved, box) == pytest.approx(0.01)
    # a single distorted hexahedron whose nodes all touch the bounding box is no box
    one = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 2], [0, 1, 1]], float)
    single = hex_mesh(one, np.arange(8)[None])
    assert bench.box_planes(one, bench.skin(single)[1]) is None


def test_child_rusage_is_the_commands_own():
    r = bench.run_child([sys.executable, "-S", "-c", "print('hi')"], timeout=30)
    assert r["rc"] == 0 and r["stdout"].strip() == "hi" and not r["timed_out"]
    assert 0 < r["peak_rss_mb"] < 100  # not this process's RSS (numpy, JAX imported)
    r = bench.run_child([sys.executable, "-S", "-c", "import time; time.sleep(30)"], timeout=0.5)
    assert r["timed_out"] and r["rc"] != 0 and r["wall_s"] < 10


@pytest.mark.slow
def test_bench_realmesh_end_to_end(tmp_path):
    """One tiny mesh (a gmsh ball split from tetrahedra, or a perturbed 5^3 cube without gmsh): jaxci cold and
    warm, msqshape where it is, the JSON fields and their values."""
    out = tmp_path / "bench.json"
    if corpus.have_gmsh():
        meshes, expect_box = ["sphere_tet2hex"], False
    else:
        cube = tmp_path / "cube5.vtk"
        corpus.write_vtk(cube, *corpus.perturbed_cube(5))  # 125 hexes: within the checked range
        meshes, expect_box = [str(cube)], True
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_realmesh.py"), "--meshes", *meshes,
                        "--sizes", "tiny", "--corpus-dir", str(tmp_path / "corpus"), "--out", str(out),
                        "--timeout", "300"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "wrote" in p.stdout
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "realmesh" and doc["settings"]["methods"] == ["default"]
    assert doc["command"].startswith("bench_realmesh.py --meshes") and doc["date"] and "commit" in doc
    (m,) = doc["meshes"]
    assert 100 <= m["hexes"] <= 1000 and m["nodes"] > m["hexes"] / 2 and m["skin_nodes"] > 0
    b = m["before"]
    assert b["inverted_elements"] == 0 and b["max_condition"] > 1.0 and b["mean_condition"] >= 1.0
    assert m["box_shaped"] is expect_box and m["msq_domain"] == ("box" if expect_box else "skin")
    runs = m["jaxci"]["default"]
    for name in ("cold", "warm"):
        r = runs[name]
        assert r["ok"] and r["rc"] == 0 and not r["timed_out"], r.get("stderr_tail")
        assert r["wall_s"] > 0 and r["cpu_s"] > 0 and 20 < r["peak_rss_mb"] < 8000
        assert "phases" in r and (r["phases"] is None or isinstance(r["phases"], dict))
        a = r["after"]
        assert a["inverted_elements"] == 0 and 1.0 <= a["max_condition"] <= b["max_condition"] + 1e-9
        assert a["mean_condition"] <= b["mean_condition"] + 1e-9
        assert r["boundary"]["skin_nodes"] == m["skin_nodes"] and isinstance(r["boundary"]["moved"], bool)
        assert r["iterations"] is not None and r["reported_wall_s"] > 0
    assert runs["cold"]["cache_entries_after"] >= 0
    assert "skipped" in runs["warm_other"]  # one mesh: nothing else warmed the cache
    msq = m["msqshape"]
    if not bench.MSQSHAPE.exists():
        assert "skipped" in msq
        return
    for mode in ("domain", "free"):
        r = msq[mode]
        assert r["ok"] and r["rc"] == 0, r.get("stderr_tail")
        assert r["wall_s"] > 0 and r["cpu_s"] >= 0 and 0 < r["peak_rss_mb"] < 2000
        assert r["after"]["inverted_elements"] == 0 and r["after"]["max_condition"] >= 1.0
        assert isinstance(r["boundary"]["moved"], bool)
    if expect_box:  # sliding on the cube's planes
        assert msq["domain"]["boundary"]["off_box_planes"] < 1e-6
    else:  # -s: the skin is fixed
        assert not msq["domain"]["boundary"]["moved"]
    assert msq["free"]["flags"] == "none"


def test_targets_of_the_default_pipeline():
    """`targets` compares the default's cold run with the p-mean, local CI, msqshape -s and plain L-BFGS as
    TARGETS says; a failed run leaves the targets it feeds undecided."""

    def run(worst, mean, wall):
        return {"ok": True, "wall_s": wall, "after": {"worst_element": worst, "element_mean": mean}}

    info = {"name": "m", "hexes": 10,
            "jaxci": {"default": {"cold": run(2.00, 1.21, 1.9)}, "lbfgs": {"cold": run(2.8, 1.20, 1.0)},
                      "pmean4": {"cold": run(1.97, 1.30, 1.2)}, "ci": {"cold": run(2.8, 1.205, 3.0)}},
            "msqshape": {"skin": run(7.0, 1.30, 0.5)}}
    t = bench.targets(info)
    assert t["worst"] == {"bound": pytest.approx(1.97 * 1.02), "value": 2.00, "met": True}
    assert t["mean"]["bound"] == pytest.approx(1.20 * 1.01) and t["mean"]["met"] is True
    assert t["wall"]["bound"] == pytest.approx(2.0) and t["wall"]["met"] is True
    info["name"] = "cube60_pert"  # 1.5x there
    assert bench.targets(info)["wall"]["met"] is False
    info["jaxci"]["pmean4"]["cold"]["after"]["worst_element"] = 1.9  # 2.00 > 1.9 * 1.02
    info["jaxci"]["lbfgs"]["cold"] = {"ok": False}
    t = bench.targets(info)
    assert t["worst"]["met"] is False and t["wall"]["met"] is None
    assert t["mean"]["bound"] == pytest.approx(1.30 * 1.01)  # msqshape's mean is the better one left
    table = bench.targets_table([info])
    assert "NO" in table and "failed" in table and "targets met: worst 0/1" in table


def test_method_flags_of_a_parameterised_method():
    """A `--method` entry NAME:PARAM=VALUE[,...] runs NAME's flags and one --param per pair; its file-name part
    keeps no ':' or '='; a pair without '=' is refused by name."""
    assert bench.method_flags("default") == []
    assert bench.method_flags("lbfgs") == ["--method", "lbfgs"]
    assert bench.method_flags("default:polish_budget=0.02") == ["--param", "polish_budget=0.02"]
    assert bench.method_flags("pmean4:polish=true,ktol=1e-3") == [
        "--method", "lbfgs", "--objective", "pmean", "--param", "p=4", "--param", "polish=true",
        "--param", "ktol=1e-3"]
    slug = bench.method_slug("default:polish_work=400,polish_budget=0.02")
    assert slug == "default_polish_work_400_polish_budget_0.02"
    with pytest.raises(SystemExit, match="'polish' is not PARAM=VALUE"):
        bench.method_flags("default:polish")


@pytest.mark.parametrize("shape", sorted(corpus._TET2HEX))
def test_tet_to_hex_shapes_are_valid_meshes_of_their_solid(shape):
    """Each tet-to-hex shape of the corpus at its small size: about the hexahedra asked for, none inverted, and its
    nodes on or inside its solid (the torus: around the tube's centre circle, none near the axis)."""
    if not corpus.have_gmsh():
        pytest.skip("the gmsh wheel is not installed (pip install gmsh): the corpus's made meshes need it")
    from jaxci.mesh import hex_mesh

    target = corpus.SIZES["small"]
    pts, hexes = corpus.make_gmsh(shape, target)
    assert 0.75 * target <= len(hexes) <= 1.33 * target  # (the generator refines its size until within these)
    mesh = hex_mesh(pts, hexes)
    assert mesh.n_hexes == len(hexes) and np.unique(hexes).size == len(pts)  # compact: every node used
    from jaxci.metrics.report import quality_report

    assert quality_report(mesh).inverted_elements == 0
    tol = 1e-9
    if shape == "torus_tet2hex":
        ring = np.hypot(pts[:, 0], pts[:, 1])
        assert np.max(np.hypot(ring - 1.0, pts[:, 2])) <= 0.35 + tol
        assert ring.min() >= 0.65 - tol
    elif shape == "sphere_tet2hex":
        assert np.max(np.linalg.norm(pts, axis=1)) <= 1.0 + tol


def test_cold_repeats_alternate_the_methods_and_take_the_median(tmp_path, monkeypatch):
    """``--repeats 3``: two more cold runs of each method, the methods alternated, each with an empty cache; the
    cold record's wall is the median of its runs, its first run's figures kept; a failed repeat is counted and left
    out; a method whose first run failed is not repeated."""
    calls = []
    walls = {"default": iter([9.0, 2.0]), "lbfgs": iter([1.0, 5.0])}

    def fake_run(args, inp, out, method, cache):
        assert cache.is_dir() and not any(cache.iterdir())  # a fresh cache each time
        (cache / "entry").write_text("x")
        calls.append(method)
        w = next(walls[method])
        return {"ok": w < 8.0, "rc": 0 if w < 8.0 else 1, "wall_s": w}

    monkeypatch.setattr(bench, "run_jaxci", fake_run)
    monkeypatch.setattr(bench, "_say", lambda *a: None)
    info = {"name": "m", "jaxci": {"default": {"cold": {"ok": True, "wall_s": 3.0, "after": {"worst_element": 1.5}}},
                                   "lbfgs": {"cold": {"ok": True, "wall_s": 2.0}},
                                   "ci": {"cold": {"ok": False, "wall_s": 1.0}}}}
    args = type("A", (), {"repeats": 3, "method": ["default", "lbfgs", "ci"]})()
    bench.cold_repeats(args, info, {"dir": tmp_path, "path": tmp_path / "in.vtk"}, tmp_path / "caches")
    assert calls == ["default", "lbfgs", "default", "lbfgs"]  # alternated; ci (failed first) not repeated
    d, lb = info["jaxci"]["default"]["cold"], info["jaxci"]["lbfgs"]["cold"]
    assert d["wall_runs"] == [3.0, 2.0] and d["failed_repeats"] == 1 and d["wall_s"] == 2.5
    assert d["wall_first_s"] == 3.0 and d["after"] == {"worst_element": 1.5}
    assert lb["wall_runs"] == [2.0, 1.0, 5.0] and lb["wall_s"] == 2.0 and lb["failed_repeats"] == 0
    assert "wall_runs" not in info["jaxci"]["ci"]["cold"]
    args.repeats = 1  # one run: nothing more
    calls.clear()
    bench.cold_repeats(args, info, {"dir": tmp_path, "path": tmp_path / "in.vtk"}, tmp_path / "caches")
    assert calls == []
