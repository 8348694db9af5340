"""Inverted cells that no allowed move can fix are reported at once (`jaxci.optim.feasibility`)."""

from __future__ import annotations

import time

import numpy as np
import pytest

import jaxci
from jaxci.errors import InvertedMeshError
from jaxci.geometry.boundary import classify_boundary
from jaxci.mesh.generate import box
from jaxci.optim.feasibility import stuck_cells


def _tangled_box():
    """A 3^3 box whose centre-most interior node is pushed through a face of its cells (some inverted)."""
    mesh = box(3, 3, 3)
    pts = np.array(mesh.points)
    node = int(np.argmin(np.linalg.norm(pts - [1 / 3, 1 / 3, 1 / 3], axis=1)))
    pts[node] += [0.45, 0.45, 0.45]
    return jaxci.hex_mesh(pts, mesh.hexes), node


def test_free_interior_node_is_not_stuck_and_untangles():
    mesh, node = _tangled_box()
    info = classify_boundary(mesh, fix_boundary=True)
    assert jaxci.quality_report(mesh).inverted_elements > 0
    assert stuck_cells(mesh, info) == {}
    res = jaxci.smooth(mesh, "lbfgs", fix_boundary=True)
    assert res.after.inverted_elements == 0


def test_fixed_nodes_make_it_stuck_and_it_is_said_at_once():
    mesh, node = _tangled_box()
    everything = np.arange(mesh.n_nodes)  # the 8 interior nodes too
    info = classify_boundary(mesh, fix_boundary=True, fixed_nodes=everything)
    stuck = stuck_cells(mesh, info)
    assert set(stuck) == {"hexahedron"}
    inverted = np.flatnonzero(jaxci.metrics.elements.inverted(mesh.points, mesh.hexes, "hexahedron"))
    np.testing.assert_array_equal(stuck["hexahedron"], inverted)  # every node is fixed
    t0 = time.perf_counter()
    with pytest.raises(InvertedMeshError, match=r"inverted elements cannot be untangled: .*four nodes are all fixed"):
        jaxci.smooth(mesh, "lbfgs", fix_boundary=True, fixed_nodes=everything)
    assert time.perf_counter() - t0 < 5  # no untangling rounds (it used to run 60 rounds, minutes)


def test_single_inverted_hexahedron_is_stuck():
    mesh = box(1, 1, 1)
    pts = np.array(mesh.points)
    pts[0] = [0.8, 0.8, 0.8]  # through the opposite corner: inverted, and every node of one hexahedron is a corner
    mesh = jaxci.hex_mesh(pts, mesh.hexes)
    with pytest.raises(InvertedMeshError, match=r"1 inverted element cannot be untangled.*\(element 0\)"):
        jaxci.smooth(mesh, fix_boundary=True)


def _two_tangles():
    """A 4^3 box with two interior nodes pushed through their cells: around node `a` every node is fixed (those
    cells can never be valid), around node `b` the nodes are free."""
    mesh = box(4, 4, 4)
    pts = np.array(mesh.points)
    a = int(np.argmin(np.linalg.norm(pts - [0.25, 0.25, 0.25], axis=1)))
    b = int(np.argmin(np.linalg.norm(pts - [0.75, 0.75, 0.75], axis=1)))
    pts[a] += [0.2, 0.2, 0.2]
    pts[b] -= [0.2, 0.2, 0.2]
    mesh = jaxci.hex_mesh(pts, mesh.hexes)
    around_a = np.unique(mesh.hexes[(mesh.hexes == a).any(axis=1)])
    return mesh, a, b, around_a


def test_partial_untangling_returns_what_could_be_untangled():
    mesh, a, b, fixed = _two_tangles()
    inverted0 = jaxci.metrics.elements.inverted(mesh.points, mesh.hexes, "hexahedron")
    near_b = (mesh.hexes == b).any(axis=1)
    assert inverted0[near_b].any() and inverted0[~near_b].any()
    with pytest.raises(InvertedMeshError, match="cannot be untangled"):  # the default: refused at once
        jaxci.smooth(mesh, fixed_nodes=fixed)
    res = jaxci.smooth(mesh, fixed_nodes=fixed, untangle="partial")
    after = jaxci.metrics.elements.inverted(res.mesh.points, mesh.hexes, "hexahedron")
    assert not after[near_b].any()  # the free tangle is untangled ...
    assert after.sum() == res.after.inverted_elements > 0  # ... the stuck one is left, and counted
    np.testing.assert_array_equal(res.mesh.points[fixed], mesh.points[fixed])
    assert any("partial untangling" in n and f"{int(after.sum())} left inverted" in n for n in res.notes)


def test_partial_untangling_through_the_cli_exits_3(tmp_path):
    import subprocess
    import sys

    from jaxci.io import write_mesh

    mesh, a, b, fixed = _two_tangles()
    mesh = jaxci.hex_mesh(mesh.points, mesh.hexes, point_sets={"stuck": fixed})
    write_mesh(mesh, str(tmp_path / "in.vtu"))
    out = tmp_path / "out.vtu"
    cmd = [sys.executable, "-m", "jaxci", "smooth", str(tmp_path / "in.vtu"), str(out), "--fixed-set", "stuck",
           "--untangle", "partial", "-v"]
    p = subprocess.run(cmd, capture_output=True, text=True)
    assert p.returncode == 3, p.stderr
    assert out.exists() and "still inverted" in p.stderr and "Traceback" not in p.stderr
    assert "jaxci: untangle  ... round 1" in p.stderr  # progress per round with -v


def test_untangling_time_budget():
    mesh, a, b, fixed = _two_tangles()
    with pytest.raises(InvertedMeshError, match=r"time budget of 1e-09 s"):
        jaxci.smooth(mesh, untangle_time_budget=1e-9)
    res = jaxci.smooth(mesh, untangle="partial", untangle_time_budget=1e-9)
    assert res.after.inverted_elements > 0 and any("time budget" in n for n in res.notes)
    assert jaxci.smooth(mesh, untangle_time_budget=60.0).after.inverted_elements == 0


def test_untangling_budget_through_the_cli(tmp_path):
    import subprocess
    import sys

    from jaxci.io import write_mesh

    mesh, *_ = _two_tangles()
    write_mesh(mesh, str(tmp_path / "in.vtk"))
    base = [sys.executable, "-m", "jaxci", "smooth", str(tmp_path / "in.vtk"), str(tmp_path / "out.vtk")]
    p = subprocess.run([*base, "--untangle-budget", "1e-9"], capture_output=True, text=True)
    assert p.returncode == 2 and "time budget of 1e-09 s" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "out.vtk").exists()
    p = subprocess.run([*base, "--untangle-budget", "1e-9", "--untangle", "partial"], capture_output=True, text=True)
    assert p.returncode == 3 and (tmp_path / "out.vtk").exists()
    p = subprocess.run([*base, "--untangle-budget", "-1", "--force"], capture_output=True, text=True)
    assert p.returncode == 2 and "time_budget" in p.stderr and "Traceback" not in p.stderr
