"""LS-DYNA keyword decks: *NODE in fixed (standard, I10, long) and free format, *ELEMENT_SOLID with its
degenerate forms, *INCLUDE, every other keyword kept byte for byte when written back, bad decks refused."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from jaxci.cli import main
from jaxci.errors import MeshReadError
from jaxci.io import LossyWriteWarning, read_mesh, write_mesh
from jaxci.mesh.generate import perturb_box
from jaxci.metrics.report import quality_report

OTHER = ("*PART\npart one\n$ pid secid mid\n         1         1         1\n*MAT_ELASTIC\n"
         "         1    7.8e-9   2.1e5     0.3\n")


def node_lines(points, fmt: str, first: int = 1) -> list[str]:
    out = []
    for k, p in enumerate(points):
        x, y, z = (f"{v:.10f}" for v in p)
        nid = first + k
        if fmt == "standard":
            out.append(f"{nid:>8}{x:>16}{y:>16}{z:>16}{0:>8}{0:>8}")
        elif fmt == "i10":
            out.append(f"{nid:>10}{x:>16}{y:>16}{z:>16}")
        elif fmt == "long":
            out.append(f"{nid:>20}{x:>20}{y:>20}{z:>20}")
        else:
            out.append(f"{nid}, {x}, {y}, {z}")
    return out


def box_deck(tmp_path, name="box.k", n=2, amplitude=0.0, fmt="standard", two_line=False) -> Path:
    box = perturb_box(n, amplitude=amplitude, seed=7) if amplitude else perturb_box(n, amplitude=0.0)
    sign = {"standard": "", "i10": " %", "long": " +", "free": ""}[fmt]
    lines = ["*KEYWORD", "*TITLE", "box", f"*NODE{sign}", "$    nid               x               y               z"]
    lines += node_lines(box.points, fmt)
    lines.append("*ELEMENT_SOLID")
    for e, row in enumerate(box.cells[0].data + 1, 1):
        if two_line:
            lines += [f"{e:>8}{1:>8}", "".join(f"{v:>8}" for v in row)]
        else:
            lines.append(f"{e:>8}{1:>8}" + "".join(f"{v:>8}" for v in row))
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n" + OTHER + "*END\n")
    return path


@pytest.mark.parametrize("fmt, two_line", [("standard", False), ("i10", False), ("long", False), ("free", True)])
def test_node_formats_and_element_lines(tmp_path, fmt, two_line):
    path = box_deck(tmp_path, amplitude=0.2, fmt=fmt, two_line=two_line)
    mesh = read_mesh(path)
    np.testing.assert_allclose(mesh.points, perturb_box(2, amplitude=0.2, seed=7).points, rtol=0, atol=1e-10)
    assert mesh.n_hexes == 8 and mesh.cells[0].ids.tolist() == list(range(1, 9))
    assert mesh.cell_data["lsdyna:pid"][0].tolist() == [1] * 8
    assert any("*MAT_ELASTIC, *PART" in n for n in mesh.notes)
    pts = mesh.points.copy()
    pts[13] += [0.01, -0.02, 1 / 3 * 0.01]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh.with_points(pts), tmp_path / "out.k")
    old, new = path.read_text().splitlines(), (tmp_path / "out.k").read_text().splitlines()
    changed = [i for i, (a, b) in enumerate(zip(old, new, strict=True)) if a != b]
    assert len(old) == len(new) and changed == [5 + 13]  # the centre node's line alone
    assert len(new[changed[0]]) == len(old[changed[0]]) or fmt == "free"
    np.testing.assert_allclose(read_mesh(tmp_path / "out.k").points, pts, rtol=0, atol=1e-14)  # 16 characters
    write_mesh(mesh, tmp_path / "same.k")
    assert (tmp_path / "same.k").read_bytes() == path.read_bytes()


def test_degenerate_solids(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1],
                    [2, 0, 0], [2, 1, 0], [1.5, 0, 1], [1.5, 1, 1], [0.5, 0.5, 2]], float)
    rows = [(1, [1, 2, 3, 4, 5, 6, 7, 8]), (2, [2, 9, 10, 3, 11, 11, 12, 12]),  # a brick and a wedge
            (3, [5, 6, 7, 8, 13, 13, 13, 13]), (4, [6, 7, 8, 13, 13, 13, 13, 13])]  # a pyramid and a tetrahedron
    lines = ["*KEYWORD", "*NODE", *node_lines(pts, "standard"), "*ELEMENT_SOLID"]
    lines += [f"{e:>8}{1:>8}" + "".join(f"{v:>8}" for v in r) for e, r in rows] + ["*END"]
    (tmp_path / "d.k").write_text("\n".join(lines) + "\n")
    mesh = read_mesh(tmp_path / "d.k")
    assert [(b.type, b.ids.tolist()) for b in mesh.cells] == [("hexahedron", [1]), ("wedge", [2]), ("pyramid", [3]),
                                                              ("tetra", [4])]
    report = quality_report(mesh)
    assert report.inverted_elements == 0 and all(v["inverted"] == 0 for v in report.by_type.values())
    fresh = dataclasses.replace(mesh, field_data={}, fix_orientation=False)
    write_mesh(fresh, tmp_path / "fresh.k")
    text = (tmp_path / "fresh.k").read_text()
    assert "       2       1       2       9      10       3      11      11      12      12" in text  # the part kept
    back = read_mesh(tmp_path / "fresh.k")
    assert [b.data.tolist() for b in back.cells] == [b.data.tolist() for b in mesh.cells]


def test_include_files_are_inlined_and_never_written_over(tmp_path):
    path = box_deck(tmp_path, amplitude=0.2)
    text = path.read_text()
    start, end = text.index("*NODE"), text.index("*ELEMENT_SOLID")
    (tmp_path / "nodes.k").write_text("*KEYWORD\n" + text[start:end] + "*END\n")
    (tmp_path / "main.k").write_text(text[:start] + "*INCLUDE\nnodes.k\n" + text[end:])
    mesh = read_mesh(tmp_path / "main.k")
    assert mesh.n_nodes == 27 and mesh.input_files == (str(tmp_path / "nodes.k"),)
    write_mesh(mesh.with_points(mesh.points * 2), tmp_path / "out.k")
    out = (tmp_path / "out.k").read_text()
    assert "*INCLUDE" not in out and out.count("*END") == 1 and out.count("*KEYWORD") == 1
    np.testing.assert_array_equal(read_mesh(tmp_path / "out.k").points, mesh.points * 2)
    (tmp_path / "broken.k").write_text("*KEYWORD\n*INCLUDE\nnowhere.k\n*END\n")
    with pytest.raises(MeshReadError, match=r"broken\.k, line 2: included file nowhere\.k not found"):
        read_mesh(tmp_path / "broken.k")


def test_fresh_deck_from_another_format(tmp_path):
    box = perturb_box(2, amplitude=0.2, seed=5)
    mesh = dataclasses.replace(box, point_sets={"FIX": np.array([0, 1])}, fix_orientation=False)
    with pytest.warns(LossyWriteWarning, match=r"lsdyna drops point sets \['FIX'\]"):
        write_mesh(mesh, tmp_path / "m.key")
    back = read_mesh(tmp_path / "m.key")
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(back.cells[0].data, mesh.cells[0].data)


def test_smooth_through_the_cli(tmp_path, capsys):
    path = box_deck(tmp_path, n=3, amplitude=0.25)
    assert main(["smooth", str(path), str(tmp_path / "out.dyn")]) == 0
    assert "drops" not in capsys.readouterr().err
    old, new = path.read_text().splitlines(), (tmp_path / "out.dyn").read_text().splitlines()
    changed = [i for i, (a, b) in enumerate(zip(old, new, strict=True)) if a != b]
    assert len(old) == len(new) and changed and all(5 <= i < 5 + 64 for i in changed)
    assert main(["quality", str(tmp_path / "out.dyn")]) == 0


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("       8       1", "       7       1"),
     r"bad\.k, line \d+: element 7 is defined twice \(first at .*bad\.k, line \d+\)"),
    (lambda t: t.replace("\n       4 ", "\n       3 "), r"bad\.k, line 9: node 3 is defined twice"),
    (lambda t: t.replace("      27      26", "      99      26"),
     r"bad\.k, line \d+: element 8 references node 99, which no \*NODE defines"),
    (lambda t: t[: t.index("       8       1")] + "       8       1      14      15\n",
     r"bad\.k, line \d+: element 8 lists 2 nodes; a solid needs at least 4 \(truncated deck\?\)"),
    (lambda t: t.replace("*ELEMENT_SOLID", "*ELEMENT_SOLID_ORTHO"), r"bad\.k, line 33: \*ELEMENT_SOLID_ORTHO: jaxci "
                                                                      r"reads \*NODE, \*ELEMENT_SOLID and \*INCLUDE"),
    (lambda t: t.replace("       1       1       2       5       4", "       1       1       2       2       4"),
     r"bad\.k, line 34: element 1 repeats nodes \(1 2 2 4 .*\) in a form jaxci does not read"),
])
def test_bad_decks_exit_2_with_one_clear_line(tmp_path, capsys, edit, message):
    text = box_deck(tmp_path).read_text()
    bad = edit(text)
    assert bad != text
    (tmp_path / "bad.k").write_text(bad)
    with pytest.raises(MeshReadError, match=message):
        read_mesh(tmp_path / "bad.k")
    assert main(["smooth", str(tmp_path / "bad.k"), str(tmp_path / "out.k")]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.startswith("jaxci: error: ") and "bad.k" in err
