"""Exodus II files: read (SEACAS's real files from ../shared/data/exodus), smoothed, written back as the same file
with only the coordinates changed, written afresh from other formats, and refused clearly when broken."""

from __future__ import annotations

import dataclasses
import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import EXODUS

import jaxci
from jaxci.cli import main
from jaxci.errors import MeshReadError
from jaxci.io import LossyWriteWarning, read_mesh, write_mesh
from jaxci.mesh import CellBlock, HexMesh
from jaxci.mesh.generate import perturb_box

netCDF4 = pytest.importorskip("netCDF4")

DATA = EXODUS
COORDS = ("coordx", "coordy", "coordz", "coord")


def netcdf_contents(path, skip=COORDS) -> dict:
    """Every dimension, global attribute, variable (values, dtype, dimensions, attributes) of a netCDF file."""
    out = {}
    with netCDF4.Dataset(path) as ds:
        ds.set_auto_mask(False)
        out["format"] = ds.file_format
        out["dims"] = {k: (len(v), v.isunlimited()) for k, v in ds.dimensions.items()}
        out["attrs"] = {k: np.asarray(ds.getncattr(k)).tolist() for k in ds.ncattrs()}
        for k, v in ds.variables.items():
            if k in skip:
                continue
            out[k] = (str(v.dtype), v.dimensions, {a: np.asarray(v.getncattr(a)).tolist() for a in v.ncattrs()},
                      np.asarray(v[:]).tobytes())
    return out


def perturbed(mesh: HexMesh, seed: int = 0, amplitude: float = 0.15) -> HexMesh:
    """`mesh` with its interior nodes (strictly inside the bounding box) moved at random."""
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    inside = ((mesh.points > lo + 1e-9) & (mesh.points < hi - 1e-9)).all(axis=1)
    pts = mesh.points.copy()
    h = np.median(np.linalg.norm(mesh.points[mesh.hexes[:, 1]] - mesh.points[mesh.hexes[:, 0]], axis=1))
    pts[inside] += np.random.default_rng(seed).uniform(-amplitude, amplitude, (int(inside.sum()), 3)) * h
    return mesh.with_points(pts)


def to_netcdf4(src, dst, fmt: str = "NETCDF4") -> None:
    """A copy of a netCDF file in another netCDF format (netCDF-4 / HDF5, CDF-5), variable by variable."""
    with netCDF4.Dataset(src) as a, netCDF4.Dataset(dst, "w", format=fmt) as b:
        a.set_auto_mask(False)
        b.setncatts({k: a.getncattr(k) for k in a.ncattrs()})
        for k, d in a.dimensions.items():
            b.createDimension(k, None if d.isunlimited() else len(d))
        for k, v in a.variables.items():
            w = b.createVariable(k, v.dtype, v.dimensions)
            w.setncatts({n: v.getncattr(n) for n in v.ncattrs() if n != "_FillValue"})
            w.set_auto_mask(False)
            w[:] = v[:]


def exodus_file(path, points, blocks, node_ids=None) -> Path:
    """A minimal Exodus II file: `blocks` is a list of (elem_type, 1-based connectivity)."""
    with netCDF4.Dataset(path, "w", format="NETCDF3_64BIT_OFFSET") as ds:
        ds.setncatts({"api_version": np.float32(8), "version": np.float32(8), "floating_point_word_size": 8,
                      "file_size": 1, "title": "test"})
        ds.createDimension("num_dim", 3)
        ds.createDimension("num_nodes", len(points))
        ds.createDimension("num_elem", sum(len(c) for _, c in blocks))
        ds.createDimension("num_el_blk", len(blocks))
        ds.createDimension("time_step", None)
        for k, c in enumerate("xyz"):
            ds.createVariable(f"coord{c}", "f8", ("num_nodes",))[:] = np.asarray(points)[:, k]
        ds.createVariable("eb_prop1", "i4", ("num_el_blk",))[:] = np.arange(1, len(blocks) + 1)
        if node_ids is not None:
            ds.createVariable("node_num_map", "i4", ("num_nodes",))[:] = node_ids
        for k, (etype, conn) in enumerate(blocks, 1):
            conn = np.asarray(conn)
            ds.createDimension(f"num_el_in_blk{k}", conn.shape[0])
            ds.createDimension(f"num_nod_per_el{k}", conn.shape[1])
            v = ds.createVariable(f"connect{k}", "i4", (f"num_el_in_blk{k}", f"num_nod_per_el{k}"))
            v.elem_type = etype
            v[:] = conn
    return Path(path)


# ------------------------------------------------------------------------------------------------ reading
@pytest.mark.shared
@pytest.mark.parametrize("name, nodes, blocks, sets", [
    ("cube.g", 27, [("hexahedron", 8)], {f"surface_{k}": 9 for k in range(1, 7)}),
    ("two-block.g", 45, [("hexahedron", 8)] * 2, {"surface_1": 9, "surface_16": 9}),
    ("2block1.g", 125, [("hexahedron", 64), ("quad", 16), ("quad", 16)],
     {"nodelist_1": 25, "nodelist_6": 25, "surface_1": 25, "surface_2": 25}),
    ("8-block.g", 125, [("hexahedron", 8)] * 8, {}),
])
def test_reads_seacas_files(name, nodes, blocks, sets):
    mesh = read_mesh(DATA / name)
    assert mesh.n_nodes == nodes and [(b.type, len(b.data)) for b in mesh.cells] == blocks
    for k, n in sets.items():
        assert len(mesh.point_sets[k]) == n
    assert set(mesh.cell_sets) == {f"block_{k}" for k in range(1, len(blocks) + 1)}
    assert mesh.node_ids.tolist() == list(range(1, nodes + 1))
    assert mesh.field_data["exodus:file"] == str(DATA / name)


@pytest.mark.shared
def test_side_set_nodes_are_the_nodes_of_their_faces():
    mesh = read_mesh(DATA / "cube.g")  # 2x2x2 bricks on [0, 2]^3: side set k is one face of the cube
    flat = []
    for k in range(1, 7):
        p = mesh.points[mesh.point_sets[f"surface_{k}"]]
        span = np.ptp(p, axis=0)
        assert len(p) == 9 and (span == 0).sum() == 1 and (span == 2).sum() == 2
        flat.append((int(np.argmin(span)), float(p[0, np.argmin(span)])))
    assert sorted(flat) == [(a, b) for a in range(3) for b in (0.0, 2.0)]


# ------------------------------------------------------------------------------------------------ in place
@pytest.mark.shared
@pytest.mark.parametrize("name", ["cube.g", "two-block.g", "2block1.g", "8-block.g", "NETCDF4", "NETCDF3_64BIT_DATA"])
def test_written_back_with_only_the_coordinates_changed(tmp_path, name):
    src = DATA / (name if name.endswith(".g") else "8-block.g")
    if not name.endswith(".g"):  # netCDF-4 (HDF5) and CDF-5 copies of a SEACAS file
        to_netcdf4(src, tmp_path / "copy.e", name)
        src = tmp_path / "copy.e"
        assert netcdf_contents(src)["format"] == name
    mesh = read_mesh(src)
    moved = perturbed(mesh)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(moved, tmp_path / "out.e")
    assert netcdf_contents(tmp_path / "out.e") == netcdf_contents(src)
    back = read_mesh(tmp_path / "out.e")
    np.testing.assert_array_equal(back.points, moved.points)
    assert not np.array_equal(back.points, mesh.points)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / "same.e")
    assert netcdf_contents(tmp_path / "same.e", skip=()) == netcdf_contents(src, skip=())


@pytest.mark.shared
def test_smooth_through_the_cli_end_to_end(tmp_path, capsys):
    mesh = read_mesh(DATA / "8-block.g")
    write_mesh(perturbed(mesh, seed=3), tmp_path / "in.e")
    assert main(["smooth", str(tmp_path / "in.e"), str(tmp_path / "out.e")]) == 0
    capsys.readouterr()
    assert netcdf_contents(tmp_path / "out.e") == netcdf_contents(DATA / "8-block.g")
    before, after = read_mesh(tmp_path / "in.e"), read_mesh(tmp_path / "out.e")
    assert np.abs(after.points - before.points).max() > 1e-3
    assert main(["quality", str(tmp_path / "in.e"), "--json"]) == 0
    q_in = json.loads(capsys.readouterr().out)
    assert main(["quality", str(tmp_path / "out.e"), "--json"]) == 0
    q_out = json.loads(capsys.readouterr().out)
    assert q_out["n_elements"] == 64 and q_out["max_condition"] < q_in["max_condition"] - 0.01


# ------------------------------------------------------------------------------------------------ quadratic bricks
UNIT = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1.0]])
EDGE_ENDS = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 5), (2, 6), (3, 7), (4, 5), (5, 6), (6, 7), (7, 4)]
FACES = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 4, 7, 3), (1, 2, 6, 5), (0, 1, 5, 4), (2, 3, 7, 6)]  # nodes 22..27


def hex27_points() -> np.ndarray:
    mids = [(UNIT[a] + UNIT[b]) / 2 for a, b in EDGE_ENDS]
    return np.concatenate([UNIT, mids, [UNIT.mean(axis=0)], [UNIT[list(f)].mean(axis=0) for f in FACES]])


@pytest.mark.parametrize("nodes", [20, 27])
def test_hex20_and_hex27_midside_nodes(tmp_path, nodes):
    pts = hex27_points()[:nodes]
    src = exodus_file(tmp_path / "q.e", pts, [(f"HEX{nodes}", np.arange(1, nodes + 1)[None])])
    mesh = read_mesh(src)
    blk = mesh.cells[0]
    assert blk.data.tolist() == [list(range(8))]
    # jaxci's edge order: bottom 0-1 1-2 2-3 3-0, top 4-5 .. 7-4, vertical 0-4 ..: the file's 9..12, 17..20, 13..16
    assert blk.midside.tolist() == [[8, 9, 10, 11, 16, 17, 18, 19, 12, 13, 14, 15]]
    a = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 1.1]])
    affine = mesh.points @ a.T + [3.0, -1.0, 0.5]
    moved = mesh.with_points(affine)  # corners moved affinely; midside nodes follow their edges
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(moved, tmp_path / "out.e")
    back = read_mesh(tmp_path / "out.e")
    np.testing.assert_allclose(back.points, pts @ a.T + [3.0, -1.0, 0.5], rtol=0, atol=1e-12)  # face nodes too


def test_other_blocks_are_kept_and_unknown_types_stay_in_the_file(tmp_path):
    base = perturb_box(2, amplitude=0.2, seed=4)
    pts = np.concatenate([base.points, [[5.0, 5, 5], [6, 5, 5], [7, 5, 5]]])
    hexes = base.cells[0].data + 1
    src = exodus_file(tmp_path / "m.e", pts, [("HEX8", hexes), ("BEAM2", [[28, 29]]), ("SUPERELEMENT", [[30]])])
    mesh = read_mesh(src)
    assert [b.type for b in mesh.cells] == ["hexahedron", "line"]
    assert any("SUPERELEMENT (1 nodes)" in n and "never moved" in n for n in mesh.notes)
    write_mesh(mesh.with_points(mesh.points * 2), tmp_path / "out.e")
    assert netcdf_contents(tmp_path / "out.e") == netcdf_contents(src)
    np.testing.assert_array_equal(read_mesh(tmp_path / "out.e").points, pts * 2)
    res = jaxci.smooth(mesh)  # the beam's and the superelement's nodes are used by no volume cell: never moved
    assert res.after.max_condition < res.before.max_condition
    np.testing.assert_array_equal(res.mesh.points[27:], pts[27:])


# ------------------------------------------------------------------------------------------------ afresh
def test_written_afresh_from_another_format(tmp_path):
    base = perturb_box(3, amplitude=0.2, seed=1)
    mesh = HexMesh(base.points, (CellBlock("hexahedron", base.cells[0].data, np.arange(501, 528)),
                                 CellBlock("quad", [[0, 1, 5, 4]])),
                   point_sets={"FIXED": np.array([0, 3, 7])},
                   cell_sets={"ALL": [np.arange(27), np.zeros(0, np.int64)], "SOME": [np.array([1]), np.array([0])]},
                   node_ids=np.arange(11, 11 + base.n_nodes))
    with pytest.warns(LossyWriteWarning, match=r"exodus drops cell sets \['SOME'\]"):
        write_mesh(mesh, tmp_path / "m.exo")
    back = read_mesh(tmp_path / "m.exo")
    np.testing.assert_array_equal(back.points, mesh.points)
    assert [b.type for b in back.cells] == ["hexahedron", "quad"]
    np.testing.assert_array_equal(back.cells[0].data, mesh.cells[0].data)
    assert back.cells[0].ids.tolist() == list(range(501, 528)) and back.cells[1].ids.tolist() == [528]
    assert back.node_ids.tolist() == mesh.node_ids.tolist()
    assert back.point_sets["FIXED"].tolist() == [0, 3, 7]
    assert back.cell_sets["ALL"][0].tolist() == list(range(27))
    with netCDF4.Dataset(tmp_path / "m.exo") as ds:
        assert ds.variables["connect1"].elem_type == "HEX8" and ds.variables["connect2"].elem_type == "SHELL4"


@pytest.mark.shared
def test_a_mesh_that_no_longer_matches_its_file_is_written_afresh_with_a_warning(tmp_path):
    mesh = read_mesh(DATA / "cube.g")
    other = dataclasses.replace(mesh, point_sets={}, fix_orientation=False)
    with pytest.warns(LossyWriteWarning, match=r"exodus drops the results, QA and info records, .* of the source "
                                               r"Exodus file cube\.g \(its node or element sets differ"):
        write_mesh(other, tmp_path / "o.e")
    with pytest.warns(LossyWriteWarning, match=r"vtu drops the results, side sets, .* of the source Exodus file"):
        write_mesh(mesh, tmp_path / "o.vtu")


# ------------------------------------------------------------------------------------------------ bad files
def _edit(path, var, fn):
    with netCDF4.Dataset(path, "r+") as ds:
        ds.set_auto_mask(False)
        v = ds.variables[var]
        v[:] = fn(np.asarray(v[:]))


@pytest.mark.parametrize("case, message", [
    ("truncated", r"bad\.e: truncated Exodus II file: its variables need \d+ bytes more"),
    ("header", r"bad\.e: corrupt or truncated netCDF file: the header is cut short"),
    ("missing_node", r"bad\.e: element 5 of block 1 \(block_1, HEX8\) references node 99, but the file has nodes "
                     r"1\.\.27"),
    ("ids_clash", r"bad\.e: node_num_map gives the id 4 to nodes 4 and 9; ids must be unique"),
    ("not_netcdf", r"bad\.e: not a readable Exodus II \(netCDF\) file"),
])
def test_bad_files_exit_2_with_one_clear_line(tmp_path, capsys, case, message):
    src = exodus_file(tmp_path / "src.e", perturb_box(2, amplitude=0.1, seed=0).points,
                      [("HEX8", perturb_box(2, amplitude=0.1, seed=0).cells[0].data + 1)],
                      node_ids=np.arange(1, 28))
    bad = tmp_path / "bad.e"
    shutil.copyfile(src, bad)
    raw = src.read_bytes()
    if case == "truncated":
        bad.write_bytes(raw[: len(raw) - 40])
    elif case == "header":
        bad.write_bytes(raw[:200])
    elif case == "missing_node":
        _edit(bad, "connect1", lambda c: np.where(np.arange(c.size).reshape(c.shape) == 4 * 8 + 2, 99, c))
    elif case == "ids_clash":
        _edit(bad, "node_num_map", lambda m: np.where(np.arange(len(m)) == 8, 4, m))
    else:
        bad.write_text("not a netCDF file\n")
    with pytest.raises(MeshReadError, match=message):
        read_mesh(bad)
    assert main(["smooth", str(bad), str(tmp_path / "out.e")]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.startswith("jaxci: error: ") and "bad.e" in err
    assert not (tmp_path / "out.e").exists()


# ---------------------------------------------------------------------------------- side sets, shell blocks
@pytest.mark.shared
def test_nodes_of_shell_blocks_on_the_bricks_are_held():
    """2block1.g: a 4^3 brick block with two SHELL4 blocks of 16 on two of its faces. The shells' nodes (50, on
    the bricks' boundary) are held, so smoothing leaves the shells as they are; without the rule those on the
    faces would slide."""
    from jaxci.geometry.boundary import CORNER, SURFACE, classify_boundary

    mesh = read_mesh(DATA / "2block1.g")
    shells = np.unique(np.concatenate([b.data.ravel() for b in mesh.cells if b.type == "quad"]))
    assert len(shells) == 50 and np.array_equal(mesh.held_nodes, shells)
    info = classify_boundary(mesh)
    assert (info.node_class[shells] == CORNER).all()
    free = classify_boundary(dataclasses.replace(mesh, held_nodes=None))
    assert (free.node_class[shells] == SURFACE).sum() >= 18  # the shells' inner face nodes would slide
    pts = np.array(mesh.points)
    inner = np.flatnonzero(info.node_class == 0)
    pts[inner] += np.random.default_rng(0).uniform(-0.1, 0.1, (len(inner), 3)) * np.ptp(pts) / 8
    res = jaxci.smooth(mesh.with_points(pts))
    assert res.after.max_condition < res.before.max_condition
    np.testing.assert_array_equal(res.mesh.points[shells], mesh.points[shells])


@pytest.mark.shared
def test_side_sets_keep_their_extent():
    """two-block.g: two bricks of 2x2x2 side by side, 12 side sets (each block's six faces). Where two side sets
    meet on one flat face of the whole, the border is a feature curve: its nodes slide along it (EDGE), not across
    it (SURFACE), so each side set keeps its extent; the face sets match their boundary faces."""
    from jaxci.geometry.boundary import CORNER, EDGE, SURFACE, classify_boundary, face_set_signature

    mesh = read_mesh(DATA / "two-block.g")
    assert len(mesh.face_sets) == 12 and all(f.shape == (4, 4) for f in mesh.face_sets.values())
    info, plain = classify_boundary(mesh), classify_boundary(dataclasses.replace(mesh, face_sets={}))
    moved = np.flatnonzero(info.node_class != plain.node_class)
    across = moved[plain.node_class[moved] == SURFACE]  # inside a flat face: now on the border curve
    ends = moved[plain.node_class[moved] == EDGE]  # where the border meets the box's edges: now corners
    assert len(across) and (info.node_class[across] == EDGE).all()
    assert len(ends) and (info.node_class[ends] == CORNER).all() and len(across) + len(ends) == len(moved)
    assert any("face sets (side sets) are feature edges" in n for n in info.notes)
    sig = face_set_signature(info.topology.faces, mesh.face_sets)
    assert (sig != 0).sum() == 4 * 12 - 8  # every face of a set is a boundary face but the two blocks' shared 8
    with pytest.raises(jaxci.errors.MeshError, match="face set 'bad' must be"):
        dataclasses.replace(mesh, face_sets={"bad": np.zeros((2, 3), np.int64)})
