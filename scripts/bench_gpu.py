"""GPU benchmark: the JAX engine on an accelerator beside the host engine on the same machine's CPU, one command.

    python scripts/bench_gpu.py --out bench_gpu.json            # on a GPU machine: at most ~8 minutes
    python scripts/bench_gpu.py --small --out small.json        # the same sections at small sizes (CPU, tests)

Every figure comes from a fresh process (a child of this script, or the ``jaxci`` command itself), so times include
JAX's start; ``cold`` is a process with an empty compilation cache (``JAXCI_CACHE_DIR``), ``warm`` a second
process with the cache the cold one filled (`jaxci.runtime.compile_cache`: nothing traced or compiled anew). The default
sections, in order (each skipped once the time budget ``--budget`` would be overrun; the JSON is rewritten after
each):

1. ``environment``: jax and jaxci versions, the devices, CPU count.
2. ``kernels``: F and its gradient in every kernel form (`scripts/bench_kernel.py`: scatter-add, gather over the
   node incidences, sorted segment sum; the C kernel on a CPU), float32 and float64, at 10^6 and 10^7 hexahedra:
   corners per second, warm.
3. ``smooth``: `jaxci.smooth` (the default pipeline, stopped at max kappa/3 <= 1.0001) on perturbed boxes of 10^6
   and 10^7 hexahedra on the JAX engine, cold then warm: wall time, every phase with its compile seconds, its
   seconds inside compiled programs (``device_s``), its host seconds (``host_s``) and the bytes moved each way
   (``h2d_bytes``, ``d2h_bytes``; `jaxci.runtime.transfer`), the host's share of the wall time, the bytes against the
   mesh's own (float64 coordinates and int64 connectivity), peak device memory per hexahedron.
4. ``engines``: ``jaxci smooth`` (the CLI) at 10^4, 10^5 and 10^6 hexahedra, ``--engine jax`` cold and warm
   against ``--engine host``: the size from which the accelerator wins (`jaxci.interface.engine.ACCELERATOR_FROM`).
5. ``largest``: the largest box that the bytes per hexahedron measured at 10^7 say fits on the device (at most
   10^8 hexahedra), smoothed in a fresh process (cold: a size of its own).

Further sections (``--sections``): ``host_prep`` and ``device_memory`` (`scripts/bench_host_prep.py`,
`scripts/bench_device_memory.py` at 10^6: the host's work by function, the programs' device bytes),
``global_ci`` (30 seeds of cube729 batched against one by one and the host engine), ``cube60_pert`` (the tangled
216,000-hex cube, both engines), ``solvers`` (``jaxci smooth --method lbfgs`` on the JAX engine with
``--param solver=lbfgs`` and ``solver=newton``, cold, on an annulus of 98,304 and 786,432 hexahedra whose nodes
were moved along its curved walls: steps and time of each solver).

The targets of one H100/H200-class GPU are printed beside the figures (F + gradient >= 40 G corners/s float32;
10^7 hexahedra in <= 10 s warm and <= 20 s cold, file I/O aside; <= 1 kB per hexahedron on the device; the JAX
engine faster than the host engine from 10^5 hexahedra warm).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"corners_per_s_float32": 40e9, "smooth_1e7_warm_s": 10.0, "smooth_1e7_cold_s": 20.0,
           "bytes_per_hex": 1000.0, "jax_wins_from_hexes": 100_000}
SECTIONS = ("kernels", "smooth", "engines", "largest")
MORE = ("host_prep", "device_memory", "global_ci", "cube60_pert", "solvers")
FULL = {"kernels": [1_000_000, 10_000_000], "smooth": [100, 215], "engines": [22, 46, 100], "largest": 464,
        "host_prep": [100], "cube": 60, "gci_seeds": 30, "gci_host_seeds": 4, "gci_attempts": None,
        "gci_case": "cube729", "annulus": [(256, 16, 24), (512, 32, 48)]}
SMALL = {"kernels": [1000], "smooth": [8], "engines": [6, 10], "largest": 12, "host_prep": [8], "cube": 9,
         "gci_seeds": 3, "gci_host_seeds": 2, "gci_attempts": 20, "gci_case": "cube27", "annulus": [(24, 3, 3)]}


# ------------------------------------------------------------------------------------------------ children
def _device_peak() -> int | None:
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def _rss_peak() -> int:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def child_kernels(*sizes: int) -> dict:
    """`bench_kernel.run`: F + gradient in every kernel form at `sizes` hexahedra, float32 and float64."""
    from bench_kernel import run

    return run(sizes=sizes, dtypes=("float32", "float64"), rounds=5)


def child_smooth(n: int, engine: str, ktol: float) -> dict:
    """`jaxci.smooth` of a perturbed box of n^3 hexahedra on `engine` in this (fresh) process: wall time, the
    phases (`jaxci.runtime.phases`: compile, device and host seconds, bytes each way), the host's share and the bytes
    against the mesh's own, peak memory."""
    from jaxci.interface import device_run
    from jaxci.interface.smooth import smooth
    from jaxci.mesh.generate import perturb_box

    # the section measures the run on the device; --small's boxes are under its threshold (DEVICE_RUN_FROM)
    device_run.DEVICE_RUN_FROM = min(device_run.DEVICE_RUN_FROM, n ** 3)
    t0 = time.perf_counter()
    mesh = perturb_box(n, amplitude=0.3, seed=0)
    gen = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = smooth(mesh, engine=engine, ktol=ktol)
    wall = time.perf_counter() - t0
    peak = _device_peak() if res.plan.engine == "jax" and res.plan.device != "cpu" else None
    total = res.phases["total"]
    own = mesh.points.nbytes + mesh.hexes.nbytes  # float64 coordinates, int64 connectivity
    return {"hexes": mesh.n_hexes, "engine": res.plan.to_dict(), "generate_s": gen, "wall_s": wall,
            "phases": res.phases, "host_share": total["host_s"] / max(total["seconds"], 1e-9),
            "h2d_per_mesh": total["h2d_bytes"] / own, "d2h_per_mesh": total["d2h_bytes"] / own,
            "iterations": res.iterations, "max_condition": res.after.max_condition,
            "mean_condition": res.after.mean_condition, "inverted": res.after.inverted_elements,
            "device_peak_bytes": peak, "device_bytes_per_hex": None if peak is None else peak / mesh.n_hexes,
            "rss_peak_bytes": _rss_peak()}


def child_global_ci(case: str, seeds: int, engine: str, mode: str, attempts: int | None) -> dict:
    """Global CI on `seeds` seeds of `case`, as `jaxci run` smooths them: ``mode`` "batched" (one program for
    every seed, `jaxci.interface.seeds.smooth_seeds`) or "serial" (`jaxci.smooth` one seed after the other, the same
    compiled program) on the JAX engine, or the host engine per seed. Whole runs: reports and checks included."""
    import jax
    import numpy as np

    from jaxci.interface.seeds import smooth_seeds
    from jaxci.interface.smooth import smooth
    from jaxci.mesh.generate import paper_case

    params = {} if attempts is None else {"attempts": attempts}
    meshes = [paper_case(case, seed=s) for s in range(seeds)]

    def run():
        if mode == "batched":
            return smooth_seeds(meshes, "ci-global", list(range(seeds)), engine=engine, **params)
        return [smooth(m, "ci-global", seed=s, engine=engine, **params) for s, m in enumerate(meshes)]

    t0 = time.perf_counter()
    out = run()
    cold = time.perf_counter() - t0
    warm = None
    if mode == "batched":  # one by one, every seed after the first ran warm already
        t0 = time.perf_counter()
        out = run()
        warm = time.perf_counter() - t0
    plan = out[0].plan
    batched = sum(any("one batched program" in n for n in r.notes) for r in out)
    return {"seeds": seeds, "engine": plan.engine, "device": plan.device if plan.engine == "host" else
            jax.default_backend(), "mode": mode, "batched_seeds": batched, "cold_s": cold, "warm_s": warm,
            "per_seed_s": (cold if warm is None else warm) / seeds,
            "objective_mean": float(np.mean([r.after.objective for r in out])),
            "device_peak_bytes": _device_peak() if plan.engine == "jax" else None}


def child_host_prep(n: int, engine: str) -> dict:
    """`bench_host_prep.run` (the host's work of a run by phase and function, the solver capped at 5 steps) on a
    box of n^3 hexahedra."""
    from bench_host_prep import run

    return run(n ** 3, engine)


def child_device_memory(n: int) -> dict:
    """`bench_device_memory.run`: the presmoothing's and L-BFGS's device bytes per hexahedron (live arrays and
    XLA's memory analysis of each program) on a box of n^3 hexahedra."""
    from bench_device_memory import run

    return run(n ** 3)


CHILDREN = {"kernels": child_kernels, "smooth": child_smooth, "global_ci": child_global_ci,
            "host_prep": child_host_prep, "device_memory": child_device_memory, "environment": None}


# -------------------------------------------------------------------------------------------------- parent
class Bench:
    def __init__(self, args):
        from bench_stamp import commit

        self.args, self.t0 = args, time.perf_counter()
        self.data: dict = {"command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]), "targets": TARGETS,
                           "date": time.strftime("%Y-%m-%d %H:%M:%S"), "commit": commit()}

    def left(self) -> float:
        return self.args.budget - (time.perf_counter() - self.t0)

    def save(self) -> None:
        out = Path(self.args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(out.name + ".tmp")
        tmp.write_text(json.dumps(self.data, indent=1, default=str) + "\n")
        os.replace(tmp, out)

    def child(self, section: str, name: str, *args, timeout: float = 600, cache: str | None = None) -> dict:
        """Run child `name` with `args` in a fresh process (`cache`: its compilation cache folder; default an
        empty one); its JSON, or ``{"error": ...}``."""
        timeout = min(timeout, self.left())
        if timeout < 5:
            return {"skipped": "time budget"}
        cmd = [sys.executable, __file__, "--child", name, *map(str, args)]
        with tempfile.TemporaryDirectory() as empty:
            return _run_json(cmd, timeout, {**self._env(), "JAXCI_CACHE_DIR": cache or empty})

    def cli(self, args: list[str], timeout: float = 600, cache: str | None = None) -> dict:
        """``jaxci ARGS --json`` in a fresh process (`cache`: its compilation cache folder; default an empty one):
        its JSON and wall time."""
        timeout = min(timeout, self.left())
        if timeout < 5:
            return {"skipped": "time budget"}
        with tempfile.TemporaryDirectory() as empty:
            env = {**self._env(), "JAXCI_CACHE_DIR": cache or empty}
            t0 = time.perf_counter()
            out = _run_json([sys.executable, "-m", "jaxci", *args, "--json", "--force"], timeout, env)
            out["process_wall_s"] = time.perf_counter() - t0
        return {k: out[k] for k in ("process_wall_s", "engine", "iterations", "phases", "error", "skipped")
                if k in out} | {key: (out.get("after") or {}).get(key) for key in ("max_condition", "objective")}

    def _env(self) -> dict:
        # each child may take most of the device's memory (one runs at a time; the parent never imports JAX)
        return {**os.environ, "PYTHONUNBUFFERED": "1", "XLA_PYTHON_CLIENT_MEM_FRACTION": "0.95",
                "PYTHONPATH": os.pathsep.join(
            [str(ROOT / "scripts"), str(ROOT / "src"), *filter(None, [os.environ.get("PYTHONPATH")])])}

    def section(self, name: str, rows) -> None:
        self.data[name] = []
        for row in rows:
            self.data[name].append(row)
            self.save()
            print(f"{name}: {json.dumps(row, default=str)[:400]}", flush=True)


def _run_json(cmd, timeout, env) -> dict:
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode not in (0, 3) or not lines:
        return {"error": f"exit {p.returncode}: {(p.stderr or p.stdout)[-1500:]}"}
    return json.loads(lines[-1])


def _annulus(tmp: Path, n_theta: int, n_r: int, n_z: int) -> Path:
    """An annulus of ``n_theta x n_r x n_z`` hexahedra with its nodes moved along its walls and inside (none
    inverted): the boundary stays the two cylinders and the end planes, so its nodes slide on curved walls."""
    import numpy as np

    from jaxci.io import write_mesh
    from jaxci.mesh.shapes import annulus

    path = tmp / f"annulus{n_theta}x{n_r}x{n_z}.vtu"
    if not path.exists():
        m = annulus(n_theta, n_r, n_z)
        p = np.asarray(m.points)
        rng = np.random.default_rng(0)
        r, th, z = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), p[:, 2]
        r = np.where((r > 0.5 + 1e-9) & (r < 1 - 1e-9), r + rng.uniform(-0.15, 0.15, len(r)) / n_r, r)
        th = th + rng.uniform(-0.3, 0.3, len(r)) * 2 * np.pi / n_theta
        z = np.where((z > 1e-9) & (z < 1 - 1e-9), z + rng.uniform(-0.3, 0.3, len(z)) / n_z, z)
        write_mesh(m.with_points(np.stack([r * np.cos(th), r * np.sin(th), z], axis=1)), path)
    return path


def _box(tmp: Path, n: int) -> Path:
    from jaxci.io import write_mesh
    from jaxci.mesh.generate import perturb_box

    path = tmp / f"box{n}.vtu"
    if not path.exists():
        write_mesh(perturb_box(n, amplitude=0.3, seed=0), path)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench_gpu.json")
    ap.add_argument("--small", action="store_true", help="small sizes (a CPU check of the script)")
    ap.add_argument("--budget", type=float, default=480.0, help="seconds for all sections (default 480)")
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=[*SECTIONS, *MORE],
                    help="the sections to run, in this order")
    ap.add_argument("--engines-sizes", type=int, nargs="+", default=None, metavar="N",
                    help="box edges of the engines section (default 22 46 100; --small: 6 10)")
    ap.add_argument("--smooth-sizes", type=int, nargs="+", default=None, metavar="N",
                    help="box edges of the smooth section (default 100 215; --small: 8)")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        name, *rest = args.child
        fn = CHILDREN[name] or child_environment
        conv = [int(a) if a.lstrip("-").isdigit() else (None if a == "None" else a) for a in rest]
        if name == "smooth":
            conv[2] = float(rest[2])
        print(json.dumps(fn(*conv), default=str))
        return 0
    sys.path[:0] = [str(ROOT / "src"), str(ROOT / "scripts")]
    size = dict(SMALL if args.small else FULL)
    if args.engines_sizes:
        size["engines"] = args.engines_sizes
    if args.smooth_sizes:
        size["smooth"] = args.smooth_sizes
    b = Bench(args)
    ktol = 1e-4
    b.data["environment"] = b.child("environment", "environment", timeout=120)
    b.save()
    print("environment:", json.dumps(b.data["environment"]), flush=True)
    gpu = b.data["environment"].get("accelerator") is not None
    with tempfile.TemporaryDirectory() as tmpdir:
        sections = _sections(b, args, size, Path(tmpdir), ktol, gpu)
        for name in args.sections:  # in the order given
            sections[name]()
    b.data["elapsed_s"] = time.perf_counter() - b.t0
    b.save()
    _summary(b.data)
    return 0


def _sections(b: Bench, args, size: dict, tmp: Path, ktol: float, gpu: bool) -> dict:
    """Each section of the benchmark as a function of no arguments (run in the order of ``--sections``)."""

    def kernels():
        b.section("kernels", [b.child("kernels", "kernels", *size["kernels"], timeout=300)])

    def smooth():
        rows = []
        for n in size["smooth"]:
            cache = str(tmp / f"cache-smooth-{n}")
            rows += [("jax", n, "cold", cache), ("jax", n, "warm", cache)]
        rows.append(("host", size["smooth"][0], "-", None))
        b.section("smooth", ({"process": kind, **b.child("smooth", "smooth", n, e, ktol, timeout=300, cache=cache)}
                             for e, n, kind, cache in rows))

    def engines():
        def row(n, e, kind):
            cache = str(tmp / f"cache-engines-{n}")
            return {"hexes": n ** 3, "engine_asked": e, "process": kind,
                    **b.cli(["smooth", str(_box(tmp, n)), str(tmp / f"o{n}{e}.vtu"), "--engine", e], timeout=180,
                            cache=cache if e == "jax" else None)}

        b.section("engines", (row(n, e, kind) for n in size["engines"]
                              for e, kind in (("jax", "cold"), ("jax", "warm"), ("host", "-"))))

    def largest():
        per_hex = max((r.get("device_bytes_per_hex") or 0 for r in b.data.get("smooth", [])), default=0)
        total = ((b.data["environment"] or {}).get("accelerator") or {}).get("bytes_limit") or 0
        if gpu and per_hex and total:
            n = min(int((0.85 * total / per_hex) ** (1 / 3)), size["largest"])
            b.section("largest", [b.child("largest", "smooth", n, "jax", ktol, timeout=600)])

    def global_ci():
        case, seeds, att = size["gci_case"], size["gci_seeds"], size["gci_attempts"]
        b.section("global_ci", (b.child("global_ci", "global_ci", case, k, e, mode, att, timeout=240) for k, e, mode in
                                ((seeds, "jax", "batched"), (seeds, "jax", "serial"),
                                 (size["gci_host_seeds"], "host", "serial"))))

    def cube():
        from realmesh_corpus import perturbed_cube, write_vtk

        path = tmp / "cube_pert.vtk"
        write_vtk(path, *perturbed_cube(size["cube"]))
        b.section("cube60_pert", ({"cube": size["cube"], "engine_asked": e,
                                   **b.cli(["smooth", str(path), str(tmp / f"c{e}.vtk"), "--engine", e], timeout=240)}
                                  for e in ("jax", "host")))

    def solvers():
        def row(dims, solver):
            path = _annulus(tmp, *dims)
            return {"annulus": list(dims), "hexes": dims[0] * dims[1] * dims[2], "solver": solver, "process": "cold",
                    **b.cli(["smooth", str(path), str(tmp / f"a{solver}.vtu"), "--engine", "jax", "--method", "lbfgs",
                             "--param", f"solver={solver}"], timeout=300)}

        b.section("solvers", (row(dims, solver) for dims in size["annulus"] for solver in ("lbfgs", "newton")))

    def host_prep():
        b.section("host_prep", (b.child("host_prep", "host_prep", n, "jax", timeout=300) for n in size["host_prep"]))

    def device_memory():
        b.section("device_memory", (b.child("device_memory", "device_memory", n, timeout=300)
                                    for n in size["host_prep"]))

    return {"kernels": kernels, "smooth": smooth, "engines": engines, "largest": largest, "global_ci": global_ci,
            "cube60_pert": cube, "host_prep": host_prep, "device_memory": device_memory, "solvers": solvers}


def child_environment() -> dict:
    import jax

    import jaxci

    dev = jax.devices()[0]
    acc = None
    if dev.platform != "cpu":
        stats = dev.memory_stats() or {}
        acc = {"platform": dev.platform, "kind": dev.device_kind, "count": len(jax.devices()),
               "bytes_limit": stats.get("bytes_limit")}
    from jaxci import native
    from jaxci.metrics import native_grad

    return {"jax": jax.__version__, "jaxci": jaxci.__version__, "python": sys.version.split()[0],
            "cpus": os.cpu_count(), "accelerator": acc, "default_backend": jax.default_backend(),
            "c_kernels": native.AVAILABLE, "ffi_api": native.ffi_api_version(),
            "ffi_on_cpu": native_grad.available("cpu"), "ffi_refusal": native_grad.refusal()}


def _summary(d: dict) -> None:
    """The figures against the targets, one line each."""
    rows = [r for k in d.get("kernels", []) for r in k.get("rows", [])]
    best32 = max((r["corners_per_s"] for r in rows if r.get("dtype") == "float32"), default=0)
    forms = ", ".join(f"{r['kernel']} {r['corners_per_s'] / 1e9:.2f}" for r in rows
                      if r.get("dtype") == "float32" and r["hexes"] == max(x["hexes"] for x in rows))
    goal = TARGETS["corners_per_s_float32"] / 1e9
    print(f"F + gradient, float32: {best32 / 1e9:.2f} G corners/s (target >= {goal:g}){f' [{forms}]' if forms else ''}")
    for r in d.get("smooth", []):
        if "wall_s" in r:
            t = r["phases"]["total"]
            print(f"smooth {r['hexes']:,} hexes, {r['engine']['name']} on {r['engine']['device']} ({r['process']}): "
                  f"{r['wall_s']:.1f} s, compile {t['compile_seconds']:.1f} s, device {t['device_s']:.1f} s, host "
                  f"{t['host_s']:.1f} s ({100 * r['host_share']:.0f}%), up {r['h2d_per_mesh']:.2f} / down "
                  f"{r['d2h_per_mesh']:.2f} x the mesh, max kappa/3 {r['max_condition']:.6f}, "
                  f"{(r['device_bytes_per_hex'] or 0):.0f} B/hex on the device")
    for r in d.get("engines", []):
        if "process_wall_s" in r:
            print(f"jaxci smooth {r['hexes']:,} hexes --engine {r['engine_asked']} ({r['process']}): "
                  f"{r['process_wall_s']:.1f} s")
    print(f"targets: {TARGETS}")
    print(f"elapsed {d.get('elapsed_s', 0):.0f} s")


if __name__ == "__main__":
    sys.exit(main())
