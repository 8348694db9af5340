"""The hashed sorts beneath the boundary faces (jaxci.geometry.topology) and the coincident nodes
(jaxci.mesh.coincident) give exactly what a plain reference gives, also when their hashes collide; and a mesh made
from another's checked cell blocks (jaxci.mesh.HexMesh) skips only the connectivity checks."""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest

import jaxci.geometry.topology as topology
import jaxci.mesh as mesh_module
import jaxci.mesh.coincident as coincident
import jaxci.mesh.sorting as sorting
from jaxci.errors import MeshError
from jaxci.geometry.topology import CELL_FACES, boundary_topology
from jaxci.mesh import CellBlock, HexMesh, close_pairs
from jaxci.mesh.generate import perturb_box


def reference_faces(blocks: dict) -> tuple[list, list]:
    """Boundary faces (in cell-block order) and the sorted nodes of faces shared by 3+ cells, by counting the
    sorted node tuples in a dict (a triangle [a, b, c, c] keyed as (-1, a, b, c) where cell types are mixed)."""
    faces = [f for t, cells in blocks.items() for c in cells for f in c[CELL_FACES[t]].tolist()]
    mixed = len(blocks) > 1

    def key(f):
        return tuple(sorted(f[:3] + [-1])) if mixed and f[3] == f[2] else tuple(sorted(f))

    count = Counter(key(f) for f in faces)
    return [f for f in faces if count[key(f)] == 1], sorted(k for k, c in count.items() if c >= 3)


def awkward_meshes():
    """A perturbed box numbered at random with one hexahedron three times (faces shared by 3 cells), and a mixed
    one whose wedges and tetrahedra are listed twice."""
    m = perturb_box(4, amplitude=0.3, seed=2)
    perm = np.random.default_rng(0).permutation(m.n_nodes)
    h = perm[m.hexes]
    yield {"hexahedron": np.concatenate([h, h[5:6], h[5:6]])}
    w = np.concatenate([h[:4, [0, 1, 2, 4, 5, 6]], h[:4, [0, 2, 3, 4, 6, 7]]])
    yield {"hexahedron": h[4:], "wedge": np.concatenate([w, w[:2]]), "tetra": np.array([h[4, :4], h[4, :4]])}


@pytest.mark.parametrize("mix", [None, (0, 0), (1, 3)])
@pytest.mark.parametrize("window", [16, 2])
def test_boundary_faces_match_a_dict_count_even_when_every_hash_collides(monkeypatch, mix, window):
    if mix is not None:  # (0, 0): every face hashes alike; (1, 3): a weak hash, many collisions
        monkeypatch.setattr(sorting, "_MIX", tuple(np.uint64(v) for v in mix))
    monkeypatch.setattr(sorting, "_WINDOW_BITS", window)  # 2: the leading-key windows in use on a small mesh
    for blocks in awkward_meshes():
        hexes = blocks["hexahedron"]
        others = {t: c for t, c in blocks.items() if t != "hexahedron"} or None
        topo = boundary_topology(hexes, int(hexes.max()) + 1, others)
        faces, shared3 = reference_faces(blocks)
        assert topo.faces.tolist() == faces
        assert topo.nonmanifold_faces.tolist() == [list(k) for k in shared3] and len(shared3)
        hex_faces = len(hexes) * 6
        face_index = np.flatnonzero(topo.face_hex >= 0)
        assert (topo.face_hex[face_index] < len(hexes)).all() and hex_faces > 0
        for f, t, c in zip(topo.faces, topo.face_type, topo.face_cell, strict=True):
            name = topology.FACE_CELL_TYPES[t]
            assert f.tolist() in blocks[name][c][CELL_FACES[name]].tolist()
        # edges: sorted distinct sides, each face's sides found again through face_edges and edge_face
        sides = {tuple(sorted((a, b))) for f in faces for a, b in zip(f, f[1:] + f[:1], strict=True) if a != b}
        assert topo.edges.tolist() == sorted(map(list, sides))
        for e in range(len(topo.edges)):
            around = topo.edge_face[topo.edge_face_ptr[e]:topo.edge_face_ptr[e + 1]]
            assert list(around) == sorted(around) and all(e in topo.face_edges[f] for f in around)


def brute_pairs(p: np.ndarray, r: float) -> list:
    d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(axis=2)
    i, j = np.nonzero(np.triu(d2 <= r * r, k=1))
    return sorted(map(list, zip(i.tolist(), j.tolist(), strict=True)))


@pytest.mark.parametrize("weak", [False, True])
def test_close_pairs_match_all_distances_even_when_cell_keys_collide(monkeypatch, weak):
    if weak:  # small multipliers: many cells share a key, and most keys share their leading bits
        monkeypatch.setattr(coincident, "_HASH", np.array([3, 7, 1], dtype=np.uint64))
    rng = np.random.default_rng(4)
    grid = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) / 5
    cloud = rng.random((300, 3))
    for p in (np.concatenate([grid, grid[::7]]), np.concatenate([cloud, cloud[:40], cloud[:9] + 1e-13])):
        for r in (0.0, 1e-9, 0.05, 0.21):
            assert close_pairs(p, r).tolist() == brute_pairs(p, r), r


def test_a_mesh_from_checked_blocks_checks_only_its_points(monkeypatch):
    m = perturb_box(3, amplitude=0.2, seed=1)
    calls = []
    checked = HexMesh._checked_blocks
    monkeypatch.setattr(HexMesh, "_checked_blocks", lambda self, n, where: calls.append(n) or checked(self, n, where))
    moved = m.with_points(m.points * 2.0)
    same = dataclasses.replace(m, points=m.points + 1.0, fix_orientation=False, check_coincident=False)
    assert calls == [] and moved.cells == m.cells and same.cells == m.cells
    # the points are still checked: inverted elements noted, non-finite or far nodes refused
    bad = np.array(m.points)
    bad[m.hexes[0, 0]] = bad[m.hexes[0, 6]] + 0.3
    assert any("inverted hexahedra" in n for n in m.with_points(bad, midside="keep").notes)
    bad[0] = np.nan
    with pytest.raises(MeshError, match="non-finite"):
        m.with_points(bad)
    assert calls == []
    # other blocks, or the same blocks with another node count, are checked
    fresh = (CellBlock("hexahedron", np.array(m.hexes)),)
    HexMesh(m.points, fresh)
    with pytest.raises(MeshError, match="out of range"):
        dataclasses.replace(m, points=m.points[:-1])
    assert calls == [m.n_nodes, m.n_nodes - 1]
    assert mesh_module._checked_unused(fresh, m.n_nodes) is None  # the checked blocks are new CellBlocks


def test_checked_blocks_cannot_change_under_the_mesh():
    """The caller's writeable connectivity stays theirs (the mesh keeps a read-only copy): changing it afterwards
    changes neither the mesh nor a mesh derived from it without a re-check; the mesh's own arrays refuse writes."""
    from jaxci.mesh import hex_mesh

    box = perturb_box(3, amplitude=0.1, seed=0)
    pts, hexes = np.asarray(box.points), np.asarray(box.hexes).astype(np.int64).copy()
    m = hex_mesh(pts, hexes)
    hexes[0, 1] = hexes[0, 0]  # a repeated node, had the mesh shared this array
    derived = dataclasses.replace(m, points=pts)
    assert len(set(derived.hexes[0].tolist())) == 8 and np.array_equal(derived.hexes, box.hexes)
    with pytest.raises(ValueError, match="read-only"):
        m.hexes[0, 1] = m.hexes[0, 0]
    with pytest.raises(MeshError, match="repeats a node"):  # a fresh array is checked again
        HexMesh(pts, (CellBlock("hexahedron", hexes),))
