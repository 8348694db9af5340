"""jaxci.io through meshio: round trips per format, the Mesquite meshes, bad input, safe writing."""

from __future__ import annotations

import importlib.util
import os
import re
import warnings

import meshio
import numpy as np
import pytest
from helpers import MESQUITE, MESQUITE_FIGURES, read_vtk_hexes, unit_cube

from jaxci.errors import MeshError, MeshReadError, MeshWriteError, UnsupportedFormatError
from jaxci.io import FORMATS, LossyWriteWarning, read_mesh, write_mesh
from jaxci.mesh import MIRROR_HEX, CellBlock, HexMesh
from jaxci.mesh.generate import box, perturb_box

QUADS = np.array([[0, 1, 5, 4], [1, 2, 6, 5]])


def rich_mesh() -> HexMesh:
    """A perturbed 3x3x3 box plus a quad block, float and int point/cell data, a cell set and a point set."""
    base = perturb_box(3, amplitude=0.2, seed=1)
    n = base.n_nodes
    return HexMesh(
        base.points,
        (base.cells[0], CellBlock("quad", QUADS)),
        point_data={"f": np.linspace(0.0, 1.0, n) / 3, "i": np.arange(n, dtype=np.int32)},
        cell_data={"q": [np.arange(27) / 7, np.array([1.5, 2.5])], "k": [np.arange(27), np.array([7, 8])]},
        cell_sets={"top": [np.array([0, 3, 5]), np.array([1])]},
        point_sets={"corner": np.array([0, 3])},
    )


def write_quietly(mesh, path, **kwargs) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        write_mesh(mesh, path, **kwargs)
    return [str(w.message) for w in caught]


# (file name, file_format, data: "dtypes" | "float64" | "points-only" | None, sets kept, lossy-write warning)
FORMAT_CASES = {
    "vtu": ("m.vtu", None, "dtypes", True, None),
    "vtk": ("m.vtk", None, "dtypes", True, None),
    "gmsh41": ("m.msh", None, "float64", False, r"drops cell sets \['top'\].*integer dtype"),
    "gmsh22": ("m.msh", "gmsh22", "points-only", False, r"cell data \['k', 'q'\] \(Gmsh 2\.2.*dtype of \['i'\]"),
    "abaqus": ("m.inp", None, None, True, r"abaqus drops point data \['f', 'i'\]; cell data \['k', 'q'\]"),
    "xdmf": ("m.xdmf", None, "dtypes", True, None),
}


@pytest.mark.parametrize("case", list(FORMAT_CASES))
def test_round_trip(tmp_path, case):
    name, file_format, data, sets, lossy = FORMAT_CASES[case]
    if case == "xdmf":
        pytest.importorskip("h5py")
    mesh = rich_mesh()
    path = tmp_path / name
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        write_mesh(mesh, path, file_format=file_format)
        back = read_mesh(path, file_format=file_format)
    messages = [str(w.message) for w in caught]
    if lossy is None:
        assert messages == []
    else:
        assert len(messages) == 1 and issubclass(caught[0].category, LossyWriteWarning)
        assert re.search(lossy, messages[0]), messages
    assert back.source == str(path)
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-12)
    assert [b.type for b in back.cells] == ["hexahedron", "quad"]
    np.testing.assert_array_equal(back.cells[0].data, mesh.cells[0].data)  # same node order, no mirroring
    np.testing.assert_array_equal(back.cells[1].data, QUADS)
    assert not back.hex_mirrored
    if data is None:
        assert dict(back.point_data) == {} and dict(back.cell_data) == {}
    else:
        for key in ("f", "i"):
            np.testing.assert_array_equal(back.point_data[key], mesh.point_data[key])
        if data == "dtypes":
            assert back.point_data["i"].dtype == np.int32 and back.cell_data["k"][0].dtype.kind == "i"
        else:
            assert back.point_data["i"].dtype == np.float64
        if data != "points-only":
            for key in ("q", "k"):
                for got, want in zip(back.cell_data[key], mesh.cell_data[key], strict=True):
                    np.testing.assert_array_equal(got, want)
    if sets:
        np.testing.assert_array_equal(back.point_sets["corner"], [0, 3])
        assert [a.tolist() for a in back.cell_sets["top"]] == [[0, 3, 5], [1]]
    else:
        assert "top" not in back.cell_sets and "corner" not in back.point_sets
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name] + (["m.h5"] if case == "xdmf" else []))


def test_connectivity_is_read_into_int32_and_written_as_int32(tmp_path):
    """A VTU whose connectivity is Int64 is read into the mesh's int32 blocks (the same node numbers); a VTU
    written holds Int32 connectivity (as the README says), and reads back the same cells."""
    mesh = perturb_box(3, amplitude=0.2, seed=2)
    src = tmp_path / "in.vtu"
    meshio.write(str(src), meshio.Mesh(mesh.points, [("hexahedron", mesh.hexes.astype(np.int64))]))
    assert re.search(r'type="Int64" Name="connectivity"', src.read_text(errors="replace"))
    got = read_mesh(str(src))
    assert all(b.data.dtype == np.int32 for b in got.cells)
    np.testing.assert_array_equal(got.hexes, mesh.hexes)
    out = tmp_path / "out.vtu"
    write_mesh(got, str(out))
    assert re.search(r'type="Int32" Name="connectivity"', out.read_text(errors="replace"))
    np.testing.assert_array_equal(read_mesh(str(out)).hexes, mesh.hexes)


@pytest.mark.parametrize("file_format", ["gmsh", "gmsh22"])
def test_gmsh_physical_groups_kept(tmp_path, file_format):
    base = box(2)
    mesh = HexMesh(
        base.points,
        (base.cells[0], CellBlock("quad", np.array([[0, 1, 4, 3]]))),
        cell_data={"gmsh:physical": [np.full(8, 1), np.array([2])], "gmsh:geometrical": [np.full(8, 1), [1]]},
        field_data={"volume": np.array([1, 3]), "skin": np.array([2, 2])},
    )
    assert write_quietly(mesh, tmp_path / "g.msh", file_format=file_format) == []
    back = read_mesh(tmp_path / "g.msh")
    assert [a.tolist() for a in back.cell_data["gmsh:physical"]] == [[1] * 8, [2]]
    assert {k: v.tolist() for k, v in back.field_data.items()} == {"volume": [1, 3], "skin": [2, 2]}


def test_left_handed_file_is_written_back_left_handed(tmp_path):
    base = box(2)
    left = base.hexes[:, MIRROR_HEX]
    meshio.vtu.write(tmp_path / "left.vtu", meshio.Mesh(base.points, [("hexahedron", left)]))
    with pytest.warns(UserWarning, match="left-handed"):
        mesh = read_mesh(tmp_path / "left.vtu")
    assert mesh.hex_mirrored
    np.testing.assert_array_equal(mesh.hexes, base.hexes)
    write_quietly(mesh, tmp_path / "again.vtu")
    np.testing.assert_array_equal(meshio.vtu.read(tmp_path / "again.vtu").cells[0].data, left)


CUBE = "".join(f"{i + 1}, {x:g}, {y:g}, {z:g}\n" for i, (x, y, z) in enumerate(unit_cube()))
NATIVE_FILES = {
    # Abaqus C3D8 and Gmsh's hexahedron (type 5) number the unit cube's nodes as VTK does
    "cube.inp": "*NODE\n" + CUBE + "*ELEMENT, TYPE=C3D8\n1, 1, 2, 3, 4, 5, 6, 7, 8\n",
    "cube.msh": "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n8\n"
    + CUBE.replace(",", "")
    + "$EndNodes\n$Elements\n1\n1 5 2 1 1 1 2 3 4 5 6 7 8\n$EndElements\n",
}


@pytest.mark.parametrize("name", sorted(NATIVE_FILES))
def test_native_hexahedron_order_is_vtk_order(tmp_path, name):
    (tmp_path / name).write_text(NATIVE_FILES[name])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a left-handed reading would warn
        mesh = read_mesh(tmp_path / name)
    np.testing.assert_array_equal(mesh.hexes, [np.arange(8)])
    assert not mesh.hex_mirrored and mesh.notes == ()
    np.testing.assert_array_equal(mesh.points, unit_cube())


@pytest.mark.shared
@pytest.mark.parametrize("name", sorted(MESQUITE_FIGURES))
def test_mesquite_meshes(name):
    n_hexes, n_nodes = MESQUITE_FIGURES[name][:2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # some are stored left-handed: HexMesh warns and mirrors them
        mesh = read_mesh(MESQUITE / name)
    assert (mesh.n_nodes, mesh.n_hexes) == (n_nodes, n_hexes)
    points, hexes = read_vtk_hexes(MESQUITE / name)
    np.testing.assert_array_equal(mesh.points, points)
    np.testing.assert_array_equal(mesh.hexes, hexes[:, MIRROR_HEX] if mesh.hex_mirrored else hexes)
    assert "fixed" in mesh.point_data and mesh.source == str(MESQUITE / name)


def test_formats_table():
    assert FORMATS[".vtu"] == "vtu" and FORMATS[".msh"] == "gmsh" and FORMATS[".inp"] == "abaqus"
    assert FORMATS[".mac"] == FORMATS[".apdl"] == FORMATS[".ans"] == "apdl"
    assert all(ext == ext.lower() and ext.startswith(".") for ext in FORMATS)


def test_extension_is_case_insensitive(tmp_path):
    write_quietly(box(1), tmp_path / "UPPER.VTU")
    assert read_mesh(tmp_path / "UPPER.VTU").n_hexes == 1


# ------------------------------------------------------------------------------------------------ bad input
def test_missing_file(tmp_path):
    with pytest.raises(MeshReadError, match=r"nothere\.vtu: no such file"):
        read_mesh(tmp_path / "nothere.vtu")


def test_folder_is_not_a_mesh(tmp_path):
    (tmp_path / "d.vtu").mkdir()
    with pytest.raises(MeshReadError, match=r"d\.vtu: is a folder"):
        read_mesh(tmp_path / "d.vtu")


def test_unknown_extension(tmp_path):
    (tmp_path / "m.stl").write_text("solid\n")
    with pytest.raises(UnsupportedFormatError, match=r"m\.stl: unknown mesh file extension '\.stl'; known "
                                                     r"extensions: \.vtk, \.vtu, .*\.cdb, \.lis, \.txt$") as info:
        read_mesh(tmp_path / "m.stl")
    assert "file_format" not in str(info.value)  # the CLI has no such option: the message names none
    with pytest.raises(UnsupportedFormatError, match=r"unknown mesh file extension '\.stl'; known extensions: "
                                                     r"[^;]*\.cdb$"):  # listings (.lis, .txt) are read only
        write_mesh(box(1), tmp_path / "out.stl")
    with pytest.raises(UnsupportedFormatError, match=r"unknown file format 'stl'; known: .*vtu"):
        read_mesh(tmp_path / "m.stl", file_format="stl")


@pytest.mark.parametrize("ext, title", [(".vtu", "VTU"), (".vtk", "legacy VTK"), (".msh", "Gmsh")])
def test_corrupt_file(tmp_path, ext, title):
    path = tmp_path / f"garbage{ext}"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(MeshReadError, match=rf"garbage\{ext}: corrupt or truncated {title} file"):
        read_mesh(path)


@pytest.mark.parametrize("ext", [".vtu", ".vtk", ".msh", ".inp"])
def test_truncated_file(tmp_path, ext):
    write_quietly(rich_mesh(), tmp_path / f"whole{ext}")
    data = (tmp_path / f"whole{ext}").read_bytes()
    (tmp_path / f"half{ext}").write_bytes(data[: len(data) // 2])
    with pytest.raises(MeshReadError, match=rf"half\{ext}(, line \d+)?: (corrupt or truncated|\d+ nodes but no "
                                            rf"(cells|elements) \(truncated|node \d+ is defined twice|element)"):
        read_mesh(tmp_path / f"half{ext}")


def test_abaqus_cut_before_its_elements(tmp_path):
    write_quietly(box(2), tmp_path / "whole.inp")
    text = (tmp_path / "whole.inp").read_text()
    (tmp_path / "cut.inp").write_text(text[: text.index("*ELEMENT")])
    with pytest.raises(MeshReadError, match=r"cut\.inp: 27 nodes but no elements \(truncated deck"):
        read_mesh(tmp_path / "cut.inp")


def test_only_tetrahedra(tmp_path):
    meshio.vtu.write(tmp_path / "tets.vtu", meshio.Mesh(np.eye(4, 3), [("tetra", np.array([[0, 1, 2, 3]]))]))
    with pytest.raises(MeshError, match=r"tets\.vtu: the mesh has no hexahedra \(found: tetra\)"):
        read_mesh(tmp_path / "tets.vtu")


HAND_VTK = """# vtk DataFile Version 2.0
one hex
ASCII
DATASET UNSTRUCTURED_GRID
POINTS 8 double
0 0 0  1 0 0  1 1 0  0 1 0
0 0 1  1 0 1  1 1 1  {x7} 1 1
CELLS 1 9
8 0 1 2 3 4 5 6 {n7}
CELL_TYPES 1
12
"""


def test_hand_written_vtk_reads(tmp_path):
    (tmp_path / "ok.vtk").write_text(HAND_VTK.format(x7=0, n7=7))
    assert read_mesh(tmp_path / "ok.vtk").n_hexes == 1


def test_nan_coordinate(tmp_path):
    (tmp_path / "nan.vtk").write_text(HAND_VTK.format(x7="nan", n7=7))
    with pytest.raises(MeshError, match=r"nan\.vtk: node 7 has non-finite coordinates"):
        read_mesh(tmp_path / "nan.vtk")


def test_node_index_out_of_range(tmp_path):
    (tmp_path / "range.vtk").write_text(HAND_VTK.format(x7=0, n7=8))
    with pytest.raises(MeshError, match=r"range\.vtk: hexahedron element 0 references node index 8, out of range"):
        read_mesh(tmp_path / "range.vtk")


def test_xdmf_without_h5py_names_the_package(tmp_path, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "h5py" else find_spec(name, *a))
    with pytest.raises(MeshWriteError, match=r"XDMF needs the h5py package.*pip install h5py"):
        write_mesh(box(1), tmp_path / "m.xdmf")
    (tmp_path / "m.xdmf").write_text("<Xdmf/>")
    with pytest.raises(MeshReadError, match=r"m\.xdmf: XDMF needs the h5py package"):
        read_mesh(tmp_path / "m.xdmf")
    assert os.listdir(tmp_path) == ["m.xdmf"]


# ------------------------------------------------------------------------------------------------ writing safely
def test_never_overwrites_the_input(tmp_path):
    write_quietly(rich_mesh(), tmp_path / "in.vtu")
    before = (tmp_path / "in.vtu").read_bytes()
    mesh = read_mesh(tmp_path / "in.vtu")
    with pytest.raises(MeshWriteError, match=r"in\.vtu: refusing to overwrite a file the mesh was read from"):
        write_mesh(mesh.with_points(mesh.points * 2), tmp_path / "in.vtu")
    os.symlink(tmp_path / "in.vtu", tmp_path / "link.vtu")
    with pytest.raises(MeshWriteError, match="refusing to overwrite"):
        write_mesh(mesh, tmp_path / "link.vtu")
    assert (tmp_path / "in.vtu").read_bytes() == before
    write_mesh(mesh, tmp_path / "other.vtu")  # any other file is fine


def test_failed_write_leaves_no_partial_file(tmp_path, monkeypatch):
    def disk_full(path, mesh, **kwargs):
        with open(path, "w") as f:
            f.write("<VTKFile partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(meshio.vtu, "write", disk_full)
    with pytest.raises(MeshWriteError, match=r"new\.vtu: cannot write \(No space left on device\)"):
        write_mesh(box(1), tmp_path / "new.vtu")
    assert os.listdir(tmp_path) == []
    (tmp_path / "old.vtu").write_text("previous content")
    with pytest.raises(MeshWriteError):
        write_mesh(box(1), tmp_path / "old.vtu")
    assert os.listdir(tmp_path) == ["old.vtu"] and (tmp_path / "old.vtu").read_text() == "previous content"


def test_mesh_the_format_cannot_hold(tmp_path):
    bad = HexMesh(box(1).points, (box(1).cells[0], CellBlock("no-such-type", np.array([[0, 1, 2]]))))
    with pytest.raises(MeshWriteError, match=r"m\.vtu: meshio cannot write this mesh as VTU \(KeyError 'no-such-"):
        write_mesh(bad, tmp_path / "m.vtu")
    assert os.listdir(tmp_path) == []


def test_write_into_missing_folder_or_onto_a_folder(tmp_path):
    with pytest.raises(MeshWriteError, match=r"folder .*nowhere does not exist"):
        write_mesh(box(1), tmp_path / "nowhere" / "m.vtu")
    (tmp_path / "d.vtu").mkdir()
    with pytest.raises(MeshWriteError, match=r"d\.vtu: is a folder"):
        write_mesh(box(1), tmp_path / "d.vtu")


def test_listing_is_read_only(tmp_path):
    with pytest.raises(UnsupportedFormatError, match=r"listings are read only; write an APDL input file"):
        write_mesh(box(1), tmp_path / "m.lis")
