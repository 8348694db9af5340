"""Benchmark: corner evaluations per second of the closed-form kappa vs jnp.linalg.cond (Frobenius and 2-norm).

For box meshes from 9^3 (5,832 corners, the paper's 729-element case) to 100^3 (8 million corners), float32 and
float64, C = 1 and 8 candidates, it times the whole objective F (gather + per-corner kappa + mean), warm, with
the connectivity already in the kernels' (8, N) layout, and prints a table and writes JSON. The reference paths
(SVD / explicit inverse) are skipped above `--max-reference-corners` corners because they take minutes there;
their throughput is flat in size.

    python scripts/bench_quality.py [--sizes 9 20 50 100] [--out results/bench_quality.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxci.mesh.generate import perturb_box  # noqa: E402
from jaxci.metrics import hexahedron as q  # noqa: E402


@jax.jit
def reference_objective_fro(points, hexes):
    a = q.corner_matrices(points, hexes)
    return jnp.mean((jnp.linalg.cond(a, "fro") / 3) ** 2) - 1


@jax.jit
def reference_objective_2(points, hexes):
    a = q.corner_matrices(points, hexes)
    return jnp.mean(jnp.linalg.cond(a) ** 2) - 1


def timeit(fn, *args, min_time=0.5, max_reps=50):
    jax.block_until_ready(fn(*args))  # compile + warm
    times = []
    t_end = time.perf_counter() + min_time
    while len(times) < max_reps and (len(times) < 3 or time.perf_counter() < t_end):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[9, 20, 50, 100])
    ap.add_argument("--cohorts", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--max-reference-corners", type=int, default=200_000)
    ap.add_argument("--max-corners", type=int, default=70_000_000, help="skip (size, C) beyond this many corners")
    ap.add_argument("--out", default="results/bench_quality.json")
    args = ap.parse_args(argv)

    rows = []
    print(f"{'n^3':>6} {'dtype':>8} {'C':>3} {'corners':>10} {'method':>15} {'time ms':>10} {'M corners/s':>12}")
    for n in args.sizes:
        mesh = perturb_box(n, amplitude=0.2, seed=0, redraw_inverted=n <= 50)
        hexes = jnp.asarray(mesh.hexes, dtype=jnp.int32)
        conn = q.transposed(mesh.hexes).astype(jnp.int32)
        for dtype in (jnp.float32, jnp.float64):
            for C in args.cohorts:
                corners = 8 * mesh.n_hexes * C
                if corners > args.max_corners:
                    continue
                pts = jnp.asarray(mesh.points, dtype=dtype)
                if C > 1:
                    pts = jnp.broadcast_to(pts, (C, *pts.shape)) + 0.0
                methods = {"closed-form": lambda p, h, conn=conn: q.objective_t(p, conn)}
                if corners <= args.max_reference_corners:
                    if C == 1:
                        methods["cond-fro"] = reference_objective_fro
                        methods["cond-2norm"] = reference_objective_2
                    else:
                        methods["cond-fro"] = lambda p, h: jax.lax.map(lambda x: reference_objective_fro(x, h), p)
                        methods["cond-2norm"] = lambda p, h: jax.lax.map(lambda x: reference_objective_2(x, h), p)
                for name, fn in methods.items():
                    t = timeit(fn, pts, hexes)
                    rate = corners / t / 1e6
                    rows.append(dict(n=n, hexes=mesh.n_hexes, dtype=jnp.dtype(dtype).name, C=C, corners=corners,
                                     method=name, seconds=t, mcorners_per_s=rate))
                    print(f"{n:>6} {jnp.dtype(dtype).name:>8} {C:>3} {corners:>10} {name:>15} {t * 1e3:>10.3f} "
                          f"{rate:>12.2f}", flush=True)
    # ratios closed form / reference at equal (n, dtype, C)
    ratios = []
    for r in rows:
        if r["method"] == "closed-form":
            for ref in ("cond-fro", "cond-2norm"):
                m = [x for x in rows if x["method"] == ref and all(x[k] == r[k] for k in ("n", "dtype", "C"))]
                if m:
                    ratios.append(dict(n=r["n"], dtype=r["dtype"], C=r["C"], reference=ref,
                                       speedup=m[0]["seconds"] / r["seconds"]))
    for x in ratios:
        print(f"speed-up closed form vs {x['reference']:>10}: n={x['n']:>3} {x['dtype']} C={x['C']}: "
              f"{x['speedup']:.0f}x")
    out = dict(
        benchmark="bench_quality", jax=jax.__version__, device=str(jax.devices()[0]),
        platform=platform.platform(), cpu_count=os.cpu_count(), python=sys.version.split()[0],
        glibc_tunables=os.environ.get("GLIBC_TUNABLES"),
        rows=rows, ratios=ratios,
    )
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    tmp = args.out + ".tmp"
    with open(tmp, "w") as f:
        json.dump(out, f, indent=1)
    os.replace(tmp, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
