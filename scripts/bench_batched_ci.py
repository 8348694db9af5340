"""Global CI on many seeds: one batched program against one seed after the other, through ``jaxci run``.

    python scripts/bench_batched_ci.py [--config configs/paper.yaml] [--mesh cube729] [--out results/batched.json]

From the config (default: the paper reproduction, 30 seeds) it keeps the global CI entries on one mesh and runs
them three ways, each in a fresh ``jaxci run`` process with an empty compilation cache: ``batch_seeds: true``
(the default: `jaxci.interface.engine.BATCH_SEEDS_FROM` or more seeds run as one program on the JAX engine), one seed
after the other on the host engine (``batch_seeds: false``: what ``auto`` picks for one seed on a CPU), and one
seed after the other on the JAX engine (``engine: jax``, ``batch_seeds: false``). It prints and writes the wall
time of each, the engine every run reports, the mean final F per method, and whether the batched runs' meshes
equal the JAX engine's one-by-one runs (their summary F, run by run).
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

import yaml

ROOT = Path(__file__).resolve().parents[1]


def _config(base: dict, mesh: str, batch: bool, engine: str | None) -> dict:
    meshes = [m for m in base["mesh"] if (m.get("name") or (m.get("generate") or {}).get("case")) == mesh]
    methods = [dict(m, **({"engine": engine} if engine else {})) for m in base["methods"]
               if m["method"] == "ci-global" and (not m.get("meshes") or mesh in m["meshes"])]
    for m in methods:
        m.pop("meshes", None)
    out = {k: v for k, v in base.items() if k not in ("mesh", "methods", "report", "output")}
    return {**out, "mesh": meshes, "methods": methods, "batch_seeds": batch, "figures": False, "write_meshes": False}


def run(config: dict, tmp: Path, name: str) -> dict:
    cfg = tmp / f"{name}.yaml"
    cfg.write_text(yaml.safe_dump(config, sort_keys=False))
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "JAXCI_CACHE_DIR": cache}
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "jaxci", "run", str(cfg), "--out", str(tmp / name)],
                           capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
    if p.returncode != 0:
        return {"name": name, "error": p.stderr[-2000:]}
    s = json.loads((tmp / name / "summary.json").read_text())
    runs = s["runs"]
    by = {}
    for r in runs:
        by.setdefault(r["label"], []).append(r["after"]["objective"])
    return {"name": name, "wall_s": wall, "runs": len(runs),
            "engines": sorted({f"{r['engine']['name']}/{r['engine']['device']}" for r in runs}),
            "reasons": sorted({r["engine"]["reason"] for r in runs}),
            "mean_F": {k: sum(v) / len(v) for k, v in by.items()},
            "F": {f"{r['label']}/{r['seed']}": r["after"]["objective"] for r in runs}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "paper.yaml"))
    ap.add_argument("--mesh", default="cube729")
    ap.add_argument("--runs", type=int, default=None, help="seeds (default: the config's)")
    ap.add_argument("--out", default="results/bench_batched_ci.json")
    args = ap.parse_args(argv)
    base = yaml.safe_load(Path(args.config).read_text())
    if args.runs:
        base.pop("seeds", None)
        base["runs"] = args.runs
    rows = []
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        for name, batch, engine in (("batched", True, None), ("host_one_by_one", False, None),
                                    ("jax_one_by_one", False, "jax")):
            row = run(_config(base, args.mesh, batch, engine), tmp, name)
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "F"}), flush=True)
    by = {r["name"]: r for r in rows}
    same = None
    if all("F" in by[k] for k in ("batched", "jax_one_by_one")):
        same = by["batched"]["F"] == by["jax_one_by_one"]["F"]
    data = {"command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]), "date": time.strftime("%Y-%m-%d"),
            "config": args.config, "mesh": args.mesh, "cpus": os.cpu_count(), "rows": rows,
            "batched_equals_jax_one_by_one": same}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(data, indent=1) + "\n")
    for r in rows:
        if "wall_s" in r:
            print(f"{r['name']:>16}: {r['wall_s']:7.1f} s for {r['runs']} runs on {', '.join(r['engines'])}")
    print(f"batched meshes equal the JAX engine's one by one: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
