"""Legacy VTK is written as version 4.2, which every reader reads (Mesquite cannot read 5.1); 5.1 when asked."""

from __future__ import annotations

import numpy as np

from jaxci.io import read_mesh, write_mesh
from jaxci.mesh.generate import perturb_box


def test_legacy_vtk_is_4_2_unless_5_1_is_asked_for(tmp_path):
    mesh = perturb_box(2, amplitude=0.2, seed=1)
    write_mesh(mesh, tmp_path / "m.vtk")
    assert (tmp_path / "m.vtk").read_text().splitlines()[0] == "# vtk DataFile Version 4.2"
    write_mesh(mesh, tmp_path / "n.vtk", file_format="vtk51")
    assert (tmp_path / "n.vtk").read_text().splitlines()[0] == "# vtk DataFile Version 5.1"
    for name in ("m.vtk", "n.vtk"):
        back = read_mesh(tmp_path / name)
        np.testing.assert_array_equal(back.points, mesh.points)
        np.testing.assert_array_equal(back.cells[0].data, mesh.cells[0].data)
