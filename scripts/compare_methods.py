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
- ``solve_s``: the method alone on a prebuilt `Problem` (`run_method`), minimum of `--repeats`.

Seeds after the first are run while the cell's time (`--cell-budget` seconds, counted after the first seed's
timings) lasts: the ``seeds`` column says how many ran. A cell whose first run takes over 20 s is timed warm
once. Least-squares methods refuse meshes with more than 1000 free coordinates (shown as ``refused``).

    python scripts/compare_methods.py [--seeds 30] [--methods lbfgs cg] [--meshes cube27 bias] [--dtype float32]
                                      [--out results/compare_methods]

Method labels beyond `jaxci.smooth`'s methods: ``auto`` (the default pipeline) and ``lbfgs-pmean`` (L-BFGS on the
p-mean objective, ``objective="pmean"``, ``p`` = `--pmean-p`, default 2).

``--corpus``: the real-mesh corpus of `scripts/bench_realmesh.py` instead (`scripts/realmesh_corpus.py`: Mesquite's
meshFiles, the perturbed peer cubes, the ANSYS archives of ``mapdl-archive``, the gmsh-made meshes at `--sizes`,
default ``small``; `--meshes` then takes corpus names or sources), each mesh as `jaxci smooth` takes it by default
(sliding boundary, ``untangle="auto"``, ``keep_worst=True``), one seed (0). Default methods: auto, lbfgs,
lbfgs-pmean, cg, smart-laplace, ci (local CI capped at `--ci-max-sweeps` sweeps). Every row reports before AND
after: max and mean kappa/3, inverted elements, F, min scaled Jacobian; iterations, wall seconds of the call (in
one worker process: compilation included the first time a shape is met; ``compile_s`` says how much) and the
notes (an iteration cap that stopped a method, untangling, the worst-element guard). Each call runs in a worker
process: one that runs past `--cell-timeout` seconds is killed and its cell marked ``timeout`` (a fresh worker
takes the next cell). A mesh that cannot be untangled is a ``failed`` row; a least-squares refusal ``refused``.

    python scripts/compare_methods.py --corpus [--sizes small] [--meshes mesquite cdb-HexBeam ...]
        [--methods auto lbfgs lbfgs-pmean cg smart-laplace ci] [--ci-max-sweeps 100] [--cell-timeout 120]
        [--out docs/results/compare_methods_realmesh]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MESQUITE = ROOT.parent / "shared" / "data" / "mesquite"

METHODS = ("ci", "ci-global", "bfgs", "lbfgs", "cg", "lm", "gauss-newton", "laplace", "smart-laplace")
MESHES = ("cube27", "cube64", "cube729", "cube729-interior", "bias", "hex_5_tangled", "pave3")
#: Row labels that are not `jaxci.smooth` method names: label -> (method, parameters).
VARIANTS = {"lbfgs-pmean": ("lbfgs", {"objective": "pmean"})}
ALL_METHODS = ("auto", *METHODS, *VARIANTS)
CORPUS_METHODS = ("auto", "lbfgs", "lbfgs-pmean", "cg", "smart-laplace", "ci")


def method_of(label: str, pmean_p: float = 2.0) -> tuple[str, dict]:
    """Row label -> (`jaxci.smooth` method, its parameters)."""
    if label in VARIANTS:
        method, params = VARIANTS[label]
        params = dict(params)
        if params.get("objective") == "pmean":
            params["p"] = pmean_p
        return method, params
    return label, {}


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


def run_cell(label, cases, kwargs, dtype, repeats, budget, pmean_p=2.0):
    import jax

    from jaxci.errors import ConfigError, InvertedMeshError
    from jaxci.interface.smooth import auto_pipeline, build_problem, run_method, smooth

    method, params = method_of(label, pmean_p)
    kwargs = {**kwargs, **params}
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
                    run_m, run_p = (auto_pipeline(mesh.n_hexes, params)[:2] if method == "auto"
                                    else (method, params))

                    def go(pr=pr, seed=seed, run_m=run_m, run_p=run_p):
                        x = run_method(pr, run_m, seed, run_p)[0]
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


# ------------------------------------------------------------------------------------------------ --corpus
QUALITY_KEYS = ("max_condition", "mean_condition", "inverted_elements", "objective", "min_scaled_jacobian")


def _corpus_module():
    """`scripts/realmesh_corpus.py`, imported as `scripts/bench_realmesh.py` imports it."""
    here = str(Path(__file__).resolve().parent)
    if here not in sys.path:
        sys.path.insert(0, here)
    import realmesh_corpus

    return realmesh_corpus


def _num(v):
    """A JSON-ready number: None for a missing or non-finite one (an inverted input has no finite max kappa/3)."""
    if v is None:
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    v = float(v)
    return v if np.isfinite(v) else None


def _report(q) -> dict:
    return {k: _num(getattr(q, k, None)) for k in QUALITY_KEYS}


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, (str, bool)) or o is None:
        return o
    if isinstance(o, (int, float, np.integer, np.floating)):
        return _num(o)
    return str(o)


def corpus_job(job: dict) -> dict:
    """One job of the worker: ``{"kind": "describe", "path"}`` -> hexes, nodes and the input's quality (float64);
    ``{"kind": "smooth", "path", "method", "params", "dtype"}`` -> one `jaxci.smooth` call, before and after."""
    import jax

    from jaxci.errors import ConfigError, InvertedMeshError, JaxciError
    from jaxci.interface.smooth import smooth
    from jaxci.io import read_mesh
    from jaxci.metrics.report import quality_report

    mesh = read_mesh(job["path"])
    if job["kind"] == "describe":
        with jax.enable_x64(True):
            rep = quality_report(mesh)
        return {"hexes": int(mesh.n_hexes), "nodes": int(mesh.n_nodes), "before": _report(rep)}
    t0 = time.perf_counter()
    try:
        res = smooth(mesh, job["method"], seed=0, dtype=job["dtype"], **job["params"])
    except ConfigError as e:
        return {"status": "refused", "reason": str(e), "wall_s": time.perf_counter() - t0}
    except InvertedMeshError as e:
        return {"status": "failed", "reason": str(e), "wall_s": time.perf_counter() - t0}
    except (JaxciError, ValueError, RuntimeError, FloatingPointError, MemoryError) as e:
        return {"status": "error", "reason": f"{type(e).__name__}: {e}", "wall_s": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    notes = [str(n) for n in res.notes]
    total = (res.phases or {}).get("total", {})
    return {"status": "ok", "before": _report(res.before), "after": _report(res.after),
            "iterations": int(res.iterations), "wall_s": wall, "compile_s": _num(total.get("compile_seconds")),
            "capped": any("stopped at its cap" in n for n in notes), "notes": notes,
            "params": _jsonable(res.params)}


def _worker_main(conn) -> None:
    """The worker process: runs jobs from `conn` until it is sent None."""
    warnings.simplefilter("ignore")
    while True:
        job = conn.recv()
        if job is None:
            return
        try:
            out = corpus_job(job)
        except Exception as e:  # noqa: BLE001 - a crashed cell is a row, not the end of the run
            out = {"status": "error", "reason": f"{type(e).__name__}: {e}"}
        conn.send(out)


class Worker:
    """A process that runs `corpus_job`s one at a time; one that runs past its timeout is killed (and the next
    job starts a fresh one: it pays the imports and compilations again)."""

    def __init__(self):
        self.proc = self.conn = None

    def run(self, job: dict, timeout: float) -> dict | None:
        """The job's result, or None if it ran past `timeout` seconds (or the worker died)."""
        import multiprocessing as mp

        if self.proc is None or not self.proc.is_alive():
            ctx = mp.get_context("spawn")  # no fork of a process that may hold JAX's threads
            self.conn, child = ctx.Pipe()
            self.proc = ctx.Process(target=_worker_main, args=(child,), daemon=True)
            self.proc.start()
            child.close()
        self.conn.send(job)
        try:
            if self.conn.poll(timeout):
                return self.conn.recv()
        except (EOFError, OSError):
            pass
        self.kill()
        return None

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.join()
            self.conn.close()
        self.proc = self.conn = None

    def close(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            try:
                self.conn.send(None)
                self.proc.join(timeout=30)
            except (OSError, BrokenPipeError):
                pass
        self.kill()


def corpus_rows(entries, labels, dtype, timeout, ci_max_sweeps, pmean_p, log=print) -> list[dict]:
    """One row per (corpus entry, method label)."""
    worker = Worker()
    rows = []
    try:
        for e in entries:
            path = str(e.ensure())
            info = worker.run({"kind": "describe", "path": path}, timeout)
            if info is None or "before" not in info:
                log(f"{e.name}: could not be read: {info and info.get('reason')}")
                for label in labels:
                    rows.append({"mesh": e.name, "source": e.source, "path": path, "method": label,
                                 "status": "error", "reason": f"mesh not read: {info and info.get('reason')}"})
                continue
            for label in labels:
                method, params = method_of(label, pmean_p)
                if method == "ci":
                    params["max_sweeps"] = ci_max_sweeps
                row = {"mesh": e.name, "source": e.source, "path": path, "hexes": info["hexes"],
                       "nodes": info["nodes"], "method": label, "jaxci_method": method, "method_params": params}
                t0 = time.perf_counter()
                r = worker.run({"kind": "smooth", "path": path, "method": method, "params": params, "dtype": dtype},
                               timeout)
                if r is None:
                    r = {"status": "timeout", "wall_s": time.perf_counter() - t0,
                         "reason": f"ran past the cell timeout of {timeout:g} s: killed, skipped"}
                row.update(r)
                row.setdefault("before", info["before"])
                rows.append(row)
                log(_row_line(row))
    finally:
        worker.close()
    return rows


def _f(v, spec=".6f", none="-"):
    return none if v is None else format(v, spec)


def _row_line(r) -> str:
    b, a = r.get("before") or {}, r.get("after") or {}
    head = f"{r['mesh']:28s} {r['method']:14s}"
    if r["status"] != "ok":
        return f"{head} {r['status']}: {str(r.get('reason', ''))[:100]}"
    return (f"{head} max k/3 {_f(b['max_condition'])} -> {_f(a['max_condition'])}  mean "
            f"{_f(b['mean_condition'])} -> {_f(a['mean_condition'])}  inv {b['inverted_elements']}->"
            f"{a['inverted_elements']}  it {r['iterations']}  {r['wall_s']:.2f} s" + ("  CAP" if r["capped"] else ""))


def _tags(r) -> str:
    """Short notes for the table (the full ones are in the JSON)."""
    if r["status"] != "ok":
        return r["status"]
    tags = []
    notes = " ".join(r.get("notes", []))
    if r.get("capped"):
        cap = re.search(r"stopped at its cap of (\d+) iterations \((\w+)\)", notes)
        tags.append(f"stopped at cap ({cap.group(2)}={cap.group(1)})" if cap else "stopped at cap")
    if (r["before"].get("inverted_elements") or 0) > 0:
        tags.append("untangled")
    back = re.search(r"(\d+) nodes put back", notes)
    if back:
        tags.append(f"worst-element guard put {back.group(1)} nodes back")
    if "the input is returned" in notes:
        tags.append("input returned (F rose)")
    return "; ".join(tags)


def corpus_markdown(rows, meta) -> str:
    lines = [
        f"# compare_methods --corpus ({meta['dtype']}, {meta['machine']}, {meta['cpus']} CPUs, jax {meta['jax']})",
        "",
        f"Corpus of `scripts/bench_realmesh.py` (sizes {', '.join(meta['sizes'])}), `jaxci.smooth` defaults "
        f"(sliding boundary, untangle auto, keep_worst), seed 0. local CI capped at {meta['ci_max_sweeps']} "
        f"sweeps; lbfgs-pmean: L-BFGS with objective pmean, p = {meta['pmean_p']:g}; cell timeout "
        f"{meta['cell_timeout_s']:g} s. max/mean k/3: `QualityReport.max_condition` / `mean_condition`, corner "
        "kappa/3 of the hexahedra over their valid corners (an inverted input's 'before' leaves its inverted "
        "corners out; other cell types are not in these figures). Wall seconds are one call each (compilation "
        "included where a shape is met first; `compile s` is that part), measured on a shared machine: noisy."
        + (f" Whole run: {meta['total_wall_s']:.0f} s." if meta.get("total_wall_s") else "")
        + (f" Code: {meta['git']}." if meta.get("git") else ""),
        "",
        "| mesh | hexes | method | inverted before -> after | max k/3 before | max k/3 after | mean k/3 before | "
        "mean k/3 after | iters | wall s | compile s | notes |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        b, a = r.get("before") or {}, r.get("after") or {}
        inv_b = b.get("inverted_elements")
        if r["status"] != "ok":
            lines.append(f"| {r['mesh']} | {r.get('hexes', '-')} | {r['method']} | {_f(inv_b, 'd')} -> - | "
                         f"{_f(b.get('max_condition'))} | - | {_f(b.get('mean_condition'))} | - | - | "
                         f"{_f(r.get('wall_s'), '.1f')} | - | {r['status']} |")
            continue
        lines.append(
            f"| {r['mesh']} | {r['hexes']} | {r['method']} | {_f(inv_b, 'd')} -> {a['inverted_elements']} | "
            f"{_f(b['max_condition'])} | {_f(a['max_condition'])} | {_f(b['mean_condition'])} | "
            f"{_f(a['mean_condition'])} | {r['iterations']} | {r['wall_s']:.2f} | {_f(r.get('compile_s'), '.2f')} | "
            f"{_tags(r)} |")
    best = best_per_mesh(rows)
    if best:
        lines += ["", "Best per mesh (after; ties within 1e-4 listed together):", "",
                  "| mesh | best max k/3 | by | best mean k/3 | by |", "|---|---|---|---|---|"]
        for m, d in best.items():
            lines.append(f"| {m} | {d['max'][0]:.6f} | {', '.join(d['max'][1])} | {d['mean'][0]:.6f} | "
                         f"{', '.join(d['mean'][1])} |")
    pm = pmean_vs_lbfgs(rows)
    if pm:
        lines += ["", "lbfgs-pmean against lbfgs (after; negative: lower, better):", "",
                  "| mesh | max k/3 lbfgs | max k/3 lbfgs-pmean | change | mean k/3 lbfgs | mean k/3 lbfgs-pmean | "
                  "change |", "|---|---|---|---|---|---|---|"]
        for m, (a, b) in pm.items():
            lines.append(f"| {m} | {a['max_condition']:.6f} | {b['max_condition']:.6f} | "
                         f"{b['max_condition'] - a['max_condition']:+.6f} | {a['mean_condition']:.6f} | "
                         f"{b['mean_condition']:.6f} | {b['mean_condition'] - a['mean_condition']:+.6f} |")
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        lines += ["", "Not run to the end:"] + [f"- {r['mesh']} / {r['method']}: {r['status']}: "
                                                f"{str(r.get('reason', '')).splitlines()[0][:300]}" for r in bad]
    return "\n".join(lines) + "\n"


def pmean_vs_lbfgs(rows) -> dict:
    """mesh -> (lbfgs after, lbfgs-pmean after) where both ran without inverted elements left."""
    def after(m, label):
        r = next((r for r in rows if r["mesh"] == m and r["method"] == label), None)
        if r is None or r["status"] != "ok" or r["after"]["inverted_elements"] or r["after"]["max_condition"] is None:
            return None
        return r["after"]

    out = {}
    for m in dict.fromkeys(r["mesh"] for r in rows):
        a, b = after(m, "lbfgs"), after(m, "lbfgs-pmean")
        if a is not None and b is not None:
            out[m] = (a, b)
    return out


def best_per_mesh(rows, tol=1e-4) -> dict:
    """mesh -> {"max": (value, [methods]), "mean": (value, [methods])} over its rows that ran without inverted
    elements left."""
    out = {}
    for m in dict.fromkeys(r["mesh"] for r in rows):
        ok = [r for r in rows if r["mesh"] == m and r["status"] == "ok" and r["after"]["inverted_elements"] == 0
              and r["after"]["max_condition"] is not None]
        if not ok:
            continue
        d = {}
        for key, name in (("max_condition", "max"), ("mean_condition", "mean")):
            v = min(r["after"][key] for r in ok)
            d[name] = (v, [r["method"] for r in ok if r["after"][key] <= v + tol])
        out[m] = d
    return out


def _write(out: Path, doc: str, md: str) -> None:
    """`out` .json and .md, each written atomically (`jaxci.experiments.results.write_text`)."""
    from jaxci.experiments.results import write_text

    write_text(out.with_suffix(".json"), doc)
    write_text(out.with_suffix(".md"), md)


def _git_state() -> str | None:
    """``<commit>`` of the checkout, ``+ uncommitted changes under src/`` when there are some; None without git."""
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src"], cwd=ROOT, capture_output=True,
                               text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (head + (" + uncommitted changes under src/" if dirty else "")) or None


def corpus_main(args) -> None:
    corpus = _corpus_module()
    import jax

    labels = args.methods or list(CORPUS_METHODS)
    chosen = corpus.select(corpus.entries(args.corpus_dir, args.sizes), args.meshes)
    if not corpus.have_gmsh():
        print("note: gmsh is not installed: no gmsh meshes", file=sys.stderr)
    meta = {"mode": "corpus", "dtype": args.dtype, "machine": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(), "jax": jax.__version__, "python": sys.version.split()[0],
            "sizes": list(args.sizes), "ci_max_sweeps": args.ci_max_sweeps, "pmean_p": args.pmean_p,
            "cell_timeout_s": args.cell_timeout, "methods": labels,
            "meshes": {e.name: f"{e.source}: {e.description}" for e in chosen},
            "command": "python scripts/compare_methods.py " + " ".join(sys.argv[1:]), "git": _git_state()}
    t0 = time.perf_counter()
    rows = corpus_rows(chosen, labels, args.dtype, args.cell_timeout, args.ci_max_sweeps, args.pmean_p,
                       log=lambda s: print(s, file=sys.stderr, flush=True))
    meta["total_wall_s"] = time.perf_counter() - t0
    md = corpus_markdown(rows, meta)
    _write(Path(args.out), json.dumps(_jsonable({"meta": meta, "results": rows}), indent=1) + "\n", md)
    print(md)


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
    ap.add_argument("--corpus", action="store_true",
                    help="run on the real-mesh corpus of scripts/bench_realmesh.py (before and after per method)")
    ap.add_argument("--seeds", type=int, default=30, help="seeds per paper cube (default 30)")
    ap.add_argument("--methods", nargs="+", default=None, choices=ALL_METHODS,
                    help=f"default: {' '.join(METHODS)}; with --corpus: {' '.join(CORPUS_METHODS)}")
    ap.add_argument("--meshes", nargs="+", default=None,
                    help=f"default: {' '.join(MESHES)}; with --corpus: corpus names or sources (default: all but "
                         "the optional ones; python scripts/realmesh_corpus.py --list)")
    ap.add_argument("--sizes", nargs="+", default=["small"], help="--corpus: gmsh mesh sizes (default small)")
    ap.add_argument("--corpus-dir", default=None,
                    help="--corpus: where made meshes go (default ~/.cache/jaxci/realmesh)")
    ap.add_argument("--ci-max-sweeps", type=int, default=100, help="--corpus: local CI's sweep cap (default 100)")
    ap.add_argument("--pmean-p", type=float, default=2.0, help="p of lbfgs-pmean (default 2)")
    ap.add_argument("--cell-timeout", type=float, default=120.0,
                    help="--corpus: seconds after which a (mesh, method) call is killed and marked timeout")
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--repeats", type=int, default=3, help="warm repetitions (minimum reported)")
    ap.add_argument("--cell-budget", type=float, default=30.0,
                    help="seconds per (mesh, method) after which no further seed is started")
    ap.add_argument("--out", default=None, help="output path without suffix (default results/compare_methods, "
                                                 "with --corpus results/compare_methods_realmesh)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    if args.corpus:
        args.out = args.out or str(ROOT / "results" / "compare_methods_realmesh")
        corpus_main(args)
        return
    args.out = args.out or str(ROOT / "results" / "compare_methods")
    args.methods = args.methods or list(METHODS)
    args.meshes = args.meshes or list(MESHES)
    import jax

    cases = mesh_cases(args.meshes, args.seeds)
    meta = {"dtype": args.dtype, "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "jax": jax.__version__, "python": sys.version.split()[0],
            "meshes": {k: v[2] for k, v in cases.items()}, "cell_budget_s": args.cell_budget}
    results = []
    for name, (meshes, kwargs, _) in cases.items():
        for method in args.methods:
            print(f"{name} / {method} ...", file=sys.stderr, flush=True)
            c = run_cell(method, meshes, kwargs, args.dtype, args.repeats, args.cell_budget, args.pmean_p)
            results.append({"mesh": name, "method": method, "smooth_kwargs": kwargs, "result": c})
            if c["status"] == "ok":
                print(f"  max k/3 {c['max_condition_worst']:.6f}  iters {c['iterations_mean']:.0f}  cold "
                      f"{c['cold_s']:.2f} s  warm {c['warm_s']:.3f} s", file=sys.stderr, flush=True)
            else:
                print(f"  {c['status']}", file=sys.stderr, flush=True)
    md = markdown(results, meta)
    _write(Path(args.out), json.dumps({"meta": meta, "results": results}, indent=1, default=float), md)
    print(md)


if __name__ == "__main__":
    main()
