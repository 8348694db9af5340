"""`jaxci.io._place`: finished files and folders moved into place without replacing what is not ours, with
``renameat2`` and without it (the fallbacks: a hard link for a file, an exclusive ``mkdir`` for a folder); and
`jaxci.io.write_mesh`'s ``overwrite`` built on it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import jaxci
from jaxci.errors import MeshWriteError
from jaxci.io import _place, read_mesh, write_mesh


@pytest.fixture(params=["renameat2", "fallback"])
def mode(request, monkeypatch):
    if request.param == "fallback":
        monkeypatch.setattr(_place, "_RENAMEAT2", [None])
    elif _place._RENAMEAT2[0] is None:
        pytest.skip("no renameat2 in this C library")
    return request.param


def test_rename_noreplace_refuses_anything_there(tmp_path, mode):
    """A file, a folder, even an EMPTY folder (which os.rename would replace) at the target: FileExistsError, and
    both sides as they were."""
    os.chdir(tmp_path)
    Path("new").write_text("new")
    os.mkdir("newdir")
    Path("theirs").write_text("theirs")
    os.mkdir("empty")
    for src in ("new", "newdir"):
        for dst in ("theirs", "empty"):
            with pytest.raises(FileExistsError):
                _place.rename_noreplace(src, dst)
    assert Path("theirs").read_text() == "theirs" and list(Path("empty").iterdir()) == []
    assert Path("new").read_text() == "new" and Path("newdir").is_dir()
    _place.rename_noreplace("new", "placed")
    _place.rename_noreplace("newdir", "placeddir")
    assert Path("placed").read_text() == "new" and Path("placeddir").is_dir()
    assert sorted(os.listdir()) == ["empty", "placed", "placeddir", "theirs"]


def test_place_files_all_or_none(tmp_path, mode):
    """Two files placed as one: the second refused (another file put in place of the checked one, even under
    the inode number the first one freed) puts the first back as it was."""
    os.chdir(tmp_path)
    for name, text in (("t1", "new1"), ("t2", "new2"), ("o1", "old1"), ("o2", "old2")):
        Path(name).write_text(text)
    checked = {Path("o1"): _place.identity("o1"), Path("o2"): _place.identity("o2")}
    os.unlink("o2")
    Path("o2").write_text("theirs")
    with pytest.raises(_place.Taken) as info:
        _place.place_files([(Path("t1"), Path("o1")), (Path("t2"), Path("o2"))], checked)
    assert info.value.path == Path("o2") and info.value.changed
    assert Path("o1").read_text() == "old1" and Path("o2").read_text() == "theirs"
    Path("t1").write_text("new1")
    _place.place_files([(Path("t1"), Path("o1"))], {Path("o1"): _place.identity("o1")})
    assert Path("o1").read_text() == "new1"
    with pytest.raises(_place.Taken) as info:  # nothing was allowed there
        _place.place_files([(Path("t2"), Path("o1"))], {Path("o1"): None})
    assert not info.value.changed and Path("o1").read_text() == "new1"


def test_write_mesh_overwrite(tmp_path):
    """overwrite=False never replaces a file (the output or its companion); a dict allows only the file checked."""
    mesh = jaxci.box(1, 1, 1)
    (tmp_path / "m.vtk").write_text("mine")
    with pytest.raises(MeshWriteError, match=r"m\.vtk: exists; not replaced \(overwrite=False\)"):
        write_mesh(mesh, tmp_path / "m.vtk", overwrite=False)
    (tmp_path / "x.h5").write_text("mine")
    with pytest.raises(MeshWriteError, match=r"x\.h5: exists; not replaced"):
        write_mesh(mesh, tmp_path / "x.xdmf", overwrite=False)
    ident = _place.identity(tmp_path / "m.vtk")
    write_mesh(mesh, tmp_path / "m.vtk", overwrite={tmp_path / "m.vtk": ident})
    assert read_mesh(tmp_path / "m.vtk").n_hexes == 1
    with pytest.raises(MeshWriteError, match="was replaced by another file while the mesh was being written"):
        write_mesh(mesh, tmp_path / "m.vtk", overwrite={tmp_path / "m.vtk": ident})  # no longer that file
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.vtk", "x.h5"]


def test_input_paths(tmp_path):
    """The files a mesh was read from: its source and every file read through it."""
    from jaxci.io import input_paths

    write_mesh(jaxci.box(1, 1, 1), tmp_path / "a.xdmf")
    assert [p.name for p in input_paths(read_mesh(tmp_path / "a.xdmf"))] == ["a.xdmf", "a.h5"]
    write_mesh(jaxci.box(1, 1, 1), tmp_path / "n.inp")
    (tmp_path / "main.inp").write_text("*INCLUDE, INPUT=n.inp\n")
    assert [p.name for p in input_paths(read_mesh(tmp_path / "main.inp"))] == ["main.inp", "n.inp"]


def test_apdl_input_noted(tmp_path):
    """An APDL file's /INPUT is not followed, and a note says so (the mesh it would add is not part of this one)."""
    write_mesh(jaxci.box(1, 1, 1), tmp_path / "b.cdb")
    text = (tmp_path / "b.cdb").read_text()
    (tmp_path / "b.cdb").write_text(text + "/INPUT,more,cdb\n")
    assert any("/INPUT (not followed)" in n for n in read_mesh(tmp_path / "b.cdb").notes)
