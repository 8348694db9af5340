"""Laplacian and smart Laplacian: plain Laplace folds a concave mesh, the smart one never does."""

from __future__ import annotations

import numpy as np
import pytest

from jaxci.cells import corner_determinants
from jaxci.errors import ConfigError
from jaxci.interface.smooth import build_problem, smooth
from jaxci.mesh import hex_mesh
from jaxci.mesh.generate import box, grid_hexes, perturb_box
from jaxci.optim.laplace import edge_neighbours, run_laplace


def v_notch(nx: int = 8, ny: int = 4, nz: int = 2, depth: float = 0.8, width: float = 0.25):
    """A block whose top face has a deep V notch, meshed by vertical columns of nodes (valid, concave).

    Next to the notch's tip the neighbours of the node below it lie ABOVE the tip, so the centroid of its
    neighbours is outside the domain: the plain Laplacian folds the elements under the tip.
    """
    xs = np.linspace(0, 1, nx + 1)
    top = 1 - depth * np.maximum(0, 1 - np.abs(xs - 0.5) / width)
    k, j, i = np.meshgrid(np.arange(nz + 1), np.arange(ny + 1), np.arange(nx + 1), indexing="ij")
    pts = np.stack([xs[i], j / ny * top[i], k / nz * 0.5], axis=-1).reshape(-1, 3)
    return hex_mesh(pts, grid_hexes(nx, ny, nz))


def test_edge_neighbours_of_a_box():
    mesh = perturb_box(2, amplitude=0.0)
    nbr, mask = edge_neighbours(mesh.hexes, mesh.n_nodes)
    assert mask.sum(axis=1).tolist()[13] == 6  # the centre node: 6 edge neighbours
    assert sorted(nbr[13][mask[13]].tolist()) == [4, 10, 12, 14, 16, 22]
    assert mask.sum(axis=1)[0] == 3  # a box corner


def test_edge_neighbours_by_blocks_and_in_int32(monkeypatch):
    """The edge keys made 5 hexahedra at a time, with extra edges, and the rows asked in int32: the same
    neighbours in the same order as all at once in int64."""
    import jaxci.optim._local as local

    mesh = perturb_box(3, amplitude=0.2, seed=4)
    hexes = np.asarray(mesh.hexes)[np.random.default_rng(1).permutation(len(mesh.hexes))]
    extra = np.array([[0, 63], [5, 40]])
    whole = edge_neighbours(hexes, mesh.n_nodes, extra)
    assert whole[1][0].sum() == 4  # a box corner and its extra neighbour
    monkeypatch.setattr(local, "EDGE_CHUNK", 5)
    for dtype in (np.int64, np.int32):
        nbr, mask = edge_neighbours(hexes, mesh.n_nodes, extra, dtype=dtype)
        assert nbr.dtype == dtype
        np.testing.assert_array_equal(nbr, whole[0])
        np.testing.assert_array_equal(mask, whole[1])


def test_plain_laplace_folds_a_concave_mesh_smart_laplace_does_not():
    mesh = v_notch()
    assert not (corner_determinants(mesh.points, mesh.hexes) <= 0).any()
    pr = build_problem(mesh, dtype=np.float64, fix_boundary=True)
    x, sweeps, hist, _ = run_laplace(pr, "laplace", {})
    inverted = (corner_determinants(np.asarray(x), mesh.hexes) <= 0).any(axis=1)
    assert inverted.sum() >= 2 and np.isinf(hist["objective"][-1])
    xs, _, hs, _ = run_laplace(pr, "smart-laplace", {})
    assert not (corner_determinants(np.asarray(xs), mesh.hexes) <= 0).any()
    f = np.asarray(hs["objective"])
    assert np.all(np.isfinite(f)) and np.all(np.diff(f) <= 1e-12 * f[0])
    # through smooth(): the folded result is refused and the input comes back, with a note
    res = smooth(mesh, "laplace", dtype="float64", fix_boundary=True)
    assert res.after.inverted_elements == 0
    np.testing.assert_array_equal(res.mesh.points, mesh.points)
    assert any("newly inverted" in n for n in res.notes)


@pytest.mark.parametrize("method", [pytest.param("laplace", marks=pytest.mark.slow), "smart-laplace"])
def test_laplace_restores_a_perturbed_box(method):
    mesh = perturb_box(3, amplitude=0.3, seed=4, which="sliding")
    res = smooth(mesh, method, dtype="float64")
    assert res.after.max_condition <= 1 + 1e-6
    assert res.after.inverted_elements == 0
    assert np.asarray(res.history["max_move"])[-1] <= 1e-5
    assert len(res.history["objective"]) == res.iterations + 1


@pytest.mark.parametrize("kw,match", [(dict(max_sweeps=0), "max_sweeps"), (dict(tol=-1), "tol"),
                                      (dict(backtrack=0), "backtrack"), (dict(bogus=1), "bogus")])
def test_bad_parameters(kw, match):
    with pytest.raises(ConfigError, match=match):
        smooth(perturb_box(2, amplitude=0.1), "smart-laplace", **kw)


@pytest.mark.parametrize("method,kw", [("laplace", {}), ("smart-laplace", {}), ("lbfgs", {"presmooth": 2})])
def test_a_mesh_with_no_movable_node_is_returned_unchanged(method, kw):
    mesh = box(1)  # one hexahedron: every node is a corner
    mesh = mesh.with_points(mesh.points + np.array([[0.1, 0, 0]] + [[0, 0, 0]] * 7))
    res = smooth(mesh, method, **kw)
    np.testing.assert_array_equal(res.mesh.points, mesh.points)
    assert res.after.max_condition == pytest.approx(res.before.max_condition)
