"""ANSYS text: NLIST/ELIST listings (the paper's input) and APDL NBLOCK/EBLOCK files, both directions."""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from jaxci.errors import MeshError, MeshReadError, MeshWriteError
from jaxci.io import LossyWriteWarning, read_ansys_listing, read_mesh, write_mesh
from jaxci.io._ansys import TO_BRICK
from jaxci.mesh import MIRROR_HEX, CellBlock, HexMesh
from jaxci.mesh.generate import box, perturb_box

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "ansys"
ATTRS = ("ansys:mat", "ansys:typ", "ansys:rel", "ansys:esy", "ansys:sec")


def fixture(tmp_path, *names) -> list[Path]:
    """Copies of fixture files in `tmp_path` (tests never write next to the fixtures)."""
    out = []
    for name in names:
        shutil.copy(FIXTURES / name, tmp_path / name)
        out.append(tmp_path / name)
    return out


def by_id(mesh: HexMesh) -> dict[int, tuple[str, tuple[int, ...]]]:
    """Element id -> (cell type, ANSYS node ids of its nodes): a numbering-independent view of a mesh."""
    out = {}
    for b in mesh.cells:
        for eid, row in zip(b.ids.tolist(), mesh.node_ids[b.data].tolist(), strict=True):
            out[eid] = (b.type, tuple(row))
    return out


# ------------------------------------------------------------------------------------------------ listings
def test_block_listing_pair():
    mesh = read_ansys_listing(FIXTURES / "block_nlist.lis", FIXTURES / "block_elist.lis")
    assert (mesh.n_nodes, mesh.n_hexes) == (18, 4)
    assert mesh.node_ids.tolist() == list(range(1, 19))
    assert mesh.cells[0].ids.tolist() == [1, 2, 3, 4]
    assert by_id(mesh)[1] == ("hexahedron", (1, 2, 5, 4, 10, 11, 14, 13))  # I..P is VTK order, unchanged
    k = {nid: i for i, nid in enumerate(mesh.node_ids.tolist())}
    np.testing.assert_array_equal(mesh.points[k[5]], [0.5, 0.5, 0.01])  # written 0.10000E-01
    np.testing.assert_array_equal(mesh.points[k[12]], [1.0, 0.0, 1.0])
    assert [a.tolist() for a in mesh.cell_data["ansys:mat"]] == [[1, 1, 2, 2]]
    assert [a.tolist() for a in mesh.cell_data["ansys:esy"]] == [[0, 0, 0, 0]]
    assert mesh.notes == () and not mesh.hex_mirrored
    assert mesh.source == f"{FIXTURES / 'block_nlist.lis'} + {FIXTURES / 'block_elist.lis'}"


def test_combined_listing_and_read_mesh_forms():
    pair = read_ansys_listing(FIXTURES / "block_nlist.lis", FIXTURES / "block_elist.lis")
    for mesh in (
        read_ansys_listing(FIXTURES / "block_combined.txt"),
        read_mesh(FIXTURES / "block_combined.txt"),
        read_mesh((FIXTURES / "block_nlist.lis", FIXTURES / "block_elist.lis")),
    ):
        np.testing.assert_array_equal(mesh.points, pair.points)
        np.testing.assert_array_equal(mesh.node_ids, pair.node_ids)
        assert by_id(mesh) == by_id(pair)


def signed_volume(x: np.ndarray, cell_type: str) -> float:
    """Volume of a cell with the sign of its VTK orientation (base face turning towards the opposite side)."""
    base = {"wedge": (0, 1, 2, 3), "pyramid": (0, 1, 3, 4), "tetra": (0, 1, 2, 3)}[cell_type]
    a, b, c, d = x[list(base)]
    return float(np.sign(np.dot(np.cross(b - a, c - a), d - a)) * ConvexHull(x).volume)


def test_degenerate_bricks_become_wedge_pyramid_tetra():
    mesh = read_mesh(FIXTURES / "degenerate.lis")
    assert [(b.type, b.ids.tolist()) for b in mesh.cells] == [
        ("hexahedron", [10]),
        ("wedge", [20]),
        ("pyramid", [30]),
        ("tetra", [40]),
    ]
    assert by_id(mesh)[20] == ("wedge", (2, 21, 3, 6, 22, 7))  # I J K K M N O O -> I J K M N O
    assert by_id(mesh)[30] == ("pyramid", (5, 6, 7, 8, 31))  # I J K L M M M M -> I J K L M
    assert by_id(mesh)[40] == ("tetra", (1, 5, 4, 41))  # I J K K M M M M -> I J K M
    assert [a.tolist() for a in mesh.cell_data["ansys:mat"]] == [[1], [2], [3], [4]]
    assert any("3 degenerate bricks converted (1 to wedge, 1 to pyramid, 1 to tetra)" in n for n in mesh.notes)
    expected = {"wedge": 0.5, "pyramid": 1 / 6, "tetra": 1 / 6}
    for b in mesh.cells[1:]:
        assert signed_volume(mesh.points[b.data[0]], b.type) == pytest.approx(expected[b.type])


def test_converted_cells_have_positive_vtk_volume():
    vtk = pytest.importorskip("vtk")
    if tuple(int(v) for v in vtk.vtkVersion.GetVTKVersion().split(".")[:2]) < (9, 7):
        pytest.skip("VTK before 9.7 numbers wedges the other way round")
    from vtk.util.numpy_support import vtk_to_numpy

    mesh = read_mesh(FIXTURES / "degenerate.lis")
    codes = {"hexahedron": 12, "wedge": 13, "pyramid": 14, "tetra": 10}
    grid, pts = vtk.vtkUnstructuredGrid(), vtk.vtkPoints()
    for x in mesh.points:
        pts.InsertNextPoint(*x)
    grid.SetPoints(pts)
    for b in mesh.cells:
        for row in b.data.tolist():
            ids = vtk.vtkIdList()
            for i in row:
                ids.InsertNextId(i)
            grid.InsertNextCell(codes[b.type], ids)
    q = vtk.vtkMeshQuality()
    q.SetInputData(grid)
    q.SetHexQualityMeasureToVolume()
    q.SetWedgeQualityMeasureToVolume()
    q.SetPyramidQualityMeasureToVolume()
    q.SetTetQualityMeasureToVolume()
    q.Update()
    volumes = vtk_to_numpy(q.GetOutput().GetCellData().GetArray("Quality"))
    np.testing.assert_allclose(volumes, [1.0, 0.5, 1 / 6, 1 / 6])


def test_solid186_continuation_lines():
    mesh = read_mesh(FIXTURES / "solid186.lis")
    assert (mesh.n_nodes, mesh.n_hexes) == (32, 2)
    assert by_id(mesh)[2] == ("hexahedron", (5, 6, 7, 8, 21, 22, 23, 24))
    assert any("2 elements listed with 20 nodes (SOLID186)" in n for n in mesh.notes)
    assert not any("inverted" in n for n in mesh.notes)


def test_missing_node():
    with pytest.raises(MeshReadError, match=r"missing_node\.lis, line 44: element 3 references node 99, which is"):
        read_mesh(FIXTURES / "bad_missing_node.lis")


def test_wrong_field_count():
    with pytest.raises(MeshReadError, match=r"bad_node_fields\.lis, line 17: node row has 6 fields, expected 7"):
        read_mesh(FIXTURES / "bad_node_fields.lis")
    with pytest.raises(MeshReadError, match=r"bad_elem_fields\.lis, line 43: element row has 13 fields, expected 14"):
        read_mesh(FIXTURES / "bad_elem_fields.lis")


def test_nodes_without_elements():
    with pytest.raises(MeshReadError, match=r"block_nlist\.lis: node rows but no ELIST section"):
        read_mesh(FIXTURES / "block_nlist.lis")
    with pytest.raises(MeshReadError, match=r"block_elist\.lis: no NLIST node rows found"):
        read_ansys_listing(FIXTURES / "block_elist.lis")
    with pytest.raises(MeshReadError, match=r"nope\.lis: no such file"):
        read_mesh((FIXTURES / "block_nlist.lis", FIXTURES / "nope.lis"))


NODES = "    NODE        X             Y             Z\n" + "".join(
    f"{i + 1:9d}   {x:.1f}   {y:.1f}   {z:.1f}\n" for i, (x, y, z) in enumerate(box(1).points)
)
ELEMS = (
    "    ELEM MAT TYP REL ESY SEC        NODES\n"
    "       7   1   1   1   0   1      1     2     4     3     5     6     8     7\n"
)


def test_listing_details(tmp_path):
    # no THXY columns, a Fortran page-eject line, a numeric-looking title line is skipped only if it has words
    (tmp_path / "ok.lis").write_text(" LIST ALL SELECTED NODES.   DSYS=      0\n" + NODES + "1\n 1 cube\n" + ELEMS)
    mesh = read_mesh(tmp_path / "ok.lis")
    assert mesh.n_hexes == 1 and mesh.cells[0].ids.tolist() == [7]
    (tmp_path / "dsys.lis").write_text(" LIST ALL SELECTED NODES.   DSYS=     11\n" + NODES + ELEMS)
    with pytest.raises(MeshReadError, match=r"dsys\.lis, line 1: nodes are listed in coordinate system DSYS=11"):
        read_mesh(tmp_path / "dsys.lis")
    (tmp_path / "twice.lis").write_text(NODES + NODES.splitlines()[3] + "\n" + ELEMS)
    with pytest.raises(MeshReadError, match=r"twice\.lis, line 10: node 3 listed twice \(first at .*line 4\)"):
        read_mesh(tmp_path / "twice.lis")
    (tmp_path / "odd.lis").write_text(NODES + ELEMS.replace(" 4     3 ", " 3     3 "))
    with pytest.raises(MeshReadError, match=r"odd\.lis, line 11: element 7 repeats nodes .* not a wedge"):
        read_mesh(tmp_path / "odd.lis")
    (tmp_path / "short186.lis").write_text(NODES + ELEMS + " " * 34 + "9    10    11\n")
    with pytest.raises(MeshReadError, match=r"short186\.lis, line 11: element 7 has 11 nodes; expected 8"):
        read_mesh(tmp_path / "short186.lis")
    (tmp_path / "word.lis").write_text(NODES.replace("1   0.0   0.0   0.0", "1   0.0   0.0   x") + ELEMS)
    with pytest.raises(MeshReadError, match=r"word\.lis, line 2: node row with a field that is not a number \('x'\)"):
        read_mesh(tmp_path / "word.lis")


def test_only_degenerate_bricks_is_not_a_hex_mesh(tmp_path):
    tet = ELEMS.replace(" 4     3     5     6     8     7", " 3     3     5     5     5     5")
    (tmp_path / "tet.lis").write_text(NODES + tet)
    with pytest.raises(MeshError, match=r"tet\.lis: the mesh has no hexahedra \(found: tetra\)"):
        read_mesh(tmp_path / "tet.lis")


# ------------------------------------------------------------------------------------------------ APDL
@pytest.mark.parametrize("listing", ["block_combined.txt", "degenerate.lis", "solid186.lis"])
@pytest.mark.parametrize("ext", [".mac", ".apdl", ".ans"])
def test_listing_to_apdl_and_back(tmp_path, listing, ext):
    mesh = read_mesh(FIXTURES / listing)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an ANSYS mesh loses nothing in APDL
        write_mesh(mesh, tmp_path / f"out{ext}")
    back = read_mesh(tmp_path / f"out{ext}")
    np.testing.assert_array_equal(back.node_ids, mesh.node_ids)
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-12)
    assert by_id(back) == by_id(mesh)
    assert [b.type for b in back.cells] == [b.type for b in mesh.cells]
    for name in ATTRS:
        for got, want in zip(back.cell_data[name], mesh.cell_data[name], strict=True):
            np.testing.assert_array_equal(got, want)
    assert back.source == str(tmp_path / f"out{ext}")
    assert os.listdir(tmp_path) == [f"out{ext}"]


def test_apdl_file_layout(tmp_path):
    write_mesh(read_mesh(FIXTURES / "degenerate.lis"), tmp_path / "deg.mac")
    lines = (tmp_path / "deg.mac").read_text().splitlines()
    assert lines[1:4] == ["/PREP7", "ET,1,SOLID185", "NBLOCK,6,SOLID,        41,        12"]
    assert lines[4] == "(3i9,6e21.13e3)"
    assert lines[5] == "        1        0        0 0.0000000000000E+000 0.0000000000000E+000 0.0000000000000E+000"
    assert lines[16] == "       41        0        0-1.0000000000000E+000 0.0000000000000E+000 0.0000000000000E+000"
    assert lines[17:20] == ["N,R5.3,LOC,       -1,", "EBLOCK,19,SOLID,        40,         4", "(19i9)"]
    wedge = [int(lines[21][i : i + 9]) for i in range(0, 19 * 9, 9)]
    assert wedge == [2, 1, 1, 1, 0, 0, 0, 0, 8, 0, 20, 2, 21, 3, 3, 6, 22, 7, 7]  # the degenerate brick again
    assert lines[24:] == ["       -1", "FINISH"]


def test_apdl_of_a_mesh_without_ids(tmp_path):
    mesh = perturb_box(2, amplitude=0.2, seed=3)
    write_mesh(mesh, tmp_path / "box.mac")
    back = read_mesh(tmp_path / "box.mac")
    assert back.node_ids.tolist() == list(range(1, 28)) and back.cells[0].ids.tolist() == list(range(1, 9))
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(back.hexes, mesh.hexes)
    assert [a.tolist() for a in back.cell_data["ansys:typ"]] == [[1] * 8]
    quad = CellBlock("quad", np.array([[0, 1, 4, 3]]))
    extra = HexMesh(mesh.points, (mesh.cells[0], quad), point_data={"f": mesh.points[:, 0]})
    with pytest.warns(LossyWriteWarning, match=r"APDL drops cells 1 quad; point/cell data \['f'\]"):
        write_mesh(extra, tmp_path / "extra.mac")


def test_apdl_keeps_a_left_handed_file_left_handed(tmp_path):
    base = box(1)
    with pytest.warns(UserWarning, match="left-handed"):
        mesh = HexMesh(base.points, (CellBlock("hexahedron", base.hexes[:, MIRROR_HEX]),))
    write_mesh(mesh, tmp_path / "left.mac")
    row = (tmp_path / "left.mac").read_text().splitlines()[-3]
    assert [int(row[i : i + 9]) for i in range(99, 171, 9)] == (base.hexes[0, MIRROR_HEX] + 1).tolist()


CDB = """/COM,ANSYS RELEASE 2019 R2
/PREP7
ET,        1,186
NBLOCK,6,SOLID,        20,        20
(3i8,6e20.13)
{nodes}N,R5.3,LOC,      -1,
EBLOCK,19,SOLID,         1,         1
(19i8)
{elem}      -1
"""


def cdb_text() -> str:
    """A CDB-style archive: 8-wide fields, trailing zero coordinates left out, one 20-node brick on two lines."""
    corners = box(1).points
    mids = (corners[[0, 1, 2, 3, 4, 5, 6, 7, 0, 1, 2, 3]] + corners[[1, 2, 3, 0, 5, 6, 7, 4, 4, 5, 6, 7]]) / 2
    rows = []
    for i, x in enumerate(np.concatenate([corners, mids])):
        coords = [f"{v:20.13E}" for v in x]
        while coords and float(coords[-1]) == 0.0:
            coords.pop()
        rows.append(f"{i + 1:8d}{0:8d}{0:8d}" + "".join(coords) + "\n")
    head = [1, 1, 1, 1, 0, 0, 0, 0, 20, 0, 5] + list(range(1, 9))
    elem = "".join(f"{v:8d}" for v in head) + "\n" + "".join(f"{v:8d}" for v in range(9, 21)) + "\n"
    return CDB.format(nodes="".join(rows), elem=elem)


def test_apdl_reads_cdb_style_blocks(tmp_path):
    (tmp_path / "beam.mac").write_text(cdb_text())
    mesh = read_mesh(tmp_path / "beam.mac")
    assert (mesh.n_nodes, mesh.n_hexes) == (20, 1) and mesh.cells[0].ids.tolist() == [5]
    np.testing.assert_array_equal(mesh.points[:8], box(1).points)
    assert any("20 nodes (SOLID186)" in n for n in mesh.notes)


def test_bad_apdl_files(tmp_path):
    write_mesh(box(2), tmp_path / "whole.mac")
    text = (tmp_path / "whole.mac").read_text()
    (tmp_path / "half.mac").write_text(text[: len(text) // 2])
    with pytest.raises(MeshReadError, match=r"half\.mac: file ends inside the NBLOCK of line 4 \(truncated\?\)"):
        read_mesh(tmp_path / "half.mac")
    (tmp_path / "few.mac").write_text(text.replace("NBLOCK,6,SOLID,        27,        27", "NBLOCK,6,SOLID,27,28"))
    with pytest.raises(MeshReadError, match=r"few\.mac, line 4: NBLOCK announces 28 rows but holds 27"):
        read_mesh(tmp_path / "few.mac")
    lines = text.splitlines()
    lines[8] = lines[8][:40] + "x" + lines[8][41:]
    (tmp_path / "field.mac").write_text("\n".join(lines))
    with pytest.raises(MeshReadError, match=r"field\.mac, line 9: field 4 .* is not a number"):
        read_mesh(tmp_path / "field.mac")
    (tmp_path / "nodes.mac").write_text(text[: text.index("EBLOCK")])
    with pytest.raises(MeshReadError, match=r"nodes\.mac: no EBLOCK \(elements\) found; the file has 27 nodes"):
        read_mesh(tmp_path / "nodes.mac")
    (tmp_path / "missing.mac").write_text(text.replace("       27        0        0", "       99        0        0"))
    with pytest.raises(MeshReadError, match=r"missing\.mac, line \d+: element \d+ references node 27, which is not in"):
        read_mesh(tmp_path / "missing.mac")


def test_never_overwrites_the_listing(tmp_path):
    nlist, elist = fixture(tmp_path, "block_nlist.lis", "block_elist.lis")
    before = elist.read_bytes()
    mesh = read_mesh((nlist, elist))
    for target in (nlist, elist):
        with pytest.raises(MeshWriteError, match="refusing to overwrite a file the mesh was read from"):
            write_mesh(mesh, target, file_format="apdl")
    assert elist.read_bytes() == before
    write_mesh(mesh, tmp_path / "in.mac")
    with pytest.raises(MeshWriteError, match="refusing to overwrite"):
        write_mesh(read_mesh(tmp_path / "in.mac"), tmp_path / "in.mac")


@pytest.mark.parametrize(
    "name, counts", [("HexBeam.cdb", {"hexahedron": 40}), ("sector.cdb", {"hexahedron": 101, "wedge": 4})]
)
def test_agrees_with_mapdl_archive(tmp_path, name, counts):
    """Real ANSYS archives shipped by mapdl-archive: same nodes and bricks both ways (skipped without it)."""
    mapdl_archive = pytest.importorskip("mapdl_archive")
    path = Path(mapdl_archive.__file__).parent / "examples" / name
    mesh = read_mesh(path)
    assert {b.type: len(b.data) for b in mesh.cells} == counts
    ref = mapdl_archive.Archive(str(path), parse_vtk=False)
    k = {nid: i for i, nid in enumerate(mesh.node_ids.tolist())}
    np.testing.assert_allclose(mesh.points[[k[n] for n in ref.nnum]], ref.nodes[:, :3], rtol=0, atol=1e-15)
    bricks = {eid: [row[i] for i in TO_BRICK[t]] for eid, (t, row) in by_id(mesh).items()}
    assert bricks == {int(e): [int(v) for v in r[10:18]] for e, r in zip(ref.enum, ref.elem, strict=True)}
    for b in mesh.cells:
        if b.type == "wedge":  # ANSYS's prisms keep positive orientation in jaxci's (VTK >= 9.7) wedge order
            assert all(signed_volume(mesh.points[row], "wedge") > 0 for row in b.data)
    write_mesh(mesh, tmp_path / "out.cdb")
    ours = mapdl_archive.Archive(str(tmp_path / "out.cdb"), parse_vtk=False)
    assert {int(e): [int(v) for v in r[10:18]] for e, r in zip(ours.enum, ours.elem, strict=True)} == bricks
    np.testing.assert_allclose(np.sort(ours.nodes[:, :3], axis=0), np.sort(ref.nodes[:, :3], axis=0), atol=1e-13)
