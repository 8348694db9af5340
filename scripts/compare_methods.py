"""Benchmark: every smoothing method on the same meshes, one table.

Meshes: the paper's three perturbed cubes (`jaxci.paper_case`: cube27, cube64, cube729, sliding boundary) for
`--seeds` seeds, the 9^3 cube perturbed by 0.3 h inside only (seed 0; the L-BFGS target case), Mesquite's
1000hex-block-internal-bias.vtk with its boundary fixed (as in Mesquite's benchmark), and the two tangled Mesquite
meshes (hex_5_tangled.vtk, pave3.e.vtk; untangled first, ``untangle="auto"``).

Per (mesh, method) it reports, over the seeds run: the final max kappa/3 (worst and mean), F (mean), the min
corner scaled Jacobian (worst), inverted elements (worst), iterations (mean; sweeps, attempts or solver steps),
and three times for the first seed:

- ``cold_s``: the first `jaxci.smooth` call in this process for that mesh shape and method (includes tracing
  and XLA compilation);
- ``warm_s``: the same call again, end to end (boundary classification, constraints, colouring, the method,
  the float64 checks and quality reports; compiled code reused), minimum of `--repeats`;
- ``solve_s``: the method alone on a prebuilt `Problem` (`_run_method`), minimum of `--repeats`.

Seeds after the first are run while the cell's time (`--cell-budget` seconds, counted after the first seed's
timings) lasts: the ``seeds`` column says how many ran. A cell whose first run takes over 20 s is timed warm
once. Least-squares methods refuse meshes with more than 1000 free coordinates (shown as ``refused``).

    python scripts/compare_methods.py [--seeds 30] [--methods lbfgs cg] [--meshes cube27 bias] [--dtype float32]
                                      [--out results/compare_methods]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MESQUITE = ROOT.parent / "shared" / "data" / "mesquite"

METHODS = ("ci", "ci-global", "bfgs", "lbfgs", "cg", "lm", "gauss-newton", "laplace", "smart-laplace")
MESHES = ("cube27", "cube64", "cube729", "cube729-interior", "bias", "hex_5_tangled", "pave3")


def mesh_cases(names, seeds):
    """name -> (list of (seed, mesh), smooth keyword arguments, description)."""
    import jaxci
    from jaxci.io import read_mesh

    out = {}
    for name in names:
        if name.startswith("cube") and name in jaxci.PAPER_CASES:
            out[name] = ([(s, jaxci.paper_case(name, seed=s)) for s in range(seeds)], {},
                         f"paper case {name}, sliding boundary, {seeds} seeds")
        elif name == "cube729-interior":
            out[name] = ([(0, jaxci.perturb_box(9, amplitude=0.3, seed=0, which="interior"))], {},
                         "9^3 cube, interior nodes perturbed by 0.3 h, seed 0, sliding boundary")
        elif name == "bias":
            out[name] = ([(0, read_mesh(MESQUITE / "1000hex-block-internal-bias.vtk"))], {"fix_boundary": True},
                         "Mesquite 1000hex-block-internal-bias.vtk, boundary fixed")
        elif name in ("hex_5_tangled", "pave3"):
            fname = "hex_5_tangled.vtk" if name == "hex_5_tangled" else "pave3.e.vtk"
            out[name] = ([(0, read_mesh(MESQUITE / fname))], {"untangle": "auto"},
                         f"Mesquite {fname}, tangled: untangled first")
        else:
            raise SystemExit(f"unknown mesh {name!r}; choose from {', '.join(MESHES)}")
    return out


def run_cell(method, cases, kwargs, dtype, repeats, budget):
    import jax

    from jaxci.errors import ConfigError, InvertedMeshError
    from jaxci.smooth import _run_method, build_problem, smooth

    rows = []
    cold = warm = solve = None
    t_cell = time.perf_counter()
    for i, (seed, mesh) in enumerate(cases):
        if i and time.perf_counter() - t_cell > budget:  # the clock starts after the first seed's timings
            break
        t0 = time.perf_counter()
        try:
            res = smooth(mesh, method, seed=seed, dtype=dtype, **kwargs)
        except ConfigError as e:
            return {"status": "refused", "reason": str(e)}
        except InvertedMeshError as e:
            return {"status": "failed", "reason": str(e)}
        t1 = time.perf_counter() - t0
        if i == 0:
            cold = t1
            def again(mesh=mesh, seed=seed):
                smooth(mesh, method, seed=seed, dtype=dtype, **kwargs)

            reps = repeats if t1 < 20 else 1  # a slow cell: one warm run is enough
            warm = min(_timed(again) for _ in range(reps))
            if not kwargs.get("untangle"):  # solve_s: the method alone (not defined with an untangling stage)
                with jax.enable_x64(dtype == "float64"):
                    pr = build_problem(mesh, dtype=np.float32 if dtype == "float32" else np.float64,
                                       fix_boundary=kwargs.get("fix_boundary", False))
                    key = jax.random.key(seed, impl="rbg")

                    def go(pr=pr, key=key):
                        x = _run_method(pr, method, key, {})[0]
                        jax.block_until_ready(x)

                    go()
                    solve = min(_timed(go) for _ in range(reps))
            t_cell = time.perf_counter()
        a = res.after
        rows.append({"seed": seed, "max_condition": a.max_condition, "objective": a.objective,
                     "min_scaled_jacobian": a.min_scaled_jacobian, "inverted_elements": a.inverted_elements,
                     "iterations": res.iterations, "wall_s": t1, "notes": list(res.notes),
                     "before_max_condition": res.before.max_condition, "before_objective": res.before.objective})
    k = [r["max_condition"] if r["max_condition"] is not None else np.inf for r in rows]
    f = [r["objective"] if r["objective"] is not None else np.inf for r in rows]
    return {
        "status": "ok", "seeds": len(rows), "max_condition_worst": float(np.max(k)),
        "max_condition_mean": float(np.mean(k)), "objective_mean": float(np.mean(f)),
        "objective_std": float(np.std(f)),
        "min_scaled_jacobian_worst": float(min(r["min_scaled_jacobian"] for r in rows)),
        "inverted_elements_worst": int(max(r["inverted_elements"] for r in rows)),
        "iterations_mean": float(np.mean([r["iterations"] for r in rows])),
        "cold_s": cold, "warm_s": warm, "solve_s": solve, "runs": rows,
    }


def _timed(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def markdown(results, meta) -> str:
    lines = [
        f"# compare_methods ({meta['dtype']}, {meta['machine']}, {meta['cpus']} CPUs, jax {meta['jax']})",
        "",
        "| mesh | method | seeds | max k/3 worst | max k/3 mean | F mean | min SJ worst | inverted | iters mean | "
        "cold s | warm s | solve s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def fmt(v, spec):
        return "-" if v is None else format(v, spec)

    for r in results:
        c = r["result"]
        if c["status"] != "ok":
            lines.append(f"| {r['mesh']} | {r['method']} | - | {c['status']} | | | | | | | | |")
            continue
        lines.append(
            f"| {r['mesh']} | {r['method']} | {c['seeds']} | {c['max_condition_worst']:.6f} | "
            f"{c['max_condition_mean']:.6f} | {c['objective_mean']:.3g} | {c['min_scaled_jacobian_worst']:.4f} | "
            f"{c['inverted_elements_worst']} | {c['iterations_mean']:.1f} | {fmt(c['cold_s'], '.2f')} | "
            f"{fmt(c['warm_s'], '.3f')} | {fmt(c['solve_s'], '.3f')} |"
        )
    lines += ["", "Meshes:"] + [f"- {k}: {v}" for k, v in meta["meshes"].items()]
    refused = [r for r in results if r["result"]["status"] != "ok"]
    if refused:
        lines += ["", "Not run:"] + [f"- {r['mesh']} / {r['method']}: {r['result']['reason']}" for r in refused]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=30, help="seeds per paper cube (default 30)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--meshes", nargs="+", default=list(MESHES), choices=MESHES)
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--repeats", type=int, default=3, help="warm repetitions (minimum reported)")
    ap.add_argument("--cell-budget", type=float, default=30.0,
                    help="seconds per (mesh, method) after which no further seed is started")
    ap.add_argument("--out", default=str(ROOT / "results" / "compare_methods"), help="output path without suffix")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    import jax

    cases = mesh_cases(args.meshes, args.seeds)
    meta = {"dtype": args.dtype, "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "jax": jax.__version__, "python": sys.version.split()[0],
            "meshes": {k: v[2] for k, v in cases.items()}, "cell_budget_s": args.cell_budget}
    results = []
    for name, (meshes, kwargs, _) in cases.items():
        for method in args.methods:
            print(f"{name} / {method} ...", file=sys.stderr, flush=True)
            c = run_cell(method, meshes, kwargs, args.dtype, args.repeats, args.cell_budget)
            results.append({"mesh": name, "method": method, "smooth_kwargs": kwargs, "result": c})
            if c["status"] == "ok":
                print(f"  max k/3 {c['max_condition_worst']:.6f}  iters {c['iterations_mean']:.0f}  cold "
                      f"{c['cold_s']:.2f} s  warm {c['warm_s']:.3f} s", file=sys.stderr, flush=True)
            else:
                print(f"  {c['status']}", file=sys.stderr, flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "results": results}, indent=1, default=float))
    md = markdown(results, meta)
    out.with_suffix(".md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
