"""Coincident nodes move as one (jaxci.geometry.coincident): an unmerged interface smoothed without being fixed,
kept where it is, written back unmerged; and the worst elements' limits after smoothing (jaxci.metrics.report)."""

from __future__ import annotations

import json

import numpy as np

import jaxci
from jaxci.cli import main
from jaxci.geometry.boundary import CORNER, classify_boundary
from jaxci.geometry.coincident import join_coincident, joined_info
from jaxci.geometry.projection import build_constraints, project_np
from jaxci.io import read_mesh, write_mesh
from jaxci.mesh import hex_mesh
from jaxci.metrics.report import limited_note, worst_elements


def split_box(seed: int = 3):
    """A perturbed 4 x 3 x 3 box whose cells right of the second node layer in x have their own copies of the
    nodes they share with the left ones (an unmerged interface): ``(mesh, pairs)``."""
    m = jaxci.perturb_box(4, 3, 3, amplitude=0.3, seed=seed, which="interior")
    h = np.array(m.hexes)
    right = m.points[h].mean(axis=1)[:, 0] > 0.5
    shared = np.intersect1d(np.unique(h[~right]), np.unique(h[right]))
    copy = np.arange(m.n_nodes)
    copy[shared] = m.n_nodes + np.arange(len(shared))
    h[right] = copy[h[right]]
    return hex_mesh(np.vstack([m.points, m.points[shared]]), h), np.stack([shared, copy[shared]], axis=1)


def test_sets_move_as_one_on_their_interface():
    mesh, pairs = split_box()
    np.testing.assert_array_equal(mesh.coincident_nodes(), pairs)
    res = jaxci.smooth(mesh, "lbfgs")
    held = jaxci.smooth(mesh, "lbfgs", fixed_nodes=pairs.ravel())  # what fixing them gave
    p = res.mesh.points
    assert res.mesh.n_nodes == mesh.n_nodes  # written back unmerged
    np.testing.assert_array_equal(p[pairs[:, 0]], p[pairs[:, 1]])  # exactly coincident
    assert np.abs(p[pairs[:, 0]] - mesh.points[pairs[:, 0]]).max() > 1e-3  # and they moved
    assert res.after.objective < held.after.objective - 0.01
    assert res.after.max_condition < held.after.max_condition
    # on the interface they lie on (each part's side of it is a boundary surface of that part), and the outer
    # boundary kept: the original's own constraints project the result onto itself
    cons = build_constraints(mesh, classify_boundary(mesh), dtype=np.float64, device=False)
    np.testing.assert_allclose(project_np(cons, p), p, atol=1e-9)
    assert any(f"{2 * len(pairs)} coincident nodes in {len(pairs)} sets" in n for n in res.notes)
    assert len(res.node_class) == mesh.n_nodes and res.after.n_nodes == mesh.n_nodes
    # nodes not in a set that did not move keep their coordinates bit for bit
    fixed = np.flatnonzero(res.node_class == CORNER)
    np.testing.assert_array_equal(p[fixed], mesh.points[fixed])


def test_joined_classification_and_its_fallbacks():
    mesh, pairs = split_box()
    joined = join_coincident(mesh)
    assert joined.sets == len(pairs) and len(joined.mesh.points) == mesh.n_nodes - len(pairs)
    assert (joined.node_of[pairs[:, 0]] == joined.node_of[pairs[:, 1]]).all()
    info = classify_boundary(mesh)
    jinfo = joined_info(joined, info, mesh.points)
    merged_cls = jinfo.node_class[joined.node_of]
    # a set takes its most constrained member's class; the interface's inner nodes slide (surface)
    np.testing.assert_array_equal(merged_cls[pairs[:, 0]], np.maximum(info.node_class[pairs[:, 0]],
                                                                         info.node_class[pairs[:, 1]]))
    assert (merged_cls[pairs[:, 0]] == 1).any()
    # every node on a curve has its two segments (one copy of each curve along the interface)
    fe = jinfo.feature_edges
    deg = np.bincount(fe.ravel(), minlength=len(joined.mesh.points))
    assert (deg[jinfo.node_class == 2] == 2).all()
    # a user-fixed member fixes its set
    res = jaxci.smooth(mesh, "lbfgs", fixed_nodes=[int(pairs[5, 0])])
    np.testing.assert_array_equal(res.mesh.points[pairs[5]], mesh.points[pairs[5]])
    assert join_coincident(jaxci.box(2)) is None


def dented_box():
    """A 3^3 box whose node (1/3, 0, 0) is pulled along the face z = 0 to (0.22, 0.12, 0): with the boundary fixed,
    corner 0 of hexahedron 0 (four fixed nodes) stays bad whatever moves."""
    m = jaxci.box(3)
    pts = np.array(m.points)
    i = int(np.argmin(np.linalg.norm(pts - [1 / 3, 0, 0], axis=1)))
    pts[i] = [0.22, 0.12, 0.0]
    return hex_mesh(pts, m.hexes)


def test_worst_elements_say_what_limits_them(capsys, tmp_path):
    mesh = dented_box()
    res = jaxci.smooth(mesh, "lbfgs", fix_boundary=True)
    worst = res.after.worst_elements
    assert len(worst) == 10 and worst[0]["kappa3"] == res.after.max_condition
    assert [w["kappa3"] for w in worst] == sorted((w["kappa3"] for w in worst), reverse=True)
    assert worst[0]["index"] == 0 and worst[0]["corner"] in (0, 1) and worst[0]["limits"][0] == "fixed corner"
    assert (res.node_class[worst[0]["nodes"]] == CORNER).all()
    assert limited_note(res.after).startswith(f"the worst element, {worst[0]['element']} (kappa/3 ")
    # sliding boundary: corner 0 of the box's corner cell lies on the boundary and has feature edges
    info = classify_boundary(jaxci.box(3))
    every = worst_elements(jaxci.box(3), jaxci.box(3).points, info.node_class, info.feature_edges, n=27)
    first = next(e for e in every if e["index"] == 0)
    assert first["corner"] == 0 and first["limits"] == ["boundary corner", "feature edge"]
    centre = next(e for e in every if e["index"] == 13)  # the box's centre cell: nothing holds it
    assert centre["limits"] == []
    # the CLI: --json lists them; the table output says it in one line when the worst is limited
    src = tmp_path / "in.vtk"
    write_mesh(mesh, src)
    code = main(["smooth", str(src), str(tmp_path / "out.vtk"), "--fix-boundary", "--json", "--method", "lbfgs"])
    listed = json.loads(capsys.readouterr().out)["after"]["worst_elements"]
    assert code == 0 and len(listed) == 10 and listed[0]["limits"][0] == "fixed corner"
    code = main(["smooth", str(src), str(tmp_path / "out2.vtk"), "--fix-boundary", "--method", "lbfgs"])
    text = capsys.readouterr().out
    assert code == 0 and text.count("is limited:") == 1 and "four nodes of its worst corner are fixed" in text
    assert read_mesh(tmp_path / "out2.vtk").n_nodes == mesh.n_nodes
