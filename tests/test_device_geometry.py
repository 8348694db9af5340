"""The device path of the boundary (jaxci.geometry.device_topology, jaxci.geometry.device_constraints) against the
host functions: the same topology, classification, constraints and exact projection, computed under
``jax.transfer_guard("disallow")`` (every transfer explicit, through jaxci.runtime.transfer)."""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import MESQUITE, SHARED, SHARED_REASON

from jaxci import read_mesh
from jaxci.geometry import device_topology
from jaxci.geometry.boundary import classify_boundary, fix_nodes
from jaxci.geometry.device_constraints import (
    device_classify_boundary,
    device_constraints,
    device_unit_frame,
    hexahedral,
    project_boundary,
)
from jaxci.geometry.device_topology import compact, device_mesh_topology
from jaxci.geometry.projection import build_constraints, project_np
from jaxci.geometry.topology import boundary_topology
from jaxci.mesh import hex_mesh, unit_frame
from jaxci.mesh.blocks import CellBlock
from jaxci.mesh.generate import perturb_box
from jaxci.mesh.shapes import annulus
from jaxci.mesh.sorting import HASH_MIX, position_bits
from jaxci.runtime.sizes import bucket
from jaxci.runtime.transfer import to_device, to_host

EXODUS = SHARED / "data" / "exodus"
TOPOLOGY_FIELDS = ("faces", "face_hex", "edges", "face_edges", "edge_face_ptr", "edge_face", "nonmanifold_faces",
                   "face_type", "face_cell")
INFO_FIELDS = ("node_class", "patch_id", "curve_id", "face_patch", "edge_is_feature", "feature_edges", "edge_curve")


def _meshes() -> dict:
    """Boxes, a curved annulus and the real meshes of ../shared (those present)."""
    cube = perturb_box(1, amplitude=0.0)
    out = {"box": perturb_box(5, amplitude=0.3, seed=1), "flat_box": perturb_box(3, 4, 2, amplitude=0.0),
           "annulus": annulus(16, 2, 3),
           # a hexahedron listed twice: no boundary face, every node interior
           "doubled_hex": hex_mesh(cube.points, np.concatenate([cube.hexes, cube.hexes]))}
    for path in sorted(MESQUITE.glob("*.vtk")) + sorted(EXODUS.glob("*.g")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out[path.name] = read_mesh(path)
    return out


MESHES = _meshes()
#: The meshes the device path is checked on (each compiles its programs: a few seconds): boxes, a curved
#: boundary, real meshes with inverted cells (pave3), shells and side sets (2block1, two-block).
HEXAHEDRAL = {k: m for k, m in MESHES.items() if hexahedral(m) and k in (
    "box", "annulus", "doubled_hex", "single_hex.vtk", "pave3.e.vtk", "2block1.g", "two-block.g")}


def _conn(hexes, pad: int | None = None):
    """The (8, M) device connectivity of `hexes`, with `pad` copies of hexahedron 0 appended (default: up to its
    size class, as a run pads it; the meshes of one class share the compiled programs)."""
    h = np.asarray(hexes)
    pad = bucket(len(h)) - len(h) if pad is None else pad
    h = np.concatenate([h, np.repeat(h[:1], pad, axis=0)])
    return to_device(np.ascontiguousarray(h.T), np.int32)


def _same(a: np.ndarray, b: np.ndarray, what: str) -> None:
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape, (what, a.dtype, b.dtype, a.shape, b.shape)
    np.testing.assert_array_equal(a, b, err_msg=what)


def _check_topology(hexes, n_nodes, pad: int | None = None, **kw):
    ref = boundary_topology(hexes, n_nodes)
    conn = _conn(hexes, pad)
    with jax.transfer_guard("disallow"):
        topo, unused = device_mesh_topology(conn, n_nodes, n_hexes=len(hexes), **kw)
    for f in TOPOLOGY_FIELDS:
        _same(getattr(topo, f), getattr(ref, f), f)
    used = np.zeros(n_nodes, bool)
    used[np.asarray(hexes).ravel()] = True
    _same(unused, np.flatnonzero(~used), "unused")
    return topo


@pytest.mark.parametrize("name", sorted(HEXAHEDRAL))
def test_device_topology_is_the_host_topology(name):
    mesh = HEXAHEDRAL[name]
    _check_topology(mesh.hexes, mesh.n_nodes)


def test_device_topology_ignores_padding_and_finds_nonmanifold_faces_and_unused_nodes():
    mesh = MESHES["box"]
    h = np.asarray(mesh.hexes)
    # the other tests pad the connectivity to its size class (the padding repeats hexahedron 0, whose faces stay
    # boundary faces); this one is not padded. Hexahedron 0 (a corner of the box) listed twice: its 3 inner faces
    # are faces of 3 cells, its boundary faces of 2; hexahedron 7 listed 5 times: its faces of 5 or 6 cells
    # (groups longer than the window of the sort's comparisons); three nodes of no cell
    topo = _check_topology(np.concatenate([h, h[:1], *[h[7:8]] * 4]), mesh.n_nodes + 3, pad=0)
    assert topo.n_nonmanifold_faces == 3 + 6


def _hash_clashes(hexes, n_nodes, bits: int) -> int:
    """How many pairs of distinct face keys of `hexes` share their hash truncated to `bits` bits (the one
    device_topology sorts by)."""
    from jaxci.geometry.topology import HEX_FACES

    s = np.sort(np.asarray(hexes)[:, HEX_FACES].reshape(-1, 4).astype(np.int64), axis=1)
    keys = np.unique(s[:, 0] * n_nodes + s[:, 1] + 1j * (s[:, 2] * n_nodes + s[:, 3]))
    k1, k2 = keys.real.astype(np.int64).view(np.uint64), keys.imag.astype(np.int64).view(np.uint64)
    with np.errstate(over="ignore"):
        h = (k1 * HASH_MIX[0] + k2) * HASH_MIX[1] >> np.uint64(64 - bits)
    _, counts = np.unique(h, return_counts=True)
    return int((counts * (counts - 1) // 2).sum())


@pytest.mark.parametrize("bits, exact", [(10, False), (1, True)])
def test_hash_collisions_are_resolved_exactly(monkeypatch, bits, exact):
    """A truncated hash makes different faces share a run of the sort: short runs are resolved by comparing
    neighbours (10 bits), long ones by the exact sort of the keys (1 bit); the topology is the host's."""
    mesh = MESHES["box"]
    assert _hash_clashes(mesh.hexes, mesh.n_nodes, bits) > 0
    assert bits <= 64 - position_bits(6 * mesh.n_hexes)
    calls = []
    real = device_topology._face_groups

    def spy(*args, **kw):
        calls.append(kw.get("exact", False))
        return real(*args, **kw)

    monkeypatch.setattr(device_topology, "_face_groups", spy)
    _check_topology(mesh.hexes, mesh.n_nodes, _hash_bits=bits)
    assert calls == ([False, True] if exact else [False])


@pytest.mark.parametrize("size", [0, 7, 300])
def test_compact_is_nonzero(size):
    rng = np.random.default_rng(size)
    mask = np.zeros(1001, bool)
    mask[rng.choice(1001, size, replace=False)] = True
    got = jax.jit(compact, static_argnums=1)(jnp.asarray(mask), size + 3)  # 3 padding entries
    np.testing.assert_array_equal(np.asarray(got), np.r_[np.flatnonzero(mask), [1001] * 3])


def _device_info(mesh, points, **kw):
    conn = _conn(mesh.hexes)
    with jax.transfer_guard("disallow"):
        topo, unused = device_mesh_topology(conn, mesh.n_nodes, n_hexes=mesh.n_hexes)
        return device_classify_boundary(mesh, points, topo, unused, **kw)


CLASSIFY_ARGS = [{}, {"fix_boundary": True}, {"feature_angle": 20.0, "fixed_nodes": [0, 5]}]


@pytest.mark.parametrize("kw", CLASSIFY_ARGS, ids=["default", "fix_boundary", "fixed"])
@pytest.mark.parametrize("name", sorted(HEXAHEDRAL))
def test_device_classification_is_the_host_classification(name, kw):
    mesh = HEXAHEDRAL[name]
    with warnings.catch_warnings(record=True) as host_warnings:
        warnings.simplefilter("always")
        ref = classify_boundary(mesh, **kw)
    with warnings.catch_warnings(record=True) as device_warnings:
        warnings.simplefilter("always")
        info = _device_info(mesh, to_device(np.asarray(mesh.points), np.float64), **kw)
    assert [str(w.message) for w in device_warnings] == [str(w.message) for w in host_warnings]
    for f in INFO_FIELDS:
        _same(getattr(info, f), getattr(ref, f), f)
    assert (info.n_patches, info.n_curves, info.notes) == (ref.n_patches, ref.n_curves, ref.notes)
    assert info.counts == ref.counts
    c = info.classes
    _same(c.nodes, np.flatnonzero(ref.node_class), "classes.nodes")
    for f in ("node_class", "patch_id", "curve_id"):
        _same(getattr(c, f), getattr(ref, f)[c.nodes], f"classes.{f}")


def test_classes_follow_fix_nodes():
    info = classify_boundary(MESHES["box"])
    fixed = fix_nodes(info, np.array([0, 40, 41]))  # a corner, interior nodes
    assert fixed.counts["corner"] == info.counts["corner"] + 2
    np.testing.assert_array_equal(fixed.classes.nodes, np.flatnonzero(fixed.node_class))
    np.testing.assert_array_equal(fixed.classes.node_class, fixed.node_class[fixed.classes.nodes])


def test_device_unit_frame_is_unit_frame():
    pts = np.asarray(MESHES["annulus"].points) * 1e5 + 3.0
    with jax.transfer_guard("disallow"):
        centre, scale = device_unit_frame(to_device(pts, np.float64))
    ref = unit_frame(pts)
    np.testing.assert_array_equal(centre, ref[0])
    assert scale == ref[1]


def test_device_path_refuses_other_cells():
    from jaxci.mesh.shapes import l_block

    mesh = l_block(2)
    wedge = dataclasses.replace(mesh, cells=[*mesh.cells, CellBlock("wedge", np.array([[0, 1, 2, 3, 4, 5]]))])
    assert hexahedral(mesh) and not hexahedral(wedge)
    with pytest.raises(ValueError, match="linear hexahedra only"):
        device_classify_boundary(wedge, to_device(np.asarray(wedge.points)), boundary_topology(mesh.hexes, 1),
                                 np.zeros(0, np.int64))


@pytest.mark.parametrize("name, dtype", [("box", np.float64), ("box", np.float32), ("annulus", np.float32),
                                         ("pave3.e.vtk", np.float64), ("2block1.g", np.float32),
                                         ("two-block.g", np.float64), ("doubled_hex", np.float32)])
def test_device_constraints_are_build_constraints(name, dtype):
    if name not in HEXAHEDRAL:
        pytest.skip(SHARED_REASON)
    mesh = HEXAHEDRAL[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref_info = classify_boundary(mesh, fixed_nodes=[3])
        points = to_device(np.asarray(mesh.points), np.float64)
        info = _device_info(mesh, points, fixed_nodes=[3])
    ref = build_constraints(mesh, ref_info, dtype=dtype, device=False)
    with jax.transfer_guard("disallow"):
        cons, tables = device_constraints(points, info, dtype=dtype)
    got = to_host(cons)
    for f in dataclasses.fields(ref):
        _same(getattr(got, f.name), getattr(ref, f.name), f.name)
        assert isinstance(getattr(cons, f.name), jax.Array), f.name
    _same(tables.corner_points, np.asarray(mesh.points, np.float64)[tables.corner_nodes], "corner_points")


@pytest.mark.parametrize("name", ["box", "annulus", "pave3.e.vtk"])
def test_project_boundary_is_project_np(name):
    if name not in HEXAHEDRAL:
        pytest.skip(SHARED_REASON)
    mesh = HEXAHEDRAL[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref_info = classify_boundary(mesh)
        points = to_device(np.asarray(mesh.points), np.float64)
        info = _device_info(mesh, points)
    host = build_constraints(mesh, ref_info, dtype=np.float64, device=False)
    rng = np.random.default_rng(3)
    x = np.asarray(mesh.points) + 0.2 * rng.standard_normal(mesh.points.shape) * np.ptp(mesh.points, axis=0) / 8
    x_dev = to_device(x, np.float64)
    with jax.transfer_guard("disallow"):
        cons, tables = device_constraints(points, info, dtype=np.float32)  # the solver's dtype: the search is float64
        projected = project_boundary(cons, tables, x_dev)
    ref = project_np(host, x)
    got = to_host(projected)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, ref)
    assert (got != x).any(axis=1).sum() > len(tables.surface_nodes) // 2  # it moved the boundary nodes
