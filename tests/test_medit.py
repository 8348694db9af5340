"""Medit .mesh files: hexahedra and the other cell types with their references, read and written; bad files
refused with one line."""

from __future__ import annotations

import warnings

import meshio
import numpy as np
import pytest

from jaxci.cli import main
from jaxci.errors import MeshReadError
from jaxci.io import LossyWriteWarning, read_mesh, write_mesh
from jaxci.mesh import CellBlock, HexMesh
from jaxci.mesh.generate import perturb_box


def mixed_mesh() -> HexMesh:
    """A perturbed 2^3 box, a wedge on its side, a boundary quad and triangle, with references on everything."""
    box = perturb_box(2, amplitude=0.2, seed=3)
    pts = np.concatenate([box.points, [[1.5, 0.0, 0.0], [1.5, 0.0, 0.5]]])
    wedge = [[2, 27, 5, 11, 28, 14]]
    cells = (CellBlock("hexahedron", box.cells[0].data), CellBlock("wedge", wedge),
             CellBlock("quad", [[0, 1, 4, 3]]), CellBlock("triangle", [[2, 27, 5]]))
    refs = [np.arange(8) % 3 + 1, np.array([7]), np.array([10]), np.array([11])]
    return HexMesh(pts, cells, point_data={"medit:ref": np.arange(29) % 4},
                   cell_data={"medit:ref": refs}, point_sets={"corners": np.array([0, 2, 6])})


def test_round_trip_with_references(tmp_path):
    mesh = mixed_mesh()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / "m.mesh")
    back = read_mesh(tmp_path / "m.mesh")
    np.testing.assert_array_equal(back.points, mesh.points)  # 17 digits: float64 exact
    assert [b.type for b in back.cells] == ["hexahedron", "wedge", "quad", "triangle"]
    for a, b in zip(back.cells, mesh.cells, strict=True):
        np.testing.assert_array_equal(a.data, b.data)
    assert [r.tolist() for r in back.cell_data["medit:ref"]] == [r.tolist() for r in mesh.cell_data["medit:ref"]]
    assert back.point_data["medit:ref"].tolist() == (np.arange(29) % 4).tolist()
    assert back.point_sets["corners"].tolist() == [0, 2, 6]
    m = meshio.medit.read(tmp_path / "m.mesh")  # another reader agrees
    assert [c.type for c in m.cells] == ["hexahedron", "wedge", "quad", "triangle"]
    np.testing.assert_array_equal(m.cells[1].data, mesh.cells[1].data)


def test_reads_what_meshio_writes_and_warns_what_it_drops(tmp_path):
    box = perturb_box(2, amplitude=0.2, seed=3)
    meshio.medit.write(tmp_path / "b.mesh", meshio.Mesh(box.points, [("hexahedron", box.cells[0].data)]))
    mesh = read_mesh(tmp_path / "b.mesh")
    np.testing.assert_array_equal(mesh.points, box.points)
    with_ids = HexMesh(box.points, (CellBlock("hexahedron", box.cells[0].data, np.arange(10, 18)),),
                       point_sets={"FIX": np.array([1])})
    with pytest.warns(LossyWriteWarning, match=r"medit drops node and element ids .*; point sets \['FIX'\]"):
        write_mesh(with_ids, tmp_path / "ids.mesh")


def test_smooth_through_the_cli(tmp_path, capsys):
    write_mesh(mixed_mesh(), tmp_path / "in.mesh")
    assert main(["smooth", str(tmp_path / "in.mesh"), str(tmp_path / "out.mesh")]) == 0
    capsys.readouterr()
    before, after = read_mesh(tmp_path / "in.mesh"), read_mesh(tmp_path / "out.mesh")
    assert np.abs(after.points - before.points).max() > 1e-3
    assert [r.tolist() for r in after.cell_data["medit:ref"]] == [r.tolist() for r in before.cell_data["medit:ref"]]
    assert main(["quality", str(tmp_path / "out.mesh")]) == 0


@pytest.mark.parametrize("edit, message", [
    (lambda t: t[: t.index("Hexahedra") + 80], r"bad\.mesh, line \d+: Hexahedra announces 8 rows of 9 values but the "
                                               r"file ends after [1-7] \(truncated\?\)"),
    (lambda t: t.replace("Hexahedra\n8\n1 ", "Hexahedra\n8\n99 "),
     r"bad\.mesh, line \d+: Hexahedra row 1 references vertex 99, but the file has vertices 1\.\.29"),
    (lambda t: t.replace("Vertices\n29", "Vertices\nmany"), r"bad\.mesh, line 6: Vertices count 'many' is not an "
                                                            r"integer"),
    (lambda t: t.replace("Dimension 3", "Dimension 2"), r"bad\.mesh, line 3: Dimension 2; jaxci reads 3-D meshes"),
])
def test_bad_files_exit_2_with_one_clear_line(tmp_path, capsys, edit, message):
    write_mesh(mixed_mesh(), tmp_path / "good.mesh")
    text = (tmp_path / "good.mesh").read_text()
    bad = edit(text)
    assert bad != text
    (tmp_path / "bad.mesh").write_text(bad)
    with pytest.raises(MeshReadError, match=message):
        read_mesh(tmp_path / "bad.mesh")
    assert main(["smooth", str(tmp_path / "bad.mesh"), str(tmp_path / "out.mesh")]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.startswith("jaxci: error: ") and "bad.mesh" in err
