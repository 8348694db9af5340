"""The command line: outputs, JSON keys, exit code 2 with one clear line for bad input, inputs never touched."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import MESQUITE, MESQUITE_FIGURES

from jaxci.cli import main

QUALITY_KEYS = {"n_nodes", "n_elements", "inverted_corners", "inverted_elements", "max_condition",
                "mean_condition", "objective", "min_scaled_jacobian", "histogram", "corner_nodes", "edge_nodes",
                "surface_nodes", "interior_nodes"}


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.shared
@pytest.mark.parametrize("name", sorted(MESQUITE_FIGURES))
def test_quality_json_reproduces_mesquite_readme(capsys, name):
    code, out, err = run(capsys, "quality", MESQUITE / name, "--json")
    assert code == 0, err
    d = json.loads(out)
    assert QUALITY_KEYS <= set(d)
    n_hex, n_nodes, inv_c, inv_e, kmax, F, sj = MESQUITE_FIGURES[name]
    assert (d["n_elements"], d["n_nodes"], d["inverted_corners"], d["inverted_elements"]) == (n_hex, n_nodes, inv_c,
                                                                                             inv_e)
    if kmax is not None:
        assert d["max_condition"] == pytest.approx(kmax, abs=1e-3)
        assert d["objective"] == pytest.approx(F, abs=1e-5 if F < 1 else 1e-3)
    if sj is not None:
        assert d["min_scaled_jacobian"] == pytest.approx(sj, abs=1e-3)
    assert [b["low"] for b in d["histogram"]] == [1, 1.5, 2, 3, 4, 5, 8]
    assert d["histogram"][-1]["high"] is None
    assert sum(d[k] for k in ("corner_nodes", "edge_nodes", "surface_nodes", "interior_nodes")) <= d["n_nodes"]


@pytest.mark.shared
def test_quality_table(capsys):
    code, out, _ = run(capsys, "quality", MESQUITE / "hexes_4by2by2.vtk")
    assert code == 0
    assert "max condition k/3" in out and "[8, inf)" in out and "1.20326" in out


def test_generate_then_smooth_roundtrip(capsys, tmp_path):
    src = tmp_path / "cube.vtu"
    code, out, _ = run(capsys, "generate", "cube64", src, "--seed", "2")
    assert code == 0 and src.exists()
    before = src.read_bytes()
    dst = tmp_path / "smoothed.vtk"
    code, out, err = run(capsys, "smooth", src, dst, "--method", "ci", "--json", "--param", "max_sweeps=10")
    assert code == 0, err
    d = json.loads(out)
    assert d["after"]["max_condition"] < d["before"]["max_condition"]
    assert d["after"]["inverted_elements"] == 0
    assert {"iterations", "wall_time", "before", "after", "method", "params"} <= set(d)
    assert src.read_bytes() == before  # the input is never touched
    code, out, _ = run(capsys, "quality", dst, "--json")
    assert json.loads(out)["max_condition"] == pytest.approx(d["after"]["max_condition"], rel=1e-9)
    # table output too
    code, out, _ = run(capsys, "smooth", src, tmp_path / "s2.vtu", "--method", "ci", "--param", "max_sweeps=2")
    assert code == 0 and "before:" in out and "after (ci" in out
    code, out, _ = run(capsys, "smooth", src, tmp_path / "s3.vtu")  # the default pipeline says which it ran
    assert code == 0 and "default method (auto): L-BFGS" in out and "after (L-BFGS on F" in out


@pytest.mark.shared
def test_classify_writes_node_classes(capsys, tmp_path):
    import meshio

    out_path = tmp_path / "classes.vtu"
    code, out, _ = run(capsys, "classify", MESQUITE / "large_box_hex_1000.vtk", out_path, "--json")
    assert code == 0
    d = json.loads(out)
    m = meshio.vtu.read(str(out_path))
    cls = np.asarray(m.point_data["node_class"])
    assert [int((cls == c).sum()) for c in (0, 1, 2, 3)] == [d["interior_nodes"], d["surface_nodes"],
                                                           d["edge_nodes"], d["corner_nodes"]]
    assert d["corner_nodes"] == 8


def _real(name: str) -> str:
    """The text of a Mesquite mesh of ../shared/data."""
    return (MESQUITE / name).read_text()


@pytest.mark.parametrize("make,match", [
    (lambda p: p / "missing.vtk", "no such file"),
    (lambda p: _write(p / "mesh.xyz", "1 2 3\n"), "extension"),
    (lambda p: _write(p / "corrupt.vtu", "\x00\x01garbage<VTKFile"), ""),
    pytest.param(lambda p: _write(p / "trunc.vtk", _real("hexes_4by2by2.vtk")[:500]), "", marks=pytest.mark.shared),
    pytest.param(lambda p: _write(p / "nan.vtk", _real("single_hex.vtk").replace("0 0 0", "nan 0 0", 1)), "non-finite",
                 marks=pytest.mark.shared),
    pytest.param(lambda p: _write(p / "range.vtk", _real("single_hex.vtk").replace("2 1 0", "2 1 99")), "out of range",
                 marks=pytest.mark.shared),
])
def test_bad_input_one_line_exit_2(capsys, tmp_path, make, match):
    path = make(tmp_path)
    code, out, err = run(capsys, "quality", path)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxci: error:"), err
    assert "Traceback" not in err and match in err
    assert str(path.name) in err or "extension" in match


def _write(path, text):
    path.write_text(text)
    return path


def test_smooth_refuses_to_overwrite_input_and_existing_output(capsys, tmp_path):
    src = tmp_path / "a.vtu"
    run(capsys, "generate", "box", src, "--n", "2", "--amplitude", "0.2")
    code, _, err = run(capsys, "smooth", src, src)
    assert code == 2 and "overwrite the input" in err
    other = tmp_path / "b.vtu"
    other.write_text("keep me")
    code, _, err = run(capsys, "smooth", src, other)
    assert code == 2 and "--force" in err and other.read_text() == "keep me"


def test_smooth_bad_param_exit_2(capsys, tmp_path):
    src = tmp_path / "a.vtu"
    run(capsys, "generate", "box", src, "--n", "2", "--amplitude", "0.2")
    code, _, err = run(capsys, "smooth", src, tmp_path / "o.vtu", "--param", "reduction=1.5")
    assert code == 2 and "reduction" in err
