"""Quality kernels against VTK/Verdict (an external truth), the mesquite README figures, and properties."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import MESQUITE, MESQUITE_FIGURES, random_valid_hexes, read_vtk_hexes, unit_cube
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxci.mesh import hex_mesh
from jaxci.mesh.generate import box, perturb_box
from jaxci.metrics import hexahedron as q
from jaxci.metrics.report import quality_report

vtk = pytest.importorskip("vtk")
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy  # noqa: E402


def vtk_quality(points: np.ndarray, hexes: np.ndarray, measure: str) -> np.ndarray:
    """Per-element VTK vtkMeshQuality values (Verdict) for an unstructured grid of hexahedra."""
    grid = vtk.vtkUnstructuredGrid()
    pts = vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    grid.SetPoints(pts)
    for h in hexes:
        ids = vtk.vtkIdList()
        for v in h:
            ids.InsertNextId(int(v))
        grid.InsertNextCell(vtk.VTK_HEXAHEDRON, ids)
    mq = vtk.vtkMeshQuality()
    mq.SetInputData(grid)
    getattr(mq, f"SetHexQualityMeasureTo{measure}")()
    mq.Update()
    return vtk_to_numpy(mq.GetOutput().GetCellData().GetArray("Quality")).copy()


def assert_rel(ours, ref, rtol=1e-6):
    ours, ref = np.asarray(ours), np.asarray(ref)
    np.testing.assert_allclose(ours, ref, rtol=rtol, atol=0)


@pytest.fixture(scope="module")
def random_hex_mesh():
    rng = np.random.default_rng(42)
    h = random_valid_hexes(rng, 200, amplitude=0.3)
    return h.reshape(-1, 3), np.arange(len(h) * 8).reshape(-1, 8)


@pytest.mark.parametrize("measure,fn", [
    ("Condition", q.element_condition),
    ("MaxAspectFrobenius", q.element_condition),
    ("MedAspectFrobenius", lambda pts, hexes: q.corner_condition(pts, hexes).mean(axis=-1)),
    ("ScaledJacobian", q.element_scaled_jacobian),
])
def test_random_hexes_match_vtk(random_hex_mesh, measure, fn):
    pts, hexes = random_hex_mesh
    assert_rel(fn(pts, hexes), vtk_quality(pts, hexes, measure))


@pytest.mark.shared
@pytest.mark.parametrize("name", sorted(MESQUITE_FIGURES))
def test_mesquite_meshes_match_vtk(name):
    pts, hexes = read_vtk_hexes(MESQUITE / name)
    cond = np.asarray(q.element_condition(pts, hexes))
    ref = vtk_quality(pts, hexes, "Condition")
    valid = np.isfinite(cond)
    assert_rel(cond[valid], ref[valid])
    assert np.all(ref[~valid] >= 1e29)  # Verdict's 1e30 for an element with an inverted corner
    assert_rel(np.asarray(q.corner_condition(pts, hexes).mean(axis=-1))[valid],
               vtk_quality(pts, hexes, "MedAspectFrobenius")[valid])
    np.testing.assert_allclose(q.element_scaled_jacobian(pts, hexes), vtk_quality(pts, hexes, "ScaledJacobian"),
                               rtol=1e-6, atol=1e-12)
    # where the corners decide it, the min corner scaled Jacobian is VTK's value
    corner_min = np.asarray(q.corner_scaled_jacobian(pts, hexes)).min(axis=1)
    decided = corner_min <= np.asarray(q.element_scaled_jacobian(pts, hexes))
    np.testing.assert_allclose(corner_min[decided], vtk_quality(pts, hexes, "ScaledJacobian")[decided],
                               rtol=1e-6, atol=1e-12)


@pytest.mark.shared
@pytest.mark.parametrize("name", sorted(MESQUITE_FIGURES))
def test_mesquite_readme_figures(name):
    n_hex, n_nodes, inv_c, inv_e, kmax, F, sj = MESQUITE_FIGURES[name]
    pts, hexes = read_vtk_hexes(MESQUITE / name)
    r = quality_report(hex_mesh(pts, hexes))
    assert (r.n_elements, r.n_nodes, r.inverted_corners, r.inverted_elements) == (n_hex, n_nodes, inv_c, inv_e)
    if kmax is not None:
        assert r.max_condition == pytest.approx(kmax, abs=1e-3)
        assert r.objective == pytest.approx(F, abs=1e-5 if F < 1 else 1e-3)
    if sj is not None:
        assert r.min_scaled_jacobian == pytest.approx(sj, abs=1e-3)
    assert sum(b[2] for b in r.histogram) == 8 * n_hex - inv_c


@pytest.mark.shared
def test_tangled_objective_with_signed_kappa():
    """The README's F = 79.82 for hex_5_tangled counts inverted corners with their (negative) kappa."""
    pts, hexes = read_vtk_hexes(MESQUITE / "hex_5_tangled.vtk")
    a = np.asarray(q.corner_matrices(pts, hexes))
    det = np.linalg.det(a)
    signed = np.linalg.cond(a, "fro") * np.sign(det) / 3
    assert np.mean(signed**2) - 1 == pytest.approx(79.82, abs=0.01)
    assert np.isinf(q.objective(pts, hexes))  # the optimizers' objective is a barrier


def test_unit_cube_is_ideal():
    pts, hexes = unit_cube(), np.arange(8)[None]
    np.testing.assert_allclose(q.corner_condition(pts, hexes), 1.0, rtol=1e-14)
    assert float(q.objective(pts, hexes)) == pytest.approx(0.0, abs=1e-14)
    np.testing.assert_allclose(q.corner_scaled_jacobian(pts, hexes), 1.0)
    np.testing.assert_allclose(q.corner_condition(pts, hexes, "2-norm"), 1.0, rtol=1e-12)


def test_structured_box_is_ideal_and_histogram():
    m = box(4, 3, 2, size=(4.0, 3.0, 2.0))
    r = quality_report(m)
    assert r.max_condition == pytest.approx(1.0) and r.objective == pytest.approx(0.0, abs=1e-14)
    assert r.histogram[0][2] == 8 * 24 and r.inverted_corners == 0


def test_inverted_corner_is_reported_not_averaged():
    pts, hexes = unit_cube(), np.arange(8)[None]
    bad = pts.copy()
    bad[6] = [0.2, 0.2, 0.2]  # pulled through the element: corner 6 inverted
    assert np.isinf(np.asarray(q.corner_condition(bad, hexes))).any()
    assert np.isinf(q.objective(bad, hexes))
    r = quality_report(hex_mesh(bad, hexes))
    assert r.inverted_elements == 1 and r.inverted_corners >= 1
    assert r.max_condition is None and r.mean_condition is None  # no valid element
    assert r.objective is not None and np.isfinite(r.objective)  # over the valid corners only


def _rotation(rng):
    qm, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return qm * np.sign(np.linalg.det(qm))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.01, 100.0))
def test_kappa_invariant_under_rigid_motion_and_scaling(seed, scale):
    rng = np.random.default_rng(seed)
    h = random_valid_hexes(rng, 5)
    pts, hexes = h.reshape(-1, 3), np.arange(40).reshape(5, 8)
    k0 = np.asarray(q.corner_condition(pts, hexes))
    moved = scale * pts @ _rotation(rng).T + rng.normal(size=3) * 10
    np.testing.assert_allclose(q.corner_condition(moved, hexes), k0, rtol=1e-9)
    assert (k0 >= 1 - 1e-12).all()


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_closed_form_equals_jnp_linalg_cond(seed):
    rng = np.random.default_rng(seed)
    h = random_valid_hexes(rng, 10, amplitude=0.35)
    pts, hexes = h.reshape(-1, 3), np.arange(80).reshape(10, 8)
    np.testing.assert_allclose(q.corner_condition(pts, hexes), q.corner_condition(pts, hexes, "frobenius-cond"),
                               rtol=1e-10)
    a = np.asarray(q.corner_matrices(pts, hexes))
    np.testing.assert_allclose(q.corner_condition(pts, hexes, "2-norm"), np.linalg.cond(a), rtol=1e-8)
    np.testing.assert_allclose(q.corner_determinant(pts, hexes), np.linalg.det(a), rtol=1e-10, atol=1e-14)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 10**6), st.integers(1, 6))
def test_batched_equals_separate_calls(seed, c):
    base = perturb_box(3, amplitude=0.3, seed=seed)
    rng = np.random.default_rng(seed)
    cands = base.points[None] + rng.uniform(-0.02, 0.02, size=(c, base.n_nodes, 3))
    hexes = base.hexes
    batched = np.asarray(q.objective(cands, hexes))
    assert batched.shape == (c,)
    for i in range(c):
        assert batched[i] == pytest.approx(float(q.objective(cands[i], hexes)), rel=1e-13)
        np.testing.assert_allclose(np.asarray(q.corner_condition(cands, hexes))[i],
                                   np.asarray(q.corner_condition(cands[i], hexes)), rtol=1e-13)


def test_objective_matches_definition():
    m = perturb_box(4, amplitude=0.3, seed=3)
    k = np.asarray(q.corner_condition(m.points, m.hexes, "frobenius-cond"))
    assert float(q.objective(m.points, m.hexes)) == pytest.approx(np.mean(k**2) - 1, rel=1e-10)


def test_float32_path_close_to_float64():
    m = perturb_box(5, amplitude=0.3, seed=1)
    f64 = float(q.objective(m.points, m.hexes))
    f32 = q.objective(np.asarray(m.points, np.float32), m.hexes)
    assert f32.dtype == np.float32 and float(f32) == pytest.approx(f64, rel=1e-5)


def test_unknown_metric():
    with pytest.raises(ValueError, match="unknown condition metric"):
        q.corner_condition(unit_cube(), np.arange(8)[None], "spectral")


@pytest.mark.parametrize("chunk", [1, 7, 64])
def test_report_in_blocks_equals_one_block(monkeypatch, chunk):
    """`quality_report` adds up its figures block by block (`REPORT_CHUNK`; 7 and 64 do not divide 125): the
    same report as one block, with inverted corners and a mixed mesh (a wedge added) too; and `worst_elements`,
    which finds each cell's worst corner in the same blocks, the same list."""
    import meshio

    from jaxci.metrics import report as R

    mesh = perturb_box(5, amplitude=0.3, seed=3)
    bad = mesh.points.copy()
    bad[mesh.hexes[40, 6]] = bad[mesh.hexes[40, 0]]  # a degenerate node: inverted corners in several hexahedra
    cells = [meshio.CellBlock("hexahedron", mesh.hexes), meshio.CellBlock("wedge", mesh.hexes[:2, [0, 1, 2, 4, 5, 6]])]
    mixed = R.as_hex_mesh(meshio.Mesh(mesh.points, cells), "test")
    for m, pts in ((mesh, None), (mesh, bad), (mixed, None)):
        monkeypatch.setattr(R, "REPORT_CHUNK", 10**9)
        whole = quality_report(m, pts).to_dict()
        listed = R.worst_elements(m, m.points if pts is None else pts)
        monkeypatch.setattr(R, "REPORT_CHUNK", chunk)
        blocks = quality_report(m, pts).to_dict()
        assert R.worst_elements(m, m.points if pts is None else pts) == listed  # (also in blocks)
        assert blocks.keys() == whole.keys()
        for k, v in whole.items():
            if isinstance(v, float):
                assert blocks[k] == pytest.approx(v, rel=1e-12), k
            elif isinstance(v, dict) and k in ("overall",):
                for kk, vv in v.items():
                    assert blocks[k][kk] == pytest.approx(vv, rel=1e-12), (k, kk)
            elif k == "by_type":
                for t in v:
                    for kk, vv in v[t].items():
                        assert blocks[k][t][kk] == pytest.approx(vv, rel=1e-12), (k, t, kk)
            else:
                assert blocks[k] == v, k
