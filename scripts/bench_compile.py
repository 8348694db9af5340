"""Compilation once per machine: the JAX engine's compile seconds in a fresh process, cold and warm, CLI and library.

    python scripts/bench_compile.py --out results/bench_compile.json          # 10^4 and 10^6 hexahedra
    python scripts/bench_compile.py --small --out small.json                   # a tiny box (a check of the script)
    python scripts/bench_compile.py --src /path/to/other/checkout/src          # another checkout's jaxci

For each box (perturbed, `jaxci.mesh.generate.perturb_box`: 22^3 = 10,648 and 100^3 = 10^6 hexahedra by default) and
each way in, every run a fresh process (a child of this script) on the JAX engine with the default pipeline:

- ``cli``: ``python -m jaxci smooth BOX OUT --engine jax --json`` (its ``phases``: compile seconds, compiled
  programs, persistent-cache hits); wall time of the whole process, start-up and file I/O included;
- ``library``: ``jaxci.smooth(mesh, engine="jax")`` on the generated mesh: its phases, and the compilation split
  into tracing, lowering, XLA compile or cache load, and jaxci's reading and writing of exported programs
  (`jaxci.runtime.transfer.compile_totals`), with `jaxci.runtime.compile_cache.stats` (programs loaded, exported, run
  plain).

``cold``: an empty cache folder (``JAXCI_CACHE_DIR``); ``warm``: a second process with the folder the cold one
filled. ``--off`` adds a run with ``JAXCI_CACHE_DIR=`` (no cache). The JSON has the date, the commit
(`bench_stamp.commit`), the machine and the command; `run` is what `scripts/bench_gpu.py` calls (on a GPU the same
runs go to the accelerator: the plan's device is in each row).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Box edges (n^3 hexahedra): 10^4 and 10^6; --small (a check of the script).
SIZES, SMALL = (22, 100), (4,)


# ------------------------------------------------------------------------------------------------ the child
def child_library(n: int) -> dict:
    """`jaxci.smooth(perturb_box(n), engine="jax")` in this (fresh) process: its figures."""
    import jax

    import jaxci
    from jaxci.mesh.generate import perturb_box
    from jaxci.runtime.phases import compile_totals

    mesh = perturb_box(n, amplitude=0.3, seed=0)
    c0, t0 = compile_totals(), time.perf_counter()
    res = jaxci.smooth(mesh, engine="jax")
    wall, c1 = time.perf_counter() - t0, compile_totals()
    try:
        from jaxci.runtime.compile_cache import stats
    except ImportError:  # a checkout from before the cache
        stats = dict
    total = res.phases["total"]
    return {"wall_s": wall, "compile_seconds": total["compile_seconds"], "compiled": total["compiled"],
            "cache_hits": total["cache_hits"], "split": {k: c1[k] - c0[k] for k in c1 if isinstance(c1[k], float)},
            "exported_programs": stats(), "device": jax.devices()[0].device_kind, "platform": jax.default_backend(),
            "max_condition": res.after.max_condition, "iterations": res.iterations}


# ---------------------------------------------------------------------------------------------- the parent
def _env(src: Path, cache: str | None) -> dict:
    path = [str(src), str(ROOT / "scripts"), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": os.pathsep.join(path)}
    env["JAXCI_CACHE_DIR"] = "" if cache is None else cache
    return env


def _last_json(p: subprocess.CompletedProcess) -> dict:
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode not in (0, 3) or not lines:
        return {"error": f"exit {p.returncode}: {(p.stderr or p.stdout)[-1500:]}"}
    return json.loads(lines[-1])


def _library(src: Path, n: int, cache: str | None, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--child", str(n)]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=_env(src, cache))
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    return {**_last_json(p), "process_wall_s": time.perf_counter() - t0}


def _cli(src: Path, box: Path, out: Path, cache: str | None, timeout: float) -> dict:
    cmd = [sys.executable, "-m", "jaxci", "smooth", str(box), str(out), "--engine", "jax", "--json", "--force"]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=_env(src, cache))
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    wall, doc = time.perf_counter() - t0, _last_json(p)
    if "error" in doc:
        return doc
    total = doc["phases"]["total"]
    return {"process_wall_s": wall, "compile_seconds": total["compile_seconds"], "compiled": total["compiled"],
            "cache_hits": total["cache_hits"], "seconds": total["seconds"],
            "smooth_phase_s": doc["phases"].get("smooth", {}).get("seconds"),
            "device": (doc.get("engine") or {}).get("device"),
            "max_condition": (doc.get("after") or {}).get("max_condition")}


def _load() -> float | None:
    """The 1-minute load average (None where the system has none): a shared machine's timings depend on it."""
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def machine() -> dict:
    """The machine this runs on: host name, CPU model and count, OS (the parent imports no JAX)."""
    model = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), model)
    except OSError:
        pass
    return {"node": platform.node(), "cpu": model, "cpus": os.cpu_count(), "system": platform.platform(),
            "python": platform.python_version()}


def run(sizes=SIZES, src: str | os.PathLike | None = None, off: bool = False, timeout: float = 1800,
        say=print) -> dict:
    """Cold and warm fresh processes, CLI and library, for boxes of ``n^3`` hexahedra for each n of `sizes`
    (``off``: and one with the cache turned off each); every child gets at most `timeout` seconds. The rows,
    stamped with date, commit, machine and command."""
    from bench_stamp import commit

    src = Path(src) if src is not None else ROOT / "src"
    data = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "commit": commit(), "src": str(src), "machine": machine(),
            "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]), "rows": []}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for n in sizes:
            box = tmp / f"box{n}.vtu"
            subprocess.run([sys.executable, "-m", "jaxci", "generate", "box", "--n", str(n), "--amplitude", "0.3",
                            "--seed", "0", str(box)], check=True, capture_output=True, env=_env(src, None))
            for way in ("cli", "library"):
                cache = str(tmp / f"cache-{way}-{n}")
                runs = {"cold": cache, "warm": cache, **({"off": None} if off else {})}
                row = {"hexes": n ** 3, "way": way}
                for name, folder in runs.items():
                    load = _load()
                    row[name] = (_cli(src, box, tmp / f"out{n}.vtu", folder, timeout) if way == "cli"
                                 else _library(src, n, folder, timeout))
                    row[name]["load_average"] = [load, _load()]  # before and after: others' work on the machine
                    say(f"{n ** 3:>9,} hexes  {way:<8} {name:<5} {_line(row[name])}")
                data["rows"].append(row)
    return data


def _line(r: dict) -> str:
    if "error" in r:
        return f"error: {r['error'][-300:]}"
    split = r.get("split")
    parts = f" ({', '.join(f'{k} {v:.2f}' for k, v in split.items())})" if split else ""
    return (f"compile {r['compile_seconds']:.2f} s{parts}, {r['compiled']} compiled / {r['cache_hits']} cache hits, "
            f"process {r['process_wall_s']:.1f} s, load {r['load_average'][0]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench_compile.json")
    ap.add_argument("--small", action="store_true", help=f"a box of {SMALL[0]}^3 (a check of the script)")
    ap.add_argument("--sizes", type=int, nargs="+", metavar="N", help="box edges (default 22 100: 10^4, 10^6)")
    ap.add_argument("--src", help="the jaxci source folder to measure (default: this checkout's src)")
    ap.add_argument("--off", action="store_true", help="also a run with the cache off (JAXCI_CACHE_DIR=)")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per child process (default 1800)")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        print(json.dumps(child_library(args.child), default=str))
        return 0
    sys.path.insert(0, str(ROOT / "scripts"))
    sizes = args.sizes or (SMALL if args.small else SIZES)
    data = run(sizes, args.src, args.off, args.timeout)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1, default=str) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
