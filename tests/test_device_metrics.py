"""The quality figures and checks measured on the device (`jaxci.metrics.device`,
`jaxci.interface.invariants.enforce_device`, `jaxci.mesh.check_volume` from the device's `volume_moments`) against the
host functions they stand for, on boxes (smooth and tangled) and real meshes, each device call under
``jax.transfer_guard("disallow")``: nothing but the explicit `jaxci.runtime.transfer` moves crosses."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest
from helpers import MESQUITE, SHARED_REASON

import jaxci
from jaxci.errors import MeshError, UsageError
from jaxci.geometry.boundary import classify_boundary
from jaxci.interface.invariants import enforce, enforce_device
from jaxci.mesh import CellBlock, HexMesh, check_volume, hex_mesh
from jaxci.mesh.generate import perturb_box
from jaxci.metrics import guard
from jaxci.metrics import objective as mixed
from jaxci.metrics.device import inverted_hexes, quality_report_device, volume_moments, worst_elements_device
from jaxci.metrics.report import quality_report, worst_elements
from jaxci.runtime import transfer

REAL = sorted(MESQUITE.glob("*.vtk")) if MESQUITE.is_dir() else []

#: Float figures agree to rounding (XLA may fuse multiply-adds where numpy/C round each product).
RTOL = 1e-12


def _box():
    return perturb_box(5, amplitude=0.3, seed=1)


def _tangled():
    return perturb_box(5, amplitude=0.9, seed=2, redraw_inverted=False)


def _real(path):
    return jaxci.read_mesh(str(path))


MESHES = [pytest.param(_box, id="box"), pytest.param(_tangled, id="tangled-box")] + [
    pytest.param(lambda p=p: _real(p), id=p.name) for p in REAL]
if not REAL:
    MESHES.append(pytest.param(None, id="real", marks=pytest.mark.skip(reason=SHARED_REASON)))


def _on_device(mesh: HexMesh, points=None):
    """The mesh's coordinates (or `points`) and transposed hexahedra, put on the device explicitly."""
    p = mesh.points if points is None else points
    return transfer.to_device(np.asarray(p, np.float64)), transfer.to_device(np.ascontiguousarray(mesh.hexes.T))


def _close(a, b):
    """Report figures equal: numbers to `RTOL`, everything else exactly."""
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _close(a[k], b[k])
    elif isinstance(a, float) and isinstance(b, float):
        assert a == pytest.approx(b, rel=RTOL, abs=1e-300), (a, b)
    else:
        assert a == b


def _same_list(dev_list, host_list):
    """Worst-element lists equal entry by entry (`_close`), but for cells whose kappa/3 tie to `RTOL` (a mesh's
    symmetric cells, whose order the last bits of each compiler's arithmetic decide): those may come in either
    order, each compared with its own entry where the other list has one."""
    assert len(dev_list) == len(host_list)
    by_index = {h["index"]: h for h in host_list}
    for d, h in zip(dev_list, host_list, strict=True):
        if d["index"] != h["index"]:
            assert d["kappa3"] == pytest.approx(h["kappa3"], rel=RTOL), (d, h)
            h = by_index.get(d["index"])
            if h is None:
                continue
        _close(d, h)


def assert_same_report(dev, host):
    for f in dataclasses.fields(host):
        _close(getattr(dev, f.name), getattr(host, f.name))


# ---------------------------------------------------------------------------------------------- quality report
@pytest.mark.parametrize("make", MESHES)
def test_report_is_the_host_report(make):
    mesh = make()
    p, c = _on_device(mesh)
    with jax.transfer_guard("disallow"):
        dev = quality_report_device(mesh, p, c)
    host = quality_report(mesh)
    assert_same_report(dev, host)
    assert dev.inverted_elements == host.inverted_elements and dev.histogram == host.histogram


def test_report_measures_in_the_unit_frame_and_moves_only_figures():
    """Coordinates in light years give the host's report (both in the unit frame); ~20 scalars come down."""
    mesh = _box()
    far = mesh.points * 9.46e15 + np.array([3e17, -1e16, 5e15])
    p, c = _on_device(mesh, far)
    before = transfer.totals()
    with jax.transfer_guard("disallow"):
        dev = quality_report_device(mesh, p, c)
    moved = transfer.totals()["d2h_bytes"] - before["d2h_bytes"]
    assert_same_report(dev, quality_report(mesh, far))
    assert dev.max_condition == pytest.approx(quality_report(mesh).max_condition, rel=1e-9)
    assert 0 < moved < 512


def test_report_refuses_what_the_host_refuses():
    mesh = _box()
    bad = np.array(mesh.points)
    bad[7] = [np.nan, 0.0, np.inf]
    p, c = _on_device(mesh, bad)
    with pytest.raises(MeshError) as host:
        quality_report(mesh, bad)
    with jax.transfer_guard("disallow"), pytest.raises(MeshError) as dev:
        quality_report_device(mesh, p, c)
    assert str(dev.value) == str(host.value)
    with pytest.raises(MeshError, match="points have shape"):
        quality_report_device(mesh, p[:-1], c)


def test_mixed_meshes_keep_the_host_functions():
    mesh = _box()
    wedge = CellBlock("wedge", np.array([[0, 1, 6, 36, 37, 42]]))
    mixed_mesh = HexMesh(mesh.points, (*mesh.cells, wedge))
    p, c = _on_device(mixed_mesh)
    with pytest.raises(UsageError, match="hexahedral meshes only"):
        quality_report_device(mixed_mesh, p, c)


# ---------------------------------------------------------------------------------------------- worst elements
@pytest.mark.parametrize("make", MESHES)
def test_worst_elements_are_the_host_list(make):
    mesh = make()
    info = classify_boundary(mesh)
    n = 12
    host_plain = worst_elements(mesh, mesh.points, n=n)
    coincident = host_plain[-1]["nodes"][:2]  # as if two nodes of a listed cell were in coincident sets
    p, c = _on_device(mesh)
    cls_dev = transfer.to_device(info.node_class)
    with jax.transfer_guard("disallow"):
        plain = worst_elements_device(mesh, p, c, n=n)
        on_dev = worst_elements_device(mesh, p, c, cls_dev, info.feature_edges, coincident, n=n)
        on_host = worst_elements_device(mesh, p, c, info.node_class, info.feature_edges, coincident, n=n)
    host = worst_elements(mesh, mesh.points, info.node_class, info.feature_edges, coincident, n=n)
    assert len(on_dev) == min(n, mesh.n_hexes)
    for dev_list, host_list in ((plain, host_plain), (on_dev, host), (on_host, host)):
        _same_list(dev_list, host_list)
    if mesh.n_hexes > 1:
        assert any(w["limits"] for w in host)  # the limits are exercised, not all empty


def test_worst_elements_ties_go_to_the_lower_index():
    """A regular grid of cubes of side 1/4 (exact in binary: every kappa/3 exactly 1 on either side): the host's
    stable sort and the device's top-k list the same cells."""
    mesh = perturb_box(4, amplitude=0.0, seed=0)
    p, c = _on_device(mesh)
    with jax.transfer_guard("disallow"):
        dev = worst_elements_device(mesh, p, c, n=5)
    assert [w["index"] for w in dev] == [w["index"] for w in worst_elements(mesh, mesh.points, n=5)]


@pytest.mark.parametrize("k", [1, 10, 37])
def test_top_k_is_a_stable_sort(k):
    """The two-stage top-k lists what the host's stable sort lists, ties (many, and infinities) by lower index."""
    from jaxci.metrics.device import top_k

    rng = np.random.default_rng(k)
    values = rng.integers(0, 40, 9000).astype(np.float64)
    values[rng.integers(0, 9000, 5)] = np.inf
    with jax.enable_x64(True):
        v = transfer.to_device(values)
        with jax.transfer_guard("disallow"):
            vals, idx = transfer.to_host(jax.jit(top_k, static_argnums=1)(v, k))
    expected = np.argsort(-values, kind="stable")[:k]
    np.testing.assert_array_equal(idx, expected)
    np.testing.assert_array_equal(vals, values[expected])


# ---------------------------------------------------------------------------------------------- validation
@pytest.mark.parametrize("make", MESHES)
def test_inverted_hexes_count_the_host_inverted_cells(make):
    mesh = make()
    p, c = _on_device(mesh)
    with jax.transfer_guard("disallow"):
        count, first = inverted_hexes(p, c)
    bad = np.flatnonzero(mixed.inverted_cells(mesh, mesh.points)["hexahedron"])
    assert count == len(bad)
    assert first == (int(bad[0]) if len(bad) else None)


def _flattened(mesh, keep: str) -> HexMesh:
    """`mesh` with its nodes moved into a plane (`keep` "plane"), onto a line or to one point, parallel to the
    axes (a tilted plane is thinner than eigh's float64 resolution of the moments, ~1e-16 of the largest, not 0:
    `check_volume` tells it from a volume on neither side)."""
    p = np.array(mesh.points)
    if keep == "plane":
        p[:, 1] = 0.375
    elif keep == "line":
        p[:, 1:] = [0.375, 0.625]
    else:
        p[:] = [0.25, 0.5, 1.0]
    return hex_mesh(p, mesh.hexes, check_coincident=False)


@pytest.mark.parametrize("keep", ["plane", "line", "point"])
def test_check_volume_raises_the_host_error(keep):
    mesh = _flattened(_box(), keep)
    p, c = _on_device(mesh)
    with pytest.raises(MeshError) as host:
        check_volume(mesh)
    with jax.transfer_guard("disallow"), pytest.raises(MeshError) as dev:
        check_volume(mesh, volume_moments(p, c))
    assert str(dev.value) == str(host.value)


@pytest.mark.parametrize("make", MESHES)
def test_check_volume_passes_a_mesh_and_reduces_on_the_device(make):
    mesh = make()
    extra = np.vstack([mesh.points, [[1e3, 1e3, 1e3]]])  # a node of no cell: not in the frame or the moments
    big = hex_mesh(extra, mesh.hexes, check_coincident=False)
    p, c = _on_device(big)
    with jax.transfer_guard("disallow"):
        check_volume(big, volume_moments(p, c))
        m, count = volume_moments(p, c)
    used = np.unique(mesh.hexes)
    from jaxci.mesh import to_unit, unit_frame

    q = to_unit(mesh.points[used], unit_frame(mesh.points[used]))
    q = q - q.mean(axis=0)
    assert count == len(used)
    np.testing.assert_allclose(m, q.T @ q, rtol=1e-12, atol=1e-14 * np.abs(m).max())


# ---------------------------------------------------------------------------------------------- final checks
@pytest.fixture(scope="module")
def smoothed():
    """A perturbed 4^3 box with its boundary fixed, and results to check against it: its L-BFGS result
    (``good``); that result with one interior node pushed so that a cell ends worse than the input's worst cell,
    F still lower than the input's (``bad``, `tests/test_guard.py`'s case); pushed further, inverting cells
    (``inverted``); the input with every node shaken (``worse``: F rises); and the default pipeline's result, whose
    polish trades a little F for a lower worst cell than ``good``'s (``polished``)."""
    mesh = perturb_box(4, 4, 4, amplitude=0.3, seed=4)
    res = jaxci.smooth(mesh, "lbfgs", dtype="float64", fix_boundary=True)
    good = np.array(res.mesh.points)
    node = int(np.flatnonzero(res.node_class == 0)[0])
    bad = good.copy()
    w0 = guard.worst(mesh, mesh.points)
    direction = np.array([1.0, 0.7, 0.4]) / np.linalg.norm([1.0, 0.7, 0.4])
    for step in np.linspace(0.01, 0.24, 47):
        bad[node] = good[node] + step * direction
        if guard.worst(mesh, bad) > w0:
            break
    inverted = good.copy()
    inverted[node] += 0.6 * direction  # past its neighbours (spacing 0.25)
    rng = np.random.default_rng(0)
    worse = np.asarray(mesh.points) + rng.normal(scale=0.02, size=mesh.points.shape)
    polished = np.array(jaxci.smooth(mesh, dtype="float64", fix_boundary=True).mesh.points)
    return mesh, {"good": good, "bad": bad, "inverted": inverted, "worse": worse, "polished": polished}


def _both(mesh, start, x, **kw):
    """`enforce` (host, already projected) and `enforce_device` (under the transfer guard) of one case."""
    host_x, host_notes = enforce(mesh, None, start, x, projected=True, **kw)
    s, d = _on_device(mesh, start)
    xd = transfer.to_device(np.asarray(x, np.float64))
    c = transfer.to_device(np.ascontiguousarray(mesh.hexes.T))
    with jax.transfer_guard("disallow"):
        y, notes = enforce_device(mesh, c, s, xd, **kw)
    return host_x, host_notes, transfer.to_host(y), notes


CHECKS = [
    {}, {"keep_worst": True}, {"keep_worst": True, "worst_start": "report"}, {"power": 4.0},
    {"keep_worst": True, "worst_first": True}, {"untangled": True, "worst_first": True},
]


@pytest.mark.parametrize("which", ["good", "bad", "inverted", "worse", "polished"])
@pytest.mark.parametrize("kw", CHECKS, ids=lambda k: ",".join(k) or "plain")
def test_enforce_device_decides_as_enforce(smoothed, which, kw):
    mesh, results = smoothed
    kw = dict(kw)
    if kw.get("worst_start") == "report":
        kw["worst_start"] = quality_report(mesh).max_condition
    host_x, host_notes, dev_x, notes = _both(mesh, mesh.points, results[which], **kw)
    assert notes == host_notes
    np.testing.assert_array_equal(dev_x, host_x)


@pytest.mark.parametrize("make", MESHES)
def test_enforce_device_on_meshes(make):
    """Real meshes and boxes, valid and tangled: the result of a small shake (F up or down, a cell worse or not)
    and of a larger one, with the guard and the worst-first order, checked as on the host."""
    mesh = make()
    rng = np.random.default_rng(3)
    h = float(np.ptp(mesh.points, axis=0).max()) / max(mesh.n_hexes, 1) ** (1 / 3)  # a typical edge
    for scale in (1e-3, 0.05):
        x = mesh.points + rng.normal(scale=scale * h, size=mesh.points.shape)
        for kw in ({}, {"keep_worst": True, "worst_first": True}):
            host_x, host_notes, dev_x, notes = _both(mesh, mesh.points, x, **kw)
            assert notes == host_notes
            np.testing.assert_array_equal(dev_x, host_x)


def test_enforce_device_exercises_every_decision(smoothed):
    """The cases above reach every outcome: kept, put back, refused for an inverted cell, refused for a rise."""
    mesh, r = smoothed
    _, n_good, _, _ = _both(mesh, mesh.points, r["good"], keep_worst=True)
    _, n_bad, _, _ = _both(mesh, mesh.points, r["bad"], keep_worst=True)
    _, n_inv, _, _ = _both(mesh, mesh.points, r["inverted"])
    _, n_worse, _, _ = _both(mesh, mesh.points, r["worse"])
    assert n_good == []
    assert n_bad and n_bad[0].startswith("worst cell kept no worse")
    assert n_inv[0].startswith("the result had newly inverted elements (")
    assert "the objective rose" in n_worse[0]


@pytest.mark.parametrize("worst_first", [True, False])
def test_enforce_device_keeps_a_lower_worst_element(smoothed, worst_first):
    """Worst first: from the L-BFGS result, the polished one has a higher F and a lower worst cell: kept with the
    note where the order is worst first, else refused, as on the host."""
    mesh, r = smoothed
    host_x, host_notes, dev_x, notes = _both(mesh, r["good"], r["polished"], worst_first=worst_first)
    assert notes == host_notes
    np.testing.assert_array_equal(dev_x, host_x)
    assert ("kept, the worst element first" in notes[0]) == worst_first


def test_enforce_device_projects_with_the_given_function(smoothed):
    mesh, r = smoothed
    calls = []

    def project(x):
        calls.append(x.shape)
        return x

    s, _ = _on_device(mesh)
    c = transfer.to_device(np.ascontiguousarray(mesh.hexes.T))
    x = transfer.to_device(r["good"])
    with jax.transfer_guard("disallow"):
        y, notes = enforce_device(mesh, c, s, x, project=project)
    assert calls == [(mesh.n_nodes, 3)] and notes == []
    assert math.isclose(float(transfer.to_host(y)[0, 0]), float(r["good"][0, 0]))


def test_bench_device_metrics_measures_every_pair(tmp_path, monkeypatch):
    """scripts/bench_device_metrics.py on a 2^3 box: a row per device function, its host function beside it."""
    import json
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import bench_device_metrics

    out = tmp_path / "dm.json"
    assert bench_device_metrics.main(["--n", "2", "--repeats", "1", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["hexes"] == 8 and set(data["rows"]) == {"quality_report", "worst_elements", "inverted_cells",
                                                         "check_volume", "enforce", "enforce_guarded"}
    for row in data["rows"].values():
        assert row["compile_s"] >= 0 and row["call_s"] > 0 and row["host_s"] > 0 and 0 < row["device_s"]
    assert data["commit"] and data["date"]
