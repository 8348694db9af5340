"""The exact numpy projection against an exhaustive search, and the node lengths of the scaled parametrisation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import MESQUITE

from jaxci.geometry import projection
from jaxci.geometry._closest import (
    closest_on_segments,
    closest_on_triangles,
    inside_tolerance,
)
from jaxci.geometry.boundary import classify_boundary
from jaxci.geometry.projection import build_constraints, project_np
from jaxci.mesh import HexMesh
from jaxci.mesh.generate import perturb_box
from jaxci.optim import parametrisation
from jaxci.optim.parametrisation import node_lengths


def exhaustive(c, x, closest_on=None):
    """`project_np` by definition: every SURFACE (EDGE) node against EVERY triangle (segment) of its own patch
    (curve); the lowest score wins (np.lexsort's order: NaN after every number), a tie going to the lowest cell;
    corners restored. `closest_on` replaces the triangles' kernel."""
    x = np.asarray(x, dtype=np.float64)
    out = x.copy()
    group = np.asarray(c.group)
    tol = inside_tolerance(np.float64)
    for nodes, table, cell_group, closest in (
        (c.surface_nodes, c.triangles, c.triangle_patch, closest_on or closest_on_triangles),
        (c.edge_nodes, c.segments, c.segment_curve, closest_on_segments),
    ):
        nodes, table, cell_group = np.asarray(nodes), np.asarray(table), np.asarray(cell_group)
        for g in np.unique(group[nodes]):
            cells = np.flatnonzero(cell_group == g)
            for sel in np.array_split(nodes[group[nodes] == g], -(-int((group[nodes] == g).sum()) // 128)):
                p, score = closest(np, tuple(x[sel][:, j, None] for j in range(3)), table[:, cells][:, None, :], tol)
                col = np.array([np.lexsort((np.arange(len(cells)), row))[0] for row in score])
                out[sel] = np.stack([pj[np.arange(len(sel)), col] for pj in p], axis=1)
    corners = np.asarray(c.corner_nodes)
    out[corners] = np.asarray(c.x_orig)[corners]
    return out


def _mesh(name):
    if name == "box":
        return perturb_box(6, amplitude=0.3, seed=0)
    from jaxci.io import read_mesh

    return read_mesh(str(MESQUITE / "pave3.e.vtk"))  # curved walls


@pytest.mark.parametrize(("name", "shift"), [("box", 0.0), ("box", 1e5),
                                                  pytest.param("pave", 0.0, marks=pytest.mark.shared)])
def test_project_np_is_the_exhaustive_search(name, shift):
    """Bit for bit the nearest point over the whole patch or curve, for moves from rounding noise to many
    elements, for points on the grid of vertices and centres (exact ties), on curved walls, far from the origin."""
    mesh = _mesh(name)
    if shift:
        mesh = HexMesh(np.asarray(mesh.points) + shift, mesh.cells)
    c = build_constraints(mesh, classify_boundary(mesh), dtype=np.float64, device=False)
    pts = np.asarray(mesh.points, dtype=np.float64)
    h = float(np.median(np.linalg.norm(pts[mesh.hexes[:, 1]] - pts[mesh.hexes[:, 0]], axis=1)))
    rng = np.random.default_rng(3)
    for amplitude in (0.0, 1e-9, 0.05, 0.5, 2.0, 8.0) if name == "box" else (0.0, 0.05, 2.0):
        for x in (pts + rng.normal(scale=amplitude * h, size=pts.shape),
                  pts + amplitude * h * rng.integers(-2, 3, size=pts.shape) / 2):
            out = project_np(c, x)
            assert out.dtype == np.float64 and out.shape == x.shape
            np.testing.assert_array_equal(out, exhaustive(c, x))


def test_nan_scores_sort_after_numbers():
    """A NaN score never wins over a number (np.lexsort's order): a point whose winning triangle scores NaN
    goes to its next best."""
    mesh = perturb_box(3, amplitude=0.3, seed=1)
    c = build_constraints(mesh, classify_boundary(mesh), dtype=np.float64, device=False)
    x = np.asarray(mesh.points) + np.random.default_rng(0).normal(scale=0.02, size=mesh.points.shape)
    plain = project_np(c, x)
    node = int(np.asarray(c.surface_nodes)[0])
    table = np.asarray(c.triangles)
    tol = inside_tolerance(np.float64)
    p, score = closest_on_triangles(np, tuple(plain[node, j, None] for j in range(3)), table, tol)
    nan_cell = int(np.argmin(np.where(np.asarray(c.triangle_patch) == c.group[node], score, np.inf)))
    centre = table[0, nan_cell]

    def nan_one(xp, x, t, tol):  # the winning triangle of `node` scores NaN for every point
        p, score = closest_on_triangles(xp, x, t, tol)
        return p, np.where(t[0] == centre, np.nan, score)

    real = projection.closest_on_triangles
    try:
        projection.closest_on_triangles = nan_one
        odd = project_np(c, x)
    finally:
        projection.closest_on_triangles = real
    assert np.isfinite(odd).all() and (odd[node] != plain[node]).any()
    np.testing.assert_array_equal(odd, exhaustive(c, x, nan_one))


def _lengths_by_definition(hexes, points):
    edges = parametrisation._EDGE_ENDS.T
    total, count = np.zeros(len(points)), np.zeros(len(points))
    for e in hexes:
        for i, j in edges:
            length = np.linalg.norm(points[e[j]] - points[e[i]])
            for v in (e[i], e[j]):
                total[v] += length
                count[v] += 1
    return np.divide(total, count, out=np.zeros(len(points)), where=count > 0)


def test_node_lengths_by_definition_and_block_size(monkeypatch):
    """The mean length of the 3 edges of every element at each node (0 for a node of no element); the blocks
    of elements gathered together do not change a bit (all elements in one block, or 7 at a time)."""
    mesh = perturb_box(4, amplitude=0.3, seed=2)
    hexes = np.asarray(mesh.hexes)[np.random.default_rng(0).permutation(len(mesh.hexes))][:50]
    points = np.vstack([mesh.points, [[9.0, 9.0, 9.0]]])  # an unused node
    whole = node_lengths(hexes, points)
    np.testing.assert_allclose(whole, _lengths_by_definition(hexes, points), rtol=1e-14, atol=0)
    assert whole[-1] == 0.0 and (whole[:-1][np.isin(np.arange(len(points) - 1), hexes)] > 0).all()
    monkeypatch.setattr(parametrisation, "_LENGTH_BLOCK", 7)
    np.testing.assert_array_equal(node_lengths(hexes, points), whole)
    np.testing.assert_array_equal(node_lengths(hexes.astype(np.int32), points), whole)


def test_far_off_points_and_float32_constraints_still_take_the_nearest_cell():
    """Points ~1e16-1e18 unit lengths off their patch (d0 + the largest radius rounds to d0: the k-d tree's bound
    must keep the nearest centre, and every point must get its own row), and constraints held in float32 (their
    tables consistent to float32 rounding only): the exhaustive search's points."""
    m = perturb_box(5, amplitude=0.3, seed=1)
    info = classify_boundary(m)
    c = build_constraints(m, info, dtype=np.float64, device=False)
    surf, grp = np.asarray(c.surface_nodes), np.asarray(c.group)
    sel = surf[grp[surf] == grp[surf[0]]]
    for off in (1e16, 1e18):
        x = np.asarray(m.points, np.float64).copy()
        x[sel[1:], 0] += off  # every node of one patch but the first far off (a row each), then all of them
        y = project_np(c, x)
        assert np.array_equal(y, exhaustive(c, x)) and np.array_equal(y[sel[0]], x[sel[0]])
        x[sel[0], 0] += off
        np.testing.assert_array_equal(project_np(c, x), exhaustive(c, x))
    c32 = build_constraints(m, info, dtype=np.float32, device=False)
    # project_np computes in float64 from the float32 tables: the exhaustive search from the same float64 values
    c64 = dataclasses.replace(c32, triangles=np.asarray(c32.triangles, np.float64),
                              segments=np.asarray(c32.segments, np.float64))
    rng = np.random.default_rng(3)
    for move in (0.0, 1e-3, 0.05):
        x = m.points + move * rng.standard_normal(m.points.shape)
        np.testing.assert_array_equal(project_np(c32, x), exhaustive(c64, x))
