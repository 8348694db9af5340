"""Smoothing hex-dominant meshes: boundary faces of every cell type, mixed-node classes, the mixed objective in
every method (jaxci.geometry.topology, jaxci.geometry.boundary, jaxci.metrics.objective, jaxci.smooth)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxci.cells import EDGES, volume_cells
from jaxci.geometry.boundary import CORNER, EDGE, INTERIOR, SURFACE, classify_boundary, face_normals, mesh_topology
from jaxci.geometry.projection import build_constraints, project, project_np
from jaxci.geometry.topology import CELL_FACES, HEX_FACES
from jaxci.interface.smooth import METHODS, build_problem, smooth
from jaxci.mesh import CellBlock, HexMesh
from jaxci.mesh.generate import box, perturb_box
from jaxci.metrics import elements as E
from jaxci.metrics import objective as mixed
from jaxci.metrics.hexahedron import objective_t, transposed
from jaxci.optim._local import gather_star
from jaxci.optim._moves import colour_slice, coloured_stars, local_sum

#: Unit cells of every type, node orders of `jaxci.metrics.elements`.
UNIT = {
    "hexahedron": np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
                           float),
    "wedge": np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], float),
    "pyramid": np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.7]], float),
    "tetra": np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
}


def wedge_box(seed: int = 0) -> HexMesh:
    """A perturbed 3^3 box whose centre column (hexahedra 4, 13, 22) is split into 2 wedges per hexahedron."""
    m = perturb_box(3, amplitude=0.2, seed=seed)
    h = m.hexes
    col = [4, 13, 22]
    w = np.concatenate([h[col][:, [0, 1, 2, 4, 5, 6]], h[col][:, [0, 2, 3, 4, 6, 7]]])
    return HexMesh(m.points, (CellBlock("hexahedron", np.delete(h, col, axis=0)), CellBlock("wedge", w)))


def all_types_box(seed: int = 1) -> HexMesh:
    """A perturbed 3^3 box: hexahedron 0 (a box corner) is 6 pyramids around a new centre node, the one on the
    boundary face x = 0 split into 2 tetrahedra; the column of hexahedra 8, 17, 26 is split into wedges."""
    m = perturb_box(3, amplitude=0.15, seed=seed)
    h, pts = m.hexes, m.points
    c = len(pts)
    pts = np.vstack([pts, pts[h[0]].mean(axis=0)])
    pyr = np.array([list(f[::-1]) + [c] for f in h[0][HEX_FACES]])  # base counter-clockwise seen from the apex
    a, b, cc, d, e = pyr[0]  # HEX_FACES[0] is the face x = 0
    tet = np.array([[a, b, cc, e], [a, cc, d, e]])
    col = [8, 17, 26]
    w = np.concatenate([h[col][:, [0, 1, 2, 4, 5, 6]], h[col][:, [0, 2, 3, 4, 6, 7]]])
    keep = np.delete(h, [0, *col], axis=0)
    return HexMesh(pts, (CellBlock("hexahedron", keep), CellBlock("wedge", w), CellBlock("pyramid", pyr[1:]),
                         CellBlock("tetra", tet)))


def reference_boundary(mesh: HexMesh) -> set:
    """Boundary faces by brute force: faces (as node sets) used by exactly one cell of any type."""
    count: dict = {}
    for t, cells in volume_cells(mesh).items():
        for cell in cells:
            for f in CELL_FACES[t]:
                key = frozenset(cell[f].tolist())
                count[key] = count.get(key, 0) + 1
    return {k for k, v in count.items() if v == 1}


def on_box_boundary(x: np.ndarray, nodes: np.ndarray, cls: np.ndarray) -> None:
    """Surface nodes on a face of the unit box, edge nodes on two, corners on three."""
    d = np.minimum(np.abs(x[nodes]), np.abs(1.0 - x[nodes]))  # (m, 3)
    need = {SURFACE: 1, EDGE: 2, CORNER: 3}
    for c, k in need.items():
        sel = cls[nodes] == c
        assert (np.sort(d[sel], axis=1)[:, :k] < 1e-9).all()


# ------------------------------------------------------------------------------------------------ topology
@pytest.mark.parametrize("cell_type", list(CELL_FACES))
def test_cell_faces_are_outward_and_closed(cell_type):
    x = UNIT[cell_type]
    faces = CELL_FACES[cell_type]
    n = face_normals(x, faces)
    centre = x.mean(axis=0)
    tri = faces[:, 3] == faces[:, 2]
    fc = np.where(tri[:, None], x[faces[:, :3]].mean(axis=1), x[faces].mean(axis=1))
    assert (np.einsum("ij,ij->i", n, fc - centre) > 0).all()
    sides = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    sides = sides[sides[:, 0] != sides[:, 1]]
    # every edge is used twice, once each way: a closed, consistently oriented surface
    assert sorted(map(tuple, sides)) == sorted(map(tuple, sides[:, ::-1]))
    assert len(np.unique(np.sort(sides, axis=1), axis=0)) == len(EDGES[cell_type])


@pytest.mark.parametrize("make", [wedge_box, all_types_box])
def test_boundary_faces_of_mixed_meshes(make):
    mesh = make()
    topo = mesh_topology(mesh)
    got = {frozenset(f.tolist()) for f in topo.faces}
    assert got == reference_boundary(mesh) and len(got) == len(topo.faces)
    assert topo.n_nonmanifold_faces == 0 and (topo.edge_valence == 2).all()
    tri = topo.faces[:, 3] == topo.faces[:, 2]  # triangles repeat their last node
    assert tri.sum() == (4 if make is wedge_box else 6)  # wedge column ends (+ the two boundary tetrahedra)
    assert ((topo.face_edges < 0).sum(axis=1) == tri).all()
    # outward: the faces of a box point away from its centre
    out = np.where(tri[:, None], mesh.points[topo.faces[:, :3]].mean(axis=1), mesh.points[topo.faces].mean(axis=1))
    assert (np.einsum("ij,ij->i", face_normals(mesh.points, topo.faces), out - 0.5) > 0).all()
    for e in range(0, len(topo.edges), 7):
        for f in topo.edge_face[topo.edge_face_ptr[e]: topo.edge_face_ptr[e + 1]]:
            assert e in topo.face_edges[f] and set(topo.edges[e]) <= set(topo.faces[f])


@pytest.mark.parametrize("make", [wedge_box, all_types_box])
def test_mixed_nodes_are_classified_like_hex_nodes(make):
    mesh = make()
    info = classify_boundary(mesh)
    ref = classify_boundary(box(3))
    n = box(3).n_nodes
    np.testing.assert_array_equal(info.node_class[:n], ref.node_class)  # same classes as the all-hex box
    assert (info.node_class[n:] == INTERIOR).all()  # the pyramids' apex
    assert info.n_patches == 6 and info.n_curves == 12 and not info.notes


def test_mixed_colouring_separates_every_cell():
    mesh = all_types_box()
    pb = build_problem(mesh)
    for t, cells in volume_cells(mesh).items():
        c = pb.colour[cells]
        assert (np.sort(c, axis=1)[:, 1:] != np.sort(c, axis=1)[:, :-1]).all(), t


def test_projection_onto_triangles_and_quads():
    mesh = all_types_box()
    info = classify_boundary(mesh)
    with jax.enable_x64(True):
        cons = build_constraints(mesh, info, dtype=jnp.float64)
        rng = np.random.default_rng(0)
        x = mesh.points + 0.05 * rng.standard_normal(mesh.points.shape)
        nodes = np.flatnonzero(info.node_class != INTERIOR)
        for y in (project_np(cons, x), np.asarray(project(cons, jnp.asarray(x)))):
            on_box_boundary(y, nodes, info.node_class)
            np.testing.assert_array_equal(y[info.node_class == CORNER], mesh.points[info.node_class == CORNER])


# ------------------------------------------------------------------------------------------------ objective
def test_hex_objective_unchanged_and_mixed_objective_matches_elements():
    mesh = all_types_box()
    x = jnp.asarray(mesh.points, jnp.float64)
    with jax.enable_x64(True):
        hexm = box(3)
        conn = transposed(hexm.hexes)
        xh = jnp.asarray(perturb_box(3, amplitude=0.2, seed=3).points)
        assert float(mixed.mixed_objective_t(xh, conn, mixed.no_extra())) == float(objective_t(xh, conn))
        extra = mixed.extra_cells(mesh)
        f = float(mixed.mixed_objective_t(x, transposed(mesh.hexes), extra))
        assert f == pytest.approx(float(E.mixed_objective(x, mesh)), rel=1e-12)
        from jaxci.optim.solver_objective import solver_objective

        for closed in (False, True):
            assert float(solver_objective(x, transposed(mesh.hexes), closed, extra)[0]) == pytest.approx(f, rel=1e-12)


def test_local_sums_are_the_change_of_the_mixed_objective():
    """Moving the nodes of one colour changes the sum over all corners by the sum of their local sums."""
    mesh = all_types_box()
    with jax.enable_x64(True):
        pb = build_problem(mesh, dtype=np.float64)
        cs = coloured_stars(mesh.hexes, pb.cons, pb.colour, pb.info.topology.faces, pb.table)
        x = jnp.asarray(mesh.points)
        n_corners = 8 * mesh.n_hexes + pb.extra.n_corners
        total = lambda p: (float(mixed.mixed_objective_t(p, pb.conn, pb.extra)) + 1.0) * n_corners  # noqa: E731
        rng = np.random.default_rng(1)
        checked = 0
        for i in range(cs.nodes.shape[0]):
            ci = colour_slice(cs, i)
            real = np.asarray(ci.mask)
            if not real.any():
                continue
            nodes = np.asarray(ci.nodes)[real]
            y = np.asarray(x)[nodes] + 0.03 * rng.standard_normal((len(nodes), 3))
            E_ = gather_star(x, ci.star)
            before = np.asarray(local_sum(x, ci, E_, x[jnp.minimum(ci.nodes, mesh.n_nodes - 1)][:, None]))[real, 0]
            yy = jnp.asarray(np.asarray(x)[np.minimum(np.asarray(ci.nodes), mesh.n_nodes - 1)])
            yy = yy.at[np.flatnonzero(real)].set(y)
            after = np.asarray(local_sum(x, ci, E_, yy[:, None]))[real, 0]
            moved = x.at[nodes].set(y)
            assert total(moved) - total(x) == pytest.approx(float((after - before).sum()), rel=1e-9, abs=1e-9)
            checked += int(np.isin(nodes, mixed.corner_table(mesh).nodes).sum())
        assert checked > 10  # nodes of non-hexahedral cells were among them


# ------------------------------------------------------------------------------------------------ every method
QUICK = {"auto": {"max_steps": 20},
         "ci": {"max_sweeps": 4}, "ci-global": {"attempts": 10}, "bfgs": {"max_steps": 20}, "lbfgs": {"max_steps": 20},
         "cg": {"max_steps": 20}, "lm": {"max_steps": 6}, "gauss-newton": {"max_steps": 6},
         "laplace": {"max_sweeps": 3}, "smart-laplace": {"max_sweeps": 3}}


@pytest.fixture(scope="module")
def mixed_box():
    return all_types_box()


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_every_method_smooths_a_mixed_mesh(mixed_box, method):
    mesh = mixed_box
    res = smooth(mesh, method, **QUICK[method])
    x = res.mesh.points
    assert not any(v.any() for v in mixed.inverted_cells(mesh, x).values())
    f0, f1 = float(E.mixed_objective(mesh.points, mesh)), float(E.mixed_objective(x, mesh))
    assert f1 < f0  # every method improves this mesh (laplace too: its moves are kept if nothing inverts)
    assert res.after.overall["objective"] == pytest.approx(f1, rel=1e-9)
    assert res.before.overall["objective"] == pytest.approx(f0, rel=1e-9)
    on_box_boundary(x, np.flatnonzero(res.node_class != INTERIOR), res.node_class)
    non_hex = np.unique(np.concatenate([c.ravel() for c in mixed.extra_blocks(mesh).values()]))
    movable = non_hex[res.node_class[non_hex] != CORNER]
    assert (np.linalg.norm(x[movable] - mesh.points[movable], axis=1) > 1e-6).sum() >= len(movable) // 2


@pytest.mark.slow
def test_presmooth_on_a_mixed_mesh(mixed_box):
    """Smart-Laplace sweeps (over the corners of every cell) then L-BFGS on the mixed F."""
    mesh = mixed_box
    lap = smooth(mesh, "smart-laplace", max_sweeps=2)
    res = smooth(mesh, "lbfgs", presmooth=2, max_steps=20)
    assert res.history["presmooth"] == 2
    np.testing.assert_allclose(res.history["objective"][:3], lap.history["objective"], rtol=1e-5)
    assert not any(v.any() for v in mixed.inverted_cells(mesh, res.mesh.points).values())
    assert res.after.overall["objective"] < lap.after.overall["objective"]
    on_box_boundary(res.mesh.points, np.flatnonzero(res.node_class != INTERIOR), res.node_class)


def test_smart_laplace_rejects_moves_that_invert_a_wedge():
    """A wedge flattened so that the Laplacian target of its apex side inverts it: smart Laplace keeps it valid."""
    mesh = wedge_box(seed=2)
    res = smooth(mesh, "smart-laplace", max_sweeps=20)
    assert not any(v.any() for v in mixed.inverted_cells(mesh, res.mesh.points).values())
    assert res.after.overall["objective"] <= res.before.overall["objective"]


def test_untangles_an_inverted_wedge():
    mesh = wedge_box()
    w = [b for b in mesh.cells if b.type == "wedge"][0].data
    info = classify_boundary(mesh)
    inner = w[0][info.node_class[w[0]] == INTERIOR]
    pts = mesh.points.copy()
    v = inner[0]
    centre = pts[w[0]].mean(axis=0)
    pts[v] = centre + 0.4 * (centre - pts[v])  # through the wedge: it inverts
    bad = HexMesh(pts, mesh.cells)
    assert any(b.any() for b in mixed.inverted_cells(bad, pts).values())
    res = smooth(bad, "lbfgs", max_steps=30)
    assert not any(v.any() for v in mixed.inverted_cells(bad, res.mesh.points).values())
    assert any("untangling" in n for n in res.notes)


# ------------------------------------------------------------------------------------------------ sector.cdb
def _sector():
    mapdl_archive = pytest.importorskip("mapdl_archive")
    from jaxci.io import read_mesh

    return read_mesh(Path(mapdl_archive.__file__).parent / "examples" / "sector.cdb")


def test_sector_interface_nodes_are_interior_and_wedges_move():
    mesh = _sector()
    info = classify_boundary(mesh)
    topo = info.topology
    assert {frozenset(f.tolist()) for f in topo.faces} == reference_boundary(mesh)
    w = [b for b in mesh.cells if b.type == "wedge"][0].data
    hex_nodes = np.unique(mesh.hexes)
    shared = np.intersect1d(np.unique(w), hex_nodes)
    on_boundary = np.isin(shared, topo.faces)
    assert (~on_boundary).any() and (info.node_class[shared[~on_boundary]] == INTERIOR).all()
    assert info.counts["interior"] == 21  # 18 before the wedges' faces were known
    res = smooth(mesh, "ci", max_sweeps=4)
    x = res.mesh.points
    assert not any(v.any() for v in mixed.inverted_cells(mesh, x).values())
    assert res.after.overall["objective"] < res.before.overall["objective"]
    movable = np.unique(w)[info.node_class[np.unique(w)] != CORNER]
    assert len(movable) and (np.linalg.norm(x[movable] - mesh.points[movable], axis=1) > 1e-6).all()
    # boundary nodes stay on the original boundary: projecting again changes nothing
    with jax.enable_x64(True):
        cons = build_constraints(mesh, info, dtype=jnp.float64)
    np.testing.assert_allclose(project_np(cons, x), x, atol=1e-12)
