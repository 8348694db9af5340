"""Candidate cells that follow their node (`jaxci.geometry.anchors`): a boundary node projects onto the 2-ring of
its anchor, which moves with it, so that the solvers can slide boundary nodes further than two cells."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import wavy_annulus

from jaxci import native, smooth
from jaxci.geometry.anchors import anchor_tables
from jaxci.geometry.near import NearProjector, anchored
from jaxci.geometry.projection import project_np
from jaxci.interface.smooth import build_problem
from jaxci.mesh import hex_mesh
from jaxci.mesh.generate import grid_hexes


def _graded_arc(nt: int = 16, ratio: float = 0.75):
    """A quarter of a thick cylinder wall, 16 x 2 x 2 cells, graded along the arc (each cell 3/4 of the last): the
    mesh of best shape has its wall nodes several cells away from where they start."""
    w = ratio ** np.arange(nt)
    t = np.concatenate([[0.0], np.cumsum(w)]) / w.sum() * (np.pi / 2)
    z, r, t = np.meshgrid(np.linspace(0, 0.3, 3), np.linspace(1.0, 1.5, 3), t, indexing="ij")
    pts = np.stack([r * np.cos(t), r * np.sin(t), z], -1).reshape(-1, 3)
    return hex_mesh(pts, grid_hexes(nt, 2, 2))


def _use(use_c, monkeypatch):
    if use_c and not native.AVAILABLE:
        pytest.skip("the C extension is not built")
    monkeypatch.setattr(native, "AVAILABLE", use_c)


def test_the_tables_know_each_nodes_own_cells():
    """Each surface node is a corner of exactly the faces around it (4 on a structured wall, 2 on its edge of the
    patch), and each triangle's corner a is the node there."""
    mesh = wavy_annulus(16, 3, 3)
    pr = build_problem(mesh, dtype=np.float64)
    c = NearProjector(pr.cons).c
    nodes = np.asarray(c.surface_nodes)
    inner, ends = anchor_tables(np.asarray(c.x_orig)[nodes], np.asarray(c.surface_cand), np.asarray(c.triangles), 0)
    own = [len(np.unique(np.asarray(c.surface_cand)[r][inner[r]] // 4)) for r in range(len(nodes))]
    assert set(own) <= {2, 4} and 4 in own
    found = ends[:, 0] >= 0
    assert found.any()
    tri = np.asarray(c.triangles)
    a = (tri[0:3] + tri[3:6]).T[found]  # centroid + spoke: corner a
    np.testing.assert_allclose(a, np.asarray(c.x_orig)[nodes[ends[found, 0]]], atol=1e-12)


@pytest.mark.parametrize("use_c", [True, False])
def test_a_node_far_from_its_ring_finds_its_point(use_c, monkeypatch):
    """Boundary nodes moved along the curved wall of an annulus by 5 cells: a new projector's first projection walks
    each node's anchor to its point and puts it on the wall there, as the search of the whole patch does; the
    node's own 2-ring would hold it on the ring's rim, 3 cells short."""
    _use(use_c, monkeypatch)
    mesh = wavy_annulus(32, 3, 3)
    pr = build_problem(mesh, dtype=np.float64)
    p = np.array(mesh.points)
    r, th = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0])
    th = th + 5 * 2 * np.pi / 32
    x = np.stack([r * np.cos(th), r * np.sin(th), p[:, 2]], axis=1)
    ref = project_np(pr.host_cons, x)  # every face of each node's patch
    proj = NearProjector(pr.cons)
    y, hint = proj(x)
    surf = np.asarray(pr.cons.surface_nodes)
    np.testing.assert_allclose(y[surf], ref[surf], atol=1e-9)
    assert not np.array_equal(proj._cand[0], np.asarray(pr.cons.surface_cand))  # the anchors moved
    assert all((h[: len(n)] >= 0).all() for h, n in zip(hint, (surf, pr.cons.edge_nodes), strict=True))


@pytest.mark.parametrize("use_c", [True, False])
def test_committed_steps_carry_the_anchor_along(use_c, monkeypatch):
    """A solver's accepted iterates, each a third of a cell further along the wall: every one is projected as the
    search of the whole patch projects it, to 1e-9, after the node has travelled 4 cells; the hints stay those of
    the same cells."""
    _use(use_c, monkeypatch)
    mesh = wavy_annulus(32, 3, 3)
    pr = build_problem(mesh, dtype=np.float64)
    proj = NearProjector(pr.cons)
    proj.commit(proj(np.array(mesh.points))[1])
    p = np.array(mesh.points)
    r, th = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0])
    surf = np.asarray(pr.cons.surface_nodes)
    for step in range(1, 13):
        t = th + step / 3 * 2 * np.pi / 32
        x = np.stack([r * np.cos(t), r * np.sin(t), p[:, 2]], axis=1)
        y, hint = proj(x)
        np.testing.assert_allclose(y[surf], project_np(pr.host_cons, x)[surf], atol=1e-9)
        cells = proj._cand[0][np.arange(len(surf)), hint[0]]
        proj.commit(hint)
        np.testing.assert_array_equal(proj._cand[0][np.arange(len(surf)), hint[0]], cells)


def test_nodes_at_their_own_cells_keep_their_own_rings():
    """Where no node left its own cells, the constraints are used as they are: `anchored` returns them, no copy;
    and a projector whose nodes stay on their own cells never makes the anchors' tables (0.56 s and 4 MB on the
    surface of a 100^3 box)."""
    mesh = wavy_annulus(16, 3, 3)
    pr = build_problem(mesh, dtype=np.float64)
    assert anchored(pr.host_cons, np.array(mesh.points)) is pr.host_cons
    proj = NearProjector(pr.cons)
    x = np.array(mesh.points)
    for _ in range(3):
        x, hint = proj(x)
        proj.commit(hint)
    assert proj._anchors == [None, None]
    p = np.array(mesh.points)  # one node a cell and a half along the wall: the tables are made, its anchor moves
    node = int(pr.cons.surface_nodes[0])
    r, th = np.hypot(p[node, 0], p[node, 1]), np.arctan2(p[node, 1], p[node, 0]) + 1.5 * 2 * np.pi / 16
    x[node, :2] = r * np.cos(th), r * np.sin(th)
    proj.commit(proj(x)[1])
    assert proj._anchors[0] is not None and proj._anchors[0][0][0] != 0


def test_lbfgs_slides_boundary_nodes_beyond_their_rings():
    """The graded arc: its wall nodes must slide several cells for the cells to even out. With candidates that
    follow their nodes L-BFGS reaches max kappa/3 1.29 and F 0.45, the default pipeline 1.25; held to their own
    2-rings the nodes stopped on the rims, at max kappa/3 5.87 and F 7.5, the default at 5.44 (2026-11-30)."""
    mesh = _graded_arc()
    res = smooth(mesh, "lbfgs", engine="host", dtype="float64")
    assert res.before.max_condition > 18 and res.after.inverted_elements == 0
    assert res.after.max_condition < 1.5 and res.after.objective < 1.0
    # on the original boundary: the search of the whole patch leaves every node where it is
    np.testing.assert_allclose(project_np(build_problem(mesh, dtype=np.float64).host_cons, res.mesh.points),
                               res.mesh.points, atol=1e-9)
    assert smooth(mesh, engine="host").after.max_condition < 1.3


def test_the_tables_take_little_memory_beyond_their_own():
    """`anchor_tables` works a block of candidates at a time: on the 9,126 surface nodes of a 40^3 box its
    temporaries stay a few MB beside its 0.9 MB of tables (all at once they were 44 MB: cube60_pert's run peaked
    at 257 MB instead of 190 MB, 2026-11-30)."""
    import tracemalloc

    from jaxci.geometry.near import host_constraints
    from jaxci.mesh.generate import box

    c = host_constraints(build_problem(box(40), dtype=np.float64).cons)
    nodes = np.asarray(c.surface_nodes)
    tracemalloc.start()
    try:
        inner, ends = anchor_tables(np.asarray(c.x_orig)[nodes], c.surface_cand, np.asarray(c.triangles), 0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert inner.any(axis=1).all() and not inner.all()  # each node's own faces, and the rest of its 2-ring
    assert peak < inner.nbytes + ends.nbytes + 6e6


def test_a_projector_that_does_not_follow_keeps_the_constraints_rings():
    """``follow=False`` (a polish round's sub-problem, whose candidates are already anchored): nodes moved 5 cells
    along the wall stay on their own rings' rims, short of their points, and no anchor table is made."""
    mesh = wavy_annulus(32, 3, 3)
    pr = build_problem(mesh, dtype=np.float64)
    p = np.array(mesh.points)
    r, th = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]) + 5 * 2 * np.pi / 32
    x = np.stack([r * np.cos(th), r * np.sin(th), p[:, 2]], axis=1)
    proj = NearProjector(pr.cons, follow=False)
    y, hint = proj(x)
    proj.commit(hint)
    surf = np.asarray(pr.cons.surface_nodes)
    assert np.abs(y[surf] - project_np(pr.host_cons, x)[surf]).max() > 0.05
    assert proj._anchors == [None, None] and proj._cand[0] is proj.c.surface_cand
