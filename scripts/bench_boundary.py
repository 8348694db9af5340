"""Benchmark: boundary topology, node classification, colouring, constraint building and projection on boxes.

For structured n^3 boxes (default 30 and 100: 27k and 1M hexahedra) it times, in seconds (median of `--repeats`
runs): `boundary_topology`, `classify_boundary` (including the topology), `node_adjacency` + `colour_nodes`,
`build_constraints`, the JAX `project` (first call = compile + run, then warm), `project_nodes` on 1/8 of the
surface nodes with 8 candidates each, and the exact numpy `project_np`. Prints a table and writes JSON.

    python scripts/bench_boundary.py [--sizes 30 100] [--dtype float64] [--out results/bench_boundary.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxci.geometry.boundary import classify_boundary  # noqa: E402
from jaxci.geometry.projection import build_constraints, project, project_nodes, project_np  # noqa: E402
from jaxci.geometry.topology import boundary_topology, colour_nodes, node_adjacency  # noqa: E402
from jaxci.mesh.generate import box  # noqa: E402


def timed(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def bench(n: int, dtype, repeats: int) -> dict:
    mesh = box(n)
    hexes, nn = mesh.hexes, mesh.n_nodes
    row: dict = {"n": n, "hexes": int(len(hexes)), "nodes": nn}
    row["topology_s"], _ = timed(lambda: boundary_topology(hexes, nn), repeats)
    row["classify_s"], info = timed(lambda: classify_boundary(mesh), repeats)
    row["adjacency_s"], adj = timed(lambda: node_adjacency(hexes, nn), repeats)
    row["colour_s"], col = timed(lambda: colour_nodes(hexes, nn, adj), repeats)
    row["n_colours"] = col.n_colours
    row["counts"] = info.counts
    row["build_constraints_s"], cons = timed(lambda: build_constraints(mesh, info, dtype=dtype), repeats)
    row["k_tri"], row["k_seg"] = int(cons.surface_cand.shape[1]), int(cons.edge_cand.shape[1])
    h = 1.0 / n
    x = jnp.asarray(mesh.points + np.random.default_rng(0).uniform(-0.3 * h, 0.3 * h, mesh.points.shape), dtype)
    f = jax.jit(project)
    row["project_first_s"], _ = timed(lambda: f(cons, x), 1)
    row["project_warm_s"], y = timed(lambda: f(cons, x), repeats)
    idx = cons.surface_nodes[::8]
    batch = jnp.broadcast_to(x[idx], (8, *x[idx].shape))
    g = jax.jit(project_nodes)
    timed(lambda: g(cons, idx, batch), 1)
    row["project_nodes_8x_s"], _ = timed(lambda: g(cons, idx, batch), repeats)
    row["project_nodes_m"] = int(idx.shape[0])
    row["project_np_s"], z = timed(lambda: project_np(cons, np.asarray(x)), repeats)
    row["jax_vs_numpy_max_diff"] = float(np.abs(np.asarray(y, np.float64) - z).max())
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[30, 100])
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None, help="JSON file to write (default: none)")
    args = ap.parse_args(argv)
    dtype = jnp.float64 if args.dtype == "float64" else jnp.float32
    rows = [bench(n, dtype, args.repeats) for n in args.sizes]
    keys = [
        "topology_s",
        "classify_s",
        "adjacency_s",
        "colour_s",
        "build_constraints_s",
        "project_first_s",
        "project_warm_s",
        "project_nodes_8x_s",
        "project_np_s",
    ]
    print(f"{'n':>5} {'hexes':>9} " + " ".join(f"{k[:-2]:>15}" for k in keys) + "  colours  K_tri")
    for r in rows:
        print(
            f"{r['n']:>5} {r['hexes']:>9} "
            + " ".join(f"{r[k]:>15.4f}" for k in keys)
            + f"  {r['n_colours']:>7}  {r['k_tri']:>5}"
        )
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        meta = {
            "python": sys.version.split()[0],
            "jax": jax.__version__,
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "dtype": args.dtype,
        }
        from pathlib import Path

        from jaxci.experiments.results import write_text

        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text(Path(args.out), json.dumps({"meta": meta, "rows": rows}, indent=1))  # atomically
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
