"""`jaxci smooth IN... --out-dir DIR`: the single form's output per file, folders as inputs, a failing file that
stops nothing, refused clashes, the JSON object, one job or two, and an interrupt that leaves no partial file."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxci import perturb_box
from jaxci.cli import main
from jaxci.io import read_mesh, write_mesh

#: Keys of the single form's ``--json`` object, which every smoothed file's record holds too.
SINGLE_KEYS = {"method", "engine", "params", "iterations", "wall_time", "before", "after", "boundary", "notes",
               "phases", "input", "output"}
HOST = ["--engine", "host", "--seed", "3", "-q"]
#: Global CI held to its sweep cap (no stopping test): 1-3 s per small box, for an interrupt to come mid-run.
SLOW = [a for k in ("max_sweeps=300", "tol=0", "atol=0", "ftol=0", "ktol=0", "patience=100000") for a in ("--param", k)]


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _meshes(folder, specs):
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, n, seed in specs:
        path = folder / name
        write_mesh(perturb_box(*n, amplitude=0.3, seed=seed), path)
        paths.append(path)
    return paths


@pytest.fixture
def three(tmp_path):
    """Three small perturbed boxes in three formats."""
    return _meshes(tmp_path / "in", [("a.vtk", (4, 3, 3), 1), ("b.vtu", (3, 4, 3), 2), ("c.inp", (3, 3, 4), 3)])


def _same_mesh(p, q):
    a, b = read_mesh(p), read_mesh(q)
    np.testing.assert_allclose(np.asarray(a.points), np.asarray(b.points), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(a.hexes), np.asarray(b.hexes))


def test_batch_writes_what_the_single_form_writes_with_one_job_or_two(capsys, tmp_path, three):
    code, out, err = run(capsys, "smooth", *three, "--out-dir", tmp_path / "two", "--jobs", "2", "--json", *HOST)
    assert code == 0, err
    doc = json.loads(out)
    assert [r["input"] for r in doc["files"]] == [str(p) for p in three]  # the order of the inputs
    for rec in doc["files"]:
        assert SINGLE_KEYS <= set(rec) and rec["exit_code"] == 0 and rec["error"] is None
        assert rec["engine"]["name"] == "host" and rec["seconds"] > 0 and rec["warnings"] == []
        assert rec["after"]["max_condition"] < rec["before"]["max_condition"]
    t = doc["totals"]
    assert (t["files"], t["ok"], t["failed"], t["exit_code"], t["jobs"]) == (3, 3, 0, 0, 2)
    assert t["wall_seconds"] > 0 and t["out_dir"] == str(tmp_path / "two")
    code, _, err = run(capsys, "smooth", *three, "--out-dir", tmp_path / "one", "--jobs", "1", *HOST)
    assert code == 0, err
    (tmp_path / "single").mkdir()
    for src in three:
        before = src.read_bytes()
        code, _, err = run(capsys, "smooth", src, tmp_path / "single" / src.name, *HOST)
        assert code == 0, err
        assert src.read_bytes() == before  # never modified
        for folder in ("one", "two"):
            batch = tmp_path / folder / src.name
            assert batch.suffix == src.suffix  # the input's format
            _same_mesh(batch, tmp_path / "single" / src.name)
            assert batch.read_bytes() == (tmp_path / "single" / src.name).read_bytes()
    assert sorted(os.listdir(tmp_path / "two")) == ["a.vtk", "b.vtu", "c.inp"]  # nothing else (no temporaries)


def test_a_folder_is_its_mesh_files_sorted_not_its_subfolders(capsys, tmp_path):
    folder = tmp_path / "in"
    _meshes(folder, [("z.vtk", (3, 3, 3), 1), ("m.msh", (3, 3, 2), 2)])
    _meshes(folder / "sub", [("deeper.vtk", (2, 2, 2), 3)])
    (folder / "notes.txt").write_text("not a mesh\n")  # .txt is an ANSYS listing, read only: not taken
    (folder / ".hidden.vtk").write_text("")
    code, out, err = run(capsys, "smooth", folder, "--out-dir", tmp_path / "out" / "new", "--jobs", "1", *HOST)
    assert code == 0, err
    assert sorted(os.listdir(tmp_path / "out" / "new")) == ["m.msh", "z.vtk"]  # DIR made, parents too
    rows = [line.split()[0] for line in out.splitlines()[1:3]]
    assert rows == ["m.msh", "z.vtk"]
    assert out.splitlines()[-1].startswith("total: 2 of 2 files ok; 1 job")
    (tmp_path / "empty").mkdir()
    code, _, err = run(capsys, "smooth", tmp_path / "empty", "--out-dir", tmp_path / "x")
    assert code == 2 and "without mesh files" in err and not (tmp_path / "x").exists()


def test_a_failing_file_stops_nothing_and_gives_the_single_forms_status(capsys, tmp_path, three):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    taken = out_dir / "b.vtu"
    taken.write_bytes(b"mine")
    broken = tmp_path / "in" / "d.vtk"
    broken.write_text("# vtk DataFile Version 4.2\nnot a mesh\n")
    single = [main(["smooth", str(three[1]), str(taken), *HOST]),
              main(["smooth", str(broken), str(tmp_path / "d_single.vtk"), *HOST])]
    capsys.readouterr()
    code, out, err = run(capsys, "smooth", *three, broken, "--out-dir", out_dir, "--jobs", "2", "--json", *HOST)
    assert single == [2, 2] and code == 2
    recs = {os.path.basename(r["input"]): r for r in json.loads(out)["files"]}
    assert [recs[n]["exit_code"] for n in ("a.vtk", "b.vtu", "c.inp", "d.vtk")] == [0, 2, 0, 2]
    assert "exists; pass --force" in recs["b.vtu"]["error"] and str(broken) in recs["d.vtk"]["error"]
    assert taken.read_bytes() == b"mine"  # not replaced
    assert sorted(os.listdir(out_dir)) == ["a.vtk", "b.vtu", "c.inp"]
    assert len([line for line in err.splitlines() if line.startswith("jaxci: error: ")]) == 2
    code, out, err = run(capsys, "smooth", *three, "--out-dir", out_dir, "--force", "--jobs", "1", *HOST)
    assert code == 0, err  # --force replaces them
    assert taken.read_bytes() != b"mine"
    assert "total: 3 of 3 files ok" in out


def test_clashing_outputs_are_refused_before_anything_is_written(capsys, tmp_path, three):
    other = _meshes(tmp_path / "other", [("a.vtk", (3, 3, 3), 5)])[0]
    code, out, err = run(capsys, "smooth", three[0], other, "--out-dir", tmp_path / "out")
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1 and str(three[0]) in err and str(other) in err and "a.vtk" in err
    assert not (tmp_path / "out").exists()
    code, out, err = run(capsys, "smooth", tmp_path / "in", "--out-dir", tmp_path / "in", "--force")
    assert code == 2 and len(err.splitlines()) == 1 and "is the input" in err
    assert sorted(os.listdir(tmp_path / "in")) == ["a.vtk", "b.vtu", "c.inp"]


def test_the_single_form_and_its_usage_errors(capsys, tmp_path, three):
    out = tmp_path / "o.vtk"
    code, _, err = run(capsys, "smooth", three[0], "--method", "lbfgs", out, *HOST)  # options between the two
    assert code == 0 and out.exists(), err
    for argv, says in (([three[0]], "got 1 path"), ([*three], "got 3 paths"), ([three[0], out, "--jobs", "2"],
                                                                               "got --jobs"),
                       ([three[0], "--out-dir", tmp_path / "d", "--report", tmp_path / "r.html"], "--report"),
                       ([three[0], "--out-dir", tmp_path / "d", "--jobs", "0"], "--jobs")):
        code, stdout, err = run(capsys, "smooth", *argv)
        assert code == 2 and stdout == "" and len(err.splitlines()) == 1 and says in err, err
    assert not (tmp_path / "d").exists()


def _written(folder) -> list[str]:
    """The outputs in place in `folder` (not the hidden temporary folders of writes under way)."""
    return [n for n in os.listdir(folder) if not n.startswith(".")] if folder.is_dir() else []


def test_an_interrupt_stops_the_workers_and_leaves_no_partial_file(tmp_path):
    src = _meshes(tmp_path / "in", [(f"m{i}.vtk", (6, 6, 5), i) for i in range(4)])
    out_dir = tmp_path / "out"
    env = dict(os.environ, JAXCI_CACHE_DIR="")
    p = subprocess.Popen([sys.executable, "-m", "jaxci", "smooth", *map(str, src), "--out-dir", str(out_dir),
                          "--jobs", "2", "--engine", "host", "-q", "--method", "ci-global", *SLOW],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, start_new_session=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not _written(out_dir) and p.poll() is None:
        time.sleep(0.05)
    time.sleep(0.3)
    os.killpg(p.pid, signal.SIGINT)  # a Ctrl-C reaches the whole process group
    _, err = p.communicate(timeout=30)
    err = err.decode()
    assert p.returncode == 130, err
    assert err.splitlines()[-1].startswith("jaxci: interrupted (SIGINT): ") and "files written to" in err
    assert "Traceback" not in err and "leaked" not in err
    left = os.listdir(out_dir)
    assert not [n for n in left if n.startswith(".")]  # no temporary file
    for name in left:
        read_mesh(out_dir / name)  # every output there is complete
    assert len(left) < len(src)


def _workers(pid: int) -> list[int]:
    """The pool's worker processes of process `pid` (Linux /proc): its children started by multiprocessing's
    spawn, not its resource tracker."""
    out = []
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                cmd = f.read()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid and b"spawn_main" in cmd:
            out.append(int(entry))
    return out


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="reads /proc")
def test_a_worker_that_dies_fails_its_own_file_only(tmp_path):
    src = _meshes(tmp_path / "in", [(f"m{i}.vtk", (6, 6, 5), i) for i in range(5)])
    out_dir = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "jaxci", "smooth", *map(str, src), "--out-dir", str(out_dir),
                          "--jobs", "2", "--engine", "host", "-q", "--json", "--method", "ci-global", *SLOW],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ, JAXCI_CACHE_DIR=""))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not _written(out_dir) and p.poll() is None:
        time.sleep(0.05)
    time.sleep(0.2)  # one file done: both workers inside another (3 of the 5 to go at least)
    os.kill(_workers(p.pid)[0], signal.SIGKILL)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 1, err
    files = json.loads(out)["files"]
    codes = sorted(r["exit_code"] for r in files)
    codes_by_name = {os.path.basename(r["input"]): r["exit_code"] for r in files}
    said = [(os.path.basename(r["input"]), r["exit_code"], r["error"]) for r in files]  # what failed, if it does
    err = err.decode()
    assert codes == [0, 0, 0, 0, 1] and "ended abruptly (killed by SIGKILL" in err, (said, err[-3000:])
    # no temporary file of the killed worker; its file's output absent, or complete where the worker had written
    # it before it was killed (under load that happens: the result was on its way back)
    names = set(os.listdir(out_dir))
    assert {f"m{i}.vtk" for i in range(5) if codes_by_name[f"m{i}.vtk"] == 0} <= names <= {f"m{i}.vtk" for i in
                                                                                         range(5)}
    for name in names:
        read_mesh(out_dir / name)


def test_bench_batch_times_the_batch_against_msqshape(tmp_path):
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = tmp_path / "bench.json"
    p = subprocess.run([sys.executable, os.path.join(root, "scripts", "bench_batch.py"), "--count", "3",
                        "--min-hexes", "100", "--max-hexes", "400", "--no-fixed", "--out", str(out), "--md",
                        str(tmp_path / "bench.md")], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    doc = json.loads(out.read_text())
    assert doc["corpus"]["count"] == 3 and {"date", "commit", "command", "machine"} <= set(doc)
    batch = doc["results"]["batch"]
    assert batch["files_ok"] == 3 and batch["median_wall_s"] > 0 and batch["cmd"].startswith("jaxci smooth DIR")
    assert all(row["batch"]["exit_code"] == 0 and row["batch"]["max_condition"] >= 1 for row in doc["meshes"])
    if "msqshape" in doc["results"]:  # where ../shared/peers has it
        assert doc["results"]["msqshape"]["files"] == 3
    assert "| batch |" in (tmp_path / "bench.md").read_text()


def test_a_dead_workers_file_says_how_the_worker_ended():
    from jaxci.cli._batch import _ending

    assert _ending(-signal.SIGKILL).startswith("killed by SIGKILL: ") and "memory" in _ending(-signal.SIGKILL)
    assert _ending(-signal.SIGSEGV) == "killed by SIGSEGV: a crash in native code"
    assert _ending(-signal.SIGHUP) == "killed by SIGHUP"
    assert _ending(1) == "exit status 1" and _ending(-200) == "killed by signal 200"


def test_a_file_tried_again_may_replace_only_the_output_its_own_worker_wrote(tmp_path):
    """A pool that breaks (another worker died) after a worker wrote its file but before its record came back
    tries that file again: the new run may replace the output that worker wrote (the identities it said), and
    nothing else: not a file put there since, not a file that was there before the batch."""
    from jaxci.cli._batch import _ours
    from jaxci.cli._files import check_output
    from jaxci.errors import MeshWriteError
    from jaxci.io._place import identity

    mesh = perturb_box(3, amplitude=0.1, seed=0)
    out = check_output(tmp_path / "m.vtk", force=False)
    item = (0, "in.vtk", out)
    assert _ours(item, None) is item and out.written is None  # a run that wrote nothing says nothing
    out.write(mesh)  # the first worker's write
    wrote = list(out.written)
    assert wrote == [identity(t) for t in out.targets]
    again = _ours(item, wrote)[2]
    again.write(mesh)  # the new run replaces it
    assert read_mesh(tmp_path / "m.vtk").points.shape == mesh.points.shape
    # a file put in its place since (another identity): not replaced
    os.remove(tmp_path / "m.vtk")
    (tmp_path / "m.vtk").write_text("the user's")
    with pytest.raises(MeshWriteError, match="appeared"):
        _ours(item, wrote)[2].write(mesh)
    assert (tmp_path / "m.vtk").read_text() == "the user's"
