"""Projection onto the original boundary and the free-coordinate parametrisation (jaxci.geometry.projection)."""

from __future__ import annotations

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import MESQUITE, MESQUITE_FIGURES
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxci.geometry.boundary import CORNER, EDGE, INTERIOR, SURFACE, classify_boundary
from jaxci.geometry.projection import (
    build_constraints,
    n_free,
    params_to_points,
    points_to_params,
    project,
    project_nodes,
    project_np,
)
from jaxci.mesh import hex_mesh
from jaxci.mesh.generate import box, perturb_box
from jaxci.mesh.shapes import annulus, bevelled_box, l_block

jax.config.update("jax_enable_x64", True)



@functools.cache
def setup(name: str):
    """(mesh, info, constraints, h) of a named test shape; h is a typical element size."""
    mesh, h, angle = {
        "box": (lambda: (box(4), 0.25, 40.0)),
        "slab": (lambda: (box(3, 2, 4, size=(1.5, 1.0, 2.0), origin=(-1.0, 0.5, 0.0)), 0.5, 40.0)),
        "l_block": (lambda: (l_block(2), 0.5, 40.0)),
        "bevel": (lambda: (bevelled_box(6), 1 / 6, 40.0)),  # x = 1, facets and z = 1 form one patch
        "bevel20": (lambda: (bevelled_box(6), 1 / 6, 20.0)),  # every facet is a patch
        "annulus": (lambda: (annulus(24, 2, 2), 0.13, 40.0)),
    }[name]()
    info = classify_boundary(mesh, feature_angle=angle)
    return mesh, info, build_constraints(mesh, info, dtype=jnp.float64), h


def moved(name: str, seed: int, amplitude: float) -> np.ndarray:
    mesh, _, _, h = setup(name)
    rng = np.random.default_rng(seed)
    return mesh.points + rng.uniform(-amplitude * h, amplitude * h, mesh.points.shape)


def plane_distance(mesh, info, x, nodes):
    """Distance of x[nodes] to the nearest PLANE of a boundary face of each node's own patch (piecewise planar
    patches), shape (len(nodes),)."""
    from jaxci.geometry.boundary import face_normals

    f = info.topology.faces
    nrm = face_normals(mesh.points, f)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    off = (nrm * mesh.points[f[:, 0]]).sum(1)
    d = np.abs(x[nodes] @ nrm.T - off)  # (m, n_faces)
    d[info.patch_id[nodes][:, None] != info.face_patch[None, :]] = np.inf
    return d.min(axis=1)


def line_distance(mesh, info, x, nodes):
    """Distance of x[nodes] to the nearest LINE through a feature edge of each node's own curve."""
    fe = info.feature_edges
    a, d = mesh.points[fe[:, 0]], mesh.points[fe[:, 1]] - mesh.points[fe[:, 0]]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    w = x[nodes][:, None, :] - a[None]  # (m, n_edges, 3)
    dist = np.linalg.norm(w - (w * d).sum(-1, keepdims=True) * d, axis=-1)
    dist[info.curve_id[nodes][:, None] != info.edge_curve[None, :]] = np.inf
    return dist.min(axis=1)


# ------------------------------------------------------------------------------------------------ projection


@pytest.mark.parametrize("name", ["box", "l_block", "bevel", "annulus"])
def test_projection_is_idempotent(name):
    _, _, c, _ = setup(name)
    x = moved(name, 1, 0.4)
    once = project_np(c, x)
    np.testing.assert_allclose(project_np(c, once), once, rtol=0, atol=1e-14)
    jx = project(c, jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(project(c, jx)), np.asarray(jx), rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", ["box", "slab", "l_block", "bevel", "annulus"])
def test_jax_projection_equals_numpy(name):
    _, _, c, _ = setup(name)
    for seed in range(3):
        x = moved(name, seed, 0.45)
        np.testing.assert_allclose(np.asarray(project(c, jnp.asarray(x))), project_np(c, x), rtol=0, atol=1e-12)


def test_original_mesh_is_fixed_point():
    for name in ("box", "l_block", "bevel", "annulus"):
        mesh, _, c, _ = setup(name)
        np.testing.assert_allclose(project_np(c, mesh.points), mesh.points, rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(project(c, mesh.points)), mesh.points, rtol=0, atol=1e-14)


def test_interior_nodes_untouched_and_corners_restored():
    mesh, info, c, _ = setup("box")
    x = moved("box", 3, 0.4)
    for out in (project_np(c, x), np.asarray(project(c, jnp.asarray(x)))):
        inner = info.node_class == INTERIOR
        corner = info.node_class == CORNER
        assert np.array_equal(out[inner], x[inner])
        assert np.array_equal(out[corner], mesh.points[corner])


def test_node_displaced_off_its_surface_comes_back():
    mesh, info, c, h = setup("box")
    node = int(np.flatnonzero((info.node_class == SURFACE) & np.isclose(mesh.points[:, 2], 0.0))[0])
    x = mesh.points.copy()
    x[node] += [0.3 * h, -0.2 * h, 0.7 * h]  # off the face z = 0, inwards
    expect = mesh.points[node] + [0.3 * h, -0.2 * h, 0.0]
    np.testing.assert_allclose(project_np(c, x)[node], expect, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(project(c, x))[node], expect, rtol=0, atol=1e-15)
    x[node, 2] = -5 * h  # far outside: the numpy search is global on the patch
    np.testing.assert_allclose(project_np(c, x)[node], expect, rtol=0, atol=1e-15)
    x[node] = mesh.points[node] + [2.6 * h, 0.0, 0.5 * h]  # beyond the 2-ring, which only the numpy search sees
    np.testing.assert_allclose(project_np(c, x)[node], mesh.points[node] + [2.6 * h, 0, 0], rtol=0, atol=1e-15)


def test_node_pushed_past_the_end_of_its_edge_stops_there():
    mesh, info, c, h = setup("box")
    p = mesh.points
    on_edge = (info.node_class == EDGE) & np.isclose(p[:, 1], 0) & np.isclose(p[:, 2], 0)  # edge along x
    node = int(np.flatnonzero(on_edge)[np.argmin(p[on_edge, 0])])  # next to the corner (0, 0, 0)
    x = p.copy()
    x[node] += [-2.5 * h, 0.1 * h, -0.2 * h]
    one = np.asarray(project_nodes(c, jnp.asarray([node]), jnp.asarray(x[[node]])))[0]
    for q in (project_np(c, x)[node], np.asarray(project(c, x))[node], one):
        np.testing.assert_allclose(q, [0.0, 0.0, 0.0], rtol=0, atol=1e-15)


def test_a_node_cannot_jump_across_a_thin_wall():
    """A slab one element thick: a node of the bottom face pushed past the top stays on the bottom plane."""
    mesh = box(4, 4, 1, size=(1.0, 1.0, 0.05))
    info = classify_boundary(mesh)
    c = build_constraints(mesh, info)
    node = int(np.flatnonzero((info.node_class == SURFACE) & np.isclose(mesh.points[:, 2], 0.0))[0])
    x = mesh.points.copy()
    x[node, 2] = 0.08
    assert project_np(c, x)[node, 2] == 0.0
    assert float(project(c, x)[node, 2]) == 0.0


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    amplitude=st.floats(0.0, 0.45),
    name=st.sampled_from(["slab", "l_block", "bevel", "bevel20"]),
)
def test_random_moves_stay_on_planar_patches_and_straight_curves(seed, amplitude, name):
    mesh, info, c, _ = setup(name)
    x = moved(name, seed, amplitude)
    s = np.flatnonzero(info.node_class == SURFACE)
    e = np.flatnonzero(info.node_class == EDGE)
    for out in (project_np(c, x), np.asarray(project(c, jnp.asarray(x)))):
        assert plane_distance(mesh, info, out, s).max() <= 1e-12
        assert line_distance(mesh, info, out, e).max() <= 1e-12


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), amplitude=st.floats(0.0, 0.45))
def test_random_moves_stay_on_the_curved_annulus(seed, amplitude):
    mesh, info, c, h = setup("annulus")
    x = moved("annulus", seed, amplitude)
    r_of = np.hypot(mesh.points[:, 0], mesh.points[:, 1])
    sagitta = 1.0 * (1 - np.cos(np.pi / 24))  # chord error of the outer circle: the input's resolution
    for out in (project_np(c, x), np.asarray(project(c, jnp.asarray(x)))):
        r = np.hypot(out[:, 0], out[:, 1])
        s = info.node_class == SURFACE
        curved = s & (np.isclose(r_of, 0.5) | np.isclose(r_of, 1.0))
        flat = s & ~curved
        # flat ends stay on z = 0 / z = 1 exactly
        assert np.abs(out[flat, 2] - mesh.points[flat, 2]).max() <= 1e-12
        # curved sides: on the faceted cylinder, i.e. between the chord and the circle of their radius
        assert (r[curved] <= r_of[curved] + 1e-12).all()
        assert (r[curved] >= r_of[curved] - sagitta - 1e-12).all()
        assert np.abs(out[curved, 2] - 0.5).max() <= 0.5 + 1e-12
        # circles: every edge node on the polyline of its circle (same z, radius within the chord error)
        e = info.node_class == EDGE
        assert np.abs(out[e, 2] - mesh.points[e, 2]).max() <= 1e-12
        assert np.abs(r[e] - r_of[e]).max() <= sagitta * r_of[e].max() + 1e-12
        # on the original discrete boundary: the distance to it, |project_np(out) - out|, is far below 1e-3 h
        assert np.abs(project_np(c, out) - out).max() <= 1e-12 < 1e-3 * h


def test_projectors_in_a_shared_tables_block_share_the_tables_search_data_and_project_the_same():
    from jaxci.geometry.near import NearProjector, shared_tables

    _, _, c, _ = setup("annulus")
    x = moved("annulus", 7, 0.3)
    alone = [NearProjector(c)(x) for _ in range(2)]
    with shared_tables():
        first, second = NearProjector(c), NearProjector(c)
        shared = [first(x), second(x)]
    for (xa, ha), (xb, hb) in zip(alone, shared, strict=True):
        assert np.array_equal(xa, xb) and all(np.array_equal(a, b) for a, b in zip(ha, hb, strict=True))
    assert first.spheres[0][0] is second.spheres[0][0]
    if first.native_tables is not None:  # the C search's cell-major copy of each table: one, not one per projector
        assert all(a[1] is b[1] and a[2] is b[2] for a, b in zip(first.native_tables, second.native_tables,
                                                                  strict=True))
    assert NearProjector(c).spheres[0][0] is not first.spheres[0][0]  # outside a block: made anew


@pytest.mark.parametrize("name", ["box", "bevel20", "annulus"])
def test_host_constraints_make_their_triangle_table_on_first_read_with_the_eager_numbers(name):
    from jaxci.geometry.projection import HostConstraints

    mesh, info, eager, _ = setup(name)  # float64 on the device: every table made at once
    host = build_constraints(mesh, info, dtype=np.float64, device=False)
    assert isinstance(host, HostConstraints) and not host.has_triangles
    for field in ("x_orig", "surface_cand", "edge_cand", "surface_basis", "segments"):
        np.testing.assert_array_equal(getattr(host, field), np.asarray(getattr(eager, field)))
    assert not host.has_triangles  # reading the other fields made nothing
    np.testing.assert_array_equal(host.triangles, np.asarray(eager.triangles))
    assert host.has_triangles and host.triangles.dtype == np.float64 and host.triangle_patch.dtype == np.int32
    np.testing.assert_array_equal(host.triangle_patch, np.asarray(eager.triangle_patch))
    with pytest.raises(AttributeError, match="no attribute 'surface_tables'"):
        host.surface_tables  # noqa: B018 - any other missing name is still an AttributeError


def test_an_exact_projection_on_host_constraints_does_not_keep_the_table_it_made():
    mesh, info, eager, _ = setup("annulus")
    host = build_constraints(mesh, info, dtype=np.float64, device=False)
    x = moved("annulus", 5, 0.3)
    np.testing.assert_array_equal(project_np(host, x), project_np(eager, x))
    assert not host.has_triangles  # made for that search, and let go
    table = host.triangles  # read by another: made again, the same numbers, and kept
    np.testing.assert_array_equal(project_np(host, x), project_np(eager, x))
    assert host.triangles is table


def test_a_host_projector_makes_the_triangle_table_at_its_first_search_only():
    from jaxci.geometry.near import NearProjector

    mesh, info, eager, _ = setup("box")
    host = build_constraints(mesh, info, dtype=np.float64, device=False)
    pr = NearProjector(host)
    x = np.array(mesh.points, dtype=np.float64)
    keep = np.zeros(len(x), bool)
    keep[np.concatenate([host.surface_nodes, host.edge_nodes])] = True  # every boundary node left where it is
    y, hint = pr(x, keep)
    pr.commit(hint)
    assert np.array_equal(y, x) and not host.has_triangles
    trial = moved("box", 3, 0.2)
    (a, ha), (b, hb) = pr(trial), NearProjector(eager)(trial)
    assert host.has_triangles
    assert np.array_equal(a, b) and all(np.array_equal(u, v) for u, v in zip(ha, hb, strict=True))


def test_smoothing_a_box_on_the_host_never_makes_its_triangle_table(monkeypatch):
    import jaxci.geometry.projection as projection
    from jaxci import smooth

    def refuse(*args):
        raise AssertionError("the triangle table was made")

    mesh = perturb_box(6, amplitude=0.3, seed=2)
    monkeypatch.setattr(projection, "surface_triangles", refuse)
    res = smooth(mesh, engine="host", dtype="float64")
    assert res.after.max_condition < 1.0 + 1e-3 and res.after.inverted_corners == 0


@pytest.mark.shared
@pytest.mark.parametrize("name", sorted(MESQUITE_FIGURES))
def test_jax_equals_numpy_on_mesquite_meshes(name):
    path = MESQUITE / name
    import meshio

    m = meshio.vtk.read(str(path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = hex_mesh(m.points, m.cells_dict["hexahedron"])
    c = build_constraints(mesh, classify_boundary(mesh))
    lo, hi = mesh.points.min(0), mesh.points.max(0)
    h = float((hi - lo).max()) / max(mesh.n_hexes ** (1 / 3), 1.0)
    x = mesh.points + np.random.default_rng(0).uniform(-0.2 * h, 0.2 * h, mesh.points.shape)
    np.testing.assert_allclose(np.asarray(project(c, x)), project_np(c, x), rtol=0, atol=1e-12 * float(hi.max()))


def test_batched_and_per_node_projection_agree():
    mesh, _, c, _ = setup("bevel")
    xs = np.stack([moved("bevel", s, 0.4) for s in range(3)])  # (C, n, 3)
    batch = np.asarray(project(c, jnp.asarray(xs)))
    for k in range(3):
        np.testing.assert_allclose(batch[k], np.asarray(project(c, jnp.asarray(xs[k]))), rtol=0, atol=1e-15)
    idx = np.random.default_rng(0).choice(mesh.n_nodes, 40)  # any classes, repeats allowed
    sub = np.asarray(project_nodes(c, jnp.asarray(idx), jnp.asarray(xs[:, idx])))
    np.testing.assert_allclose(sub, batch[:, idx], rtol=0, atol=1e-15)


def test_projection_compiles_once():
    _, _, c1, _ = setup("box")
    c2 = build_constraints(perturb_box(4, seed=3), classify_boundary(perturb_box(4, seed=3)), dtype=jnp.float64)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(c, x):
        return project(c, x)

    for c, seed in ((c1, 0), (c1, 1), (c2, 2)):
        run(c, jnp.asarray(moved("box", seed, 0.3)))


# ------------------------------------------------------------------------------------------------ parameters


@pytest.mark.parametrize("n", [2, 3, 5, 9])
def test_n_free_formula(n):
    mesh = box(n)
    c = build_constraints(mesh, classify_boundary(mesh))
    assert n_free(c) == 3 * (n - 1) ** 3 + 2 * 6 * (n - 1) ** 2 + 12 * (n - 1)
    assert n_free(build_constraints(box(9), classify_boundary(box(9)))) == 2400


@pytest.mark.parametrize("name", ["box", "bevel", "annulus"])
def test_zero_parameters_give_x0(name):
    mesh, _, c, _ = setup(name)
    u = jnp.zeros(n_free(c))
    np.testing.assert_allclose(np.asarray(params_to_points(c, u, mesh.points)), mesh.points, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(np.asarray(points_to_params(c, mesh.points, mesh.points)), np.zeros(n_free(c)))


def test_parameter_jacobian_is_the_tangent_basis_on_planar_boundaries():
    """On planar patches and straight edges d params_to_points / du at u = 0 is exactly B (not 0 at vertices)."""
    mesh, info, c, _ = setup("slab")
    x0 = jnp.asarray(mesh.points)
    jac = np.asarray(jax.jit(jax.jacfwd(lambda u: params_to_points(c, u, x0)))(jnp.zeros(n_free(c))))
    basis = basis_matrix(c, mesh.n_nodes)
    np.testing.assert_allclose(jac, basis, rtol=0, atol=1e-15)
    assert np.abs(jac[info.node_class == CORNER]).max() == 0.0
    moving = np.abs(jac).sum(axis=1) > 0  # (n_nodes, n_free): which parameters move each node
    assert (moving[info.node_class == SURFACE].sum(1) == 2).all() and (
        moving[info.node_class == EDGE].sum(1) == 1
    ).all()


_jacobian_at = jax.jit(jax.jacfwd(params_to_points, argnums=1))  # constraints traced: compiles once per shape


def basis_matrix(c, n_nodes):
    """B as an array of shape (n_nodes, 3, n_free), written independently of params_to_points."""
    basis = np.zeros((n_nodes, 3, n_free(c)))
    ni, ns = len(c.interior_nodes), len(c.surface_nodes)
    for k, v in enumerate(np.asarray(c.interior_nodes)):
        basis[v, :, 3 * k : 3 * k + 3] = np.eye(3)
    for k, v in enumerate(np.asarray(c.surface_nodes)):
        basis[v, :, 3 * ni + 2 * k : 3 * ni + 2 * k + 2] = np.asarray(c.surface_basis[k]).T
    for k, v in enumerate(np.asarray(c.edge_nodes)):
        basis[v, :, 3 * ni + 2 * ns + k] = np.asarray(c.edge_tangent[k])
    return basis


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_parameter_jacobian_on_rotated_perturbed_boxes(seed):
    """Tilted planes: rounding noise at the vertices must not break the preference for triangle projections."""
    from scipy.spatial.transform import Rotation

    m0 = perturb_box(3, seed=seed % 1000, amplitude=0.3)
    rot = Rotation.random(random_state=seed).as_matrix()
    mesh = hex_mesh(m0.points @ rot.T + [0.3, -1.2, 2.0], m0.hexes)
    c = build_constraints(mesh, classify_boundary(mesh), dtype=jnp.float64)
    jac = np.asarray(_jacobian_at(c, jnp.zeros(n_free(c)), jnp.asarray(mesh.points)))
    np.testing.assert_allclose(jac, basis_matrix(c, mesh.n_nodes), rtol=0, atol=1e-13)


def test_bases_are_orthonormal_and_tangent():
    mesh, info, c, _ = setup("annulus")
    b = np.asarray(c.surface_basis)
    np.testing.assert_allclose(np.einsum("sik,sjk->sij", b, b), np.broadcast_to(np.eye(2), (len(b), 2, 2)), atol=1e-14)
    x = mesh.points[np.asarray(c.surface_nodes)]
    r = np.hypot(x[:, 0], x[:, 1])
    side = np.isclose(r, 0.5) | np.isclose(r, 1.0)
    radial = np.stack([x[:, 0] / r, x[:, 1] / r, 0 * r], axis=1)
    assert np.abs(np.einsum("sk,sjk->sj", radial[side], b[side])).max() < 1e-12  # tangent to the cylinder
    t = np.asarray(c.edge_tangent)
    xe = mesh.points[np.asarray(c.edge_nodes)]
    assert np.abs((t * xe).sum(1)).max() < 1e-12  # circle tangents are orthogonal to the radius (z part is 0)
    del info


def test_parameter_round_trip_and_batches():
    mesh, _, c, h = setup("slab")
    rng = np.random.default_rng(5)
    u = jnp.asarray(rng.uniform(-0.3 * h, 0.3 * h, (2, n_free(c))))  # a batch of 2
    x = params_to_points(c, u, mesh.points)
    assert x.shape == (2, mesh.n_nodes, 3)
    np.testing.assert_allclose(np.asarray(points_to_params(c, x, mesh.points)), np.asarray(u), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(x[1]), np.asarray(params_to_points(c, u[1], mesh.points)), atol=0)
    with pytest.raises(ValueError, match="free coordinates"):
        params_to_points(c, jnp.zeros(n_free(c) + 1), mesh.points)


def test_constraints_without_sliding_nodes():
    """Fixed boundaries and a single hexahedron: no surface or edge node, padded tables, still jit-able."""
    mesh = box(3)
    c = build_constraints(mesh, classify_boundary(mesh, fix_boundary=True), dtype=jnp.float64)
    assert n_free(c) == 3 * 8 and c.surface_nodes.shape == (0,) and c.edge_nodes.shape == (0,)
    x = mesh.points + 0.01
    out = np.asarray(project(c, x))
    inner = np.asarray(c.interior_nodes)
    np.testing.assert_array_equal(np.delete(out, inner, axis=0), np.delete(mesh.points, inner, axis=0))
    np.testing.assert_array_equal(out[inner], x[inner])
    one = box(1)
    c1 = build_constraints(one, classify_boundary(one), dtype=jnp.float64)
    assert n_free(c1) == 0
    np.testing.assert_array_equal(np.asarray(project_nodes(c1, jnp.arange(8), one.points + 0.1)), one.points)
    np.testing.assert_array_equal(project_np(c1, one.points + 0.1), one.points)


@pytest.mark.shared
def test_planar_rings_in_blocks_are_the_whole_computation(monkeypatch):
    """`planar_rings` works through the surface nodes in blocks of `RING_CHUNK` (bounded temporaries): the same
    origins, normals and radii for any block size, on a paved mesh with curved walls and planar parts."""

    from jaxci.io import read_mesh
    from jaxci.optim import _moves

    mesh = read_mesh(str(MESQUITE / "pave3.e.vtk"))
    info = classify_boundary(mesh)
    cons = build_constraints(mesh, info, dtype=np.float64, device=False)
    whole = _moves.planar_rings(np.asarray(mesh.points), info.topology.faces, cons)
    assert (whole[:, 6] > 0).sum() > 100  # some planar rings, and some not
    assert ((whole[:, 6] == 0) & np.isin(np.arange(mesh.n_nodes), np.asarray(cons.surface_nodes))).any()
    monkeypatch.setattr(_moves, "RING_CHUNK", 7)
    np.testing.assert_array_equal(_moves.planar_rings(np.asarray(mesh.points), info.topology.faces, cons), whole)


@pytest.mark.parametrize("name", ["l_block", "annulus"])
def test_candidates_in_blocks_are_one_blocks(monkeypatch, name):
    """`jaxci.geometry.tables._ring_candidates` makes its rows `RING_BLOCK` nodes at a time: the same rows, the same
    padding, as every node at once."""
    from jaxci.geometry import tables

    mesh, info, _, _ = setup(name)
    whole = build_constraints(mesh, info, dtype=np.float64, device=False)
    ref = (np.array(whole.surface_cand), np.array(whole.edge_cand))
    monkeypatch.setattr(tables, "RING_BLOCK", 5)
    blocks = build_constraints(mesh, info, dtype=np.float64, device=False)
    np.testing.assert_array_equal(blocks.surface_cand, ref[0])
    np.testing.assert_array_equal(blocks.edge_cand, ref[1])
    assert len(ref[0]) > 5 and len(ref[1]) > 5


@pytest.mark.parametrize("name", ["l_block", "bevel20", "annulus", "pave3"])
def test_dropped_candidates_come_back_the_same(name):
    """`HostConstraints.drop_candidates` lets the surface nodes' candidate triangles go; the next read makes them
    again from the boundary faces in the mesh's own numbering (`jaxci.geometry.tables.surface_candidates`): the
    same numbers as the tables made in the boundary's numbering."""
    from jaxci.geometry.projection import HostConstraints

    if name == "pave3":
        if not MESQUITE.exists():
            pytest.skip(f"{MESQUITE} not found (../shared beside the repository)")
        from jaxci.io import read_mesh

        mesh = read_mesh(str(MESQUITE / "pave3.e.vtk"))
        info = classify_boundary(mesh)
    else:
        mesh, info, _, _ = setup(name)
    c = build_constraints(mesh, info, dtype=np.float64, device=False)
    assert isinstance(c, HostConstraints)
    cand = np.array(c.surface_cand)
    c.drop_candidates()
    assert "surface_cand" not in vars(c)
    np.testing.assert_array_equal(c.surface_cand, cand)
    assert c.surface_cand.dtype == np.int32
