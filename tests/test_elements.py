"""Wedge, pyramid and tetrahedron quality against VTK/Verdict, the mixed objective, the per-type report."""

from __future__ import annotations

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxci.cli import main
from jaxci.mesh import CellBlock, HexMesh
from jaxci.mesh.generate import perturb_box
from jaxci.metrics import elements as E
from jaxci.metrics import hexahedron as q
from jaxci.metrics.report import quality_report

vtk = pytest.importorskip("vtk")
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy  # noqa: E402

S3 = math.sqrt(3.0) / 2.0
#: The ideal cell of each type (all edges 1), VTK >= 9.7 node order.
IDEAL = {
    "hexahedron": np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1.0]]),
    "wedge": np.array([[0, 0, 0], [1, 0, 0], [0.5, S3, 0], [0, 0, 1], [1, 0, 1], [0.5, S3, 1]]),
    "pyramid": np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, math.sqrt(0.5)]]),
    "tetra": np.array([[0, 0, 0], [1, 0, 0], [0.5, S3, 0], [0.5, S3 / 3, math.sqrt(2 / 3)]]),
}
VTK_CODE = {"hexahedron": vtk.VTK_HEXAHEDRON, "wedge": vtk.VTK_WEDGE, "pyramid": vtk.VTK_PYRAMID,
            "tetra": vtk.VTK_TETRA}
VTK_NAME = {"hexahedron": "Hex", "wedge": "Wedge", "pyramid": "Pyramid", "tetra": "Tet"}


def vtk_quality(cells_xyz: np.ndarray, cell_type: str, measure: str) -> np.ndarray:
    """vtkMeshQuality (Verdict) per cell of shape (N, k, 3), float64 points."""
    n, k, _ = cells_xyz.shape
    grid, pts = vtk.vtkUnstructuredGrid(), vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(cells_xyz.reshape(-1, 3), dtype=np.float64), deep=True))
    grid.SetPoints(pts)
    for c in range(n):
        ids = vtk.vtkIdList()
        for j in range(k):
            ids.InsertNextId(c * k + j)
        grid.InsertNextCell(VTK_CODE[cell_type], ids)
    mq = vtk.vtkMeshQuality()
    mq.SetInputData(grid)
    getattr(mq, f"Set{VTK_NAME[cell_type]}QualityMeasureTo{measure}")()
    mq.Update()
    return vtk_to_numpy(mq.GetOutput().GetCellData().GetArray("Quality")).copy()


def random_cells(cell_type: str, n: int, amplitude: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`n` random valid cells (ideal cell, nodes moved by up to `amplitude`, stretched): points and cells."""
    rng = np.random.default_rng(seed)
    k = len(IDEAL[cell_type])
    x = IDEAL[cell_type][None] * rng.uniform(0.7, 1.6, (4 * n, 1, 3))
    x = x + rng.uniform(-amplitude, amplitude, (4 * n, k, 3))
    cells = np.arange(4 * n * k).reshape(-1, k)
    ok = ~E.inverted(x.reshape(-1, 3), cells, cell_type)
    x = x[ok][:n]
    assert len(x) == n
    return x.reshape(-1, 3), np.arange(n * k).reshape(-1, k)


def assert_rel(ours, ref, rtol=1e-6):
    np.testing.assert_allclose(np.asarray(ours), np.asarray(ref), rtol=rtol, atol=0)


# ------------------------------------------------------------------------------------------------ VTK truth
@pytest.mark.parametrize("cell_type,measure,fn", [
    ("wedge", "Condition", E.element_condition),
    ("wedge", "ScaledJacobian", E.scaled_jacobian),
    ("tetra", "Condition", E.element_condition),
    ("tetra", "ScaledJacobian", E.scaled_jacobian),
    ("pyramid", "ScaledJacobian", E.scaled_jacobian),
    ("hexahedron", "Condition", E.element_condition),
    ("hexahedron", "ScaledJacobian", E.scaled_jacobian),
])
def test_random_cells_match_vtk(cell_type, measure, fn):
    pts, cells = random_cells(cell_type, 300, 0.3, seed=len(measure) + len(cell_type))
    if cell_type == "pyramid":  # and nearly square pyramids, taller than the ideal one
        rng = np.random.default_rng(7)
        tall = np.repeat(IDEAL["pyramid"][None], 100, axis=0)
        tall[:, 4, 2] = rng.uniform(0.75, 1.3, 100)
        tall += rng.uniform(-0.03, 0.03, tall.shape)
        pts, cells = np.concatenate([pts, tall.reshape(-1, 3)]), np.arange(400 * 5).reshape(-1, 5)
    ref = vtk_quality(pts.reshape(len(cells), -1, 3), cell_type, measure)
    assert_rel(fn(pts, cells, cell_type), ref)
    if cell_type == "pyramid":  # both branches of Verdict's fold at 1 (s' <= 1 and s' > 1) are exercised
        s = math.sqrt(2) * np.min([E.scaled_jacobian(pts, cells[:, t], "tetra") for t in E.PYRAMID_TETS], axis=0)
        assert (s > 1).any() and (s < 1).any()


@pytest.mark.parametrize("cell_type", ["wedge", "pyramid", "tetra", "hexahedron"])
def test_node_order_has_positive_vtk_volume(cell_type):
    pts, cells = random_cells(cell_type, 50, 0.25, seed=3)
    assert (vtk_quality(pts.reshape(len(cells), -1, 3), cell_type, "Volume") > 0).all()
    assert (np.asarray(E.corner_determinant(pts, cells, cell_type)) > 0).all()


def test_tet_corner_condition_is_verdict_tet_condition_at_every_corner():
    pts, cells = random_cells("tetra", 100, 0.3, seed=5)
    k = np.asarray(E.corner_condition(pts, cells, "tetra"))
    assert_rel(k, np.repeat(vtk_quality(pts.reshape(-1, 4, 3), "tetra", "Condition")[:, None], 4, axis=1), 1e-9)


# ------------------------------------------------------------------------------------------------ definitions
@pytest.mark.parametrize("cell_type", E.ELEMENT_TYPES)
def test_ideal_cells(cell_type):
    x, cells = IDEAL[cell_type], np.arange(len(IDEAL[cell_type]))[None]
    np.testing.assert_allclose(E.corner_condition(x, cells, cell_type), 1.0, rtol=1e-12)
    np.testing.assert_allclose(E.scaled_jacobian(x, cells, cell_type), 1.0, rtol=1e-12)
    expected = 1.0000034 if cell_type == "wedge" else 1.0  # Verdict's rounded normaliser 1.16477
    np.testing.assert_allclose(E.element_condition(x, cells, cell_type), expected, rtol=1e-6)
    assert not E.inverted(x, cells, cell_type).any()


def rotation(seed: int) -> np.ndarray:
    qm, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    qm = qm * np.sign(np.diag(r))
    return qm if np.linalg.det(qm) > 0 else -qm


@pytest.mark.parametrize("cell_type", E.ELEMENT_TYPES)
@pytest.mark.parametrize("seed", [0, 1])
def test_invariant_under_rigid_motion_and_scale(cell_type, seed):
    pts, cells = random_cells(cell_type, 20, 0.3, seed=seed)
    moved = 3.7 * pts @ rotation(seed).T + np.array([1.0, -2.0, 5.0])
    for fn in (E.corner_condition, E.scaled_jacobian, E.element_condition):
        np.testing.assert_allclose(fn(moved, cells, cell_type), fn(pts, cells, cell_type), rtol=1e-10)


@pytest.mark.parametrize("cell_type", ["wedge", "pyramid", "tetra"])
def test_corner_condition_is_fro_condition_of_target_map(cell_type):
    """kappa/3 = cond(A W^-1, 'fro')/3 with A from `CORNERS` and W from `TARGETS` (the reference route)."""
    pts, cells = random_cells(cell_type, 30, 0.3, seed=11)
    x = pts[cells]  # (N, k, 3)
    t = E.CORNERS[cell_type]
    a = np.stack([x[:, t[:, j]] - x[:, t[:, 0]] for j in (1, 2, 3)], axis=-1)  # (N, c, 3 comps, 3 cols)
    ref = np.linalg.cond(a @ np.linalg.inv(E.TARGETS[cell_type]), "fro") / 3
    np.testing.assert_allclose(E.corner_condition(pts, cells, cell_type), ref, rtol=1e-10)


@pytest.mark.parametrize("cell_type,flip", [("wedge", [3, 4, 5, 0, 1, 2]), ("pyramid", [0, 3, 2, 1, 4]),
                                            ("tetra", [0, 2, 1, 3])])
def test_inverted_cells(cell_type, flip):
    x = IDEAL[cell_type][flip]
    cells = np.arange(len(x))[None]
    assert E.inverted(x, cells, cell_type).all()
    assert np.isinf(np.asarray(E.corner_condition(x, cells, cell_type))).all()
    assert float(np.asarray(E.scaled_jacobian(x, cells, cell_type))[0]) <= 0


def test_pyramid_with_folded_base_is_inverted():
    x = IDEAL["pyramid"].copy()
    x[2, 2] = 2.0  # node 2 lifted above the apex: a base corner folds over
    assert E.inverted(x, np.arange(5)[None], "pyramid").all()


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown cell type 'prism'"):
        E.corner_condition(IDEAL["wedge"], np.arange(6)[None], "prism")
    with pytest.raises(ValueError, match=r"wedge cells must have shape \(N, 6\), got \(1, 5\)"):
        E.scaled_jacobian(IDEAL["wedge"], np.arange(5)[None], "wedge")


# ------------------------------------------------------------------------------------------------ objective
def test_mixed_objective_is_eq_3_1_on_hexahedra():
    mesh = perturb_box(3, amplitude=0.3, seed=4)
    f = float(E.mixed_objective(mesh.points, mesh))
    assert f == pytest.approx(float(q.objective(mesh.points, mesh.hexes)), rel=1e-13, abs=0)
    cohort = np.stack([mesh.points, perturb_box(3, amplitude=0.2, seed=5).points])
    np.testing.assert_allclose(E.mixed_objective(cohort, mesh), q.objective(cohort, mesh.hexes), rtol=1e-13)
    bad = mesh.points.copy()
    bad[mesh.hexes[0, 0]] = bad[mesh.hexes[0, 6]] + 1.0  # fold element 0
    assert np.isinf(float(E.mixed_objective(bad, mesh)))


def mixed_mesh() -> HexMesh:
    """Random cells of all four types, disconnected, in one mesh (with a quad block that is not measured)."""
    parts, blocks, start = [], [], 0
    for i, t in enumerate(E.ELEMENT_TYPES):
        pts, cells = random_cells(t, 7 + i, 0.25, seed=20 + i)
        parts.append(pts)
        blocks.append(CellBlock(t, cells + start))
        start += len(pts)
    blocks.append(CellBlock("quad", np.array([[0, 1, 2, 3]])))
    return HexMesh(np.concatenate(parts), tuple(blocks))


def test_mixed_objective_is_the_mean_over_all_corners():
    mesh = mixed_mesh()
    terms = [np.asarray(E.corner_condition(mesh.points, b.data, b.type)).ravel() ** 2 - 1
             for b in mesh.cells if b.type in E.ELEMENT_TYPES]
    assert sum(map(len, terms)) == 7 * 8 + 8 * 6 + 9 * 4 + 10 * 4
    f = float(E.mixed_objective(mesh.points, mesh))
    assert f == pytest.approx(np.mean(np.concatenate(terms)), rel=1e-12)
    assert float(E.mixed_objective(jnp.asarray(mesh.points), mesh)) == pytest.approx(f, rel=1e-14)


# ------------------------------------------------------------------------------------------------ report, CLI
def test_report_by_type_and_overall():
    mesh = mixed_mesh()
    r = quality_report(mesh)
    assert list(r.by_type) == ["hexahedron", "wedge", "pyramid", "tetra"]
    for t, fig in r.by_type.items():
        cells = [b.data for b in mesh.cells if b.type == t][0]
        k = np.asarray(E.corner_condition(mesh.points, cells, t))
        assert fig["count"] == len(cells) and fig["inverted"] == 0
        assert fig["max_condition"] == pytest.approx(k.max(), rel=1e-12)
        assert fig["mean_condition"] == pytest.approx(k.mean(), rel=1e-12)
        assert fig["min_scaled_jacobian"] == pytest.approx(
            np.min(E.corner_scaled_jacobian(mesh.points, cells, t)) if t == "hexahedron"
            else np.min(E.scaled_jacobian(mesh.points, cells, t)), rel=1e-12)
        assert fig["verdict_condition"] == pytest.approx(np.max(E.element_condition(mesh.points, cells, t)), rel=1e-12)
    assert r.overall["count"] == 34 and r.overall["inverted"] == 0
    assert r.overall["objective"] == pytest.approx(float(E.mixed_objective(mesh.points, mesh)), rel=1e-12)
    assert r.overall["max_condition"] == max(f["max_condition"] for f in r.by_type.values())
    # the hexahedra-only keys are unchanged
    assert r.n_elements == 7 and r.max_condition == r.by_type["hexahedron"]["max_condition"]
    assert r.objective == pytest.approx(r.by_type["hexahedron"]["objective"], rel=1e-12)
    assert r.other_cells == {"wedge": 8, "pyramid": 9, "tetra": 10, "quad": 1}


def test_report_of_a_hex_mesh_and_an_inverted_wedge():
    box = perturb_box(2, amplitude=0.2, seed=1)
    r = quality_report(box)
    assert list(r.by_type) == ["hexahedron"]
    h = r.by_type["hexahedron"]
    assert (h["max_condition"], h["mean_condition"], h["min_scaled_jacobian"]) == pytest.approx(
        (r.max_condition, r.mean_condition, r.min_scaled_jacobian), rel=1e-12)
    assert r.overall["objective"] == pytest.approx(r.objective, rel=1e-12)
    wedge = IDEAL["wedge"][[3, 4, 5, 0, 1, 2]] + 5.0
    mesh = HexMesh(np.concatenate([box.points, wedge]),
                   (box.cells[0], CellBlock("wedge", np.arange(6)[None] + box.n_nodes)))
    d = quality_report(mesh).to_dict()
    assert d["by_type"]["wedge"] == {"count": 1, "inverted": 1, "max_condition": None, "mean_condition": None,
                                     "min_scaled_jacobian": pytest.approx(-1.0), "objective": None,
                                     "verdict_condition": None}
    assert d["overall"]["inverted"] == 1 and d["overall"]["objective"] == pytest.approx(r.objective)
    json.dumps(d)


def test_cli_quality_per_type(capsys, tmp_path):
    import meshio

    mesh = mixed_mesh()
    path = tmp_path / "mixed.vtu"
    meshio.vtu.write(str(path), meshio.Mesh(mesh.points, [(b.type, b.data) for b in mesh.cells]))
    assert main(["quality", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d["by_type"]) == {"hexahedron", "wedge", "pyramid", "tetra"}
    assert {"count", "inverted", "max_condition", "mean_condition", "min_scaled_jacobian"} <= set(d["by_type"]["wedge"])
    assert d["n_elements"] == 7 and d["overall"]["count"] == 34
    assert main(["quality", str(path)]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith("    ") and
            line.split()[0] in ("hexahedron", "wedge", "pyramid", "tetra", "all")}
    assert rows["wedge"][1:3] == ["8", "0"] and rows["all"][1] == "34"
    assert float(rows["tetra"][3]) == pytest.approx(d["by_type"]["tetra"]["max_condition"], rel=1e-5)


def test_hexahedron_determinants_take_the_fast_path_with_the_kernels_numbers():
    """`corner_determinant` of hexahedra is `jaxci.cells.corner_determinants` (the determinants alone): the
    numbers of the generic kernel's invariants, bit for bit, inverted corners included; the shape is checked."""
    mesh = perturb_box(6, amplitude=0.3, seed=2)
    pts = mesh.points + np.random.default_rng(0).uniform(-0.08, 0.08, mesh.points.shape)
    fast = E.corner_determinant(pts, mesh.hexes, "hexahedron")
    ref = E.cell_corner_kernel(pts, np.ascontiguousarray(mesh.hexes.T), "hexahedron")[0]
    assert (ref <= 0).any() and fast.shape == (mesh.n_hexes, 8)
    np.testing.assert_array_equal(fast, ref)
    with pytest.raises(ValueError, match="shape"):
        E.corner_determinant(pts, mesh.hexes[:, :6], "hexahedron")
