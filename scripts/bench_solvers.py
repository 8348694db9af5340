"""The solvers side by side: plain L-BFGS (``method="lbfgs"``) against truncated Newton (``solver="newton"``,
`jaxci.optim.newton`) on real meshes, in one process, one run after the other (the host engine; the JAX engine
with ``engine="jax"`` in a solver's parameters).

Per mesh and solver it records the outer iterations (L-BFGS: its accepted steps; Newton: its Newton iterations),
the gradient evaluations (every solver step is one: the real cost unit), the seconds of the ``smooth`` phase (the
solve alone) and of the whole `jaxci.smooth` call, F after, and VTK's per-element condition of the output (each
cell's worst corner kappa/3: its max, the worst element, and its mean), measured as `scripts/bench_realmesh.py`
measures. Prints a table and writes JSON (`--out`).

    PYTHONPATH=src python3 scripts/bench_solvers.py [--meshes sphere_tet2hex-large ... PATH]
        [--solvers lbfgs newton newton:cg_max=50 auto/lbfgs auto/newton default] [--repeat 2]
        [--out docs/results/bench_solvers.json]

`--meshes` takes corpus names (``python scripts/realmesh_corpus.py --list``; default: the ~25k gmsh meshes) or
mesh file paths. A solver is ``default`` (the default pipeline; ``default:KEY=VALUE,...`` with parameters), ``lbfgs``,
``newton``, or ``newton:KEY=VALUE,...`` (extra `jaxci.smooth` keywords,
JSON values: `GradientParams`, ``engine="jax"``), run as
``method="lbfgs"``; ``auto/`` before it runs the default pipeline with that solver (then the worst-element polish:
its evaluations are in the count; "outer" is still the solver's: Newton iterations, or accepted steps).
Timings on a shared machine are noisy: run it alone.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_realmesh  # noqa: E402
import realmesh_corpus as corpus  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LARGE = ("sphere_tet2hex-large", "bracket_tet2hex-large", "cylinder_ogrid-large", "annulus_quad-large",
         "plate_holes_quad-large")


def solver_params(spec: str) -> tuple[str, dict]:
    """``(method, params)`` of a solver spec: ``lbfgs``, ``newton``, ``newton:cg_max=50`` (``method="lbfgs"``),
    ``auto/lbfgs``, ``auto/newton`` (the default pipeline, its L-BFGS stage with that solver: the polish after it),
    ``default`` (the default pipeline as it is: ``method="auto"``, no parameter), ``default:KEY=VALUE,...`` (the
    default pipeline with those parameters only, e.g. ``default:polish_cell_power=32``)."""
    if spec == "default" or spec.startswith("default:"):
        return "auto", {k: json.loads(v) for k, _, v in (item.partition("=") for item in
                                                          filter(None, spec.partition(":")[2].split(",")))}
    method, _, spec = spec.rpartition("/")
    name, _, extra = spec.partition(":")
    params = {"solver": name}
    for item in filter(None, extra.split(",")):
        key, _, value = item.partition("=")
        params[key] = json.loads(value)
    return method or "lbfgs", params


def mesh_paths(names: list[str]) -> list[tuple[str, Path]]:
    """``(name, path)`` of corpus names or paths."""
    out, known = [], None
    for name in names:
        if Path(name).exists():
            out.append((Path(name).name, Path(name)))
            continue
        known = known or {e.name: e for e in corpus.entries()}
        out.append((name, known[name].ensure()))
    return out


def run(mesh, method: str, params: dict, repeat: int = 1) -> dict:
    """`jaxci.smooth` of `mesh` with `method` and `params` `repeat` times: the row of the table (the seconds the
    least of the runs', every other figure the same in each)."""
    import jaxci

    walls, solves = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = jaxci.smooth(mesh, method=method, **params)
        walls.append(time.perf_counter() - t0)
        solves.append(float((res.phases or {}).get("smooth", {}).get("seconds", 0.0)))  # none: already optimal
    hist = res.history
    f = np.asarray(hist["objective"], np.float64)
    f = f[np.isfinite(f)]
    accepted = int(np.sum(np.diff(f) < 0))  # an accepted step lowers F (Armijo), a rejected one keeps it
    outer = int(hist["newton_iterations"]) if "newton_iterations" in hist else accepted
    q = bench_realmesh.quality(res.mesh)
    return dict(outer=outer, grad_evals=int(res.iterations), smooth_s=min(solves), wall_s=min(walls),
                F=float(res.after.objective), worst=q["worst_element"], mean=q["element_mean"],
                max_kappa=float(res.after.max_condition), result=hist.get("solver_result"), notes=list(res.notes),
                polish_stopped=(hist.get("polish") or {}).get("stopped"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", nargs="+", default=list(LARGE))
    ap.add_argument("--solvers", nargs="+", default=["lbfgs", "newton"])
    ap.add_argument("--repeat", type=int, default=1, help="runs of each (the least seconds kept)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "bench_solvers.json"))
    args = ap.parse_args(argv)
    from jaxci.io import read_mesh

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    out = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), commit=commit,
               machine=platform.processor() or platform.machine(), command=" ".join(sys.argv), rows=[])
    head = (f"{'mesh':28s} {'solver':18s} {'hexes':>7s} {'outer':>6s} {'grads':>6s} {'solve s':>8s} "
            f"{'F':>10s} {'worst':>8s} {'mean':>8s}")
    print(head)
    for name, path in mesh_paths(args.meshes):
        mesh = read_mesh(path)
        for spec in args.solvers:
            row = dict(mesh=name, solver=spec, hexes=int(mesh.n_hexes),
                       **run(mesh, *solver_params(spec), repeat=args.repeat))
            out["rows"].append(row)
            print(f"{name:28s} {spec:18s} {row['hexes']:7d} {row['outer']:6d} {row['grad_evals']:6d} "
                  f"{row['smooth_s']:8.2f} {row['F']:10.6f} {row['worst']:8.4f} {row['mean']:8.5f}", flush=True)
            Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
