"""Topology (boundary faces, adjacency, colouring) and node classification (jaxci.geometry.topology,
jaxci.geometry.boundary)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import MESQUITE
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxci.errors import MeshError
from jaxci.geometry.boundary import CORNER, EDGE, INTERIOR, SURFACE, classify_boundary, face_normals
from jaxci.geometry.topology import HEX_FACES, boundary_topology, colour_nodes, node_adjacency
from jaxci.mesh import CellBlock, HexMesh, hex_mesh
from jaxci.mesh.generate import box, perturb_box
from jaxci.mesh.shapes import annulus, bevelled_box, l_block


def read_mesh(path: Path) -> HexMesh:
    """The mesh at `path`: through jaxci.io.read_mesh when it exists, else meshio's VTK reader."""
    try:
        from jaxci.io import read_mesh as jaxci_read
    except ImportError:
        jaxci_read = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if jaxci_read is not None:
            return jaxci_read(path)
        import meshio

        m = meshio.vtk.read(str(path))
        return hex_mesh(m.points, m.cells_dict["hexahedron"], source=str(path))


def classify_quiet(mesh, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean mesh must not warn
        return classify_boundary(mesh, **kw)


def renumbered(mesh: HexMesh, perm: np.ndarray) -> HexMesh:
    """The same mesh with node i renamed perm[i]."""
    pts = np.empty_like(mesh.points)
    pts[perm] = mesh.points
    return hex_mesh(pts, perm[mesh.hexes])


def assert_valid_colouring(col, hexes, n_nodes):
    c = col.colour[hexes]
    srt = np.sort(c, axis=1)
    assert (srt[:, 1:] != srt[:, :-1]).all(), "two nodes of one colour share a hexahedron"
    assert col.colour.shape == (n_nodes,) and col.colour.dtype == np.int32
    assert set(np.unique(col.colour).tolist()) == set(range(col.n_colours)), "a colour without a node"


# ------------------------------------------------------------------------------------------------ topology


@pytest.mark.parametrize("n", [1, 2, 3])
def test_boundary_faces_of_a_box_are_outward(n):
    mesh = box(n, n + 1, n + 2)
    topo = boundary_topology(mesh.hexes, mesh.n_nodes)
    assert len(topo.faces) == 2 * (n * (n + 1) + (n + 1) * (n + 2) + n * (n + 2))
    assert topo.n_nonmanifold_faces == 0
    assert (topo.edge_valence == 2).all()
    centre = mesh.points.mean(axis=0)
    out = mesh.points[topo.faces].mean(axis=1) - centre
    assert (np.einsum("ij,ij->i", face_normals(mesh.points, topo.faces), out) > 0).all()
    # each boundary face is a face of the hexahedron it belongs to
    own = np.sort(mesh.hexes[topo.face_hex][:, HEX_FACES], axis=2)
    assert (own == np.sort(topo.faces, axis=1)[:, None, :]).all(axis=2).any(axis=1).all()
    # edge <-> face tables agree
    for e in range(len(topo.edges)):
        for f in topo.edge_face[topo.edge_face_ptr[e] : topo.edge_face_ptr[e + 1]]:
            assert e in topo.face_edges[f]
            assert set(topo.edges[e]) <= set(topo.faces[f])


@pytest.mark.parametrize("chunk", [1, 5])
def test_boundary_faces_found_in_blocks_are_the_same(monkeypatch, chunk):
    """`boundary_topology` makes its face keys `KEY_CHUNK` cells at a time and `group_pairs` compares them in
    blocks (`jaxci.mesh.sorting._firsts`): the same topology as in one block, on a perturbed box and on a mixed mesh
    (wedges and tetrahedra beside the hexahedra: triangle faces)."""
    import jaxci.geometry.topology as T
    from jaxci.mesh import sorting

    mesh = perturb_box(3, amplitude=0.2, seed=2)
    n = mesh.n_nodes
    wedges = np.array([[n, n + 1, n + 2, n + 3, n + 4, n + 5]])
    tets = np.array([[n + 3, n + 4, n + 5, n + 6]])
    firsts = sorting._firsts
    for others, n_nodes in ((None, n), ({"wedge": wedges, "tetra": tets}, n + 7)):
        monkeypatch.setattr(T, "KEY_CHUNK", 10**9)
        whole = boundary_topology(mesh.hexes, n_nodes, others)
        monkeypatch.setattr(T, "KEY_CHUNK", chunk)
        monkeypatch.setattr(sorting, "_firsts", lambda k1, k2, order, chunk=chunk: firsts(k1, k2, order, chunk))
        parts = boundary_topology(mesh.hexes, n_nodes, others)
        monkeypatch.setattr(sorting, "_firsts", firsts)
        for f in ("faces", "face_hex", "edges", "face_edges", "edge_face_ptr", "edge_face", "face_type", "face_cell"):
            np.testing.assert_array_equal(getattr(parts, f), getattr(whole, f), err_msg=f)


def test_node_adjacency_matches_brute_force():
    mesh = l_block(2)
    indptr, indices = node_adjacency(mesh.hexes, mesh.n_nodes)
    expect = [set() for _ in range(mesh.n_nodes)]
    for h in mesh.hexes:
        for a in h:
            expect[a].update(int(b) for b in h if b != a)
    for i in range(mesh.n_nodes):
        assert indices[indptr[i] : indptr[i + 1]].tolist() == sorted(expect[i])


def test_node_adjacency_by_the_sparse_product_is_the_sorted_one(monkeypatch):
    """Large meshes take the adjacency from scipy's ``A A^T`` (diagonal dropped in place, int32 indices): the
    same neighbours as the sort of the small ones, also with a node no cell uses, and the same colouring."""
    from jaxci.geometry import topology

    mesh = l_block(3)
    hexes = np.asarray(mesh.hexes)
    n = mesh.n_nodes + 1  # one unused node
    ref = node_adjacency(hexes, n)
    monkeypatch.setattr(topology, "SORTED_ADJACENCY_MAX", 0)
    got = node_adjacency(hexes, n)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])
    np.testing.assert_array_equal(colour_nodes(hexes, n, got).colour, colour_nodes(hexes, n, ref).colour)


def test_the_colouring_of_a_mesh_is_computed_once():
    """`colour_nodes` keeps its last result for a read-only connectivity (`HexMesh.hexes`, shared by the
    untangling stage and the shape improvement of one run); a writable array is coloured afresh."""
    mesh = box(3)
    first = colour_nodes(mesh.hexes, mesh.n_nodes)
    assert colour_nodes(mesh.hexes, mesh.n_nodes) is first
    fresh = colour_nodes(np.array(mesh.hexes), mesh.n_nodes)
    assert fresh is not first and np.array_equal(fresh.colour, first.colour)
    assert colour_nodes(mesh.hexes, mesh.n_nodes + 1) is not first
    from jaxci.geometry import topology

    colour_nodes(mesh.hexes, mesh.n_nodes)
    assert topology._LAST_COLOURING
    del mesh, first
    import gc

    gc.collect()
    assert not topology._LAST_COLOURING  # not kept past its mesh


@pytest.mark.parametrize("n", [1, 2, 3, 5, 9])
def test_box_colouring_has_8_colours(n):
    mesh = box(n)
    col = colour_nodes(mesh.hexes, mesh.n_nodes)
    assert col.n_colours == 8
    assert_valid_colouring(col, mesh.hexes, mesh.n_nodes)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 4))
def test_colouring_valid_for_any_numbering(seed, n):
    mesh = renumbered(box(n, n + 1, 2), np.random.default_rng(seed).permutation(box(n, n + 1, 2).n_nodes))
    col = colour_nodes(mesh.hexes, mesh.n_nodes)
    assert_valid_colouring(col, mesh.hexes, mesh.n_nodes)
    assert col.n_colours <= 27  # first-fit: at most max degree + 1


@pytest.mark.shared
@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 4))
def test_c_colouring_is_the_first_fit_of_the_numpy_rounds(seed, n):
    """`jaxci.native.greedy_colour` (the one-pass C colouring `colour_nodes` uses) gives exactly the colours of
    the numpy rounds (Jones-Plassmann, index priority), on renumbered boxes and on pave3's unstructured mesh."""
    from jaxci import native
    from jaxci.geometry import topology

    if not native.AVAILABLE:
        pytest.skip("the C kernels are not built")
    mesh = renumbered(box(n, n + 1, 2), np.random.default_rng(seed).permutation(box(n, n + 1, 2).n_nodes))
    pave = read_mesh(MESQUITE / "pave3.e.vtk")
    for m in (mesh, pave):
        hexes = np.asarray(m.hexes)
        ref = topology._first_fit_rounds(hexes, m.n_nodes + 2, None)  # two nodes in no cell: colour 0
        got = native.greedy_colour(hexes, m.n_nodes + 2)
        assert got.dtype == np.int32 and np.array_equal(got, ref)
    with pytest.raises(IndexError, match="greedy_colour"):
        native.greedy_colour(np.asarray(mesh.hexes), 3)


@pytest.mark.parametrize("make", [lambda: l_block(2), lambda: bevelled_box(4), lambda: annulus(12, 2, 2)])
def test_colouring_valid_on_shapes(make):
    mesh = make()
    assert_valid_colouring(colour_nodes(mesh.hexes, mesh.n_nodes), mesh.hexes, mesh.n_nodes)


# ------------------------------------------------------------------------------------------------ classification


@pytest.mark.parametrize("n", [2, 3, 5, 9])
def test_box_classes(n):
    info = classify_quiet(box(n))
    assert info.counts == {
        "interior": (n - 1) ** 3,
        "surface": 6 * (n - 1) ** 2,
        "edge": 12 * (n - 1),
        "corner": 8,
    }
    assert (info.n_patches, info.n_curves) == (6, 12)
    assert info.notes == ()
    assert np.array_equal(info.patch_id >= 0, info.node_class == SURFACE)
    assert np.array_equal(info.curve_id >= 0, info.node_class == EDGE)


def test_box_classes_follow_geometry():
    mesh = box(3, 4, 5, size=(1.0, 2.0, 3.0))
    info = classify_quiet(mesh)
    p = mesh.points
    on = (np.isclose(p, 0) | np.isclose(p, [1.0, 2.0, 3.0])).sum(axis=1)  # number of box planes a node is on
    assert np.array_equal(info.node_class, on)  # 0 interior, 1 face, 2 edge, 3 corner
    # nodes on one face share a patch; nodes on one edge share a curve
    for axis, value in ((0, 0.0), (2, 3.0)):
        s = (info.node_class == SURFACE) & np.isclose(p[:, axis], value)
        assert len(np.unique(info.patch_id[s])) == 1


def test_single_hex_is_all_corners():
    info = classify_quiet(box(1))
    assert info.counts == {"interior": 0, "surface": 0, "edge": 0, "corner": 8}


def test_l_block_reentrant_edge():
    mesh = l_block(2)
    info = classify_quiet(mesh)
    p = mesh.points
    line = np.flatnonzero(np.isclose(p[:, 0], 1.0) & np.isclose(p[:, 1], 1.0))
    ends = line[np.isclose(p[line, 2], 0.0) | np.isclose(p[line, 2], 1.0)]
    mid = np.setdiff1d(line, ends)
    assert len(ends) == 2 and len(mid) == 1
    assert (info.node_class[ends] == CORNER).all()
    assert (info.node_class[mid] == EDGE).all()
    # the re-entrant edge is a feature edge
    fe = {tuple(sorted(e)) for e in info.feature_edges.tolist()}
    for a, b in zip(np.sort(line)[:-1], np.sort(line)[1:], strict=True):
        assert (int(a), int(b)) in fe
    # an L prism: 6 section vertices x 2 = 12 corners, 8 planar faces, 18 straight edges
    assert info.counts["corner"] == 12
    assert (info.n_patches, info.n_curves) == (8, 18)


def test_bevel_is_a_feature_only_below_its_angle():
    """Two chamfer facets turn the normal by 30 degrees at each of the three bevel edges."""
    mesh = bevelled_box(6)
    p = mesh.points
    sharp = classify_quiet(mesh, feature_angle=20.0)
    smooth = classify_quiet(mesh, feature_angle=40.0)
    at_y = np.isclose(p[:, 1], 0.5)
    bevel = at_y & (p[:, 0] > 0.69) & (p[:, 2] > 0.69) & (p[:, 0] + p[:, 2] > 1.69)  # the 3 chamfer vertices
    assert bevel.sum() == 3
    assert (sharp.node_class[bevel] == EDGE).all()
    assert (smooth.node_class[bevel] == SURFACE).all()
    assert sharp.counts["corner"] == 12 and smooth.counts["corner"] == 6
    assert (sharp.n_patches, sharp.n_curves) == (8, 18)
    assert (smooth.n_patches, smooth.n_curves) == (5, 9)
    # at 40 degrees the faces x = 1, both facets and z = 1 are one patch
    top = np.isclose(p[:, 2], 1.0) & at_y & (p[:, 0] > 0.1) & (p[:, 0] < 0.6)
    side = np.isclose(p[:, 0], 1.0) & at_y & (p[:, 2] > 0.1) & (p[:, 2] < 0.6)
    assert len(np.unique(smooth.patch_id[top | side | bevel])) == 1


def test_annulus_has_circles_without_corners():
    mesh = annulus(24, 2, 3)
    info = classify_quiet(mesh)
    assert info.counts["corner"] == 0
    assert (info.n_patches, info.n_curves) == (4, 4)
    edge = info.node_class == EDGE
    r = np.hypot(mesh.points[:, 0], mesh.points[:, 1])
    z = mesh.points[:, 2]
    assert np.allclose(np.sort(np.unique(np.round(r[edge], 12))), [0.5, 1.0])
    assert np.allclose(np.sort(np.unique(np.round(z[edge], 12))), [0.0, 1.0])
    assert edge.sum() == 4 * 24
    # each circle is one curve
    for rr in (0.5, 1.0):
        for zz in (0.0, 1.0):
            on = edge & np.isclose(r, rr) & np.isclose(z, zz)
            assert on.sum() == 24 and len(np.unique(info.curve_id[on])) == 1
    # coarse circles turn by 360/8 = 45 degrees per node: corners everywhere on them
    assert classify_quiet(annulus(8, 1, 1)).counts["corner"] == 4 * 8


#: file -> (interior, surface, edge, corner, patches, curves), computed once and checked by hand: the blocks
#: are boxes (4x2x2 and 10x10x10 cells: (n-1)^3, 6(n-1)^2, 12(n-1), 8); pave3 is a half-cylinder (flat
#: face x = 0, curved face, top, bottom: 4 patches, 2 half-circles + 4 straight lines, 4 corners).
MESQUITE_COUNTS = {
    "single_hex.vtk": (0, 0, 0, 8, 6, 12),
    "hexes_4by2by2.vtk": (3, 14, 20, 8, 6, 12),
    "large_box_hex_1000.vtk": (729, 486, 108, 8, 6, 12),
    "1000hex-block-internal-bias.vtk": (729, 486, 108, 8, 6, 12),
    "hex_5_tangled.vtk": (64, 96, 48, 8, 6, 12),
    "pave3.e.vtk": (1293, 963, 125, 4, 4, 6),
}


@pytest.mark.shared
@pytest.mark.parametrize("name", sorted(MESQUITE_COUNTS))
def test_mesquite_meshes_classify(name):
    path = MESQUITE / name
    if not path.exists():
        pytest.skip(f"{path} not found")
    info = classify_quiet(read_mesh(path))
    c = info.counts
    assert (c["interior"], c["surface"], c["edge"], c["corner"], info.n_patches, info.n_curves) == (
        MESQUITE_COUNTS[name]
    )


# ------------------------------------------------------------------------------------------------ overrides


def test_fix_boundary_and_fixed_nodes_and_sets():
    mesh = box(3)
    info = classify_quiet(mesh, fix_boundary=True)
    assert info.counts == {"interior": 8, "surface": 0, "edge": 0, "corner": 56}
    assert (info.patch_id == -1).all() and (info.curve_id == -1).all()
    info = classify_quiet(mesh, fixed_nodes=[1, 21])  # 1: on an edge; 21: interior
    base = classify_quiet(mesh)
    assert base.node_class[1] == EDGE and base.node_class[21] == INTERIOR
    assert info.node_class[1] == CORNER and info.node_class[21] == CORNER
    assert info.curve_id[1] == -1
    assert info.n_curves == base.n_curves  # fixing does not split curves
    tagged = HexMesh(mesh.points, mesh.cells, point_sets={"clamp": np.array([17, 18])})
    info = classify_quiet(tagged, fixed_sets=["clamp"])
    assert (info.node_class[[17, 18]] == CORNER).all()


def test_bad_overrides_raise():
    mesh = box(2)
    with pytest.raises(MeshError, match="no point set 'nope'"):
        classify_boundary(mesh, fixed_sets=["nope"])
    with pytest.raises(MeshError, match=r"fixed_nodes must be node indices in \[0, 27\)"):
        classify_boundary(mesh, fixed_nodes=[27])
    with pytest.raises(MeshError, match="feature_angle"):
        classify_boundary(mesh, feature_angle=0.0)


def test_unreferenced_and_quadratic_wedge_nodes_are_fixed():
    mesh = box(2)
    pts = np.vstack([mesh.points, [[5.0, 5.0, 5.0]] * 16])
    wedge = np.arange(27, 33)[None]
    midside = np.arange(33, 42)[None]  # a quadratic wedge (wedge15): its nodes stay fixed; node 42 is unused
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = HexMesh(pts, (CellBlock("hexahedron", mesh.hexes), CellBlock("wedge", wedge, midside=midside)))
    info = classify_quiet(m)
    assert (info.node_class[27:] == CORNER).all()
    assert any("quadratic non-hexahedral" in s for s in info.notes)


# ------------------------------------------------------------------------------------------------ bad input


def _two_cubes(shift) -> HexMesh:
    a = box(1).points
    pts = np.vstack([a, a + np.asarray(shift, dtype=float)])
    pts, inv = np.unique(np.round(pts, 12), axis=0, return_inverse=True)
    return hex_mesh(pts, inv.reshape(2, 8))


def test_cubes_touching_along_an_edge_warn():
    mesh = _two_cubes([1, 1, 0])
    with pytest.warns(UserWarning) as rec:
        info = classify_boundary(mesh)
    text = " ".join(str(w.message) for w in rec)
    assert "non-manifold boundary: 1 boundary edges" in text and "2 boundary nodes join separate fans" in text
    assert len(info.notes) == 2
    assert info.counts["corner"] == 14  # 16 cube corners, 2 of them shared
    assert info.counts["interior"] == 0


def test_cubes_touching_at_a_vertex_warn():
    mesh = _two_cubes([1, 1, 1])
    with pytest.warns(UserWarning, match="separate fans"):
        info = classify_boundary(mesh)
    assert info.counts["corner"] == 15


def test_open_boundary_warns():
    """A duplicated hexahedron glued to a third: their shared face is used three times."""
    mesh = box(2, 1, 1)
    hexes = np.vstack([mesh.hexes, mesh.hexes[:1]])
    bad = hex_mesh(mesh.points, hexes)
    with pytest.warns(UserWarning) as rec:
        info = classify_boundary(bad)
    text = " ".join(str(w.message) for w in rec)
    assert "three or more cells" in text and "open boundary" in text
    assert len(info.notes) >= 2
    shared = mesh.hexes[0, [1, 2, 5, 6]]  # the face of the duplicated element glued to the third
    assert (info.node_class[shared] == CORNER).all()
    # the other nodes of the duplicated element are on no boundary face: nothing marks them
    assert (info.node_class[mesh.hexes[0, [0, 3, 4, 7]]] == INTERIOR).all()


def test_components_are_scipys():
    """`jaxci.geometry.topology.components` (no scipy.sparse.csgraph import at start-up) labels as scipy does: random
    graphs, isolated vertices, a long shuffled chain (many rounds of pointer jumping)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from jaxci.geometry.topology import components

    rng = np.random.default_rng(0)
    for n, m in [(1, 0), (10, 0), (50, 30), (1000, 900), (3000, 6000), (5000, 4999)]:
        a, b = rng.integers(0, n, m), rng.integers(0, n, m)
        if m == n - 1:
            perm = rng.permutation(n)
            a, b = perm[:-1], perm[1:]
        count, labels = connected_components(sp.coo_matrix((np.ones(m), (a, b)), shape=(n, n)), directed=False)
        got = components(n, a, b)
        assert got[0] == count and np.array_equal(got[1], labels)
