"""`jaxci.experiments.report`: the summary of an experiment, its CSV, and ``report.md`` in the layout of the paper's
Tables.

The paper (Sapre, Kulkarni, Shinde, "Finite Element Mesh Smoothing Using Cohort Intelligence") reports:

- Table 1: corners of the 27-element cube per kappa/3 bin (`jaxci.metrics.report.HISTOGRAM_EDGES`), originally,
  after stage 1 (roulette-wheel following) and after stage 2 (everyone follows the best);
- Table 2: max kappa/3 of each case before and after;
- Table 3: worst / best / mean max kappa/3 over 30 runs and the standard deviation of F.

`render_report` puts our figures beside those numbers (`PAPER_TABLE1` ... `PAPER_TABLE3`). Our aggregates
per (mesh, method) are over the seeds of the experiment; the standard deviation is the sample one (N - 1,
MATLAB's ``std``, which the paper used), 0 for a single run.

It also holds the output side of `jaxci.experiments.runner.run_experiment`: the `RunRecord` of a run, strict JSON
(`json_ready`) and the smoothed meshes with their quality fields (`annotated_mesh`, `write_vtus`); the output
folder itself (atomic, never losing earlier results) is `jaxci.experiments.results`.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import platform
import statistics
import warnings
from pathlib import Path

import numpy as np

from ..metrics.report import HISTOGRAM_EDGES

#: Table 1 of the paper: corner counts of the 27-element cube per kappa/3 bin.
PAPER_TABLE1 = {
    "original": (35, 82, 56, 16, 11, 12, 4),
    "stage 1": (79, 93, 42, 2, 0, 0, 0),
    "stage 2": (216, 0, 0, 0, 0, 0, 0),
}

#: Table 2 of the paper: max kappa/3 before and after, per case.
PAPER_TABLE2 = {
    "cube27": (510.1303, 1.0117),
    "cube64": (26.0429, 1.2136),
    "cube729": (12.1118, 1.7188),
}

#: Table 3 of the paper over 30 runs: worst, best, mean max kappa/3 and the standard deviation of F.
PAPER_TABLE3 = {
    "cube27": (1.0117, 1.0014, 1.0065, 0.001429098),
    "cube64": (1.2136, 1.0045, 1.1041, 0.006551462),
    "cube729": (1.7188, 1.0216, 1.3702, 0.00012563),
}


def bin_labels() -> list[str]:
    """The Table 1 bin names, ``1-1.5`` ... ``8+``."""
    e = HISTOGRAM_EDGES
    return [f"{e[i]:g}-{e[i + 1]:g}" if math.isfinite(e[i + 1]) else f"{e[i]:g}+" for i in range(len(e) - 1)]


def _stats(values):
    v = [x for x in values if x is not None]
    if not v:
        return None, None, None
    return max(v), min(v), sum(v) / len(v)


def aggregate(records) -> list[dict]:
    """Per (mesh, method label), over the seeds: worst / best / mean final max kappa/3, mean and std of F,
    median wall time, mean iterations, mean input max kappa/3; counts of runs and failures."""
    groups: dict[tuple[str, str], list] = {}
    for r in records:
        groups.setdefault((r.mesh, r.label), []).append(r)
    out = []
    for (mesh, label), rs in groups.items():
        ok = [r for r in rs if r.status == "ok"]
        kappa = [r.after["max_condition"] for r in ok]
        f = [r.after["objective"] for r in ok if r.after["objective"] is not None]
        worst, best, mean = _stats(kappa)
        out.append({
            "mesh": mesh,
            "method": label,
            "algorithm": rs[0].method,
            "runs": len(rs),
            "failed": len(rs) - len(ok),
            "worst_max_condition": worst,
            "best_max_condition": best,
            "mean_max_condition": mean,
            "mean_objective": sum(f) / len(f) if f else None,
            "std_objective": (statistics.stdev(f) if len(f) > 1 else 0.0) if f else None,
            "median_wall_time": statistics.median(r.wall_time for r in ok) if ok else None,
            "mean_iterations": sum(r.iterations for r in ok) / len(ok) if ok else None,
            "mean_before_max_condition": _stats(r.before["max_condition"] for r in ok)[2],
        })
    return out


def build_summary(exp, records, *, partial: bool, total_runs: int, elapsed: float) -> dict:
    """The ``summary.json`` object: config echo, versions, the machine (``device``: what was asked for, the
    accelerator JAX sees if any, the CPU), per-run records (each with the engine that ran it: ``engine``, a
    `jaxci.interface.engine.Plan` dict) and aggregates."""
    import importlib.metadata

    from .. import __version__
    from ..interface.engine import accelerator, cpu_model

    cfg, acc = exp.config, accelerator()
    return {
        "partial": partial,
        "runs_done": len(records),
        "runs_planned": total_runs,
        "config_file": str(exp.path),
        "config": cfg.model_dump(mode="json"),
        "seeds": list(exp.seeds),
        "meshes": [{"name": m.name, "file": str(m.path) if m.path else None, "paper_case": m.paper_case}
                   for m in exp.meshes],
        "methods": [{"name": m.label, "method": m.method, "params": m.params} for m in exp.methods],
        "table1": table1_choice(exp),
        "versions": {"jaxci": __version__, "jax": importlib.metadata.version("jax"), "numpy": np.__version__,
                     "python": platform.python_version()},
        "device": {"requested": cfg.device,
                   "accelerator": None if acc is None else {"platform": acc[0], "kind": acc[1]},
                   "cpu": cpu_model()},
        "elapsed": elapsed,
        "runs": [r.to_dict() for r in records],
        "aggregates": aggregate(records),
    }


def table1_choice(exp) -> dict:
    """Mesh and stage columns of Table 1: the config's ``report.table1``, else the 27-element case (or the first
    mesh) and no stage mapping (every method gets a column)."""
    t1 = exp.config.report.table1
    mesh = t1.mesh
    if mesh is None:
        mesh = next((m.name for m in exp.meshes if m.paper_case == "cube27"), exp.meshes[0].name)
    return {"mesh": mesh, "stage1": t1.stage1, "stage2": t1.stage2}


def _engines(summary) -> list[str]:
    """Which engine, device, dtype and kernel ran each method (one line per distinct combination)."""
    out = ["## Engines", "", "| method | engine | device | dtype | kernel | runs | why |",
           "|---|---|---|---|---|---|---|"]
    for m in summary["methods"]:
        seen: dict = {}
        for r in summary["runs"]:
            e = r.get("engine")
            if r["label"] == m["name"] and e:
                key = (e["name"], e["device"] + ("" if e["devices"] == 1 else f" x{e['devices']}"), e["dtype"],
                       e["kernel"], e["reason"].split("; this mesh has")[0])  # the rule, not each mesh's size
                seen[key] = seen.get(key, 0) + 1
        for (name, device, dtype, kernel, why), n in seen.items():
            out.append(f"| {m['name']} | {name} | {device} | {dtype} | {kernel} | {n} | {why} |")
    return out


CSV_COLUMNS = (
    "mesh", "method", "algorithm", "seed", "status", "engine", "device", "dtype", "kernel", "n_nodes", "n_elements",
    "iterations", "wall_time",
    "before_max_condition", "after_max_condition", "before_objective", "after_objective",
    "before_min_scaled_jacobian", "after_min_scaled_jacobian", "before_inverted_elements",
    "after_inverted_elements", "mesh_file", "error",
)


def runs_csv(records) -> str:
    """``runs.csv``: one row per run, `CSV_COLUMNS`."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in records:
        b, a, e = r.before or {}, r.after or {}, r.engine or {}
        w.writerow([
            r.mesh, r.label, r.method, r.seed, r.status, e.get("name", ""), e.get("device", ""), e.get("dtype", ""),
            e.get("kernel", ""), b.get("n_nodes", ""), b.get("n_elements", ""),
            _c(r.iterations), _c(r.wall_time), _c(b.get("max_condition")), _c(a.get("max_condition")),
            _c(b.get("objective")), _c(a.get("objective")), _c(b.get("min_scaled_jacobian")),
            _c(a.get("min_scaled_jacobian")), _c(b.get("inverted_elements")), _c(a.get("inverted_elements")),
            r.mesh_file or "", r.error or "",
        ])
    return buf.getvalue()


def _c(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    return str(v)


def _f(v, fmt=".4f") -> str:
    return "-" if v is None else format(v, fmt)


def _first(summary, mesh, label):
    """The record of the first seed of (mesh, label) that ran, or None."""
    seed0 = summary["seeds"][0]
    return next((r for r in summary["runs"] if r["mesh"] == mesh and r["label"] == label and r["seed"] == seed0),
                None)


def _counts(quality: dict | None) -> list:
    if not quality:
        return [None] * (len(HISTOGRAM_EDGES) - 1)
    return [b["count"] for b in quality["histogram"]]


def render_report(summary: dict) -> str:
    """``report.md``: the paper's Tables 1-3 with our figures beside the paper's (from a `build_summary` dict)."""
    lines = [f"# Experiment report: {summary['config_file']}", ""]
    if summary["config"].get("description"):
        lines += [summary["config"]["description"], ""]
    if summary["partial"]:
        lines += [f"**PARTIAL**: interrupted after {summary['runs_done']} of {summary['runs_planned']} runs.", ""]
    dev = summary["device"]
    acc = dev.get("accelerator")
    lines += [
        f"Seeds: {len(summary['seeds'])} ({', '.join(map(str, summary['seeds'][:10]))}"
        f"{', ...' if len(summary['seeds']) > 10 else ''}); device asked for: {dev['requested']}; machine: "
        f"{acc['kind'] + ' (' + acc['platform'] + ') and ' if acc else ''}{dev['cpu']}; jaxci "
        f"{summary['versions']['jaxci']}, jax {summary['versions']['jax']}.",
        "Condition figures are kappa/3 (Frobenius, Verdict convention), F is the paper's Eq. 3.1. Generated meshes are "
        "perturbed by the run seed (each seed smooths a different perturbation of the same case).",
        "",
    ]
    lines += _engines(summary) + [""] + _table1(summary) + [""] + _table2(summary) + [""] + _table3(summary)
    failed = [r for r in summary["runs"] if r["status"] != "ok"]
    if failed:
        lines += ["", "## Failed runs", ""]
        lines += [f"- {r['mesh']} / {r['label']} / seed {r['seed']}: {r['error']}" for r in failed]
    return "\n".join(lines) + "\n"


def _table1(summary) -> list[str]:
    t1 = summary["table1"]
    mesh = t1["mesh"]
    labels = [m["name"] for m in summary["methods"]]
    stages = [(f"stage {i}", t1[f"stage{i}"]) for i in (1, 2) if t1[f"stage{i}"]]
    staged = {lab for _, lab in stages}
    first = [_first(summary, mesh, lab) for lab in labels]
    before = next((r["before"] for r in first if r and r["status"] == "ok"), None)
    is27 = before is not None and before["n_elements"] == 27
    head = ["kappa/3"]
    cols = []
    if is27:
        head.append("paper original")
        cols.append(list(PAPER_TABLE1["original"]))
    head.append("ours before")
    cols.append(_counts(before))
    for name, lab in stages:
        if is27:
            head.append(f"paper {name}")
            cols.append(list(PAPER_TABLE1[name]))
        head.append(f"ours {name} ({lab})")
        cols.append(_counts((_first(summary, mesh, lab) or {}).get("after")))
    for lab, r in zip(labels, first, strict=True):
        if lab not in staged and r is not None:
            head.append(f"ours {lab}")
            cols.append(_counts(r.get("after")))
    out = [f"## Table 1: corners per kappa/3 bin, mesh {mesh!r} (seed {summary['seeds'][0]})", ""]
    if stages:
        out += ["Stage mapping: the paper's stage 1 (roulette-wheel following) and stage 2 (everyone follows the "
                "best, after stage 1) are the config's method entries named in report.table1. With global CI, "
                "a run of `attempts: S, stage_switch: 1.0` follows exactly the first S attempts of a run of "
                "`attempts: A, stage_switch: S/A` with the same seed (the configs: S = 200 of the default A = 1000, "
                "`jaxci.optim.ci.GLOBAL_DEFAULTS`), so 'stage 1' is the state at the switch and 'stage 2' the "
                "final state of the two-stage run.", ""]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, b in enumerate(bin_labels()):
        out.append("| " + " | ".join([b] + ["-" if c[i] is None else str(c[i]) for c in cols]) + " |")
    out.append("| total | " + " | ".join(str(sum(x for x in c if x is not None)) if any(x is not None for x in c)
                                          else "-" for c in cols) + " |")
    return out


def _table2(summary) -> list[str]:
    labels = [m["name"] for m in summary["methods"]]
    head = ["mesh", "elements", "paper before", "paper after", "ours before"] + [f"{lab} after" for lab in labels]
    out = [f"## Table 2: max kappa/3 before and after (seed {summary['seeds'][0]})", "",
           "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in summary["meshes"]:
        rs = [_first(summary, m["name"], lab) for lab in labels]
        ok = [r for r in rs if r and r["status"] == "ok"]
        before = ok[0]["before"] if ok else None
        paper = PAPER_TABLE2.get(m["paper_case"] or "", (None, None))
        row = [m["name"], str(before["n_elements"]) if before else "-", _f(paper[0]), _f(paper[1]),
               _f(before["max_condition"] if before else None)]
        for r in rs:
            if r is None:
                row.append("")
            elif r["status"] != "ok":
                row.append("failed")
            else:
                row.append(_f(r["after"]["max_condition"]))
        out.append("| " + " | ".join(row) + " |")
    return out


def _table3(summary) -> list[str]:
    n = len(summary["seeds"])
    head = ["mesh", "method", "runs", "worst", "best", "mean", "std F", "mean F", "mean before", "median time s",
            "mean iterations"]
    out = [f"## Table 3: robustness over {n} seeds (max kappa/3 after; std of final F)", "",
           "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    cases = {m["name"]: m["paper_case"] for m in summary["meshes"]}
    done = set()
    for a in summary["aggregates"]:
        case = cases.get(a["mesh"])
        if case in PAPER_TABLE3 and a["mesh"] not in done:
            w, b, mean, s = PAPER_TABLE3[case]
            out.append(f"| {a['mesh']} | **paper (CI)** | 30 | {w:.4f} | {b:.4f} | {mean:.4f} | {s:.4g} "
                       f"| - | - | - | - |")
            done.add(a["mesh"])
        runs = f"{a['runs']}" + (f" ({a['failed']} failed)" if a["failed"] else "")
        out.append(
            f"| {a['mesh']} | {a['method']} | {runs} | {_f(a['worst_max_condition'])} | {_f(a['best_max_condition'])} "
            f"| {_f(a['mean_max_condition'])} | {_f(a['std_objective'], '.4g')} | {_f(a['mean_objective'], '.4g')} | "
            f"{_f(a['mean_before_max_condition'])} | {_f(a['median_wall_time'], '.2f')} | "
            f"{_f(a['mean_iterations'], '.1f')} |"
        )
    return out


# ----------------------------------------------------------------------------------------------- output files
@dataclasses.dataclass
class RunRecord:
    """One (mesh, method, seed) run: status ``"ok"`` or ``"failed"`` (with `error`), figures, `history`."""

    mesh: str
    label: str
    method: str
    seed: int
    status: str
    iterations: int | None = None
    wall_time: float | None = None
    before: dict | None = None
    after: dict | None = None
    notes: list = dataclasses.field(default_factory=list)
    error: str | None = None
    mesh_file: str | None = None
    history: dict | None = None
    engine: dict | None = None

    def to_dict(self) -> dict:
        """The JSON record of ``summary.json`` (without the history, which goes to ``history.json``)."""
        d = dataclasses.asdict(self)
        d.pop("history")
        return d


def json_ready(x):
    """`x` with numpy scalars/arrays as Python values and non-finite floats as None (strict JSON)."""
    if isinstance(x, dict):
        return {str(k): json_ready(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [json_ready(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_ready(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def annotated_mesh(mesh, points, node_class=None, reference_points=None):
    """`mesh` with coordinates `points` and the quality fields jaxci writes with a smoothed mesh.

    Cell data ``element_condition`` (max corner kappa/3, inf for an inverted element) and ``scaled_jacobian``
    (Verdict's element scaled Jacobian), NaN on non-hexahedron blocks; point data ``node_class``
    (`jaxci.geometry.boundary` classes) when given, and ``displacement`` = `points` - `reference_points` when given.
    """
    import jax

    from ..metrics.hexahedron import element_condition, element_scaled_jacobian

    pts = np.asarray(points, dtype=np.float64)
    hexes = mesh.hexes
    with jax.enable_x64(True):
        ec = np.asarray(element_condition(pts, hexes), dtype=np.float64)
        sj = np.asarray(element_scaled_jacobian(pts, hexes), dtype=np.float64)
    cell_data = dict(mesh.cell_data)
    for name, values in (("element_condition", ec), ("scaled_jacobian", sj)):
        per_block, start = [], 0
        for blk in mesh.cells:
            if blk.type == "hexahedron":
                per_block.append(values[start:start + len(blk.data)])
                start += len(blk.data)
            else:
                per_block.append(np.full(len(blk.data), np.nan))
        cell_data[name] = per_block
    point_data = dict(mesh.point_data)
    if node_class is not None:
        point_data["node_class"] = np.asarray(node_class, dtype=np.int32)
    if reference_points is not None:
        point_data["displacement"] = pts - np.asarray(reference_points, dtype=np.float64)
    return dataclasses.replace(mesh, points=pts, cell_data=cell_data, point_data=point_data, fix_orientation=False,
                               notes=())


def write_vtus(tmp: Path, rm, meth, seed: int, mesh, res) -> str:
    from ..io import write_mesh

    folder = tmp / "meshes"
    folder.mkdir(exist_ok=True)
    inp = folder / f"{rm.slug}_input_seed{seed}.vtu"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # VTU keeps everything a smoothed mesh needs; sets are not drawn
        if not inp.exists():
            write_mesh(annotated_mesh(mesh, mesh.points, res.node_class, mesh.points), inp)
        name = f"meshes/{rm.slug}_{meth.slug}_seed{seed}.vtu"
        write_mesh(annotated_mesh(res.mesh, res.mesh.points, res.node_class, mesh.points), tmp / name)
    return name
