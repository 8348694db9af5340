"""Untangling: the Mesquite tangled meshes come out with no inverted element and the boundary kept."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import MESQUITE

from jaxci import native
from jaxci.cells import corner_determinants
from jaxci.errors import ConfigError, InvertedMeshError
from jaxci.geometry.boundary import classify_boundary
from jaxci.geometry.projection import build_constraints, project_np
from jaxci.interface.smooth import smooth
from jaxci.io import read_mesh
from jaxci.mesh.generate import perturb_box
from jaxci.optim.untangle import UntangleParams, untangle
from jaxci.runtime.phases import compile_totals


def boundary_error(mesh_in, points) -> float:
    """Largest move of a node under the exact projection onto mesh_in's boundary, relative to its size."""
    cons = build_constraints(mesh_in, classify_boundary(mesh_in), dtype=np.float64)
    x = np.asarray(points)
    size = float(np.ptp(np.asarray(mesh_in.points), axis=0).max())
    return float(np.abs(project_np(cons, x) - x).max()) / size


@pytest.mark.shared
@pytest.mark.parametrize("name,method,params", [
    ("hex_5_tangled.vtk", "lbfgs", {}),
    ("pave3.e.vtk", "smart-laplace", {"max_sweeps": 10}),  # a few sweeps: this test is about untangling
])
def test_tangled_meshes_are_untangled_with_the_boundary_kept(name, method, params):
    mesh = read_mesh(MESQUITE / name)
    before = mesh.points.copy()
    res = smooth(mesh, method, dtype="float64", untangle="auto", **params)
    assert res.before.inverted_elements > 0
    assert res.after.inverted_elements == 0 and res.after.inverted_corners == 0
    assert (corner_determinants(res.mesh.points, mesh.hexes) > 0).all()
    assert boundary_error(mesh, res.mesh.points) <= 1e-9
    assert any(n.startswith("untangling:") and "untangled" in n for n in res.notes)
    assert np.isfinite(res.after.objective) and res.after.objective <= 2.0
    np.testing.assert_array_equal(mesh.points, before)  # the input is never modified
    if name == "hex_5_tangled.vtk":  # a tangled 5x5x5 block of a box: back to the perfect grid
        assert res.after.max_condition <= 1 + 1e-6
        # untangle="always" on the (valid) result: nothing to do (same shapes: compiled code is reused)
        again = smooth(res.mesh, method, dtype="float64", untangle="always")
        assert any("nothing to do" in n for n in again.notes)
        assert again.after.max_condition <= 1 + 1e-6


NEEDS_C = pytest.mark.skipif(not native.AVAILABLE, reason="the untangling's Laplace sweeps are the C kernels")


@pytest.mark.shared
@pytest.mark.parametrize("name,sweeps,laplace", [
    pytest.param("hex_5_tangled.vtk", 1, True, marks=NEEDS_C),  # one sweep of the plain Laplacian untangles it
    pytest.param("pave3.e.vtk", 1, False, marks=NEEDS_C),  # one leaves 57 of 106 inverted: the Winslow rounds
    ("pave3.e.vtk", 0, False),
])
def test_a_laplace_sweep_first_where_it_untangles(name, sweeps, laplace):
    """`UntangleParams.laplace_sweeps` (default: 1 from `LAPLACE_UNTANGLE_FROM` hexahedra, 0 below): plain
    Laplace sweeps before the Winslow rounds; their result is the stage's where it leaves every corner above the
    margin (the note says how it was untangled), else the rounds start from the input as without them (the same
    result as ``laplace_sweeps=0``); boundary nodes stay on the boundary either way."""
    mesh = read_mesh(MESQUITE / name)
    res = smooth(mesh, untangle_laplace_sweeps=sweeps)
    note = next(n for n in res.notes if n.startswith("untangling:"))
    assert res.after.inverted_elements == 0
    assert boundary_error(mesh, res.mesh.points) <= 1e-9
    assert ("sweep of the plain Laplacian" in note) is laplace
    if sweeps and not laplace:
        assert "after 1 Laplace sweeps that did not untangle it" in note
        plain = smooth(mesh, untangle_laplace_sweeps=0)
        np.testing.assert_array_equal(res.mesh.points, plain.mesh.points)
    if laplace:
        assert res.after.max_condition <= 1 + 1e-5


@pytest.mark.shared
@NEEDS_C
def test_a_laplace_untangled_mesh_skips_the_default_presmoothing(monkeypatch):
    """Where the untangling's plain Laplace sweep untangled the mesh it has just smoothed it too: the default
    pipeline then runs L-BFGS without its smart-Laplace sweeps (and says so); presmoothing the user asked for
    runs as asked."""
    import jaxci.interface.methods

    monkeypatch.setattr(jaxci.interface.methods, "AUTO_PRESMOOTH_FROM", 1)  # the default presmoothing on a small mesh
    mesh = read_mesh(MESQUITE / "hex_5_tangled.vtk")
    auto = smooth(mesh, untangle_laplace_sweeps=1)
    assert int(auto.history.get("presmooth", 0)) == 0 and auto.params.get("presmooth", 0) == 0
    assert any("Laplace sweep stands for the smart-Laplace sweeps" in n for n in auto.notes)
    assert auto.after.inverted_elements == 0 and auto.after.max_condition <= 1 + 1e-5
    asked = smooth(mesh, untangle_laplace_sweeps=1, presmooth=2)
    assert int(asked.history["presmooth"]) == 2
    winslow = smooth(mesh, untangle_laplace_sweeps=0)
    assert int(winslow.history["presmooth"]) == 3


@pytest.mark.shared
def test_the_default_laplace_sweep_from_a_size_on():
    """Below `LAPLACE_UNTANGLE_FROM` hexahedra the default untangles with the Winslow rounds alone (their
    set-up is cheaper than the sweep's); the threshold is where one sweep paid on cube60_pert."""
    from jaxci.optim import untangle as U

    mesh = read_mesh(MESQUITE / "hex_5_tangled.vtk")
    assert U.UntangleParams().laplace_sweeps is None and U.LAPLACE_UNTANGLE_FROM > mesh.n_hexes
    note = next(n for n in smooth(mesh).notes if n.startswith("untangling:"))
    assert "Winslow" in note and "Laplace" not in note
    with pytest.raises(ConfigError, match="laplace_sweeps"):
        UntangleParams(laplace_sweeps=-1)


def tangled_cube():
    mesh = perturb_box(2, amplitude=0.0)
    pts = mesh.points.copy()
    pts[13] = pts[13] + [0.9, 0.9, 0.9]  # the centre node pulled through the elements
    return mesh.with_points(pts)


def test_never_refuses_and_failure_is_reported_with_the_input_untouched():
    bad = tangled_cube()
    with pytest.raises(InvertedMeshError, match="untangle='never'"):
        smooth(bad, "lbfgs", untangle="never")
    before = bad.points.copy()
    with pytest.raises(InvertedMeshError, match="cannot be untangled"):  # nothing may move: refused at once
        smooth(bad, "lbfgs", fixed_nodes=np.arange(bad.n_nodes))
    # one L-BFGS step (the evaluation at the start) in one round: the stage fails, with exact counts
    with pytest.raises(InvertedMeshError, match=r"untangling failed: 7 elements are inverted after 1 rounds "
                                                r"\(7 were in the input; \d L-BFGS steps.*input is left unchanged"):
        smooth(bad, "lbfgs", untangle_max_rounds=1, untangle_inner_steps=1)
    np.testing.assert_array_equal(bad.points, before)


def test_bad_parameters():
    mesh = perturb_box(2, amplitude=0.1, seed=1)
    with pytest.raises(ConfigError, match="margin"):
        smooth(tangled_cube(), "lbfgs", untangle_margin=2.0)
    with pytest.raises(ConfigError, match="untangle must be"):
        smooth(mesh, "lbfgs", untangle="sometimes")


@pytest.fixture(scope="module")
def hex5():
    mesh = read_mesh(MESQUITE / "hex_5_tangled.vtk")
    info = classify_boundary(mesh)
    return mesh, info, build_constraints(mesh, info, dtype=np.float64)


@pytest.mark.shared
def test_every_round_runs_in_one_compiled_loop(hex5):
    """Rounds, steps, margin, theta and tolerances are traced: once compiled for a mesh, no value compiles again,
    however many rounds a run takes."""
    mesh, info, cons = hex5
    with jax.enable_x64(True):
        untangle(mesh, info, cons)
        before = compile_totals()["compiled"]
        _, many = untangle(mesh, info, cons, UntangleParams(margin=0.3, inner_steps=50, rtol=1e-5))
        _, few = untangle(mesh, info, cons, UntangleParams(max_rounds=3, theta=0.3, atol=1e-6))
    assert compile_totals()["compiled"] == before
    assert many["rounds"] > 10 and len(many["eps"]) == len(many["energy"]) == many["rounds"]
    assert len(many["min_det"]) == many["rounds"] + 1 and few["untangled"]


@pytest.mark.shared
def test_flat_regions_first_then_the_projection(hex5):
    """On a box every moving boundary node has a flat region: the rounds run without the projection; a round
    that ends with a node near the edge of its region (here: any move, flat_reach=0) hands over to the
    projection, and the result is on the original boundary either way."""
    mesh, info, cons = hex5
    with jax.enable_x64(True):
        x, rep = untangle(mesh, info, cons, UntangleParams(backend="jax"))  # the compiled loop's strict runs
        y, rep2 = untangle(mesh, info, cons, UntangleParams(inner_steps=6, backend="jax"), flat_reach=0.0)
        z, rep3 = untangle(mesh, info, cons)  # a small mesh: numpy, which projects only where it must
    assert [r[0] for r in rep3["runs"]] == ["numpy"] and rep3["untangled"]
    assert [r[0] for r in rep["runs"]] == ["flat regions"] and rep["untangled"]
    assert [r[0] for r in rep2["runs"]] == ["flat regions", "projected"] and rep2["untangled"]
    assert rep2["steps"] == sum(r[2] for r in rep2["runs"]) and rep2["rounds"] == sum(r[1] for r in rep2["runs"])
    for pts in (x, y, z):
        assert boundary_error(mesh, pts) <= 1e-9
        assert (corner_determinants(pts, mesh.hexes) > 0).all()


# --------------------------------------------------------------------------------------------- --untangle-boundary
def pit_slab():
    """A 2 x 2 x 1 box whose top centre node is pushed below the bottom face: its four hexahedra are inverted,
    and only boundary nodes touch them (the top centre a corner of the pit it makes, the rest the box's corners
    and edges, the bottom centre held in the bottom plane), so no allowed move untangles them."""
    from jaxci.mesh.generate import box

    mesh = box(2, 2, 1)
    p = np.array(mesh.points, dtype=np.float64)
    top = np.flatnonzero((np.abs(p[:, 0] - 0.5 * p[:, 0].max()) < 1e-9) & (np.abs(p[:, 1] - 0.5 * p[:, 1].max()) < 1e-9)
                         & (p[:, 2] == p[:, 2].max()))
    p[top, 2] = -0.2 * p[:, 2].max()
    return mesh.with_points(p)


def test_untangle_boundary_frees_the_corner_and_edge_nodes_that_hold_an_inversion():
    """Without the flag the stage fails and its message names the way out; with it the mesh is untangled by
    sliding a few of the boundary's corner and edge nodes on the original surface, every other node of the
    boundary stays where it was, and a note says how many moved. Nodes the user fixed are never freed."""
    from jaxci.geometry.boundary import slide_on_surface

    mesh = pit_slab()
    with pytest.raises(InvertedMeshError, match="--untangle-boundary"):
        smooth(mesh)
    res = smooth(mesh, untangle_boundary=True)
    assert res.after.inverted_elements == 0 and res.after.inverted_corners == 0
    note = [n for n in res.notes if n.startswith("untangle_boundary:")]
    assert len(note) == 1, res.notes
    x0, x = np.asarray(mesh.points), np.asarray(res.mesh.points)
    info = classify_boundary(mesh)
    moved = np.flatnonzero((x != x0).any(axis=1) & (np.asarray(info.node_class) == 3))  # corners never move else
    assert 0 < len(moved) <= int(note[0].split()[1]) <= 4, (moved, note)
    # each moved corner lies on the original boundary surface (the patch it slid on)
    cons = build_constraints(mesh, slide_on_surface(info, moved), dtype=np.float64, device=False)
    np.testing.assert_allclose(project_np(cons, x)[moved], x[moved], atol=1e-12)
    with pytest.raises(InvertedMeshError):
        smooth(mesh, untangle_boundary=True, fix_boundary=True)
    assert (np.asarray(info.node_class)[moved] == 3).all()  # slide_on_surface left `info` itself alone


def test_untangle_boundary_from_the_command_line(tmp_path):
    from jaxci.cli import main
    from jaxci.io import write_mesh

    write_mesh(pit_slab(), str(tmp_path / "in.vtu"))
    assert main(["smooth", str(tmp_path / "in.vtu"), str(tmp_path / "a.vtu")]) == 2
    assert not (tmp_path / "a.vtu").exists()
    assert main(["smooth", str(tmp_path / "in.vtu"), str(tmp_path / "b.vtu"), "--untangle-boundary"]) == 0
    assert read_mesh(str(tmp_path / "b.vtu")).n_hexes == 4


@pytest.mark.parametrize("chunk", [1, 7])
def test_the_scaled_min_det_in_blocks_is_one_blocks(monkeypatch, chunk):
    """The untangling's min det / L^3 (`_scaled_min_det`) is measured `MIN_DET_CHUNK` hexahedra at a time: the same
    number as in one block (7 does not divide the 64 hexahedra), on a box with an interior node moved through its
    cell."""
    from jaxci.optim import untangle as U

    mesh = perturb_box(4, amplitude=0.3, seed=5)
    lens = U._safe_lengths(U.element_lengths(mesh.points, mesh.hexes))
    x = np.array(mesh.points, np.float64)
    x[mesh.hexes[21, 6]] = x[mesh.hexes[21, 0]] - 0.05  # through its cell: inverted corners
    assert (corner_determinants(x, mesh.hexes) <= 0).any()
    monkeypatch.setattr(U, "MIN_DET_CHUNK", 10**9)
    whole = U._scaled_min_det(mesh, x, lens)
    monkeypatch.setattr(U, "MIN_DET_CHUNK", chunk)
    assert U._scaled_min_det(mesh, x, lens) == whole < 0
