"""A smoothing run on the JAX engine keeps its mesh on the device from upload to download
(`jaxci.interface.device_run`): no implicit transfer between host and device, the traffic and host time counted per
phase, the guarantees of `jaxci.smooth` kept, and the same mesh as the run whose stages run on the host."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import MESQUITE, no_implicit_transfers

import jaxci
from jaxci.geometry.boundary import classify_boundary
from jaxci.geometry.projection import build_constraints, project_np
from jaxci.interface import device_run
from jaxci.mesh.generate import perturb_box
from jaxci.metrics.guard import cell_worst


@pytest.fixture(autouse=True)
def _small_meshes_on_the_device(monkeypatch):
    """The run on the device from any size here (`device_run.DEVICE_RUN_FROM`: the suite's meshes are small)."""
    monkeypatch.setattr(device_run, "DEVICE_RUN_FROM", 0)


#: The phases of a run on the device, in order.
DEVICE_PHASES = ["validate", "upload", "report", "setup", "smooth", "checks", "download"]


def _on_the_boundary(mesh, points) -> None:
    """Every boundary node of `points` on the original boundary of `mesh` (its own patch or curve)."""
    cons = build_constraints(mesh, classify_boundary(mesh), dtype=np.float64, device=False)
    np.testing.assert_allclose(project_np(cons, points), points, rtol=0, atol=1e-12)


def _general(mesh, **kw):
    """The same run with its stages on the host (jaxci.smooth's general path)."""
    applies = device_run.applies
    device_run.applies = lambda *a: False
    try:
        return jaxci.smooth(mesh, engine="jax", **kw)
    finally:
        device_run.applies = applies


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_a_box_is_smoothed_on_the_device_without_implicit_transfers(dtype):
    mesh = perturb_box(6, amplitude=0.3, seed=2)  # sliding walls: surface, edge and corner nodes
    jaxci.smooth(mesh, engine="jax", dtype=dtype)  # compiled (the guard allows no constant in a compilation)
    with no_implicit_transfers():
        res = jaxci.smooth(mesh, engine="jax", dtype=dtype)
    assert [k for k in res.phases if k != "total"] == DEVICE_PHASES
    ph = res.phases
    assert ph["upload"]["h2d_bytes"] >= mesh.points.nbytes + 4 * mesh.hexes.size
    assert ph["download"]["d2h_bytes"] == mesh.points.nbytes
    assert all(ph[k]["host_s"] >= 0 for k in DEVICE_PHASES) and ph["smooth"]["device_s"] > 0
    assert res.after.inverted_elements == 0 and res.after.max_condition < 1.001
    assert res.after.max_condition <= res.before.max_condition
    _on_the_boundary(mesh, res.mesh.points)
    ref = _general(mesh, dtype=dtype)  # its presmoothing colours the nodes otherwise: not the same mesh
    assert "upload" not in ref.phases
    assert res.after.max_condition == pytest.approx(ref.after.max_condition, abs=1e-4)


def test_the_same_mesh_as_the_general_path():
    """Without the presmoothing (whose colouring differs: greedy on the host, parallel on the device) the run on
    the device is the general path's run: the same L-BFGS iterates, the same polish, the same checks. (The default
    pipeline's solver differs: the general path's is truncated Newton with the two-level preconditioner, built on
    the host, the device's L-BFGS.)"""
    mesh = perturb_box(5, amplitude=0.35, seed=3)
    res = jaxci.smooth(mesh, engine="jax", dtype="float64", presmooth=0)
    assert res.params["solver"] == "lbfgs" and _general(mesh, dtype="float64", presmooth=0).params["solver"] == "newton"
    ref = _general(mesh, dtype="float64", presmooth=0, solver="lbfgs")
    assert "upload" in res.phases and "upload" not in ref.phases
    assert res.iterations == ref.iterations
    assert res.after.objective == pytest.approx(ref.after.objective, rel=1e-9)
    np.testing.assert_allclose(res.mesh.points, ref.mesh.points, rtol=0, atol=1e-9)


def test_truncated_newton_runs_on_the_device():
    """``solver="newton"`` in the run on the device (`jaxci.optim.newton.newton_loop`): no implicit transfer, the
    same mesh as the general path's Newton without the two-level preconditioner (built on the host from the mesh
    there: not in the run on the device, which refuses ``precondition="coarse"``)."""
    mesh = perturb_box(5, amplitude=0.35, seed=3)
    kw = dict(engine="jax", dtype="float64", presmooth=0, method="lbfgs", solver="newton")
    jaxci.smooth(mesh, **kw)
    with no_implicit_transfers():
        res = jaxci.smooth(mesh, **kw)
    with pytest.raises(jaxci.ConfigError, match="in a run on the device"):
        jaxci.smooth(mesh, precondition="coarse", **kw)
    ref = _general(mesh, precondition="none", **{k: v for k, v in kw.items() if k != "engine"})
    assert "upload" in res.phases and res.history["newton_iterations"] > 0
    assert res.iterations == ref.iterations and res.after.inverted_elements == 0
    np.testing.assert_allclose(res.mesh.points, ref.mesh.points, rtol=0, atol=1e-9)


@pytest.mark.shared
def test_a_real_mesh_with_a_sliding_boundary_is_smoothed_on_the_device():
    mesh = jaxci.read_mesh(MESQUITE / "1000hex-block-internal-bias.vtk")
    jaxci.smooth(mesh, engine="jax")
    with no_implicit_transfers():
        res = jaxci.smooth(mesh, engine="jax")
    assert "upload" in res.phases
    ref = _general(mesh)
    for r in (res, ref):
        assert r.after.inverted_elements == 0
    w = cell_worst(mesh, res.mesh.points)["hexahedron"]
    assert res.after.max_condition == pytest.approx(w.max(), rel=1e-12)
    # both reach the optimum (the bias taken out: every corner within 1e-6 of an ideal one), each by its
    # presmoothing's colouring
    assert res.after.max_condition <= ref.after.max_condition + 1e-5 and res.after.max_condition < 1 + 1e-5
    assert res.after.objective <= ref.after.objective + 1e-6
    assert res.boundary == ref.boundary
    _on_the_boundary(mesh, res.mesh.points)
    fixed = res.node_class == 3
    np.testing.assert_array_equal(res.mesh.points[fixed], mesh.points[fixed])  # corners, bit for bit


def test_other_runs_take_the_general_path():
    """Tangled input, other methods, coincident nodes, the host engine, a mesh under `DEVICE_RUN_FROM`
    hexahedra: no upload phase."""
    box = perturb_box(3, amplitude=0.2, seed=1)
    tangled = box.with_points(box.points * np.where(np.arange(box.n_nodes) == 21, -1.0, 1.0)[:, None])
    assert tangled.inverted_hexes
    for mesh, kw in ((tangled, {"engine": "jax"}), (box, {"engine": "jax", "method": "smart-laplace"}),
                     (box, {"engine": "host"})):
        res = jaxci.smooth(mesh, **kw)
        assert "upload" not in res.phases, kw
        if res.plan.engine == "jax":
            plan = res.plan
    with pytest.MonkeyPatch.context() as mp:
        for threshold, applies in ((box.n_hexes + 1, False), (box.n_hexes, True)):
            mp.setattr(device_run, "DEVICE_RUN_FROM", threshold)
            assert device_run.applies(box, "lbfgs", plan, None, 0, False, "auto") is applies
