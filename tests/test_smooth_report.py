"""``jaxci smooth IN OUT --report FILE`` (`jaxci.experiments.smooth_report`, `jaxci.cli._report`): what the report
holds (histograms of every corner, the worst elements with their ids and positions, the surface coloured by
element condition), that an HTML report needs no network, and that the report file follows the output rules of
the mesh (never an input or the mesh output, an existing file only with --force, nothing written on refusal)."""

from __future__ import annotations

import base64
import re

import numpy as np
import pytest
from helpers import MESQUITE

import jaxci
from jaxci.cli import main
from jaxci.experiments import smooth_report as R
from jaxci.io import read_mesh, write_mesh
from jaxci.mesh.generate import box
from jaxci.metrics.guard import cell_worst

PNG = b"\x89PNG\r\n\x1a\n"


def _bad_box():
    """A 4^3 box with one interior node pulled hard towards a corner: the 8 hexahedra around it are the worst."""
    mesh = box(4, 4, 4)
    pts = np.array(mesh.points)
    k = int(np.argmin(np.linalg.norm(pts - [0.5, 0.5, 0.5], axis=1)))
    pts[k] += [0.1, 0.08, 0.06]
    return mesh.with_points(pts), k


def test_worst_elements_are_ranked_with_ids_and_centroids():
    mesh, k = _bad_box()
    res = jaxci.smooth(mesh)
    before, after = R.worst_elements(mesh, mesh.points, res.mesh.points, n=5)
    kb, ka = cell_worst(mesh, mesh.points)["hexahedron"], cell_worst(mesh, res.mesh.points)["hexahedron"]
    assert [w.before for w in before] == sorted(kb, reverse=True)[:5]
    assert [w.after for w in after] == sorted(ka, reverse=True)[:5]
    w = before[0]
    assert k in mesh.hexes[w.index]  # the worst element holds the pulled node
    assert w.after == ka[w.index] and w.label == mesh.hex_label(w.index)
    np.testing.assert_allclose(w.centroid, mesh.points[mesh.hexes[w.index]].mean(axis=0))
    assert after[0].after < before[0].before


@pytest.mark.shared
def test_corner_histogram_counts_every_corner_and_the_inverted_apart():
    mesh = read_mesh(MESQUITE / "hex_5_tangled.vtk")  # 125 hexahedra, 48 inverted corners
    edges = np.geomspace(1.0, 1e6, 21)
    counts, inverted = R.corner_histogram(mesh, mesh.points, edges)
    assert inverted == 48
    assert counts.sum() + inverted == 8 * 125


@pytest.mark.shared
@pytest.mark.parametrize("suffix", [".html", ".png"])
def test_cli_report_on_a_real_mesh(tmp_path, capsys, suffix):
    out, rep = tmp_path / "out.vtk", tmp_path / f"report{suffix}"
    assert main(["smooth", str(MESQUITE / "pave3.e.vtk"), str(out), "--report", str(rep), "--json"]) == 0
    capsys.readouterr()
    data = rep.read_bytes()
    assert out.exists()
    if suffix == ".png":
        assert data.startswith(PNG)
        return
    page = data.decode()
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) == 2 and all(base64.b64decode(i).startswith(PNG) for i in images)
    assert not re.search(r'(src|href)="(?!data:)', page) and "http" not in page  # opens without network access
    res_worst = read_mesh(out)
    ka = cell_worst(res_worst, res_worst.points)["hexahedron"]
    top = int(np.argmax(ka))
    # the worst element after smoothing is listed first, by its id, with its kappa/3 and centroid
    first = re.search(r"<h2>Worst elements after smoothing</h2><table>.*?</tr><tr><td>1</td><td>([^<]*)</td>"
                      r"<td>hexahedron</td><td>[^<]*</td><td>([^<]*)</td><td>([^<]*)</td>", page)
    assert first is not None
    assert first.group(1) == res_worst.hex_label(top)
    assert float(first.group(2)) == pytest.approx(ka[top], rel=1e-5)
    centroid = [float(v) for v in first.group(3).split(",")]
    np.testing.assert_allclose(centroid, res_worst.points[res_worst.hexes[top]].mean(axis=0), rtol=1e-5, atol=1e-6)
    assert "inverted elements</td><td>106</td><td>0</td>" in page


def test_large_surfaces_draw_the_worst_faces(monkeypatch):
    mesh, _ = _bad_box()
    res = jaxci.smooth(mesh)
    monkeypatch.setattr(R, "MAX_SURFACE_FACES", 10)
    worst = R.worst_elements(mesh, mesh.points, res.mesh.points)
    fig = R.surface_figure(mesh, mesh.points, res.mesh.points, worst)
    titles = [ax.get_title() for ax in fig.axes]
    assert any("the 10 faces of the worst elements of 96" in t for t in titles)


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_report_follows_the_output_rules(tmp_path, capsys):
    src = tmp_path / "in.vtk"
    write_mesh(_bad_box()[0], src)
    out = tmp_path / "out.vtk"

    def refused(*extra, match):
        before = _snapshot(tmp_path)
        assert main(["smooth", str(src), str(out), *map(str, extra)]) == 2
        err = capsys.readouterr().err
        assert re.search(match, err), err
        assert _snapshot(tmp_path) == before  # nothing written, nothing touched
        assert len(err.strip().splitlines()) == 1

    refused("--report", tmp_path / "r.pdf", match="expected a .html")
    (tmp_path / "in.html").symlink_to(src)  # the input, by another name
    refused("--report", tmp_path / "in.html", match="refusing to overwrite the input")
    refused("--report", tmp_path / "in.html", "--force", match="refusing to overwrite the input")
    refused("--report", tmp_path / "out.vtk", match="expected a .html")
    before = _snapshot(tmp_path)
    assert main(["smooth", str(src), str(tmp_path / "x.png"), "--report", str(tmp_path / "sub" / ".." / "x.png")]) == 2
    assert "is also where the smoothed mesh goes" in capsys.readouterr().err and _snapshot(tmp_path) == before
    refused("--report", tmp_path / "missing" / "r.html", match="does not exist")
    (tmp_path / "r.html").write_text("mine")
    refused("--report", tmp_path / "r.html", match="r.html: exists; pass --force")
    assert main(["smooth", str(src), str(out), "--report", str(tmp_path / "r.html"), "--force"]) == 0
    capsys.readouterr()
    assert (tmp_path / "r.html").read_text().startswith("<!DOCTYPE html>")
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
