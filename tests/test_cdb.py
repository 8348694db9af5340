"""ANSYS CDB archives against mapdl-archive (an independent reader), quadratic elements, components, bad input."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxci
from jaxci import smooth
from jaxci.cells import EDGES
from jaxci.cli import main
from jaxci.errors import MeshError, MeshReadError, MeshWriteError
from jaxci.io import LossyWriteWarning, read_mesh, write_mesh
from jaxci.mesh import MIRROR_HEX, CellBlock, HexMesh

mapdl_archive = pytest.importorskip("mapdl_archive")
EXAMPLES = Path(mapdl_archive.__file__).parent / "examples"

#: Where each cell's nodes go in the 8 corner fields I..P of the ANSYS brick (degenerate forms), and where its
#: midside nodes ("m", i) or corner nodes ("c", j) go in the 12 midside fields Q..B (ANSYS's SOLID186 forms).
BRICK = {"hexahedron": [0, 1, 2, 3, 4, 5, 6, 7], "wedge": [0, 1, 2, 2, 3, 4, 5, 5],
         "pyramid": [0, 1, 2, 3, 4, 4, 4, 4], "tetra": [0, 1, 2, 2, 3, 3, 3, 3]}
MID = {
    "hexahedron": [("m", i) for i in range(12)],
    "wedge": [("m", 0), ("m", 1), ("c", 2), ("m", 2), ("m", 3), ("m", 4), ("c", 5), ("m", 5), ("m", 6), ("m", 7),
              ("m", 8), ("m", 8)],
    "pyramid": [("m", 0), ("m", 1), ("m", 2), ("m", 3), ("c", 4), ("c", 4), ("c", 4), ("c", 4), ("m", 4), ("m", 5),
                ("m", 6), ("m", 7)],
    "tetra": [("m", 0), ("m", 1), ("c", 2), ("m", 2), ("c", 3), ("c", 3), ("c", 3), ("c", 3), ("m", 3), ("m", 4),
              ("m", 5), ("m", 5)],
}


def archive(path) -> mapdl_archive.Archive:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mapdl_archive.Archive(str(path), parse_vtk=False)


def ref_view(a) -> dict:
    """mapdl-archive's reading: element id -> (routine, TYP, MAT, REAL, SEC, node numbers as in the EBLOCK)."""
    routine = dict(a.ekey.tolist())
    return {int(e): (routine[int(t)], int(t), int(m), int(r), int(s), tuple(int(v) for v in row[10:]))
            for e, t, m, r, s, row in zip(a.enum, a.et_id, a.material_type, a.elem_real_constant, a.section, a.elem,
                                          strict=True)}


def jaxci_view(mesh: HexMesh) -> dict:
    """The same from a jaxci mesh: element types from ``ansys:et``, nodes rebuilt in ANSYS's brick layout."""
    routine = dict(mesh.field_data["ansys:et"].tolist())
    ids = mesh.node_ids
    out = {}
    for bi, b in enumerate(mesh.cells):
        typ, mat, rel, sec = (mesh.cell_data[f"ansys:{k}"][bi] for k in ("typ", "mat", "rel", "sec"))
        for k, eid in enumerate(b.ids.tolist()):
            nodes = [int(ids[b.data[k, j]]) for j in BRICK[b.type]]
            if routine[int(typ[k])] == 186:
                mid = b.midside[k] if b.midside is not None else np.full(12, -1)
                nodes += [int(ids[b.data[k, i]]) if w == "c" else (int(ids[mid[i]]) if mid[i] >= 0 else 0)
                          for w, i in MID[b.type]]
            out[eid] = (routine[int(typ[k])], int(typ[k]), int(mat[k]), int(rel[k]), int(sec[k]), tuple(nodes))
    return out


def points_by_id(mesh: HexMesh) -> dict[int, np.ndarray]:
    return dict(zip(mesh.node_ids.tolist(), mesh.points, strict=True))


def assert_same_as_archive(mesh: HexMesh, a, atol=1e-15) -> None:
    """Same elements, nodes (to `atol`: mapdl-archive's own number parsing is off by an ulp at times), sets and
    key options."""
    assert jaxci_view(mesh) == ref_view(a)
    k = {nid: i for i, nid in enumerate(mesh.node_ids.tolist())}
    np.testing.assert_allclose(mesh.points[[k[n] for n in a.nnum]], a.nodes[:, :3], rtol=0, atol=atol)
    assert sorted(mesh.node_ids.tolist()) == sorted(a.nnum.tolist())
    assert {n: sorted(mesh.node_ids[idx].tolist()) for n, idx in mesh.point_sets.items()} == {
        n: sorted(v.tolist()) for n, v in a.node_components.items()}
    elem_sets = {n: sorted(int(i) for b, rows in zip(mesh.cells, per, strict=True) for i in b.ids[rows])
                 for n, per in mesh.cell_sets.items()}
    assert elem_sets == {n: sorted(v.tolist()) for n, v in a.element_components.items()}
    keyopts = mesh.field_data.get("ansys:keyopt", np.zeros((0, 3), int)).tolist()
    assert {t: [[k, v] for tt, k, v in keyopts if tt == t] for t in a.key_option} == a.key_option


# ------------------------------------------------------------------------------------------------ real archives
@pytest.mark.parametrize("name, counts", [
    ("sector.cdb", {"hexahedron": 101, "wedge": 4}),
    ("academic_rotor.cdb", {"hexahedron": 524}),
    ("HexBeam.cdb", {"hexahedron": 40}),
])
def test_reads_what_mapdl_archive_reads(name, counts):
    mesh = read_mesh(EXAMPLES / name)
    assert {b.type: len(b.data) for b in mesh.cells} == counts
    assert_same_as_archive(mesh, archive(EXAMPLES / name))
    assert not any("inverted" in n for n in mesh.notes)


def test_hexbeam_keeps_its_20_node_bricks():
    mesh = read_mesh(EXAMPLES / "HexBeam.cdb")
    (blk,) = mesh.cells
    assert blk.midside.shape == (40, 12) and (blk.midside >= 0).all()
    assert not any("unreferenced" in n for n in mesh.notes)  # midside nodes are referenced
    nodes, ends = mesh.midside_edges
    assert len(nodes) + len(np.unique(mesh.hexes)) == mesh.n_nodes == 321
    np.testing.assert_allclose(mesh.points[nodes], mesh.points[ends].mean(axis=1), atol=1e-12)  # straight edges
    assert mesh.field_data["ansys:et"].tolist() == [[1, 186]]
    assert sorted(mesh.point_sets) == ["NCOMP2", "NODE_SELECTION"] and sorted(mesh.cell_sets) == ["ECOMP1", "ECOMP2"]


@pytest.fixture(scope="module")
def smoothed_sector():
    mesh = read_mesh(EXAMPLES / "sector.cdb")
    return mesh, smooth(mesh, "ci", max_sweeps=5)


def test_sector_smooths_and_writes_back(smoothed_sector, tmp_path):
    mesh, res = smoothed_sector
    out = res.mesh
    assert res.after.objective < res.before.objective and res.after.max_condition < res.before.max_condition
    for rep in (res.before, res.after):
        assert rep.overall["inverted"] == 0 and set(rep.by_type) == {"hexahedron", "wedge"}
    # linear wedges are smoothed with the hexahedra (mixed objective): they stay valid and their free nodes move
    wedge = [b for b in out.cells if b.type == "wedge"][0]
    assert np.abs(out.points[wedge.data] - mesh.points[wedge.data]).max() > 1e-3
    assert res.after.overall["objective"] < res.before.overall["objective"]
    assert np.abs(out.points - mesh.points).max() > 1e-3  # hexahedra moved
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a CDB mesh loses nothing
        write_mesh(out, tmp_path / "sector_smoothed.cdb")
    a = archive(tmp_path / "sector_smoothed.cdb")
    ref = archive(EXAMPLES / "sector.cdb")
    assert ref_view(a) == ref_view(ref)  # same ids, element types, attributes and nodes: wedges still K=L, O=P
    assert a.ekey.tolist() == [[1, 200], [2, 185]] and a.key_option == {1: [[1, 7]]}
    assert_same_as_archive(out, a, atol=1e-13 * np.abs(out.points).max())
    wedges = [v[5] for v in ref_view(a).values() if len(set(v[5])) == 6]
    assert len(wedges) == 4 and all(w[2] == w[3] and w[6] == w[7] for w in wedges)
    back = read_mesh(tmp_path / "sector_smoothed.cdb")
    assert [(b.type, len(b.data)) for b in back.cells] == [("hexahedron", 101), ("wedge", 4)]
    assert jaxci.quality_report(back).overall["inverted"] == 0


@pytest.mark.parametrize("name", ["academic_rotor.cdb", "HexBeam.cdb"])
def test_write_read_round_trip(tmp_path, name):
    mesh = read_mesh(EXAMPLES / name)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / name)
    assert ref_view(archive(tmp_path / name)) == ref_view(archive(EXAMPLES / name))
    back = read_mesh(tmp_path / name)
    assert jaxci_view(back) == jaxci_view(mesh)
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-13 * np.abs(mesh.points).max())


def test_hexbeam_smooths_corners_and_midside_nodes_follow(tmp_path):
    mesh = read_mesh(EXAMPLES / "HexBeam.cdb")
    info = jaxci.classify_boundary(mesh)
    interior = np.flatnonzero(np.asarray(info.node_class) == 0)
    assert len(interior) == 9
    pts = mesh.points.copy()
    pts[interior] += np.random.default_rng(0).uniform(-0.05, 0.05, (9, 3))
    bent = mesh.with_points(pts)  # corners moved: their midside nodes follow
    nodes, ends = bent.midside_edges
    np.testing.assert_allclose(bent.points[nodes], bent.points[ends].mean(axis=1), atol=1e-14)
    assert any("222 midside nodes" in n for n in bent.notes)
    res = smooth(bent, "ci", max_sweeps=5)
    assert res.after.objective < res.before.objective and res.after.inverted_elements == 0
    out = res.mesh
    np.testing.assert_allclose(out.points[nodes], out.points[ends].mean(axis=1), atol=1e-14)
    assert np.abs(out.points[interior] - bent.points[interior]).max() > 1e-4
    write_mesh(out, tmp_path / "beam.cdb")
    a = archive(tmp_path / "beam.cdb")
    assert ref_view(a) == ref_view(archive(EXAMPLES / "HexBeam.cdb"))  # SOLID186, same ids and 20 nodes each
    assert_same_as_archive(out, a, atol=1e-13)


# ------------------------------------------------------------------------------------------------ quadratic forms
def quadratic_cdb(tet_type: int = 186, midside_b: str = "A") -> str:
    """A CDB with a SOLID186 brick, a SOLID186 wedge, pyramid (degenerate bricks) and a tetrahedron (SOLID186
    degenerate brick, or SOLID187 10-node), midside nodes on every edge, shared where cells share edges."""
    s = np.sqrt(0.5)
    corners = {1: (0, 0, 0), 2: (1, 0, 0), 3: (1, 1, 0), 4: (0, 1, 0), 5: (0, 0, 1), 6: (1, 0, 1), 7: (1, 1, 1),
               8: (0, 1, 1), 9: (2, 0, 0), 10: (2, 0, 1), 11: (0.5, 0.5, 1 + s), 12: (3, 0, 0), 13: (4, 0, 0),
               14: (3, 1, 0), 15: (3, 0, 1)}
    cells = {"hexahedron": [1, 2, 3, 4, 5, 6, 7, 8], "wedge": [2, 9, 3, 6, 10, 7], "pyramid": [5, 6, 7, 8, 11],
             "tetra": [12, 13, 14, 15]}
    xyz = dict(corners)
    mid_of = {}

    def mid(a, b):
        key = (min(a, b), max(a, b))
        if key not in mid_of:
            mid_of[key] = 100 + len(mid_of)
            xyz[mid_of[key]] = tuple((np.array(corners[a]) + np.array(corners[b])) / 2)
        return mid_of[key]

    rows = []
    for eid, (t, c) in enumerate(cells.items(), 1):
        m = [mid(c[a], c[b]) for a, b in EDGES[t]]
        typ = 3 if t == "tetra" and tet_type == 187 else 1
        if typ == 3:
            nodes = c + m
        else:
            nodes = [c[j] for j in BRICK[t]] + [c[i] if w == "c" else m[i] for w, i in MID[t]]
            if t == "wedge" and midside_b != "A":
                nodes[19] = int(midside_b)
        rows.append([1, typ, 1, 1, 0, 0, 0, 0, len(nodes), 0, eid] + nodes)
    lines = ["/PREP7", "ET,1,186", "ET,3,187", f"NBLOCK,6,SOLID,{max(xyz)},{len(xyz)}", "(3i9,6e21.13e3)"]
    lines += [f"{n:9d}{0:9d}{0:9d}" + "".join(f"{v:21.13E}" for v in x) for n, x in sorted(xyz.items())]
    lines += ["N,R5.3,LOC,       -1,", f"EBLOCK,19,SOLID,{len(rows)},{len(rows)}", "(19i9)"]
    for r in rows:
        lines += ["".join(f"{v:9d}" for v in r[:19]), "".join(f"{v:9d}" for v in r[19:])]
    lines += ["       -1", "CMBLOCK,PYR,ELEM,       1", "(8i10)", "         3", "FINISH"]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("tet_type", [186, 187])
def test_degenerate_solid186_and_solid187_round_trip(tmp_path, tet_type):
    (tmp_path / "quad.cdb").write_text(quadratic_cdb(tet_type))
    mesh = read_mesh(tmp_path / "quad.cdb")
    assert [(b.type, b.ids.tolist()) for b in mesh.cells] == [("hexahedron", [1]), ("wedge", [2]),
                                                              ("pyramid", [3]), ("tetra", [4])]
    assert [b.midside.shape for b in mesh.cells] == [(1, 12), (1, 9), (1, 8), (1, 6)]
    assert not any("unreferenced" in n for n in mesh.notes)
    nodes, ends = mesh.midside_edges
    np.testing.assert_allclose(mesh.points[nodes], mesh.points[ends].mean(axis=1), atol=1e-13)
    assert [rows.tolist() for rows in mesh.cell_sets["PYR"]] == [[], [], [0], []]
    ref = ref_view(archive(tmp_path / "quad.cdb"))
    write_mesh(mesh, tmp_path / "back.cdb")
    assert ref_view(archive(tmp_path / "back.cdb")) == ref
    assert read_mesh(tmp_path / "back.cdb").midside_edges[0].tolist() == nodes.tolist()


def test_degenerate_solid186_with_inconsistent_midside_pattern(tmp_path):
    (tmp_path / "odd.cdb").write_text(quadratic_cdb(midside_b="3"))
    with pytest.raises(MeshReadError, match=r"odd\.cdb, line \d+: 20-node element 2 is a degenerate brick \(wedge\) "
                                            r"whose midside nodes .* do not follow ANSYS's pattern"):
        read_mesh(tmp_path / "odd.cdb")


def test_midside_follow_midpoint_keep():
    base = jaxci.box(1)
    mid = np.arange(8, 20)[None]
    ends = base.points[base.hexes[0][EDGES["hexahedron"]]]
    pts = np.concatenate([base.points, ends.mean(axis=1)])
    pts[8] += [0.0, -0.1, 0.0]  # edge 0-1 bowed outwards (a curved boundary edge)
    mesh = HexMesh(pts, (CellBlock("hexahedron", base.hexes, midside=mid),))
    moved = mesh.points.copy()
    moved[1] += [0.2, 0.0, 0.0]
    moved[8:] = 99.0  # ignored unless "keep"
    follow = mesh.with_points(moved)
    np.testing.assert_allclose(follow.points[8], [0.6, -0.1, 0.0])
    np.testing.assert_allclose(follow.points[9], [1.1, 0.5, 0.0])  # straight edge 1-2: its new midpoint
    np.testing.assert_allclose(follow.points[17], [1.1, 0.0, 0.5])  # edge 1-5
    still = [10, 11, 12, 13, 14, 15, 16, 18, 19]  # edges without node 1
    np.testing.assert_allclose(follow.points[still], pts[still])
    assert "(1 on curved edges keep their offset from the midpoint)" in follow.notes[0]
    np.testing.assert_allclose(mesh.with_points(moved, midside="midpoint").points[8], [0.6, 0.0, 0.0])
    np.testing.assert_array_equal(mesh.with_points(moved, midside="keep").points[8:], 99.0)
    with pytest.raises(ValueError, match="midside must be"):
        mesh.with_points(moved, midside="snap")


def test_midside_nodes_must_belong_to_one_edge():
    box = jaxci.box(2, 1, 1)  # two hexahedra sharing the face x = 1
    n = box.n_nodes
    pts = np.concatenate([box.points, np.zeros((24, 3))])
    mid = np.arange(n, n + 24).reshape(2, 12)
    mid[1, 3] = mid[0, 1]  # the shared edge has one midside node: consistent
    HexMesh(pts, (CellBlock("hexahedron", box.hexes, midside=mid),))
    bad = mid.copy()
    bad[1, 0] = mid[0, 0]  # one node on two different edges
    with pytest.raises(MeshError, match=rf"midside node {mid[0, 0]} is shared inconsistently: it lies on edge 0-1 "
                                        r"of hexahedron element 0 but on edge 1-\d+ of hexahedron element 1"):
        HexMesh(pts, (CellBlock("hexahedron", box.hexes, midside=bad),))
    corner = mid.copy()
    corner[0, 0] = box.hexes[1, 1]
    with pytest.raises(MeshError, match=r"is a midside node of hexahedron element 0 .* and a corner node of a cell"):
        HexMesh(pts, (CellBlock("hexahedron", box.hexes, midside=corner),))
    with pytest.raises(MeshError, match=r"midside nodes of cell block 0 \(hexahedron\) have shape \(2, 8\)"):
        HexMesh(pts, (CellBlock("hexahedron", box.hexes, midside=mid[:, :8]),))


def test_left_handed_20_node_bricks_are_mirrored_with_their_midside_nodes(tmp_path):
    text = (EXAMPLES / "HexBeam.cdb").read_text().splitlines()
    start = next(i for i, line in enumerate(text) if line.startswith("EBLOCK")) + 2
    for i in range(start, start + 80, 2):  # swap I..L with M..P and Q..T with U..X: every brick left-handed
        first, second = text[i], text[i + 1]
        f = [first[k:k + 10] for k in range(0, len(first), 10)]
        s = [second[k:k + 10] for k in range(0, len(second), 10)]
        text[i] = "".join(f[:11] + f[15:19] + f[11:15])
        text[i + 1] = "".join(s[4:8] + s[0:4] + s[8:])
    (tmp_path / "left.cdb").write_text("\n".join(text) + "\n")
    with pytest.warns(UserWarning, match="left-handed"):
        mesh = read_mesh(tmp_path / "left.cdb")
    ref = read_mesh(EXAMPLES / "HexBeam.cdb")
    assert mesh.hex_mirrored
    np.testing.assert_array_equal(mesh.cells[0].data, ref.cells[0].data[:, MIRROR_HEX][:, MIRROR_HEX])
    assert mesh.midside_edges[0].tolist() == ref.midside_edges[0].tolist()
    np.testing.assert_array_equal(mesh.midside_edges[1], ref.midside_edges[1])
    write_mesh(mesh, tmp_path / "left_back.cdb")  # written in the file's own (left-handed) convention
    assert ref_view(archive(tmp_path / "left_back.cdb")) == ref_view(archive(tmp_path / "left.cdb"))


# ------------------------------------------------------------------------------------------------ components
def test_sets_become_components(tmp_path):
    mesh = jaxci.perturb_box(2, amplitude=0.1, seed=0)
    mesh = HexMesh(mesh.points, mesh.cells, point_sets={"FIXED": np.array([0, 1, 2, 5]), "bad name": np.array([3])},
                   cell_sets={"LAYER_1": [np.array([0, 1, 2, 3])]})
    with pytest.warns(LossyWriteWarning, match=r"APDL drops sets \['bad name'\] \(not valid ANSYS component names\)"):
        write_mesh(mesh, tmp_path / "sets.cdb")
    text = (tmp_path / "sets.cdb").read_text()
    assert "CMBLOCK,FIXED,NODE,       3\n(8i10)\n         1        -3         6\n" in text
    a = archive(tmp_path / "sets.cdb")
    assert a.node_components["FIXED"].tolist() == [1, 2, 3, 6] and a.element_components["LAYER_1"].tolist() == [1, 2,
                                                                                                                 3, 4]
    back = read_mesh(tmp_path / "sets.cdb")
    assert back.point_sets["FIXED"].tolist() == [0, 1, 2, 5] and back.cell_sets["LAYER_1"][0].tolist() == [0, 1, 2, 3]


def test_linear_type_with_midside_nodes_is_refused(tmp_path):
    mesh = read_mesh(EXAMPLES / "HexBeam.cdb")
    mesh = HexMesh(mesh.points, mesh.cells, cell_data=mesh.cell_data, node_ids=mesh.node_ids,
                   field_data={"ansys:et": np.array([[1, 185]])})
    with pytest.raises(MeshWriteError, match=r"element 1 has midside nodes, but its TYPE 1 is SOLID185"):
        write_mesh(mesh, tmp_path / "lin.cdb")


# ------------------------------------------------------------------------------------------------ bad input, CLI
def bad_sector(tmp_path, name, edit) -> Path:
    lines = (EXAMPLES / "sector.cdb").read_text().splitlines()
    edit(lines)
    (tmp_path / name).write_text("\n".join(lines) + "\n")
    return tmp_path / name


def first_row(lines, block):
    return next(i for i, line in enumerate(lines) if line.startswith(block)) + 2


@pytest.mark.parametrize("name, edit, message", [
    ("missing_node.cdb",
     lambda L: L.__setitem__(first_row(L, "EBLOCK"), L[first_row(L, "EBLOCK")][:-9] + f"{9999:9d}"),
     r"missing_node\.cdb, line 697: element 224 references node 9999, which is not in the NBLOCK"),
    ("truncated.cdb", lambda L: L.__delitem__(slice(first_row(L, "NBLOCK") + 100, None)),
     r"truncated\.cdb: file ends inside the NBLOCK of line 37 \(truncated\?\)"),
    ("short.cdb", lambda L: L.__delitem__(slice(first_row(L, "NBLOCK") + 100, first_row(L, "NBLOCK") + 110)),
     r"short\.cdb, line 37: NBLOCK announces 655 rows but holds 645"),
    ("shell.cdb", lambda L: L.__setitem__(L.index("ET,        2,185"), "ET,        2,181"),
     r"shell\.cdb, line 697: element 224 has TYPE 2 = element type 181 \(ET at line 36\), an element type jaxci "
     r"cannot read; jaxci reads the 3-D solids SOLID45, .*SOLID185"),
    ("notype.cdb", lambda L: L.__delitem__(L.index("ET,        2,185")),
     r"notype\.cdb, line 696: element 224 has TYPE 2, which no ET record of the file defines"),
])
def test_bad_archives_exit_2_with_one_clear_line(tmp_path, capsys, name, edit, message):
    path = bad_sector(tmp_path, name, edit)
    with pytest.raises(MeshReadError, match=message):
        read_mesh(path)
    assert main(["quality", str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and err.startswith("jaxci: error: ")
    assert name in err


def test_quality_of_a_cdb_by_type(capsys):
    assert main(["quality", str(EXAMPLES / "sector.cdb")]) == 0
    out = capsys.readouterr().out
    assert "4 degenerate bricks converted (4 to wedge)" in out
    wedge = next(line.split() for line in out.splitlines() if line.strip().startswith("wedge"))
    assert wedge[1:3] == ["4", "0"]


def test_etblock_keyopts_and_node_angles(tmp_path):
    lines = (EXAMPLES / "sector.cdb").read_text().splitlines()
    et = lines.index("ET,        1,200")
    lines[et:et + 3] = ["ETBLOCK,        2,        2", "(2i9,19a9)",
                        "        1      200        7        0        0", "        2      185", "       -1"]
    nb = first_row(lines, "NBLOCK")
    lines[nb] += f"{0.0:21.13E}{30.0:21.13E}"  # node 1: THXY 0, THYZ 30
    (tmp_path / "etblock.cdb").write_text("\n".join(lines) + "\n")
    mesh = read_mesh(tmp_path / "etblock.cdb")
    assert mesh.field_data["ansys:et"].tolist() == [[1, 200], [2, 185]]
    assert mesh.field_data["ansys:keyopt"].tolist() == [[1, 1, 7]]
    angles = mesh.point_data["ansys:angles"]
    assert angles[0].tolist() == [0.0, 30.0, 0.0] and (angles[1:] == 0).all()
    write_mesh(mesh, tmp_path / "back.cdb")  # the archive's own text, ETBLOCK and all
    assert (tmp_path / "back.cdb").read_bytes() == (tmp_path / "etblock.cdb").read_bytes()
    fresh = dataclasses.replace(mesh, field_data={k: v for k, v in mesh.field_data.items() if k != "ansys:deck"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(fresh, tmp_path / "fresh.cdb")  # written afresh: ET and KEYOPT records
    a = archive(tmp_path / "fresh.cdb")
    assert a.ekey.tolist() == [[1, 200], [2, 185]] and a.key_option == {1: [[1, 7]]}
    np.testing.assert_allclose(a.node_angles[0], [0.0, 30.0, 0.0])
    assert read_mesh(tmp_path / "fresh.cdb").point_data["ansys:angles"][0].tolist() == [0.0, 30.0, 0.0]


def test_other_formats_warn_about_midside_nodes(tmp_path):
    mesh = read_mesh(EXAMPLES / "HexBeam.cdb")
    with pytest.warns(LossyWriteWarning) as caught:
        write_mesh(mesh, tmp_path / "beam.vtu")
    assert any("vtu gets the 40 quadratic cells as linear cells" in str(w.message) for w in caught)


@pytest.mark.parametrize("method,params", [
    ("ci-global", dict(attempts=40, init_width=0.02)), ("bfgs", dict(max_steps=60)), ("lbfgs", dict(max_steps=60)),
    ("cg", dict(max_steps=60)), ("laplace", dict(max_sweeps=5)), ("smart-laplace", dict(max_sweeps=5)),
])
def test_sector_smooths_with_every_method(method, params):
    """Every method on a mixed hex + wedge archive: no inversion of any cell, the mixed F (over hexahedron and
    wedge corners) not raised, ids kept."""
    mesh = read_mesh(EXAMPLES / "sector.cdb")
    res = smooth(mesh, method, **params)
    assert res.after.overall["inverted"] == 0
    assert res.after.overall["objective"] <= res.before.overall["objective"]
    assert [(b.type, len(b.data)) for b in res.mesh.cells] == [(b.type, len(b.data)) for b in mesh.cells]
    assert all(np.array_equal(a.ids, b.ids) for a, b in zip(res.mesh.cells, mesh.cells, strict=True))
