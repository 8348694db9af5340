"""The mesh model's validation and orientation handling, and the box generator's protocol."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from helpers import unit_cube

import jaxci
from jaxci.cells import corner_determinants
from jaxci.errors import MeshError
from jaxci.mesh import (
    MIRROR_HEX,
    CellBlock,
    HexMesh,
    check_volume,
    close_pairs,
    coincident_pairs,
    from_unit,
    hex_mesh,
    to_unit,
    unit_frame,
)
from jaxci.mesh.generate import box, box_free_axes, perturb_box


def test_valid_cube():
    m = hex_mesh(unit_cube(), [list(range(8))])
    assert m.n_nodes == 8 and m.n_hexes == 1 and m.notes == () and not m.hex_mirrored


def test_node_index_out_of_range():
    with pytest.raises(MeshError, match=r"element 0 references node index 8, out of range \[0, 8\)"):
        hex_mesh(unit_cube(), [[0, 1, 2, 3, 4, 5, 6, 8]])


def test_repeated_node_in_hex():
    with pytest.raises(MeshError, match="repeats a node"):
        hex_mesh(unit_cube(), [[0, 1, 2, 2, 4, 5, 6, 7]])


def test_non_finite_coordinates():
    pts = unit_cube()
    pts[3, 1] = np.nan
    with pytest.raises(MeshError, match="node 3 has non-finite coordinates"):
        hex_mesh(pts, [list(range(8))])


def test_no_hexahedra():
    with pytest.raises(MeshError, match="no hexahedra"):
        HexMesh(unit_cube(), (CellBlock("tetra", np.array([[0, 1, 3, 4]])),))


def test_unreferenced_nodes_are_reported_not_rejected():
    pts = np.vstack([unit_cube(), [[5.0, 5.0, 5.0]]])
    m = hex_mesh(pts, [list(range(8))])
    assert any("1 unreferenced nodes" in n for n in m.notes)


def test_degenerate_element_reported():
    pts = unit_cube()
    pts[4:, 2] = 0.0  # flattened
    m = hex_mesh(pts, [list(range(8))], fix_orientation=False)
    assert any("degenerate" in n for n in m.notes)


def test_all_left_handed_are_mirrored_and_said():
    mesh = box(2, 2, 1)
    left = mesh.hexes[:, MIRROR_HEX]
    assert (corner_determinants(mesh.points, left) < 0).all()
    with pytest.warns(UserWarning, match="left-handed"):
        m = hex_mesh(mesh.points, left)
    assert m.hex_mirrored and any("mirrored" in n for n in m.notes)
    assert (corner_determinants(m.points, m.hexes) > 0).all()


def test_some_left_handed_are_inverted_not_reordered():
    mesh = box(2, 1, 1)
    hexes = mesh.hexes.copy()
    hexes[0] = hexes[0][MIRROR_HEX]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = hex_mesh(mesh.points, hexes)
    assert not m.hex_mirrored
    assert any("1 inverted hexahedra" in n for n in m.notes)


@pytest.mark.parametrize("chunk", [1, 7])
def test_corner_checks_in_blocks_say_what_one_block_says(monkeypatch, chunk):
    """`HexMesh` measures its corner determinants `DET_CHUNK` hexahedra at a time: the same notes (inverted,
    degenerate, mirrored), the same count of inverted hexahedra and the same node order as in one block, on a box
    with inverted and degenerate elements (7 does not divide its 27) and on one whose hexahedra are all
    left-handed."""
    import jaxci.mesh as M

    mesh = perturb_box(3, amplitude=0.3, seed=1)
    pts = mesh.points.copy()
    pts[mesh.hexes[13, 6]] = pts[mesh.hexes[13, 0]]  # inverted corners around one interior node
    flat = unit_cube()
    flat[4:, 2] = 0.0
    cases = [(pts, mesh.hexes), (box(2, 2, 1).points, box(2, 2, 1).hexes[:, MIRROR_HEX]),
             (np.concatenate([pts, flat]), np.concatenate([mesh.hexes, len(pts) + np.arange(8)[None]]))]
    for p, h in cases:
        made = []
        for c in (10**9, chunk):
            monkeypatch.setattr(M, "DET_CHUNK", c)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                made.append(hex_mesh(p, h))
        a, b = made
        assert a.notes == b.notes and a.hex_mirrored == b.hex_mirrored
        assert a.__dict__["_inverted_hexes"] == b.__dict__["_inverted_hexes"]
        np.testing.assert_array_equal(a.hexes, b.hexes)
    assert any("inverted" in n for n in made[1].notes) and any("degenerate" in n for n in made[1].notes)


def test_with_points_keeps_everything_but_coordinates():
    m = jaxci.paper_case("cube27", seed=0)
    moved = m.with_points(m.points + 0.0)
    assert moved.cells[0].data is not None and np.array_equal(moved.hexes, m.hexes)
    with pytest.raises(MeshError, match="shape"):
        m.with_points(m.points[:-1])


def test_connectivity_is_int32_and_its_keys_do_not_overflow():
    """The mesh keeps every cell block in int32 (`CONN_DTYPE`), whatever the input's integer type; the C kernels
    take it as it is and refuse what does not fit. Past 46,341 nodes ``low * n + high`` overflows int32: the
    topology, the edge neighbours, the stars and the classification are the same from int32 as from int64 there."""
    from jaxci import native
    from jaxci.geometry.boundary import classify_boundary
    from jaxci.geometry.topology import boundary_topology
    from jaxci.mesh import CONN_DTYPE
    from jaxci.optim._local import edge_neighbours, node_stars

    m = perturb_box(37, amplitude=0.2, seed=1)  # 54,872 nodes
    assert m.n_nodes ** 2 > 2**31 and m.hexes.dtype == CONN_DTYPE == np.int32
    assert all(b.data.dtype == np.int32 for b in m.cells)
    assert hex_mesh(m.points, m.hexes.astype(np.uint64)).hexes.dtype == np.int32
    h32, h64 = m.hexes, m.hexes.astype(np.int64)
    t32, t64 = boundary_topology(h32, m.n_nodes), boundary_topology(h64, m.n_nodes)
    assert all(np.array_equal(getattr(t32, f), getattr(t64, f)) for f in ("faces", "face_hex", "edges", "face_edges"))
    for a, b in zip(edge_neighbours(h32, m.n_nodes), edge_neighbours(h64, m.n_nodes), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(node_stars(h32, m.n_nodes, True).star, node_stars(h64, m.n_nodes, True).star)
    i32 = classify_boundary(m)
    i64 = classify_boundary(dataclasses.replace(m, cells=(CellBlock("hexahedron", h64),)))
    np.testing.assert_array_equal(i32.node_class, i64.node_class)
    np.testing.assert_array_equal(i32.feature_edges, i64.feature_edges)
    assert native.hex_objective(m.points, h64) == native.hex_objective(m.points, h32)
    with pytest.raises(ValueError, match="int32"):
        native.as_conn(np.array([[0, 2**31]]))


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_box_counts_and_ideal(n):
    m = box(n, n + 1, n + 2, size=(1.0, 2.0, 3.0))
    assert m.n_hexes == n * (n + 1) * (n + 2)
    assert m.n_nodes == (n + 1) * (n + 2) * (n + 3)
    assert (corner_determinants(m.points, m.hexes) > 0).all()


def test_perturbation_protocol():
    n = 4
    base = box(n)
    m = perturb_box(n, amplitude=0.4, seed=3)
    d = m.points - base.points
    free = box_free_axes(n, n, n, "sliding")
    assert np.all(d[~free] == 0)  # corners fixed, faces stay on faces, edges on edges
    assert np.abs(d).max() <= 0.4 / n + 1e-15
    assert (corner_determinants(m.points, m.hexes) > 0).all()  # inverting draws were redrawn
    again = perturb_box(n, amplitude=0.4, seed=3)
    assert np.array_equal(again.points, m.points)
    interior = perturb_box(n, amplitude=0.4, seed=3, which="interior")
    on_boundary = ~box_free_axes(n, n, n, "interior").any(axis=1)
    assert np.all(interior.points[on_boundary] == base.points[on_boundary])


def test_paper_cases_by_name():
    for name, n in (("cube27", 27), ("cube64", 64), ("cube729", 729)):
        assert jaxci.paper_case(name, seed=1).n_hexes == n
    with pytest.raises(MeshError, match="unknown paper case"):
        jaxci.paper_case("cube1000")


def test_bad_box_arguments():
    with pytest.raises(MeshError, match="positive integer"):
        box(0)
    with pytest.raises(MeshError, match="amplitude"):
        perturb_box(2, amplitude=-1)
    for bad in ("abc", float("nan"), 2.5, True):
        with pytest.raises(MeshError, match="nx must be a positive integer"):
            box(bad)
    with pytest.raises(MeshError, match="size must be three positive finite"):
        box(2, size=(1.0, float("inf"), 1.0))
    with pytest.raises(MeshError, match="amplitude"):
        perturb_box(2, amplitude=float("nan"))
    with pytest.raises(MeshError, match="which"):
        perturb_box(2, which="all")


@pytest.mark.parametrize("scale,offset", [(1.0, 0.0), (1e300, 0.0), (1e-300, 0.0), (3e-3, 1e4)])
def test_unit_frame(scale, offset):
    p = box(3).points * scale + offset
    frame = unit_frame(p)
    u = to_unit(p, frame)
    assert np.abs(u).max() <= 1.0 and np.ptp(u, axis=0).max() >= 0.5
    np.testing.assert_allclose(from_unit(u, frame), p, rtol=1e-15, atol=1e-15 * scale)
    assert frame[1] == 2.0 ** np.floor(np.log2(scale * (1 + 1e-12)))  # a power of two: dividing by it is exact


def test_coincident_pairs():
    p = np.array([[0, 0, 0], [1, 1, 1], [0, 0, 1e-12], [1, 1, 1], [1, 1, 1]], float)
    np.testing.assert_array_equal(coincident_pairs(p), [[0, 2], [1, 3], [1, 4], [3, 4]])
    np.testing.assert_array_equal(coincident_pairs(p, tol=0.0), [[1, 3], [1, 4], [3, 4]])
    np.testing.assert_array_equal(coincident_pairs(p, nodes=[0, 1, 2]), [[0, 2]])
    assert box(2).coincident_nodes().shape == (0, 2) and not any("coincident" in n for n in box(2).notes)


@pytest.mark.parametrize("r", [0.0, 1e-9, 0.02, 0.15])  # 0.15: pairs across two grid spacings
def test_close_pairs_match_a_kd_tree(r):
    """`close_pairs` (a hashed grid, no scipy.spatial) finds exactly the pairs of scipy's k-d tree: random
    points with near-duplicates, and a grid with exact duplicates whose pairs lie on cell faces."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    p = rng.random((2000, 3))
    p[rng.integers(0, 2000, 300)] = p[rng.integers(0, 2000, 300)] + rng.normal(size=(300, 3)) * 1e-10
    g = np.asarray(box(12).points) / 12
    for pts in (p, np.concatenate([g, g[::5]])):
        want = cKDTree(pts).query_pairs(r, output_type="ndarray")
        got = close_pairs(pts, r)
        assert (got[:, 0] < got[:, 1]).all()
        m = len(pts)
        assert np.array_equal(np.sort(got[:, 0] * m + got[:, 1]), np.unique(np.sort(want, axis=1) @ [m, 1]))


def test_zero_volume_detected():
    check_volume(box(2))
    m = box(2)
    for axis, what in ((2, "in one plane"), (slice(1, 3), "on one line")):
        p = m.points.copy()
        p[:, axis] = 0.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            flat = hex_mesh(p, m.hexes)
        with pytest.raises(MeshError, match=f"lie {what}"):
            check_volume(flat)
