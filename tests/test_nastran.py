"""Nastran bulk data decks: small, large and free field GRIDs with continuations, solid elements (with midside
nodes), every other card kept byte for byte when written back, fields too narrow refused, bad decks refused."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from jaxci.cli import main
from jaxci.errors import MeshReadError, MeshWriteError
from jaxci.io import LossyWriteWarning, read_mesh, write_mesh
from jaxci.mesh import CellBlock, HexMesh
from jaxci.mesh.generate import perturb_box


def grid(nid: int, xyz, style: str) -> list[str]:
    x, y, z = (repr(float(v)) for v in xyz)
    if style == "small":
        return [f"GRID    {nid:>8}{'':>8}{x[:8]:>8}{y[:8]:>8}{z[:8]:>8}"]
    if style == "large":
        return [f"GRID*   {nid:>16}{'':>16}{x:>16}{y:>16}", f"*       {z:>16}"]
    return [f"GRID,{nid},,{x},{y},{z}"]


def box_deck(tmp_path, name="box.bdf", n=2, amplitude=0.0, extra="", styles=("small", "large", "free")) -> Path:
    """An n^3 box of CHEXAs; GRIDs in turn in small, large and free field; materials and a load beside them."""
    box = perturb_box(n, amplitude=amplitude, seed=2) if amplitude else perturb_box(n, amplitude=0.0)
    pts = np.round(box.points, 4)
    lines = ["SOL 101", "CEND", "TITLE = box", "BEGIN BULK", "$ nodes"]
    for k, p in enumerate(pts):
        lines += grid(k + 1, p, styles[k % len(styles)])
    for e, row in enumerate(box.cells[0].data + 1, 1):
        lines += [f"CHEXA   {e:>8}{1:>8}" + "".join(f"{v:>8}" for v in row[:6]), "+       " + "".join(
            f"{v:>8}" for v in row[6:])]
    lines += ["PSOLID         1       1", "MAT1           1   2.1+5              .3", "FORCE          1       1       "
              "0     1.0      0.      0.     -1.", extra, "ENDDATA", "$ after the bulk data"]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_reads_small_large_and_free_field(tmp_path):
    path = box_deck(tmp_path)
    mesh = read_mesh(path)
    assert mesh.n_nodes == 27 and mesh.n_hexes == 8
    np.testing.assert_array_equal(mesh.points, np.round(perturb_box(2, amplitude=0.0).points, 4))
    assert mesh.node_ids.tolist() == list(range(1, 28)) and mesh.cells[0].ids.tolist() == list(range(1, 9))
    assert mesh.cell_data["nastran:pid"][0].tolist() == [1] * 8
    assert any("MAT1" in n and "PSOLID" in n and "FORCE" in n for n in mesh.notes)


def test_short_exponents_tabs_and_free_continuations(tmp_path):
    text = ("GRID\t1\t\t0.\t0.\t0.\nGRID,2,,1.+0,0.,0.\nGRID,3,,1.,1.,\n,0.\nGRID    4               0.      1.-0    "
            "0.\nGRID,5,,0.,0.,1.\nGRID,6,,1.,0.,1.\nGRID,7,,1.,1.,1.\nGRID,8,,.0,1.,10.-1\n"
            "CHEXA,9,1,1,2,3,4,5,6,\n,7,8\n")
    (tmp_path / "m.nas").write_text(text)
    mesh = read_mesh(tmp_path / "m.nas")
    unit = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
    np.testing.assert_array_equal(mesh.points, unit)
    assert mesh.cells[0].data.tolist() == [list(range(8))] and mesh.cells[0].ids.tolist() == [9]


def test_written_back_with_only_moved_grid_fields_changed(tmp_path):
    path = box_deck(tmp_path)
    mesh = read_mesh(path)
    pts = mesh.points.copy()
    moved = {12: [0.4, 0.55, 0.525], 13: [0.525, 0.475, 0.55], 14: [0.5, 0.55, 0.45]}  # GRIDs of all three styles
    for k, v in moved.items():
        pts[k] = v
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh.with_points(pts), tmp_path / "out.bdf")
    old, new = path.read_text().splitlines(), (tmp_path / "out.bdf").read_text().splitlines()
    assert len(old) == len(new)
    changed = [i for i, (a, b) in enumerate(zip(old, new, strict=True)) if a != b]
    grid_lines = [i for i, a in enumerate(old) if a.startswith(("GRID", "*"))]
    assert set(changed) <= set(grid_lines) and len(changed) >= 3
    for i in changed:  # fixed-field lines keep their width; free-field lines keep their commas
        assert len(new[i]) == len(old[i]) or "," in old[i]
        assert new[i].count(",") == old[i].count(",")
    back = read_mesh(tmp_path / "out.bdf")
    np.testing.assert_allclose(back.points, pts, rtol=0, atol=5e-7)  # 8-character fields: 7 digits
    write_mesh(mesh, tmp_path / "same.bdf")
    assert (tmp_path / "same.bdf").read_bytes() == path.read_bytes()


def test_a_value_a_small_field_cannot_hold_is_refused(tmp_path):
    path = box_deck(tmp_path, styles=("small",))
    mesh = read_mesh(path)
    far = dataclasses.replace(mesh, points=mesh.points * 1e-3 + 12345.0, fix_orientation=False)
    deck = far.field_data["nastran:deck"]
    for k in range(27):  # the deck as it would be with those coordinates, in 16-character fields
        deck = deck.replace(grid(k + 1, mesh.points[k], "small")[0], "\n".join(grid(k + 1, far.points[k], "large")))
    pts = far.points.copy()
    pts[13] += 1e-5
    src = dataclasses.replace(far, field_data={"nastran:deck": deck}, fix_orientation=False)
    write_mesh(src.with_points(pts), tmp_path / "wide.bdf")  # 16 characters hold it
    np.testing.assert_allclose(read_mesh(tmp_path / "wide.bdf").points, pts, rtol=0, atol=1e-9)
    small = dataclasses.replace(mesh, points=mesh.points + 12345.0, fix_orientation=False)
    small_deck = small.field_data["nastran:deck"]
    for k in range(27):
        small_deck = small_deck.replace(grid(k + 1, mesh.points[k], "small")[0],
                                        grid(k + 1, small.points[k], "small")[0])
    small = dataclasses.replace(small, field_data={"nastran:deck": small_deck}, fix_orientation=False)
    pts = small.points.copy()
    pts[13] += 0.0123456789
    with pytest.raises(MeshWriteError, match=r"narrow\.bdf: GRID 14 \(line \d+ of the deck\): its new x coordinate "
                                             r"12345\.5123456789 cannot be written in its 8-character field "
                                             r"closer than 0\.00235 \(12345\.51\)"):
        write_mesh(small.with_points(pts), tmp_path / "narrow.bdf")
    assert not (tmp_path / "narrow.bdf").exists()


def test_chexa20_midside_nodes_and_fresh_deck(tmp_path):
    corners = perturb_box(1, amplitude=0.0).points
    ends = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
    mids = np.array([(corners[a] + corners[b]) / 2 for a, b in ends])
    mesh = HexMesh(np.concatenate([corners, mids]), (CellBlock("hexahedron", np.arange(8)[None],
                                                               midside=np.arange(8, 20)[None]),))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(mesh, tmp_path / "q.bdf")
    text = (tmp_path / "q.bdf").read_text()
    # G9..G12 the bottom edges, G13..G16 the vertical edges, G17..G20 the top edges (PATRAN's order)
    assert "CHEXA          1       1       1       2       3       4       5       6\n" \
           "+              7       8       9      10      11      12      17      18\n" \
           "+             19      20      13      14      15      16\n" in text
    back = read_mesh(tmp_path / "q.bdf")
    assert back.cells[0].midside.tolist() == [list(range(8, 20))]
    np.testing.assert_array_equal(back.points, mesh.points)


def test_fresh_deck_from_another_format_warns_what_it_drops(tmp_path):
    box = perturb_box(2, amplitude=0.2, seed=5)
    mesh = dataclasses.replace(box, point_sets={"FIX": np.array([0, 1])}, fix_orientation=False)
    with pytest.warns(LossyWriteWarning, match=r"nastran drops point sets \['FIX'\]"):
        write_mesh(mesh, tmp_path / "m.nas")
    back = read_mesh(tmp_path / "m.nas")
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-14)  # 16 characters: 15 digits
    np.testing.assert_array_equal(back.cells[0].data, mesh.cells[0].data)


def test_dat_files_are_sniffed(tmp_path):
    path = box_deck(tmp_path, name="job.dat")
    assert read_mesh(path).n_hexes == 8
    write_mesh(perturb_box(1, amplitude=0.0), tmp_path / "plain.cdb")
    (tmp_path / "ds.dat").write_text((tmp_path / "plain.cdb").read_text())
    mesh = read_mesh(tmp_path / "ds.dat")  # an ANSYS input file named .dat
    assert "ansys:deck" in mesh.field_data
    (tmp_path / "other.dat").write_text("1 2 3\n4 5 6\n")
    with pytest.raises(MeshReadError, match=r"other\.dat: a \.dat file with neither Nastran cards"):
        read_mesh(tmp_path / "other.dat")


def test_smooth_through_the_cli(tmp_path, capsys):
    path = box_deck(tmp_path, n=3, amplitude=0.25, styles=("large", "free"))
    assert main(["smooth", str(path), str(tmp_path / "out.bdf")]) == 0
    assert "drops" not in capsys.readouterr().err
    old, new = path.read_text().splitlines(), (tmp_path / "out.bdf").read_text().splitlines()
    changed = [i for i, (a, b) in enumerate(zip(old, new, strict=True)) if a != b]
    assert len(old) == len(new) and changed and all(old[i].startswith(("GRID", "*")) for i in changed)
    assert read_mesh(tmp_path / "out.bdf").cells[0].data.tolist() == read_mesh(path).cells[0].data.tolist()


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("CHEXA          8       1", "CHEXA          7       1"),
     r"bad\.bdf, line \d+: element 7 is defined twice \(first at .*bad\.bdf, line \d+\)"),
    (lambda t: t.replace("GRID           4", "GRID           3"), r"bad\.bdf, line \d+: GRID 3 is defined twice"),
    (lambda t: t.replace("      27      26", "      99      26"),
     r"bad\.bdf, line \d+: CHEXA 8 references GRID 99, which the deck does not define"),
    (lambda t: t[: t.index("CHEXA          8")] + "CHEXA          8       1      14      15      18\n",
     r"bad\.bdf, line \d+: CHEXA 8 has no node G4 \(it needs 8 corner nodes; truncated deck\?\)"),
    (lambda t: t.replace("GRID           1        ", "GRID           1       2"),
     r"bad\.bdf, line 6: GRID 1 has its coordinates in coordinate system CP=2; jaxci reads GRIDs in the basic"),
    (lambda t: t.replace("GRID           1             0.0", "GRID           1              x."),
     r"bad\.bdf, line 6: x coordinate of GRID 1 'x\.' is not a number"),
])
def test_bad_decks_exit_2_with_one_clear_line(tmp_path, capsys, edit, message):
    text = box_deck(tmp_path, styles=("small",)).read_text()
    bad = edit(text)
    assert bad != text
    (tmp_path / "bad.bdf").write_text(bad)
    with pytest.raises(MeshReadError, match=message):
        read_mesh(tmp_path / "bad.bdf")
    assert main(["smooth", str(tmp_path / "bad.bdf"), str(tmp_path / "out.bdf")]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.startswith("jaxci: error: ") and "bad.bdf" in err


def test_include_files_and_kept_shells(tmp_path):
    text = box_deck(tmp_path).read_text()
    start, end = text.index("$ nodes"), text.index("CHEXA")
    (tmp_path / "grids.bdf").write_text(text[start:end])
    main_text = text[:start] + "INCLUDE 'grids.bdf'\n" + text[end:].replace(
        "PSOLID", "CQUAD4        99       2       1       2       5       4\nPSOLID")
    (tmp_path / "main.bdf").write_text(main_text)
    mesh = read_mesh(tmp_path / "main.bdf")
    assert mesh.n_nodes == 27 and mesh.input_files == (str(tmp_path / "grids.bdf"),)
    assert [(b.type, b.ids.tolist()) for b in mesh.cells] == [("hexahedron", list(range(1, 9))), ("quad", [99])]
    write_mesh(mesh.with_points(mesh.points * 2), tmp_path / "out.bdf")
    out = (tmp_path / "out.bdf").read_text()
    assert "INCLUDE" not in out and "CQUAD4        99       2       1       2       5       4\n" in out
    np.testing.assert_allclose(read_mesh(tmp_path / "out.bdf").points, mesh.points * 2, rtol=0, atol=1e-6)
    (tmp_path / "broken.bdf").write_text("INCLUDE 'nowhere.bdf'\n")
    with pytest.raises(MeshReadError, match=r"broken\.bdf, line 1: included file nowhere\.bdf not found"):
        read_mesh(tmp_path / "broken.bdf")
