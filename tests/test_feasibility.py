"""Inverted cells that no allowed move can fix are reported at once (`jaxci.optim.feasibility`, issue 15)."""

from __future__ import annotations

import time

import numpy as np
import pytest

import jaxci
from jaxci.boundary import classify_boundary
from jaxci.errors import InvertedMeshError
from jaxci.generate import box
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
    inverted = np.flatnonzero(jaxci.elements.inverted(mesh.points, mesh.hexes, "hexahedron"))
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
