"""The worst-element polish on a window of a device mesh (jaxci.optim.polish_window): what comes down is the
window, the polish decides as on the whole mesh, and its result goes back to the device."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxci.geometry.boundary import classify_boundary
from jaxci.geometry.projection import build_constraints
from jaxci.interface.smooth import smooth
from jaxci.mesh.shapes import bevelled_box
from jaxci.metrics.guard import cell_worst
from jaxci.optim.parametrisation import make_parametrisation
from jaxci.optim.polish import PolishParams, Rest, polish
from jaxci.optim.polish_window import put_back, window
from jaxci.runtime.transfer import to_device, to_host, totals


def _setup(mesh, x, fix_boundary=False):
    info = classify_boundary(mesh, fix_boundary=fix_boundary)
    host = build_constraints(mesh, info, dtype=np.float64, device=False)
    hpar = make_parametrisation(mesh, info, host, x, dtype=np.float64)
    with jax.enable_x64(True):
        cons = build_constraints(mesh, info, dtype=np.float64, device=True)
        par = make_parametrisation(mesh, info, cons, x, dtype=np.float64)
    return host, hpar, cons, par


@pytest.fixture(scope="module")
def smoothed():
    mesh = bevelled_box(10)  # curved sliding walls: surface, edge and corner nodes; the polish keeps rounds
    x = np.array(smooth(mesh, "lbfgs", engine="host").mesh.points)
    return mesh, x


@pytest.mark.parametrize("mean_steps", [0, 25])
def test_a_whole_mesh_window_polishes_as_the_host(smoothed, mean_steps):
    """The window of every cell polishes as the host does, its mean phase (`PolishParams.mean_steps`) included."""
    mesh, x = smoothed
    host, hpar, cons, par = _setup(mesh, x)
    y_host, rep_host = polish(mesh, host, hpar, x, PolishParams(mean_steps=mean_steps))
    assert rep_host["kept"] >= 1 and (rep_host["mean_phase"] is None) == (mean_steps == 0)
    with jax.enable_x64(True), jax.transfer_guard("disallow"):
        xd, conn = to_device(x), to_device(np.ascontiguousarray(mesh.hexes.T, np.int32))
        win = window(xd, conn, cons, par, host, k=mesh.n_hexes)
        assert win.rest == Rest() and len(win.nodes) == mesh.n_nodes
        y, rep = polish(None, win.cons, win.par, win.x, PolishParams(mean_steps=mean_steps), win.blocks, win.rest)
        out = to_host(put_back(xd, win, y))
    assert rep["worst"] == rep_host["worst"] and rep["kept"] == rep_host["kept"]
    assert rep["mean_phase"] == rep_host["mean_phase"]
    np.testing.assert_allclose(out, y_host, rtol=0, atol=1e-12)


def test_a_small_window_moves_only_its_worst_cells_nodes(smoothed):
    mesh, x = smoothed
    host, hpar, cons, par = _setup(mesh, x)
    k = 8
    worst = cell_worst(mesh, x)["hexahedron"]
    top = np.argsort(-worst, kind="stable")[:k]
    with jax.enable_x64(True), jax.transfer_guard("disallow"):
        xd, conn = to_device(x), to_device(np.ascontiguousarray(mesh.hexes.T, np.int32))
        before = totals()
        win = window(xd, conn, cons, par, host, k=k)
        down = totals()["d2h_bytes"] - before["d2h_bytes"]
        y, rep = polish(None, win.cons, win.par, win.x, PolishParams(), win.blocks, win.rest)
        out = to_host(put_back(xd, win, y))
    # the window: the worst cells and the cells around their nodes; the rest as sums
    ring = np.isin(mesh.hexes, mesh.hexes[top]).any(axis=1)
    assert len(win.blocks["hexahedron"]) == ring.sum() and win.rest.n_cells == (~ring).sum()
    assert win.rest.k_max == pytest.approx(worst[~ring].max(), rel=1e-12)
    assert win.rest.k_sum == pytest.approx(worst[~ring].sum(), rel=1e-12)
    assert down < 0.25 * (x.nbytes + mesh.hexes.nbytes)  # a window, not the mesh
    moved = np.flatnonzero((out != x).any(axis=1))
    assert len(moved) and np.isin(moved, mesh.hexes[top]).all()
    # the polish's figures are the whole mesh's
    w1 = cell_worst(mesh, out)["hexahedron"]
    assert rep["worst"][1] == pytest.approx(w1.max(), rel=1e-12)
    assert rep["mean"][1] == pytest.approx(w1.mean(), rel=1e-12)
    assert rep["worst"][0] == pytest.approx(worst.max(), rel=1e-12) and w1.max() < worst.max()
    # boundary nodes stayed on the boundary (their own patch or curve)
    from jaxci.geometry.projection import project_np

    np.testing.assert_allclose(project_np(host, out), out, atol=1e-12)


def test_a_window_of_a_mesh_without_flat_regions_polishes_as_the_host():
    """The boundary held fixed: the run has no flat region (nothing to gather its rows from), and the window's
    polish, its mean phase included, is the host's (it failed to compile a gather from no rows)."""
    mesh = bevelled_box(6)
    x = np.array(smooth(mesh, "lbfgs", engine="host", fix_boundary=True).mesh.points)
    host, hpar, cons, par = _setup(mesh, x, fix_boundary=True)
    assert par.flat_origin.shape[0] == 0
    y_host, rep_host = polish(mesh, host, hpar, x, PolishParams(mean_steps=25))
    with jax.enable_x64(True), jax.transfer_guard("disallow"):
        xd, conn = to_device(x), to_device(np.ascontiguousarray(mesh.hexes.T, np.int32))
        win = window(xd, conn, cons, par, host, k=mesh.n_hexes)
        y, rep = polish(None, win.cons, win.par, win.x, PolishParams(mean_steps=25), win.blocks, win.rest)
        out = to_host(put_back(xd, win, y))
    assert rep["worst"] == rep_host["worst"] and rep["kept"] == rep_host["kept"]
    assert rep["mean_phase"] == rep_host["mean_phase"]
    np.testing.assert_allclose(out, y_host, rtol=0, atol=1e-12)
