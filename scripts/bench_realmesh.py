"""Real-mesh benchmark: the `jaxci smooth` command (cold and warm compile cache) against Mesquite's msqshape.

For every mesh of the corpus (`scripts/realmesh_corpus.py`: Mesquite's meshFiles, the perturbed unit cubes msqshape
was measured on, the ANSYS archives of ``mapdl-archive``, curved and unstructured meshes made with gmsh) it runs,
one after the other, each as its own process:

- ``jaxci smooth IN OUT --json [--method M]`` (``python -m jaxci``, `--jaxci-cmd` to change), per `--method`
  (``default``: no ``--method`` flag, jaxci's default; ``pmean4``: ``--method lbfgs --objective pmean --param
  p=4``; any other name: ``--method NAME``, e.g. ``lbfgs`` plain L-BFGS, ``ci`` local CI; ``NAME:PARAM=VALUE`` adds
  ``--param PARAM=VALUE``, e.g. ``default:polish_work=400``):

  - ``cold``: with an EMPTY persistent compile cache (``JAXCI_CACHE_DIR`` a fresh folder): a first use;
  - ``warm``: again with that cache (the same mesh smoothed before);
  - ``warm_other``: with a copy of the cache another mesh of a similar size (hex counts within `--similar`) left:
    the target case, "a different mesh of a similar size smoothed before" (``--no-warm-other`` to skip);

- ``/work/shared/peers/msqshape`` on a legacy ASCII VTK copy of the same mesh (points and linear cells as
  `jaxci.io.read_mesh` reads them, written with meshio ``binary=False``; no point data, so no ``fixed`` flags),
  per `--msq-modes`:

  - ``domain``: the skin held as jaxci holds it where msqshape can: a mesh whose skin lies on the faces of its
    bounding box slides on those planes, edges and corners (``-P/-l/-v``, as ``cube_domain_args.txt`` for the
    unit cube); any other mesh has its skin fixed (``-s``);
  - ``free``: no flag (msqshape's own default: does the boundary move?);
  - ``skin``: ``-s`` on every mesh (the skin fixed).

Before the runs it writes the bytecode of the jaxci package (``compileall``, `ensure_bytecode`), as installing
a package does: with ``PYTHONDONTWRITEBYTECODE`` set (as on the machines of docs/results) no ``jaxci`` process
would ever write it, and every run would compile jaxci's sources anew (about 0.1 s of each start-up here), which
no installed copy does (``--no-bytecode``: leave it as it is; the JSON's ``settings.bytecode`` says which).

``--repeats N`` makes every jaxci method's cold run N times, each with an empty cache, the methods alternated
(`cold_repeats`): the wall times in the tables and the targets are then each method's median, and the JSON keeps
every run's (``wall_runs``). One run's ratio moves by 0.2-0.3 on a shared 2-core machine.

Per run it records the wall time, the child's CPU time (user + system) and peak RSS (``os.wait4``), exit status,
the end of stderr, and for jaxci what ``--json`` says (iterations, its own wall time, notes, and a ``phases`` or
``timings`` dict where the command reports one). Every output is then measured here by the same code
(`jaxci.io.read_mesh` + `jaxci.metrics.report.quality_report`, float64), as is the input: inverted elements, max and
mean kappa/3, F, min scaled Jacobian, and how far the skin nodes moved (``boundary_moved``: more than 1e-9 of the
bounding-box diagonal), and per element VTK's condition (the worst corner's kappa/3 of each cell: ``worst_element``,
``element_mean`` over the cells). Prints a table and writes JSON (`--out`, rewritten after every mesh).

``--targets`` runs what the default pipeline is held to (cold runs only: ``default``, ``lbfgs``, ``pmean4``, ``ci``
and msqshape ``skin``) and prints per mesh, after the table, the default against the p-mean, local CI and msqshape
-s (worst element, mean element, cold wall) and whether each target holds (`TARGETS`): the default's worst element
within 2% of the best of p-mean, local CI and msqshape -s; its mean element within 1% of the better of plain
L-BFGS and msqshape -s; its cold wall at most 2x plain L-BFGS's (1.5x on cube60_pert).

    python scripts/bench_realmesh.py [--meshes cube9_pert pave3 sphere_tet2hex ...] [--method default lbfgs]
        [--sizes small large] [--timeout 900] [--skip-msq] [--msq-modes domain free skin] [--no-warm-other]
        [--cold-only] [--targets] [--repeats 3]
        [--corpus-dir ~/.cache/jaxci/realmesh] [--out docs/results/bench_realmesh.json]

`--meshes` takes corpus names (``python scripts/realmesh_corpus.py --list``), a source (``mesquite``, ``peers``,
``cdb``, ``gmsh``), a gmsh shape for all its sizes, or paths of mesh files. Timings on a shared machine are noisy:
run it alone.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import realmesh_corpus as corpus  # noqa: E402
from bench_stamp import stamp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MSQSHAPE = corpus.PEERS / "msqshape"
DEFAULT_OUT = ROOT / "docs" / "results" / "bench_realmesh.json"
QUALITY_KEYS = ("inverted_elements", "inverted_corners", "max_condition", "mean_condition", "objective",
                "min_scaled_jacobian")
#: A skin node that moved more than this fraction of the bounding-box diagonal counts as moved.
MOVED_REL = 1e-9

#: `--method` names that stand for more than ``--method NAME``: ``default`` (no flag: jaxci's default pipeline)
#: and ``pmean4`` (L-BFGS on the p-mean, p = 4).
VARIANTS = {"default": [], "pmean4": ["--method", "lbfgs", "--objective", "pmean", "--param", "p=4"]}


def method_flags(method: str) -> list[str]:
    """The ``jaxci smooth`` flags of a `--method` entry ``NAME[:PARAM=VALUE[,PARAM=VALUE...]]``: NAME's (a
    `VARIANTS` name, else ``--method NAME``), then ``--param PARAM=VALUE`` for each, e.g.
    ``default:polish_budget=0.02`` the default pipeline with ``--param polish_budget=0.02``."""
    name, _, params = method.partition(":")
    flags = list(VARIANTS.get(name, ["--method", name]))
    for p in filter(None, params.split(",")):
        if "=" not in p:
            raise SystemExit(f"bench_realmesh: --method {method!r}: {p!r} is not PARAM=VALUE")
        flags += ["--param", p]
    return flags


def method_slug(method: str) -> str:
    """`method` as a file name's part (its ``:``, ``=`` and ``,`` as ``_``)."""
    return method.replace(":", "_").replace("=", "_").replace(",", "_")

#: What the default pipeline is held to (`--targets`): its worst element within `worst` of the best of the p-mean
#: (p = 4), local CI and msqshape -s; its mean element within `mean` of the better of plain L-BFGS and msqshape
#: -s; its cold wall time at most `wall` times plain L-BFGS's (`wall_large` on the meshes of `large`).
TARGETS = {"worst": 0.02, "mean": 0.01, "wall": 2.0, "wall_large": 1.5, "large": ("cube60_pert",)}
#: The runs `--targets` makes.
TARGET_METHODS, TARGET_MSQ = ("default", "lbfgs", "pmean4", "ci"), ("skin",)


# ------------------------------------------------------------------------------------------------ children
#: A small process that runs the command and reports its rusage: a child's ru_maxrss starts at the RSS of the
#: process it was forked from (Linux keeps the old memory's high-water mark across exec), so the command must not
#: be forked from this one (numpy, JAX: hundreds of MB). GNU time where installed (~1 MB), else a bare Python.
_PY_LAUNCHER = r"""
import os, sys
out, cmd = sys.argv[1], sys.argv[2:]
pid = os.fork()
if pid == 0:
    try:
        os.execvp(cmd[0], cmd)
    finally:
        os._exit(127)
_, st, ru = os.wait4(pid, 0)
with open(out, "w") as f:
    f.write("%r %r %d" % (ru.ru_utime, ru.ru_stime, ru.ru_maxrss))
code = os.waitstatus_to_exitcode(st)
sys.exit(code if code >= 0 else 128 - code)
"""
GNU_TIME = "/usr/bin/time"


def _gnu_time() -> bool:
    try:
        p = subprocess.run([GNU_TIME, "-f", "%M", "true"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return False
    return p.returncode == 0 and p.stderr.strip().isdigit()


HAVE_GNU_TIME = _gnu_time()


def run_child(cmd: list[str], *, env: dict | None = None, timeout: float, cwd: str | None = None) -> dict:
    """Run `cmd` under a small launcher and return its exit status, wall and CPU seconds (user + system, from
    ``os.wait4``: the launcher's few milliseconds included), peak RSS in MB (the command's own ``ru_maxrss``, as
    the launcher saw it), stdout and the end of stderr. Past `timeout` seconds its process group is killed
    (``timed_out``)."""
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe, \
            tempfile.NamedTemporaryFile("r", suffix=".rusage") as fs:
        if HAVE_GNU_TIME:
            full = [GNU_TIME, "-q", "-f", "0 0 %M", "-o", fs.name, "--", *cmd]
        else:
            full = [sys.executable, "-S", "-c", _PY_LAUNCHER, fs.name, *cmd]
        t0 = time.perf_counter()
        try:
            p = subprocess.Popen(full, stdout=fo, stderr=fe, stdin=subprocess.DEVNULL, env=env, cwd=cwd,
                                 start_new_session=True)
        except OSError as e:
            return dict(cmd=cmd, rc=None, timed_out=False, error=f"{type(e).__name__}: {e}", wall_s=None,
                        cpu_s=None, user_s=None, sys_s=None, peak_rss_mb=None, stdout="", stderr_tail="")
        killed = threading.Event()

        def kill():
            killed.set()
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass

        timer = threading.Timer(timeout, kill)
        timer.start()
        try:
            _, status, ru = os.wait4(p.pid, 0)
        finally:
            timer.cancel()
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
        fo.seek(0)
        fe.seek(0)
        out = fo.read().decode(errors="replace")
        err = fe.read().decode(errors="replace")
        try:
            rss_kb = float(fs.read().split()[-1])
        except (ValueError, IndexError):
            rss_kb = None
    rc = p.returncode
    if killed.is_set() or (HAVE_GNU_TIME and rc > 128):  # GNU time: 128 + signal of a killed command
        rc = rc if not killed.is_set() else -signal.SIGKILL
    return dict(cmd=cmd, rc=rc, timed_out=killed.is_set(), wall_s=wall, cpu_s=ru.ru_utime + ru.ru_stime,
                user_s=ru.ru_utime, sys_s=ru.ru_stime, peak_rss_mb=None if rss_kb is None else rss_kb / 1024.0,
                rss_via="gnu-time" if HAVE_GNU_TIME else "python-launcher", stdout=out, stderr_tail=err[-3000:])


def last_json(text: str) -> dict | None:
    """The last line of `text` that parses as a JSON object."""
    for line in reversed(text.splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return None


def run_jaxci(args, inp: Path, out: Path, method: str, cache: Path) -> dict:
    """One ``jaxci smooth`` run with `cache` as its compile cache; what ``--json`` said folded in."""
    cmd = [*shlex.split(args.jaxci_cmd), "smooth", str(inp), str(out), "--json", "--force"]
    cmd += method_flags(method)
    cmd += shlex.split(args.jaxci_args)
    env = dict(os.environ, JAXCI_CACHE_DIR=str(cache))
    r = run_child(cmd, env=env, timeout=args.timeout)
    summary = last_json(r.pop("stdout"))
    r["cache_entries_after"] = sum(1 for _ in cache.rglob("*") if _.is_file()) if cache.exists() else 0
    if summary is not None:
        phases_key = next((k for k in ("phases", "timings") if isinstance(summary.get(k), dict)), None)
        r.update(method_run=summary.get("method"), iterations=summary.get("iterations"),
                 reported_wall_s=summary.get("wall_time"), notes=summary.get("notes"),
                 boundary_classes=summary.get("boundary"), phases_key=phases_key,
                 phases=summary.get(phases_key) if phases_key else None,
                 reported_after={k: (summary.get("after") or {}).get(k) for k in QUALITY_KEYS})
    else:
        r.update(phases_key=None, phases=None)
    r["ok"] = r["rc"] == 0 and summary is not None and out.exists()
    return r


# ------------------------------------------------------------------------------------------------ meshes
def skin(mesh) -> tuple[np.ndarray, np.ndarray]:
    """``(nodes, faces)`` of the boundary of the volume cells: jaxci's own topology (a triangle is a quadrilateral
    with its last node repeated), plain hexahedron faces as a fallback."""
    try:
        from jaxci.geometry.boundary import mesh_topology

        faces = np.asarray(mesh_topology(mesh).faces, dtype=np.int64)
    except Exception:  # noqa: BLE001 - only a fallback for a library in flux
        h = np.asarray(mesh.hexes)
        f = h[:, [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]].reshape(-1, 4)
        _, inv, cnt = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
        faces = f[cnt[inv.ravel()] == 1]
    return np.unique(faces), faces


def box_planes(points: np.ndarray, faces: np.ndarray) -> dict | None:
    """When every boundary face lies in one face plane of the bounding box of `points`: ``lo``, ``hi`` and, per
    node, which of the 6 planes (x=lo, x=hi, y=lo, ...) it lies in (``on``, bool ``(n_nodes, 6)``); else None."""
    if not len(faces):
        return None
    lo, hi = points.min(axis=0), points.max(axis=0)
    tol = 1e-9 * max(float(np.linalg.norm(hi - lo)), 1e-300)
    fp = points[faces]  # (F, 4, 3)
    face_on = np.stack([(np.abs(fp[:, :, d] - c[d]) <= tol).all(axis=1) for d in range(3) for c in (lo, hi)], 1)
    if not face_on.any(axis=1).all():
        return None
    on = np.zeros((len(points), 6), dtype=bool)
    for k in range(6):
        on[np.unique(faces[face_on[:, k]]), k] = True
    return dict(lo=lo, hi=hi, on=on)


def box_domain_args(box: dict) -> list[str]:
    """msqshape's ``-P/-l/-v`` arguments for the faces, edges and corners of the box (`box_planes`):
    ``cube_domain_args.txt`` for the unit cube."""
    lo, hi = box["lo"], box["hi"]

    def fmt(*v):
        return ",".join(f"{float(x):.17g}" for x in v)

    out: list[str] = []
    for d in range(3):
        n = [0, 0, 0]
        n[d] = 1
        for c in (lo, hi):
            q = lo.copy()
            q[d] = c[d]
            out += ["-P", fmt(*n, *q)]
    for d in range(3):
        a, b = [k for k in range(3) if k != d]
        n = [0, 0, 0]
        n[d] = 1
        for ca in (lo[a], hi[a]):
            for cb in (lo[b], hi[b]):
                q = [0.0, 0.0, 0.0]
                q[d], q[a], q[b] = lo[d], ca, cb
                out += ["-l", fmt(*n, *q)]
    for x in (lo[0], hi[0]):
        for y in (lo[1], hi[1]):
            for z in (lo[2], hi[2]):
                out += ["-v", fmt(x, y, z)]
    return out


def off_box(points: np.ndarray, box: dict) -> float:
    """Largest distance of a node from a box face plane it lay in (0 when every node stayed in its planes)."""
    worst = 0.0
    for k in range(6):
        d, c = divmod(k, 2)
        sel = box["on"][:, k]
        if sel.any():
            ref = (box["lo"], box["hi"])[c][d]
            worst = max(worst, float(np.abs(points[sel, d] - ref).max()))
    return worst


LINEAR = {"hexahedron", "wedge", "pyramid", "tetra"}


def write_msq_copy(mesh, path: Path) -> dict:
    """Legacy ASCII VTK 4.2 of the linear cells of `mesh` (corner nodes; nodes no cell uses dropped), meshio
    ``binary=False``. Returns how the copy's nodes map back (``nodes``: index in `mesh` of each node)."""
    import meshio

    blocks = [(b.type, np.asarray(b.data, dtype=np.int64)) for b in mesh.cells if b.type in LINEAR and len(b.data)]
    used = np.unique(np.concatenate([d.ravel() for _, d in blocks]))
    new = np.full(mesh.n_nodes, -1, dtype=np.int64)
    new[used] = np.arange(len(used))
    m = meshio.Mesh(np.asarray(mesh.points, dtype=np.float64)[used], [(t, new[d]) for t, d in blocks])
    corpus.write_ascii_vtk(path, m)
    return dict(nodes=used, cells={t: len(d) for t, d in blocks})


def quality(mesh) -> dict:
    """The report's `QUALITY_KEYS` and VTK's per-element condition (each cell's worst corner kappa/3, every cell
    type): ``worst_element`` (the max) and ``element_mean`` (the mean over valid cells)."""
    from jaxci.metrics.guard import cell_worst
    from jaxci.metrics.report import quality_report

    d = quality_report(mesh).to_dict()
    out = {k: d.get(k) for k in QUALITY_KEYS}
    k = np.concatenate([v for v in cell_worst(mesh, mesh.points).values()])
    ok = k[np.isfinite(k)]
    out["worst_element"] = float(k.max()) if len(k) else None
    out["element_mean"] = float(ok.mean()) if len(ok) else None
    return out


def measure_output(out: Path, ref_points: np.ndarray, skin_idx: np.ndarray, diag: float, box: dict | None) -> dict:
    """Quality of the mesh in `out`, how far its skin nodes moved from `ref_points` (same node numbering) and, for
    a box-shaped mesh, how far they left the box face planes they lay in."""
    from jaxci.io import read_mesh

    try:
        m = read_mesh(out)
    except Exception as e:  # noqa: BLE001 - a broken output is a result
        return dict(after=None, read_error=f"{type(e).__name__}: {e}")
    res = dict(after=quality(m))
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.shape == ref_points.shape:
        d = np.linalg.norm(pts - ref_points, axis=1)
        bmax = float(d[skin_idx].max()) if len(skin_idx) else 0.0
        res["boundary"] = dict(max_move=bmax, max_move_rel=bmax / diag, moved=bool(bmax > MOVED_REL * diag),
                               nodes_moved=int((d[skin_idx] > MOVED_REL * diag).sum()), skin_nodes=int(len(skin_idx)),
                               off_box_planes=None if box is None else off_box(pts, box))
        res["max_node_move"] = float(d.max()) if len(d) else 0.0
    else:
        res["boundary"] = None
        res["node_count_changed"] = [int(ref_points.shape[0]), int(pts.shape[0])]
    return res


def prepare(entry, work: Path) -> tuple[dict, dict]:
    """Read the input with jaxci, measure it, write msqshape's copy and its domain flags."""
    from jaxci.io import read_mesh
    from jaxci.metrics.report import quality_report

    path = entry.ensure()
    t0 = time.perf_counter()
    mesh = read_mesh(path)
    read_s = time.perf_counter() - t0
    rep = quality_report(mesh)
    pts = np.asarray(mesh.points, dtype=np.float64)
    skin_idx, faces = skin(mesh)
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) or 1.0
    d = work / entry.name
    d.mkdir(parents=True, exist_ok=True)
    msq_in = d / "msq_in.vtk"
    copy = write_msq_copy(mesh, msq_in)
    msq_mesh = read_mesh(msq_in)
    msq_pts = np.asarray(msq_mesh.points, dtype=np.float64)
    msq_skin, msq_faces = skin(msq_mesh)
    box = box_planes(pts, faces)
    msq_box = box_planes(msq_pts, msq_faces)
    info = dict(name=entry.name, source=entry.source, path=str(path), description=entry.description,
                hexes=mesh.n_hexes, nodes=mesh.n_nodes, other_cells=rep.other_cells, read_s=read_s,
                read_notes=list(mesh.notes), hex_mirrored=bool(getattr(mesh, "hex_mirrored", False)),
                skin_nodes=int(len(skin_idx)), bbox_diagonal=diag, box_shaped=box is not None,
                before={k: rep.to_dict().get(k) for k in QUALITY_KEYS},
                msq_domain="box" if msq_box is not None else "skin",
                msq_domain_args=box_domain_args(msq_box) if msq_box is not None else ["-s"],
                msq_copy_cells=copy["cells"])
    ctx = dict(path=path, pts=pts, skin=skin_idx, box=box, diag=diag, dir=d, msq_in=msq_in, msq_pts=msq_pts,
               msq_skin=msq_skin, msq_box=msq_box)
    return info, ctx


# ------------------------------------------------------------------------------------------------ the run
def _fresh(cache: Path) -> Path:
    """`cache` as an empty folder (a cold run's compilation cache)."""
    if cache.exists():
        shutil.rmtree(cache)
    cache.mkdir(parents=True)
    return cache


def bench_mesh(args, info: dict, ctx: dict, caches: Path) -> None:
    d: Path = ctx["dir"]
    info["jaxci"] = {}
    for method in args.method:
        cache = _fresh(caches / f"{info['name']}__{method_slug(method)}")
        runs = {}
        for run in ("cold",) if args.cold_only else ("cold", "warm"):
            out = d / f"jaxci_{method_slug(method)}_{run}.vtk"
            r = run_jaxci(args, ctx["path"], out, method, cache)
            if r["ok"]:
                r.update(measure_output(out, ctx["pts"], ctx["skin"], ctx["diag"], ctx["box"]))
            runs[run] = r
            _say(info["name"], f"jaxci {method} {run}", r)
            if not r["ok"]:
                break
        info["jaxci"][method] = runs
    cold_repeats(args, info, ctx, caches)
    info["msqshape"] = {}
    if args.skip_msq:
        return
    if not MSQSHAPE.exists():
        info["msqshape"] = {"skipped": f"{MSQSHAPE} not found"}
        return
    for mode in args.msq_modes:
        flags = {"domain": info["msq_domain_args"], "skin": ["-s"]}.get(mode, [])
        out = d / f"msq_{mode}.vtk"
        if out.exists():
            out.unlink()
        r = run_child([str(MSQSHAPE), *flags, str(ctx["msq_in"]), str(out)], timeout=args.timeout, cwd=str(d))
        stdout = r.pop("stdout")
        r["stdout_tail"] = stdout[-1500:]
        r["flags"] = "none" if not flags else (info["msq_domain"] if mode == "domain" else " ".join(flags))
        r["ok"] = r["rc"] == 0 and out.exists()
        if out.exists():
            r.update(measure_output(out, ctx["msq_pts"], ctx["msq_skin"], ctx["diag"], ctx["msq_box"]))
        info["msqshape"][mode] = r
        _say(info["name"], f"msqshape {mode}", r)


def cold_repeats(args, info: dict, ctx: dict, caches: Path) -> None:
    """With ``--repeats N`` (N > 1): N - 1 more cold runs of every method, each with an empty cache, the methods
    alternated (repeat k runs each method once, in `--method`'s order), so that the runs of one repeat are seconds
    apart and a ratio of medians is taken over the same spells of the machine. Each method's ``cold`` record keeps
    its first run's figures (its output measured), and gets ``wall_runs`` (every run's wall seconds, the first
    first), ``wall_first_s`` (the first's) and ``wall_s`` := their median, which the tables and the targets read.
    A method whose first run failed is not repeated; a failed repeat is left out of the median and counted in
    ``failed_repeats``."""
    if args.repeats <= 1:
        return
    walls = {m: [info["jaxci"][m]["cold"]["wall_s"]] for m in args.method
             if (info["jaxci"][m].get("cold") or {}).get("ok")}
    failed = dict.fromkeys(walls, 0)
    for k in range(1, args.repeats):
        for method in walls:
            cache = _fresh(caches / f"{info['name']}__{method_slug(method)}")
            out = ctx["dir"] / f"jaxci_{method_slug(method)}_cold_{k + 1}.vtk"
            r = run_jaxci(args, ctx["path"], out, method, cache)
            _say(info["name"], f"jaxci {method} cold, repeat {k + 1}", r)
            if r["ok"]:
                walls[method].append(r["wall_s"])
            else:
                failed[method] += 1
            if out.exists():
                out.unlink()
    for method, w in walls.items():
        cold = info["jaxci"][method]["cold"]
        cold.update(wall_runs=w, wall_first_s=w[0], wall_s=float(np.median(w)), failed_repeats=failed[method])


def bench_warm_other(args, rows: list[dict], ctxs: dict, caches: Path) -> None:
    """For every mesh and method: run it with a copy of the compile cache of the most similar-sized other mesh."""
    for info in rows:
        for method in args.method:
            runs = info["jaxci"].get(method) or {}
            if not (runs.get("cold") or {}).get("ok"):
                continue
            others = [o for o in rows if o is not info and ((o["jaxci"].get(method) or {}).get("cold") or {}).get("ok")]
            if not others:
                runs["warm_other"] = {"skipped": "no other mesh ran"}
                continue
            partner = min(others, key=lambda o: abs(math.log(max(o["hexes"], 1) / max(info["hexes"], 1))))
            ratio = max(partner["hexes"], 1) / max(info["hexes"], 1)
            if max(ratio, 1 / ratio) > args.similar:
                runs["warm_other"] = {"skipped": f"no other mesh within a factor {args.similar:g} of "
                                                 f"{info['hexes']} hexes (closest: {partner['name']}, "
                                                 f"{partner['hexes']})"}
                continue
            cache = caches / f"{info['name']}__{method_slug(method)}__from__{partner['name']}"
            if cache.exists():
                shutil.rmtree(cache)
            shutil.copytree(caches / f"{partner['name']}__{method_slug(method)}", cache)
            ctx = ctxs[info["name"]]
            out = ctx["dir"] / f"jaxci_{method_slug(method)}_warm_other.vtk"
            r = run_jaxci(args, ctx["path"], out, method, cache)
            if r["ok"]:
                r.update(measure_output(out, ctx["pts"], ctx["skin"], ctx["diag"], ctx["box"]))
            r.update(partner=partner["name"], partner_hexes=partner["hexes"])
            runs["warm_other"] = r
            _say(info["name"], f"jaxci {method} warm_other (cache of {partner['name']})", r)
            shutil.rmtree(cache, ignore_errors=True)


def _say(name: str, what: str, r: dict) -> None:
    if r.get("ok"):
        a = r.get("after") or {}
        mc = a.get("max_condition")
        print(f"  {name}: {what}: {r['wall_s']:.2f} s wall, {r['cpu_s']:.2f} s CPU, {r['peak_rss_mb']:.0f} MB, "
              f"inverted {a.get('inverted_elements')}, max k/3 {'-' if mc is None else f'{mc:.5g}'}", flush=True)
    else:
        why = "timed out" if r.get("timed_out") else f"exit {r.get('rc')}"
        tail = (r.get("stderr_tail") or r.get("error") or "").strip().splitlines()[-1:] or [""]
        print(f"  {name}: {what}: FAILED ({why}) {tail[0][:300]}", flush=True)


def _f(x, spec=".2f", none="-"):
    return none if x is None else format(x, spec)


def table(rows: list[dict]) -> str:
    head = (f"{'mesh':28s} {'hexes':>7s} {'inv0':>5s} {'k/3 max0':>9s}  {'tool/run':24s} {'wall s':>8s} "
            f"{'cpu s':>8s} {'MB':>6s} {'inv':>5s} {'k/3 max':>9s} {'k/3 mean':>9s} {'bnd':>5s}")
    lines = [head, "-" * len(head)]
    for info in rows:
        b = info["before"]
        first = f"{info['name'][:28]:28s} {info['hexes']:7d} {b['inverted_elements']:5d} " \
                f"{_f(b['max_condition'], '9.4g'):>9s}"
        items = []
        for method, runs in info.get("jaxci", {}).items():
            for run in ("cold", "warm", "warm_other"):
                if run in runs:
                    items.append((f"jaxci {method} {run}", runs[run]))
        for mode, r in (info.get("msqshape") or {}).items():
            if isinstance(r, dict):
                items.append((f"msq {mode} ({r.get('flags', '')})", r))
        for i, (label, r) in enumerate(items):
            lead = first if i == 0 else " " * len(first)
            if "skipped" in r:
                lines.append(f"{lead}  {label[:24]:24s} skipped: {r['skipped']}")
                continue
            if not r.get("ok"):
                why = "timeout" if r.get("timed_out") else f"rc {r.get('rc')}"
                lines.append(f"{lead}  {label[:24]:24s} {_f(r.get('wall_s')):>8s} FAILED ({why})")
                continue
            a = r.get("after") or {}
            bnd = r.get("boundary") or {}
            moved = "-" if not bnd else ("fixed" if not bnd["moved"] else "slid" if (
                bnd.get("off_box_planes") is not None and bnd["off_box_planes"] <= 1e-6 * info["bbox_diagonal"])
                else "moved")
            lines.append(f"{lead}  {label[:24]:24s} {_f(r['wall_s']):>8s} {_f(r['cpu_s']):>8s} "
                         f"{_f(r['peak_rss_mb'], '.0f'):>6s} {_f(a.get('inverted_elements'), 'd'):>5s} "
                         f"{_f(a.get('max_condition'), '9.5g'):>9s} {_f(a.get('mean_condition'), '9.5g'):>9s} "
                         f"{moved:>5s}")
        if not items:
            lines.append(first)
    return "\n".join(lines)


def _run(info: dict, method: str) -> dict | None:
    r = (info.get("jaxci", {}).get(method) or {}).get("cold")
    return r if r and r.get("ok") else None


def _figures(r: dict | None) -> dict | None:
    """``{worst, mean, wall}`` of a run (worst and mean: VTK's per-element condition), None if it failed."""
    if r is None or not r.get("after"):
        return None
    a = r["after"]
    return {"worst": a.get("worst_element"), "mean": a.get("element_mean"), "wall": r.get("wall_s")}


def targets(info: dict) -> dict:
    """The default pipeline's `TARGETS` on one mesh of a ``--targets`` run: per run its figures, and per target
    the bound, the default's value and whether it holds (None where a run it needs failed)."""
    msq = (info.get("msqshape") or {}).get("skin")
    runs = {m: _figures(_run(info, m)) for m in ("default", "lbfgs", "pmean4", "ci")}
    runs["msq -s"] = _figures(msq if msq and msq.get("ok") else None)
    d = runs["default"]
    out = {"runs": runs}
    peers = [runs[k]["worst"] for k in ("pmean4", "ci", "msq -s") if runs[k] and runs[k]["worst"] is not None]
    means = [runs[k]["mean"] for k in ("lbfgs", "msq -s") if runs[k] and runs[k]["mean"] is not None]
    wall = TARGETS["wall_large"] if info["name"] in TARGETS["large"] else TARGETS["wall"]

    def check(value, bound):
        return {"bound": bound, "value": value, "met": None if value is None or bound is None else value <= bound}

    out["worst"] = check(d and d["worst"], min(peers) * (1 + TARGETS["worst"]) if peers else None)
    out["mean"] = check(d and d["mean"], min(means) * (1 + TARGETS["mean"]) if means else None)
    out["wall"] = check(d and d["wall"], runs["lbfgs"]["wall"] * wall if runs["lbfgs"] else None)
    return out


def targets_table(rows: list[dict]) -> str:
    """Per mesh: worst element / mean element / cold wall of the default, the p-mean (p = 4), local CI, msqshape
    -s and plain L-BFGS, and the three targets (yes / NO / - where a run failed)."""
    cols = ("default", "pmean4", "ci", "msq -s", "lbfgs")
    head = f"{'mesh':28s} {'hexes':>7s}  " + "  ".join(f"{c + ' worst/mean/wall':>26s}" for c in cols) + \
        "  worst  mean  wall"
    lines = [head, "-" * len(head)]

    def cell(f):
        if f is None:
            return f"{'failed':>26s}"
        return f"{_f(f['worst'], '.4g'):>8s}/{_f(f['mean'], '.5g'):>8s}/{_f(f['wall'], '.2f'):>7s}s"

    def mark(t):
        return "-" if t["met"] is None else ("yes" if t["met"] else "NO")

    for info in rows:
        t = info.get("targets") or targets(info)
        lines.append(f"{info['name'][:28]:28s} {info['hexes']:7d}  " + "  ".join(cell(t["runs"][c]) for c in cols)
                     + f"  {mark(t['worst']):>5s} {mark(t['mean']):>5s} {mark(t['wall']):>5s}")
    met = {k: sum(1 for i in rows if (i.get("targets") or targets(i))[k]["met"]) for k in ("worst", "mean", "wall")}
    lines.append(f"targets met: worst {met['worst']}/{len(rows)}, mean {met['mean']}/{len(rows)}, wall "
                 f"{met['wall']}/{len(rows)} (worst within {TARGETS['worst']:.0%} of the best of pmean4, ci and msq "
                 f"-s; mean within {TARGETS['mean']:.0%} of the better of lbfgs and msq -s; cold wall <= "
                 f"{TARGETS['wall']:g}x lbfgs, {TARGETS['wall_large']:g}x on {', '.join(TARGETS['large'])})")
    return "\n".join(lines)


def write_json(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1, default=_jsonable))
    os.replace(tmp, path)


def _jsonable(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON: {type(o).__name__}")


def entries_for(args) -> list:
    all_entries = corpus.entries(args.corpus_dir, args.sizes)
    names, files = [], []
    for n in args.meshes or []:
        (files if os.path.sep in n or os.path.exists(n) else names).append(n)
    chosen = corpus.select(all_entries, names) if names or not files else []
    for f in files:
        p = Path(f).resolve()
        if not p.exists():
            raise SystemExit(f"{f}: no such mesh file")
        chosen.append(corpus.Entry(p.stem, "file", p, f"file {p}"))
    return chosen


def ensure_bytecode(package_dir: Path) -> str:
    """Write the bytecode of every module under `package_dir` where it is missing or stale (``compileall``, which
    writes it whatever ``PYTHONDONTWRITEBYTECODE`` says; Python then reads it): what the runs' start-up sees."""
    import compileall

    ok = compileall.compile_dir(str(package_dir), quiet=1, workers=1)
    return "compiled (compileall)" if ok else "compileall reported errors"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", help="corpus names, sources, gmsh shapes or mesh files (default: the "
                                                "corpus less the optional cube60_pert)")
    ap.add_argument("--method", nargs="+", default=["default"],
                    help="jaxci methods; 'default' = no --method flag, 'pmean4' the p-mean (p = 4); "
                         "NAME:PARAM=VALUE[,PARAM=VALUE] adds --param PARAM=VALUE, e.g. "
                         "default:polish_budget=0.02 (default: %(default)s)")
    ap.add_argument("--jaxci-cmd", default=f"{shlex.quote(sys.executable)} -m jaxci",
                    help="the jaxci command (default: this Python's -m jaxci; or 'jaxci')")
    ap.add_argument("--jaxci-args", default="", help="more flags for every jaxci smooth run, e.g. '--dtype float64'")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per run (default %(default)s)")
    ap.add_argument("--skip-msq", action="store_true", help="do not run msqshape")
    ap.add_argument("--msq-modes", nargs="+", choices=["domain", "free", "skin"], default=["domain", "free"],
                    help="msqshape runs: domain (-s, or box sliding flags), free (no flag), skin (-s everywhere)")
    ap.add_argument("--cold-only", action="store_true", help="jaxci cold runs only (no warm rerun)")
    ap.add_argument("--targets", action="store_true",
                    help="the default pipeline's targets: cold runs of default, lbfgs, pmean4 and ci and msqshape "
                         "-s, then per mesh the targets and whether each holds (implies --cold-only, "
                         "--no-warm-other)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="cold runs of each jaxci method per mesh, the methods alternated; wall times are their "
                         "median (default %(default)s)")
    ap.add_argument("--no-warm-other", action="store_true",
                    help="skip the run warm from another mesh's compile cache")
    ap.add_argument("--similar", type=float, default=3.0,
                    help="warm_other: the other mesh's hex count within this factor (default %(default)s)")
    ap.add_argument("--sizes", nargs="+", default=list(corpus.DEFAULT_SIZES),
                    help=f"gmsh corpus sizes: {', '.join(f'{k}={v}' for k, v in corpus.SIZES.items())} or hex counts")
    ap.add_argument("--corpus-dir", default=str(corpus.DEFAULT_CORPUS_DIR), help="made meshes (default %(default)s)")
    ap.add_argument("--work-dir", help="keep the inputs, outputs and caches here (default: a temporary folder, "
                                       "removed at the end)")
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="JSON path (default %(default)s)")
    ap.add_argument("--no-bytecode", action="store_true",
                    help="do not write jaxci's bytecode first (then, with PYTHONDONTWRITEBYTECODE set, every run "
                         "compiles its sources)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: must be 1 or more")
    if args.targets:
        args.method = list(dict.fromkeys([*TARGET_METHODS, *(m for m in args.method if m != "default")]))
        args.msq_modes = list(TARGET_MSQ)
        args.cold_only = args.no_warm_other = True

    import jax

    jax.config.update("jax_enable_x64", True)  # the yardstick: float64 reports, whatever the size
    import jaxci

    bytecode = "as found" if args.no_bytecode else ensure_bytecode(Path(jaxci.__file__).parent)
    chosen = entries_for(args)
    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="jaxci-realmesh-"))
    work.mkdir(parents=True, exist_ok=True)
    caches = work / "caches"
    doc = dict(benchmark="realmesh", created=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
               **stamp(),
               host=dict(platform=platform.platform(), cpu_count=os.cpu_count(), python=platform.python_version(),
                         jax=jax.__version__, jaxci=getattr(jaxci, "__version__", None)),
               msqshape=str(MSQSHAPE) if MSQSHAPE.exists() else None,
               settings=dict(methods=args.method, jaxci_cmd=args.jaxci_cmd, jaxci_args=args.jaxci_args,
                             timeout_s=args.timeout, msq_modes=[] if args.skip_msq else args.msq_modes,
                             warm_other=not args.no_warm_other, similar=args.similar, sizes=args.sizes,
                             repeats=args.repeats,
                             moved_rel=MOVED_REL, bytecode=bytecode,
                             pythondontwritebytecode=os.environ.get("PYTHONDONTWRITEBYTECODE")),
               notes=[("timings from one run each on this machine" if args.repeats == 1 else
                       f"jaxci's cold wall times the median of {args.repeats} runs, the methods alternated "
                       "(wall_runs: each; msqshape one run)") + "; CPU = user + system of the child (os.wait4), "
                      "peak_rss_mb = its ru_maxrss", "quality measured by jaxci.quality_report (float64) on "
                      "every output file, msqshape's included"],
               meshes=[])
    out = Path(args.out)
    ctxs = {}
    try:
        prepared = []
        for e in chosen:
            print(f"preparing {e.name} ...", flush=True)
            try:
                info, ctx = prepare(e, work)
            except Exception as ex:  # noqa: BLE001 - a mesh that cannot be read is reported, not fatal
                print(f"  {e.name}: cannot prepare: {type(ex).__name__}: {ex}", flush=True)
                doc["meshes"].append(dict(name=e.name, source=e.source, path=str(e.path),
                                          error=f"{type(ex).__name__}: {ex}"))
                continue
            prepared.append(info)
            ctxs[e.name] = ctx
        prepared.sort(key=lambda i: i["hexes"])
        for info in prepared:
            b = info["before"]
            print(f"{info['name']}: {info['hexes']} hexes, {info['nodes']} nodes, {b['inverted_elements']} inverted, "
                  f"max k/3 {_f(b['max_condition'], '.5g')}; msqshape domain {info['msq_domain']}", flush=True)
            bench_mesh(args, info, ctxs[info["name"]], caches)
            doc["meshes"].append(info)
            write_json(out, doc)
        if not args.no_warm_other:
            bench_warm_other(args, prepared, ctxs, caches)
        write_json(out, doc)
    finally:
        if not args.work_dir:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(table([m for m in doc["meshes"] if "error" not in m]))
    if args.targets:
        rows = [m for m in doc["meshes"] if "error" not in m]
        for m in rows:
            m["targets"] = targets(m)
        doc["targets"] = dict(TARGETS, large=list(TARGETS["large"]))
        write_json(out, doc)
        print()
        print(targets_table(rows))
    for m in doc["meshes"]:
        if "error" in m:
            print(f"{m['name']}: not run: {m['error']}")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
