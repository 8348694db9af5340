"""Never lose or silently change a user's data.

Round trips of every format with what `jaxci.io.write_mesh`'s table says it keeps (ids, sets, element types, the
source deck of Abaqus and ANSYS files); headers that announce more or less than a file holds; duplicate, huge,
non-positive and wide ids; non-finite coordinates; the argument and write-failure errors of the API.
"""

from __future__ import annotations

import dataclasses
import errno
import importlib.util
import os
import re
import shutil
import warnings
from pathlib import Path

import meshio
import numpy as np
import pytest

from jaxci.errors import JaxciError, MeshReadError, MeshWriteError, UsageError
from jaxci.io import LossyWriteWarning, read_mesh, write_mesh
from jaxci.io._place import TEMP_PREFIX
from jaxci.mesh import CellBlock, HexMesh
from jaxci.mesh.generate import box, perturb_box

FIXTURES = Path(__file__).parent / "fixtures"
DECK = FIXTURES / "abaqus" / "block_c3d8_variants.inp"
QUADS = np.array([[0, 1, 5, 4], [1, 2, 6, 5]])
HAS_H5PY = importlib.util.find_spec("h5py") is not None


def ided_mesh() -> HexMesh:
    """A perturbed 3^3 box and a quad block; node ids 101.., hexahedron ids 5001.., a point set and a cell set."""
    base = perturb_box(3, amplitude=0.2, seed=1)
    return HexMesh(
        base.points,
        (CellBlock("hexahedron", base.cells[0].data, np.arange(5001, 5028)), CellBlock("quad", QUADS)),
        point_sets={"FIXED": np.array([0, 3, 7])},
        cell_sets={"TOP": [np.array([0, 4, 26]), np.array([1])]},
        node_ids=np.arange(101, 101 + base.n_nodes),
    )


def quiet_write(mesh, path, **kw) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        write_mesh(mesh, path, **kw)
    assert all(issubclass(w.category, LossyWriteWarning) for w in caught), [str(w.message) for w in caught]
    return [str(w.message) for w in caught]


def cell_set_ids(mesh: HexMesh, name: str) -> list[int]:
    return sorted(int(i) for b, rows in zip(mesh.cells, mesh.cell_sets[name], strict=True) for i in b.ids[rows])


# ------------------------------------------------------------------------------------------------ every format
#: name -> (file, file_format, keeps ids, sets kept: "all" | "none", quads kept)
FORMATS = {
    "vtk": ("m.vtk", None, False, "all", True),
    "vtu": ("m.vtu", None, False, "all", True),
    "gmsh41": ("m.msh", None, False, "none", True),
    "gmsh22": ("m.msh", "gmsh22", False, "none", True),
    "abaqus": ("m.inp", None, True, "all", True),
    "xdmf": ("m.xdmf", None, False, "all", True),
    "cdb": ("m.cdb", None, True, "all", False),
    "apdl": ("m.mac", None, True, "all", False),
}


@pytest.mark.parametrize("case", list(FORMATS))
def test_every_format_keeps_what_its_table_says(tmp_path, case):
    name, file_format, ids, sets, quads = FORMATS[case]
    if case == "xdmf" and not HAS_H5PY:
        pytest.skip("h5py not installed")
    mesh = ided_mesh()
    messages = quiet_write(mesh, tmp_path / name, file_format=file_format)
    back = read_mesh(tmp_path / name, file_format=file_format)
    atol = 1e-13 if case in ("cdb", "apdl") else 0.0
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=atol)
    np.testing.assert_array_equal(back.cells[0].data, mesh.cells[0].data)
    assert [b.type for b in back.cells] == (["hexahedron", "quad"] if quads else ["hexahedron"])
    if ids:
        assert back.node_ids.tolist() == mesh.node_ids.tolist()
        assert back.cells[0].ids.tolist() == list(range(5001, 5028))
        assert not any("ids" in m for m in messages)
    else:
        assert back.node_ids is None and back.cells[0].ids is None
        assert any("node and element ids" in m for m in messages)
    if sets == "all":
        assert back.point_sets["FIXED"].tolist() == [0, 3, 7]
        assert back.cell_sets["TOP"][0].tolist() == [0, 4, 26]
        if quads:
            assert back.cell_sets["TOP"][1].tolist() == [1]
    else:
        assert "FIXED" not in back.point_sets and "TOP" not in back.cell_sets
        assert any("point sets ['FIXED']" in m and "cell sets ['TOP']" in m for m in messages)
    if not quads:
        assert any("cells 2 quad" in m for m in messages)


def test_abaqus_numbers_cells_without_ids_after_the_largest():
    mesh = ided_mesh()
    assert mesh.cells[1].ids is None  # the quads: numbered 5028, 5029 by the writer


# ------------------------------------------------------------------------------------------------ Abaqus decks
def deck_lines(path) -> list[str]:
    return Path(path).read_bytes().decode().splitlines(keepends=True)


def test_abaqus_deck_keeps_element_types_and_sets():
    mesh = read_mesh(DECK)
    assert mesh.field_data["abaqus:element_types"] == ("C3D8R", "C3D8I", "C3D8H", "C3D8RH")
    assert [len(b.data) for b in mesh.cells] == [7, 7, 7, 6] and mesh.n_nodes == 64
    assert mesh.node_ids.tolist() == list(range(10, 650, 10))
    assert np.concatenate([b.ids for b in mesh.cells]).tolist() == list(range(1001, 1028))
    assert mesh.point_sets["BOTTOM"].tolist() == list(range(16))  # *NSET, GENERATE 10..160 step 10
    assert cell_set_ids(mesh, "ALL") == list(range(1001, 1028))  # an *ELSET of four sets
    assert cell_set_ids(mesh, "FIRST_LAYER") == list(range(1001, 1010))
    assert cell_set_ids(mesh, "E_C3D8I") == list(range(1008, 1015))


def test_abaqus_deck_written_back_unchanged_is_the_same_file(tmp_path):
    mesh = read_mesh(DECK)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / "same.inp")
    assert (tmp_path / "same.inp").read_bytes() == DECK.read_bytes()  # CRLF line endings, comments, case


def test_abaqus_deck_written_back_after_moving_nodes(tmp_path):
    """Bug 4: only the *NODE coordinates change; element types, materials, sections and steps pass through."""
    mesh = read_mesh(DECK)
    pts = mesh.points.copy()
    moved = np.array([21, 22, 25, 26])  # interior nodes
    pts[moved] += np.array([0.01, -0.02, 0.1 / 3])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh.with_points(pts), tmp_path / "moved.inp")
    old, new = deck_lines(DECK), deck_lines(tmp_path / "moved.inp")
    assert len(old) == len(new)
    node_line = {4 + k for k in range(64)}  # *Node is line 4 (0-based 3); its data lines follow
    changed = [i for i, (a, b) in enumerate(zip(old, new, strict=True)) if a != b]
    assert changed == sorted(4 + k for k in moved.tolist()) and set(changed) <= node_line
    assert all(line.endswith("\r\n") for line in new)
    assert "*Material, name=STEEL\r\n" in new and "*Element, type=C3D8RH, elset=E_C3D8RH\r\n" in new
    back = read_mesh(tmp_path / "moved.inp")
    np.testing.assert_array_equal(back.points, pts)  # float64-exact
    assert back.field_data["abaqus:element_types"] == ("C3D8R", "C3D8I", "C3D8H", "C3D8RH")
    assert new[4 + 21].startswith("    220, ")  # the id field keeps its text


def test_abaqus_deck_to_other_formats_warns_what_is_lost(tmp_path):
    mesh = read_mesh(DECK)
    with pytest.warns(LossyWriteWarning, match=r"vtu drops the keyword blocks \*SOLID SECTION, \*MATERIAL, "
                                                r"\*DENSITY, \*ELASTIC, \*STEP, \*STATIC, \*BOUNDARY, \*CLOAD, \.\.\. "
                                                r"\(9 in all\) and the element types C3D8R, C3D8I, C3D8H, C3D8RH of "
                                                r"the source Abaqus deck"):
        write_mesh(mesh, tmp_path / "m.vtu")
    with pytest.warns(LossyWriteWarning, match=r"APDL drops the keyword blocks \*SOLID SECTION"):
        write_mesh(mesh, tmp_path / "m.cdb")


def test_abaqus_deck_whose_cells_changed_warns_before_writing(tmp_path):
    mesh = read_mesh(DECK)
    fewer = dataclasses.replace(mesh, cells=mesh.cells[:3], cell_sets={}, fix_orientation=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(LossyWriteWarning, match=r"abaqus drops the keyword blocks \*SOLID SECTION, .* of the "
                                                    r"source Abaqus deck \(its cell blocks differ from the deck's, so "
                                                    r"the deck cannot be rewritten in place\)"):
            write_mesh(fewer, tmp_path / "fewer.inp")
    assert os.listdir(tmp_path) == []  # warned before anything was written
    quiet_write(fewer, tmp_path / "fewer.inp")
    back = read_mesh(tmp_path / "fewer.inp")  # written afresh: ids and element types still kept
    assert back.field_data["abaqus:element_types"] == ("C3D8R", "C3D8I", "C3D8H")
    assert back.node_ids.tolist() == mesh.node_ids.tolist()
    assert [b.ids.tolist() for b in back.cells] == [b.ids.tolist() for b in mesh.cells[:3]]


def test_fresh_abaqus_deck_names_and_quadratic_cells(tmp_path):
    """A 20-node brick (from an ANSYS archive or an Abaqus C3D20R block) goes out as C3D20 and reads back."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1.0]])
    edges = [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]
    mids = np.array([(corners[a] + corners[b]) / 2 for a, b in edges])
    mid = np.arange(8, 20)[None]
    mesh = HexMesh(np.concatenate([corners, mids]), (CellBlock("hexahedron", np.arange(8)[None], midside=mid),))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / "q.inp")
    text = (tmp_path / "q.inp").read_text()
    assert "*ELEMENT, TYPE=C3D20\n1, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15,\n16, 17, 18, 19, 20\n" in text
    back = read_mesh(tmp_path / "q.inp")
    assert back.cells[0].midside.tolist() == mid.tolist()
    renamed = text.replace("TYPE=C3D20", "TYPE=C3D20R")
    (tmp_path / "r.inp").write_text(renamed)
    moved = read_mesh(tmp_path / "r.inp")
    moved = moved.with_points(moved.points * 2.0)
    write_mesh(moved, tmp_path / "r2.inp")  # in place: the type name stays C3D20R
    assert "TYPE=C3D20R" in (tmp_path / "r2.inp").read_text()
    np.testing.assert_array_equal(read_mesh(tmp_path / "r2.inp").points, moved.points)


def test_abaqus_include_files_are_read_and_inlined(tmp_path):
    text = DECK.read_text()
    start, end = text.index("*Node"), text.index("*Element")
    (tmp_path / "nodes.inc").write_text(text[start:end])
    (tmp_path / "main.inp").write_text(text[:start] + "*INCLUDE, INPUT=nodes.inc\n" + text[end:])
    mesh = read_mesh(tmp_path / "main.inp")
    assert mesh.n_nodes == 64 and any("1 *INCLUDE files read (nodes.inc)" in n for n in mesh.notes)
    write_mesh(mesh.with_points(mesh.points + 1.0), tmp_path / "out.inp")
    out = (tmp_path / "out.inp").read_text()
    assert "*INCLUDE" not in out and "*Node, nset=ALLNODES" in out
    np.testing.assert_array_equal(read_mesh(tmp_path / "out.inp").points, mesh.points + 1.0)
    (tmp_path / "broken.inp").write_text("*INCLUDE, INPUT=nowhere.inc\n")
    with pytest.raises(MeshReadError, match=r"broken\.inp, line 1: \*INCLUDE file nowhere\.inc not found"):
        read_mesh(tmp_path / "broken.inp")


def test_abaqus_elements_of_other_types_stay_in_the_deck(tmp_path):
    text = DECK.read_text().replace("*Nset, nset=BOTTOM", "*Element, type=MASS, elset=M\n2001, 640\n*Nset, nset=BOTTOM")
    (tmp_path / "mass.inp").write_text(text)
    mesh = read_mesh(tmp_path / "mass.inp")
    assert any("types jaxci does not read (1 MASS)" in n for n in mesh.notes) and len(mesh.cells) == 4
    write_mesh(mesh.with_points(mesh.points * 3), tmp_path / "out.inp")
    assert "*Element, type=MASS, elset=M\n2001, 640\n" in (tmp_path / "out.inp").read_text()


# ------------------------------------------------------------------------------------------------ ANSYS archives
def box_cdb(tmp_path, extra: str = "") -> Path:
    """A 2^3 box written by jaxci as .cdb, with `extra` APDL commands (materials, loads) before FINISH."""
    write_mesh(box(2), tmp_path / "plain.cdb")
    text = (tmp_path / "plain.cdb").read_text().replace("FINISH", extra + "FINISH")
    (tmp_path / "box.cdb").write_text(text)
    return tmp_path / "box.cdb"


MATERIALS = "MPTEMP,R5.0, 1, 1,  0.00000000    ,\nMPDATA,R5.0, 1,EX  ,       1, 1,  210000.000    ,\nD,1,UX,0\n"


def test_cdb_written_back_keeps_the_commands_jaxci_does_not_model(tmp_path):
    path = box_cdb(tmp_path, MATERIALS)
    mesh = read_mesh(path)
    assert any("3 other APDL commands not modelled (MPTEMP, MPDATA, D)" in n for n in mesh.notes)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / "same.cdb")
        assert (tmp_path / "same.cdb").read_bytes() == path.read_bytes()
        pts = mesh.points.copy()
        pts[13] += [0.1, 0.05, -0.125]  # the centre node
        write_mesh(mesh.with_points(pts), tmp_path / "moved.mac")
    old, new = path.read_text().splitlines(), (tmp_path / "moved.mac").read_text().splitlines()
    changed = [i for i, (a, b) in enumerate(zip(old, new, strict=True)) if a != b]
    assert len(old) == len(new) and changed == [old.index(next(r for r in old if r.startswith("       14 ")))]
    assert new[changed[0]] == f"{14:9d}{0:9d}{0:9d}" + " 6.0000000000000E-001 5.5000000000000E-001 3.7500000000000E-001"
    np.testing.assert_array_equal(read_mesh(tmp_path / "moved.mac").points, pts)


def test_cdb_whose_cells_changed_warns_about_its_commands(tmp_path):
    mesh = read_mesh(box_cdb(tmp_path, MATERIALS))
    other = dataclasses.replace(mesh, point_sets={"NEW": np.array([1, 2])}, fix_orientation=False)
    with pytest.warns(LossyWriteWarning, match=r"APDL drops the other APDL commands of the source file \(MPTEMP, "
                                               r"MPDATA, D\) \(its node or element sets differ from the deck's"):
        write_mesh(other, tmp_path / "other.cdb")
    assert "MPDATA" not in (tmp_path / "other.cdb").read_text()
    with pytest.warns(LossyWriteWarning, match=r"vtu drops the other APDL commands of the source file"):
        write_mesh(mesh, tmp_path / "m.vtu")


def test_hexbeam_archive_round_trip_in_place(tmp_path):
    """A real archive (mapdl-archive's HexBeam.cdb: (3i9,6e21.13e3), materials, 20-node bricks) moved and written
    back: mapdl-archive reads the new coordinates and the same elements."""
    mapdl_archive = pytest.importorskip("mapdl_archive")
    src = Path(mapdl_archive.__file__).parent / "examples" / "HexBeam.cdb"
    mesh = read_mesh(src)
    rng = np.random.default_rng(0)
    pts = mesh.points + rng.uniform(-1e-3, 1e-3, mesh.points.shape)
    moved = mesh.with_points(pts, midside="keep")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(moved, tmp_path / "beam.cdb")
    old, new = src.read_text().splitlines(), (tmp_path / "beam.cdb").read_text().splitlines()
    assert len(old) == len(new) and [a for a in old if "MPDATA" in a] == [b for b in new if "MPDATA" in b]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = mapdl_archive.Archive(str(tmp_path / "beam.cdb"), parse_vtk=False)
        ref = mapdl_archive.Archive(str(src), parse_vtk=False)
    order = {nid: k for k, nid in enumerate(mesh.node_ids.tolist())}
    np.testing.assert_allclose(a.nodes[:, :3], pts[[order[n] for n in a.nnum]], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(a.elem, ref.elem)


# ------------------------------------------------------------------------------------------------ wide and huge ids
@pytest.mark.parametrize("ext", [".cdb", ".mac", ".inp"])
@pytest.mark.parametrize("first", [999_999_990, 2_000_000_000, 10**15])
def test_wide_ids_read_back(tmp_path, ext, first):
    """Bug 5: ids of 10 digits and more are written in fields wide enough, and read back."""
    base = box(2)
    mesh = HexMesh(base.points, (CellBlock("hexahedron", base.cells[0].data, first + 50 + np.arange(8)),),
                   node_ids=first + np.arange(base.n_nodes), point_sets={"ALL": np.arange(27)},
                   cell_sets={"SOME": [np.array([0, 1, 2, 7])]})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / f"wide{ext}")
    back = read_mesh(tmp_path / f"wide{ext}")
    assert back.node_ids.tolist() == mesh.node_ids.tolist()
    assert back.cells[0].ids.tolist() == mesh.cells[0].ids.tolist()
    assert back.point_sets["ALL"].tolist() == list(range(27)) and back.cell_sets["SOME"][0].tolist() == [0, 1, 2, 7]
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-13)
    if ext == ".cdb":
        text = (tmp_path / "wide.cdb").read_text()
        width = 9 if first + 26 < 10**8 else len(str(first + 58)) + 1
        assert (f"(3i{width},6e21.13e3)" in text) and (f"(19i{width})" in text)
    if ext == ".cdb" and first + 58 < 2**31:
        mapdl_archive = pytest.importorskip("mapdl_archive")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            a = mapdl_archive.Archive(str(tmp_path / "wide.cdb"), parse_vtk=False)
        assert a.nnum.tolist() == mesh.node_ids.tolist() and a.enum.tolist() == mesh.cells[0].ids.tolist()
        np.testing.assert_allclose(a.nodes[:, :3], mesh.points, rtol=0, atol=1e-13)
        assert sorted(a.element_components["SOME"].tolist()) == (first + 50 + np.array([0, 1, 2, 7])).tolist()


def test_wide_ids_through_the_cli(tmp_path, capsys):
    """Bug 5 as reported: smooth big-ids.cdb o.cdb, then quality o.cdb."""
    from jaxci.cli import main

    base = perturb_box(2, amplitude=0.1, seed=0)
    mesh = HexMesh(base.points, (CellBlock("hexahedron", base.cells[0].data, 10**10 + np.arange(8)),),
                   node_ids=10**10 + np.arange(base.n_nodes))
    write_mesh(mesh, tmp_path / "big-ids.cdb")
    assert main(["smooth", str(tmp_path / "big-ids.cdb"), str(tmp_path / "o.cdb"), "--json"]) == 0
    assert main(["quality", str(tmp_path / "o.cdb")]) == 0
    assert read_mesh(tmp_path / "o.cdb").node_ids.tolist() == mesh.node_ids.tolist()


LISTING = FIXTURES / "ansys" / "block_combined.txt"


def listing_with(tmp_path, old: str, new: str) -> Path:
    text = LISTING.read_text()
    assert old in text
    (tmp_path / "bad.txt").write_text(text.replace(old, new, 1))
    return tmp_path / "bad.txt"


@pytest.mark.parametrize("old, new, message", [
    ("\n        1   0.0", "\n 10000000000000000000   0.0",
     r"bad\.txt, line 13: node number 10000000000000000000 is too large \(jaxci reads ids up to 9223372036854775807\)"),
    ("\n        1   0.0", "\n        0   0.0", r"bad\.txt, line 13: node number 0 is not positive"),
    ("\n        1   0.0", "\n       -1   0.0", r"bad\.txt, line 13: node number -1 is not positive"),
    ("        2   0.5000000000 ", "        2   nan          ",
     r"bad\.txt, line 14: coordinate X of node 2 is 'nan'; coordinates must be finite"),
    ("        2   0.5000000000 ", "        2   1e999        ", r"bad\.txt, line 14: coordinate X of node 2 is '1e999'"),
    ("        3   1.0000000000 ", "        1   1.0000000000 ", r"bad\.txt, line 15: node 1 listed twice \(first at "),
])
def test_listing_ids_and_coordinates(tmp_path, old, new, message):
    """Bug 10: huge ids were an OverflowError ("internal error"); now one clear line naming file and line."""
    with pytest.raises(MeshReadError, match=message):
        read_mesh(listing_with(tmp_path, old, new))


def test_listing_huge_element_number(tmp_path):
    text = LISTING.read_text()
    row = next(line for line in text.splitlines() if re.match(r"\s+1\s+1\s+1\s+1\s+0\s+1\s", line))
    (tmp_path / "el.txt").write_text(text.replace(row, row.replace("       1   1", " 99999999999999999999   1", 1)))
    with pytest.raises(MeshReadError, match=r"el\.txt, line \d+: field 1 \(ELEM\) 99999999999999999999 is too large"):
        read_mesh(tmp_path / "el.txt")


def cdb_row_edit(tmp_path, edit) -> Path:
    write_mesh(box(1), tmp_path / "one.cdb")
    lines = (tmp_path / "one.cdb").read_text().splitlines()
    edit(lines)
    (tmp_path / "bad.cdb").write_text("\n".join(lines) + "\n")
    return tmp_path / "bad.cdb"


def _wide_first_node(lines):
    lines[4] = "(3i21,6e21.13e3)"
    lines[5] = f"{10**20:21d}{0:21d}{0:21d}" + lines[5][27:]
    for k in range(6, 13):
        lines[k] = f"{int(lines[k][:9]):21d}{0:21d}{0:21d}" + lines[k][27:]


@pytest.mark.parametrize("edit, message", [
    (_wide_first_node, r"bad\.cdb, line 6: field 1 '100000000000000000000' is too large"),
    (lambda L: L.__setitem__(5, f"{0:9d}" + L[5][9:]), r"bad\.cdb, line 6: node number 0 is not positive"),
    (lambda L: L.__setitem__(6, L[6][:27] + f"{'NaN':>21}" + L[6][48:]),
     r"bad\.cdb, line 7: node 2 has a non-finite coordinate or angle \(nan, "),
    (lambda L: L.__setitem__(6, f"{1:9d}" + L[6][9:]), r"bad\.cdb, line 7: node 1 listed twice \(first at .*line 6\)"),
    (lambda L: L.__setitem__(16, L[16][:90] + f"{-4:9d}" + L[16][99:]),
     r"bad\.cdb, line 17: element number -4 is not positive"),
])
def test_cdb_ids_and_coordinates(tmp_path, edit, message):
    with pytest.raises(MeshReadError, match=message):
        read_mesh(cdb_row_edit(tmp_path, edit))


# ------------------------------------------------------------------------------------------------ duplicate ids
def test_abaqus_duplicate_node_with_other_coordinates(tmp_path):
    """Bug 7: the second definition used to win silently."""
    text = DECK.read_text().replace("*Element, type=C3D8R", "    220, 5.0, 5.0, 5.0\n*Element, type=C3D8R", 1)
    (tmp_path / "dup.inp").write_text(text)
    with pytest.raises(MeshReadError, match=r"dup\.inp, line 69: node 220 is defined twice \(first at .*dup\.inp, "
                                            r"line 26\)"):
        read_mesh(tmp_path / "dup.inp")


#: (file, text of the deck replaced (it occurs once), its replacement, message)
ABAQUS_BAD_FIELDS = [
    ("elem.inp", " 1002, ", " 1001, ", r"elem\.inp, line 71: element 1001 is defined twice \(first at .*line 70\)"),
    ("zero.inp", "     10, 0.000000", "      0, 0.000000", r"zero\.inp, line 5: node id 0 is not positive"),
    ("huge.inp", "     10, 0.000000", "99999999999999999999, 0.000000",
     r"huge\.inp, line 5: node id 99999999999999999999 is too large"),
    ("nan.inp", "     10, 0.000000,", "     10, nan,",
     r"nan\.inp, line 5: coordinate x of node 10 is 'nan'; coordinates must be finite"),
    ("long.inp", " 1002, ", " 1002, 99999, ", r"long\.inp, line 71: element 1002 lists 9 nodes; TYPE=C3D8R has 8"),
    ("short.inp", ", 220\r\n 1003", "\r\n 1003",
     r"short\.inp, line 72: element 1002 \(continued from line 71\) lists 16 nodes; TYPE=C3D8R has 8"),
    ("ref.inp", " 1002, 20,", " 1002, 25,",
     r"ref\.inp, line 71: element 1002 references node 25, which no \*NODE defines"),
    ("set.inp", "\r\nE_C3D8RH\r\n", "\r\nE_NOPE\r\n",
     r"set\.inp, line \d+: element set ALL lists 'E_NOPE', which is neither"),
    ("ngen.inp", "*Nset, nset=BOTTOM", "*NGEN\n10, 40\n*Nset, nset=BOTTOM",
     r"ngen\.inp, line \d+: \*NGEN generates or moves nodes"),
]


@pytest.mark.parametrize(("name", "old", "new", "message"), ABAQUS_BAD_FIELDS, ids=[c[0] for c in ABAQUS_BAD_FIELDS])
def test_abaqus_duplicate_element_and_bad_fields(tmp_path, name, old, new, message):
    good = DECK.read_bytes().decode()  # CRLF line endings kept
    (tmp_path / name).write_bytes(good.replace(old, new, 1).encode())
    with pytest.raises(MeshReadError, match=message):
        read_mesh(tmp_path / name)


def test_abaqus_parts_numbered_from_one_are_refused(tmp_path):
    part = "*Node\n1, 0., 0., 0.\n2, 1., 0., 0.\n"
    (tmp_path / "parts.inp").write_text(f"*Part, name=A\n{part}*End Part\n*Part, name=B\n{part}*End Part\n")
    with pytest.raises(MeshReadError, match=r"parts\.inp, line 8: node 1 is defined twice \(first at .*line 3\) "
                                            r"\(in parts A and B; jaxci needs node ids unique"):
        read_mesh(tmp_path / "parts.inp")


@pytest.mark.parametrize("version", ["4.1", "2.2"])
@pytest.mark.parametrize("binary", [False, True])
def test_gmsh_duplicate_node_tag(tmp_path, version, binary):
    m = box(1)
    mm = meshio.Mesh(m.points, [("hexahedron", m.cells[0].data)],
                     cell_data={"gmsh:physical": [np.ones(1, int)], "gmsh:geometrical": [np.ones(1, int)]})
    meshio.gmsh.write(tmp_path / "one.msh", mm, version, binary=binary)
    data = (tmp_path / "one.msh").read_bytes()
    if binary and version == "2.2":  # records (int32 tag, 3 doubles) after "$Nodes\n8\n"
        at = data.index(b"$Nodes\n8\n") + len(b"$Nodes\n8\n") + 28
        data = data[:at] + np.int32(1).tobytes() + data[at + 4:]
    elif binary:  # 4 size_t, then one block: 3 ints and a size_t, then the 8 tags as size_t
        at = data.index(b"$Nodes\n") + len(b"$Nodes\n") + 32 + 12 + 8 + 8
        data = data[:at] + np.uint64(1).tobytes() + data[at + 8:]
    elif version == "2.2":
        data = data.replace(b"\n2 ", b"\n1 ", 1)
    else:
        data = data.replace(b"\n2\n", b"\n1\n", 1)
    (tmp_path / "dup.msh").write_bytes(data)
    with pytest.raises(MeshReadError, match=r"dup\.msh: node tag 1 is defined twice in \$Nodes"):
        read_mesh(tmp_path / "dup.msh", file_format="gmsh22" if version == "2.2" else None)


# ------------------------------------------------------------------------------------------------ trust no header
def legacy_vtk(tmp_path) -> str:
    write_mesh(box(4), tmp_path / "b4.vtk")
    return (tmp_path / "b4.vtk").read_text()


def test_vtk_cut_inside_cell_types(tmp_path):
    """Bug 6: 64 cells announced, 15 present, was smoothed as a 15-cell mesh."""
    text = legacy_vtk(tmp_path)
    head, tail = text.split("CELL_TYPES 64\n")
    (tmp_path / "cut.vtk").write_text(head + "CELL_TYPES 64\n" + "\n".join(tail.splitlines()[:15]) + "\n")
    with pytest.raises(MeshReadError, match=r"cut\.vtk: corrupt or truncated legacy VTK file: CELL_TYPES announces 64 "
                                            r"cell types, the file holds 15 cells"):
        read_mesh(tmp_path / "cut.vtk")


@pytest.mark.parametrize("old, new, message", [
    ("POINTS 125", "POINTS 126", r"POINTS announces 126 points \(378 values\), the file holds 375 values"),
    ("POINTS 125", "POINTS 124", r"POINTS announces 124 points \(372 values\), the file holds more values"),
    ("CELLS 64 576", "CELLS 63 567", r"CELLS announces 63 cells in 567 values, the file holds more values"),
    ("CELLS 64 576", "CELLS 64 580", r"CELLS announces 64 cells in 580 values, the file holds 576 values"),
    ("CELL_TYPES 64", "CELL_TYPES 65", r"CELL_TYPES announces 65 cell types, the file holds 64"),
    ("CELL_TYPES 64", "CELL_TYPES 63", r"CELL_TYPES announces 63 cell types, the file holds more values"),
])
def test_vtk_headers_must_match(tmp_path, old, new, message):
    text = legacy_vtk(tmp_path)
    assert old in text
    (tmp_path / "bad.vtk").write_text(text.replace(old, new))
    with pytest.raises(MeshReadError, match=r"bad\.vtk: corrupt or truncated legacy VTK file: " + message):
        read_mesh(tmp_path / "bad.vtk")


@pytest.mark.parametrize("binary", [False, True])
def test_vtk_cut_anywhere(tmp_path, binary):
    """A legacy VTK file (ASCII 4.2, or binary) with point and cell data, cut at 24 places: never read as a
    smaller mesh; the ASCII one names the section and what it lacks."""
    mesh = dataclasses.replace(box(2), point_data={"f": np.arange(27.0)}, cell_data={"k": [np.arange(8)]})
    m = meshio.Mesh(mesh.points, [("hexahedron", mesh.cells[0].data)], point_data=dict(mesh.point_data),
                    cell_data={"k": [np.arange(8)]})
    meshio.vtk.write(tmp_path / "d.vtk", m, "4.2", binary=binary)
    data = (tmp_path / "d.vtk").read_bytes()
    for cut in np.linspace(data.index(b"POINTS") + 12, len(data) - 2, 24).astype(int):
        (tmp_path / "cut.vtk").write_bytes(data[:cut])
        with pytest.raises(MeshReadError, match=r"cut\.vtk: corrupt or truncated legacy VTK file" +
                           ("" if binary else r": .*(announces|ends inside)")):
            read_mesh(tmp_path / "cut.vtk")


@pytest.mark.parametrize("old, new", [('NumberOfCells="8"', 'NumberOfCells="12"'),
                                      ('NumberOfCells="8"', 'NumberOfCells="5"'),
                                      ('NumberOfPoints="27"', 'NumberOfPoints="30"')])
def test_vtu_header_counts(tmp_path, old, new):
    meshio.vtu.write(tmp_path / "a.vtu", meshio.Mesh(box(2).points, [("hexahedron", box(2).cells[0].data)]),
                     binary=False)
    (tmp_path / "bad.vtu").write_text((tmp_path / "a.vtu").read_text().replace(old, new))
    with pytest.raises(MeshReadError, match=r"bad\.vtu: corrupt or truncated VTU file(: piece 0 announces \d+ cells "
                                            r"\(NumberOfCells\) and holds 8 offsets and 8 types| \(.*shape)"):
        read_mesh(tmp_path / "bad.vtu")


def ascii_gmsh(tmp_path, version) -> bytes:
    m = box(2)
    mm = meshio.Mesh(m.points, [("hexahedron", m.cells[0].data)],
                     cell_data={"gmsh:physical": [np.ones(8, int)], "gmsh:geometrical": [np.ones(8, int)]})
    meshio.gmsh.write(tmp_path / "g.msh", mm, version, binary=False)
    return (tmp_path / "g.msh").read_bytes()


@pytest.mark.parametrize("version, old, new, message", [
    ("4.1", b"$Nodes\n1 27 1 27", b"$Nodes\n1 30 1 30", r"\$Nodes: the header announces 30 nodes, its 1 entity "
                                                        r"blocks hold 27"),
    ("4.1", b"$Elements\n1 8 1 8", b"$Elements\n1 12 1 12", r"\$Elements: the header announces 12 elements"),
    ("4.1", b"$Elements\n1 8 1 8\n3 1 5 8", b"$Elements\n1 5 1 8\n3 1 5 5",
     r"\$Elements: 27 values more than its headers announce"),
    ("2.2", b"$Nodes\n27\n", b"$Nodes\n30\n", r"\$Nodes: the header announces 30 nodes, the section holds fewer"),
    ("2.2", b"$Elements\n8\n", b"$Elements\n5\n", r"\$Elements: 39 values more than its headers announce"),
    ("2.2", b"$Elements\n8\n", b"$Elements\n12\n", r"\$Elements: fewer values than its headers announce"),
    ("2.2", b"$EndElements", b"", r"\$Elements: no \$EndElements \(the file ends inside the section\)"),
])
def test_gmsh_counts_must_match(tmp_path, version, old, new, message):
    data = ascii_gmsh(tmp_path, version)
    assert old in data
    (tmp_path / "bad.msh").write_bytes(data.replace(old, new))
    with pytest.raises(MeshReadError, match=r"bad\.msh: corrupt or truncated Gmsh file: " + message):
        read_mesh(tmp_path / "bad.msh", file_format="gmsh22" if version == "2.2" else None)


@pytest.mark.parametrize("file_format", [None, "gmsh22"])
def test_binary_gmsh_cut_short(tmp_path, file_format):
    write_mesh(box(3), tmp_path / "b.msh", file_format=file_format)
    data = (tmp_path / "b.msh").read_bytes()
    for cut in (0.4, 0.7, 0.95):
        (tmp_path / "cut.msh").write_bytes(data[: int(len(data) * cut)])
        with pytest.raises(MeshReadError, match=r"cut\.msh: corrupt or truncated Gmsh file"):
            read_mesh(tmp_path / "cut.msh", file_format=file_format)


def test_files_jaxci_writes_pass_the_count_checks(tmp_path):
    mesh = dataclasses.replace(ided_mesh(), node_ids=None, cells=(ided_mesh().cells[0].__class__(
        "hexahedron", ided_mesh().cells[0].data), CellBlock("quad", QUADS)), fix_orientation=False)
    for name, fmt in (("a.vtk", None), ("a.vtu", None), ("a.msh", None), ("b.msh", "gmsh22")):
        quiet_write(mesh, tmp_path / name, file_format=fmt)
        assert read_mesh(tmp_path / name, file_format=fmt).n_hexes == 27


# ------------------------------------------------------------------------------------------------ the API
def test_write_mesh_checks_its_arguments(tmp_path):
    """Bugs 11/12: write_mesh(ndarray, ...) was an AttributeError."""
    with pytest.raises(UsageError, match=r"write_mesh: mesh must be a jaxci HexMesh, got numpy\.ndarray \(make one "
                                         r"with jaxci\.mesh\.hex_mesh"):
        write_mesh(np.zeros((8, 3)), tmp_path / "m.vtu")
    with pytest.raises(UsageError, match=r"mesh must be a jaxci HexMesh, got pathlib\.PosixPath \(the mesh comes "
                                         r"first"):
        write_mesh(tmp_path / "m.vtu", box(1))
    with pytest.raises(UsageError, match=r"write_mesh: path must be a file path \(str or os\.PathLike\), got int"):
        write_mesh(box(1), 3)
    with pytest.raises(TypeError):  # UsageError is a TypeError too
        write_mesh(box(1), tmp_path / "m.vtu", file_format=7)
    with pytest.raises(JaxciError, match=r"read_mesh: path must be a file path \(str or os\.PathLike\), got "
                                         r"jaxci\.mesh\.HexMesh"):
        read_mesh(box(1))
    with pytest.raises(UsageError, match="the file path is empty"):
        read_mesh("")
    assert os.listdir(tmp_path) == []


def test_a_folder_is_said_to_be_a_folder(tmp_path):
    (tmp_path / "meshes").mkdir()
    with pytest.raises(MeshReadError, match=r"meshes: is a folder, not a mesh file"):
        read_mesh(tmp_path / "meshes")
    with pytest.raises(MeshReadError, match=r"meshes: is a folder"):
        read_mesh((tmp_path / "meshes", tmp_path / "meshes"))


@pytest.mark.parametrize("name", ["m.vtu", "m.inp", "m.cdb"])
def test_disk_full_names_the_output_and_says_so(tmp_path, monkeypatch, name):
    real_open = open

    def full_disk(file, mode="r", *args, **kwargs):
        if "w" in mode and TEMP_PREFIX in str(file):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(file))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr("builtins.open", full_disk)
    monkeypatch.setattr(meshio.vtu, "write", lambda path, *a, **k: full_disk(path, "w"))
    with pytest.raises(MeshWriteError) as info:
        write_mesh(box(1), tmp_path / name)
    message = str(info.value)
    assert message == f"{tmp_path / name}: cannot write (No space left on device)"
    assert TEMP_PREFIX not in message and os.listdir(tmp_path) == []


def test_numpy_write_error_on_a_full_disk(tmp_path, monkeypatch):
    """numpy's tofile says 'problem writing element 555 to file' with no errno: the free space tells."""
    def fail(path, *a, **k):
        raise OSError("problem writing element 555 to file")

    monkeypatch.setattr(meshio.vtu, "write", fail)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(100, 100, 0))
    with pytest.raises(MeshWriteError, match=r"m\.vtu: cannot write \(no space left on device: problem writing "
                                             r"element 555 to file\)") as info:
        write_mesh(box(1), tmp_path / "m.vtu")
    assert TEMP_PREFIX not in str(info.value)


def test_writer_errors_name_the_output_not_the_temporary_file(tmp_path):
    mesh = HexMesh(box(1).points, (CellBlock("hexahedron", box(1).cells[0].data, np.array([0])),))
    with pytest.raises(MeshWriteError) as info:
        write_mesh(mesh, tmp_path / "m.cdb")
    assert str(info.value) == f"{tmp_path / 'm.cdb'}: element id 0 is not positive; ANSYS ids start at 1"


def test_smoothing_an_abaqus_deck_through_the_cli(tmp_path, capsys):
    """Bug 4 as reported: `jaxci smooth t.inp o.inp` kept neither C3D8R nor *MATERIAL, with rc 0 and no warning."""
    from jaxci.cli import main

    assert main(["smooth", str(DECK), str(tmp_path / "o.inp"), "--json"]) == 0
    assert "drops" not in capsys.readouterr().err
    old, new = deck_lines(DECK), deck_lines(tmp_path / "o.inp")
    assert len(old) == len(new)
    changed = [i for i, (a, b) in enumerate(zip(old, new, strict=True)) if a != b]
    assert changed and all(4 <= i < 4 + 64 for i in changed)  # node lines only
    before, after = read_mesh(DECK), read_mesh(tmp_path / "o.inp")
    assert after.field_data["abaqus:element_types"] == ("C3D8R", "C3D8I", "C3D8H", "C3D8RH")
    assert np.abs(after.points - before.points).max() > 1e-3


@pytest.mark.parametrize("version", ["4.1", "2.2"])
def test_gmsh_elements_must_reference_defined_nodes_once(tmp_path, version):
    data = ascii_gmsh(tmp_path, version)
    ff = "gmsh22" if version == "2.2" else None
    head, elements = data.split(b"$Elements\n")
    rows = elements.split(b"\n")
    first = 2 if version == "4.1" else 1  # the first element line (4.1: after the totals and the block header)
    fields = rows[first].split()
    bad = fields[:-1] + [b"999"]
    (tmp_path / "ref.msh").write_bytes(head + b"$Elements\n" + b"\n".join(rows[:first] + [b" ".join(bad)] +
                                                                         rows[first + 1:]))
    with pytest.raises(MeshReadError, match=r"ref\.msh: an element of \$Elements lists node tag 999, which \$Nodes "
                                            r"does not define"):
        read_mesh(tmp_path / "ref.msh", file_format=ff)
    second = rows[first + 1].split()
    dup = [fields[0]] + second[1:]
    (tmp_path / "dup.msh").write_bytes(head + b"$Elements\n" + b"\n".join(rows[:first + 1] + [b" ".join(dup)] +
                                                                         rows[first + 2:]))
    with pytest.raises(MeshReadError, match=r"dup\.msh: element tag 1 is defined twice in \$Elements"):
        read_mesh(tmp_path / "dup.msh", file_format=ff)


@pytest.mark.parametrize("array, old, new, message", [
    ("offsets", "8\n16\n", "8\n15\n", r"cell 1 has 7 nodes by its offsets, but its type 12 \(hexahedron\) has 8"),
    ("types", "12\n12\n", "12\n10\n", r"cell 1 has 8 nodes by its offsets, but its type 10 \(tetra\) has 4"),
    ("types", "12\n12\n", "12\n99\n", r"holds 1 cells of VTK type 99, which jaxci cannot read"),
    ("offsets", "56\n64\n", "56\n", r"announces 8 cells \(NumberOfCells\) and holds 7 offsets and 8 types"),
])
def test_vtu_cell_arrays_must_agree(tmp_path, array, old, new, message):
    """meshio slices the connectivity by offsets and type sizes: a wrong offset or type gave other cells, silently."""
    m = meshio.Mesh(box(2).points, [("hexahedron", box(2).cells[0].data)])
    meshio.vtu.write(tmp_path / "a.vtu", m, binary=False)
    text = (tmp_path / "a.vtu").read_text()
    head, rest = text.split(f'Name="{array}" format="ascii">\n', 1)
    assert rest.startswith(old) or old in rest[: rest.index("</DataArray>")]
    body, tail = rest.split("</DataArray>", 1)
    (tmp_path / "bad.vtu").write_text(head + f'Name="{array}" format="ascii">\n' + body.replace(old, new, 1) +
                                      "</DataArray>" + tail)
    with pytest.raises(MeshReadError, match=r"bad\.vtu: (corrupt or truncated VTU file: piece 0:? )?" + message):
        read_mesh(tmp_path / "bad.vtu")


@pytest.mark.skipif(not HAS_H5PY, reason="h5py not installed")
@pytest.mark.parametrize("old, new, message", [
    ('Dimensions="27 3"', 'Dimensions="24 3"', r"the Geometry announces 24 x 3 values, the data hold 27 points"),
    ('NumberOfElements="8"', 'NumberOfElements="9"', r"the Topology announces 9 elements, the data hold 8"),
    ('Dimensions="8 8"', 'Dimensions="8 7"', r"the Topology data item announces 8 x 7 values"),
])
def test_xdmf_dimensions_must_match_the_data(tmp_path, old, new, message):
    write_mesh(box(2), tmp_path / "b.xdmf")
    text = (tmp_path / "b.xdmf").read_text()
    assert old in text
    (tmp_path / "b.xdmf").write_text(text.replace(old, new))
    with pytest.raises(MeshReadError, match=r"b\.xdmf: corrupt XDMF file: " + message):
        read_mesh(tmp_path / "b.xdmf")


def test_cdb_ids_above_2_53_stay_distinct(tmp_path):
    """Ids between 2^53 and 2^63 went through float64 and two of them became one ("listed twice")."""
    base = box(1)
    big = 2**62
    mesh = HexMesh(base.points, (CellBlock("hexahedron", base.cells[0].data, np.array([big + 7])),),
                   node_ids=big + np.arange(8))
    write_mesh(mesh, tmp_path / "big.cdb")
    back = read_mesh(tmp_path / "big.cdb")
    assert back.node_ids.tolist() == mesh.node_ids.tolist() and back.cells[0].ids.tolist() == [big + 7]
