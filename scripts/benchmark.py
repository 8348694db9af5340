"""Scaling benchmark: perturbed boxes from 10^3 to 100^3 hexes, time to reach max kappa/3 <= 1.01 and <= 1.0001,
both engines side by side (``--engines host jax``, the default: `jaxci.interface.engine`).

For every (size, method) a fresh subprocess (so peak memory and 'cold' are clean) generates the box (amplitude
0.3, sliding boundary, seed 0, inverting draws redrawn), runs `jaxci.smooth` once cold (compilation included)
and once warm to convergence, reads from the history the first iteration where max kappa/3 <= each threshold,
then re-runs with the iteration cap set to that count (once to compile, once timed): that is the warm time to
the threshold (setup included: classification, constraints, colouring, the float64 quality reports and checks).
Sizes above ``--full-upto`` (default 60) are run once, cold, with the iterations to each threshold but no
re-timed runs (each would take minutes on a 2-core CPU). ``--repeats N`` makes each warm time and each time
to a threshold the fastest of N runs (default 1, as before). It also
times the objective kernel alone on the mesh (corner evaluations per second). Device: `--device cpu|gpu|auto`
(unchanged code on a GPU machine); ``--engines`` the engines to run each (size, method) on (``auto`` lets
`jaxci.interface.engine.resolve_plan` choose; every row records the plan that ran). The children run with transparent
huge pages for glibc's large allocations
where that applies (`jaxci.runtime.process`; ``--hugepages off`` to compare). Prints a table and writes JSON (`--out`).

``--devices 1 2 4`` runs every (size, method) once per device count, sharded (`jaxci.smooth`'s ``devices``: the
elements split over the devices, `jaxci.optim.sharding`); each child is started with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` so that a CPU has N devices (on a GPU machine the GPUs
are counted instead). Each row records its ``devices``, the time and the peak resident memory (also per
hexahedron) and ``xla_cpu_threads`` / ``cpus``: XLA:CPU's intra-op pool has max(cores, N) threads, so N forced
devices beyond the cores oversubscribe them; those children also get `jaxci.runtime.process.cpu_device_flags`
(XLA's per-fusion partitioning off; docs/sharding.md); without ``--devices`` the runs are on one device, with
no ``devices`` argument (a sharded run is the JAX engine's: host rows are not run with ``--devices``).

    python scripts/benchmark.py --sizes 10 20 30 60 100 --methods lbfgs ci smart-laplace
    python scripts/benchmark.py --sizes 30 --methods lbfgs --devices 1 2 4 [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

THRESHOLDS = (1.01, 1.0001)
#: The keyword that caps the iterations of each method family (CI: sweeps; Laplace: sweeps; optimistix: steps).
CAP = {"ci": "max_sweeps", "smart-laplace": "max_sweeps", "laplace": "max_sweeps"}
CAP_DEFAULT = "max_steps"
def child(args) -> dict:
    """Run one (size, method, engine) in this process and return its figures (`jaxci.errors.ConfigError` if the
    engine or device asked for cannot run it)."""
    return _measure(args)


def _fastest(run, repeats: int):
    """``(seconds, result)`` of the fastest of `repeats` (at least 1) calls of `run`."""
    best = None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        res = run()
        dt = time.perf_counter() - t0
        best = (dt, res) if best is None or dt < best[0] else best
    return best


def _measure(args) -> dict:
    import importlib.metadata
    import resource

    import numpy as np

    from jaxci.interface.smooth import smooth
    from jaxci.mesh.generate import perturb_box

    n = args.size
    t0 = time.perf_counter()
    mesh = perturb_box(n, amplitude=args.amplitude, seed=args.seed, redraw_inverted=True)
    t_gen = time.perf_counter() - t0
    params = json.loads(args.params) if args.params else {}
    if args.devices:
        params["devices"] = args.devices
    params.update(engine=args.engine, device=args.device)
    out = dict(size=n, hexes=mesh.n_hexes, nodes=mesh.n_nodes, method=args.method, dtype=args.dtype,
               devices=args.devices, engine_asked=args.engine, jax=importlib.metadata.version("jax"),
               generate_s=t_gen, params=params, glibc_tunables=os.environ.get("GLIBC_TUNABLES"),
               xla_flags=os.environ.get("XLA_FLAGS"))
    t0 = time.perf_counter()
    res = smooth(mesh, args.method, dtype=args.dtype, **params)
    out["cold_s"] = time.perf_counter() - t0
    out["engine"] = res.plan.to_dict()
    single = n > args.full_upto  # one (cold) run only: too slow to repeat
    out["single_run"] = single
    if single:
        out["warm_s"] = None
    else:  # the fastest of `repeats` warm runs: a shared machine's load adds, it never subtracts
        out["repeats"] = args.repeats
        out["warm_s"], res = _fastest(lambda: smooth(mesh, args.method, dtype=args.dtype, **params), args.repeats)
    k = np.asarray(res.history["max_condition"], dtype=float)
    out.update(iterations=res.iterations, before_max_condition=res.before.max_condition,
               after_max_condition=res.after.max_condition, after_objective=res.after.objective,
               inverted_after=res.after.inverted_elements, history_max_condition=k.tolist(),
               history_objective=np.asarray(res.history["objective"], dtype=float).tolist(),
               restarts=res.history.get("restarts"), solver_result=res.history.get("solver_result"))
    cap = CAP.get(args.method, CAP_DEFAULT)
    for thr in THRESHOLDS:
        hit = np.flatnonzero(k <= thr)
        key = f"to_{thr:g}"
        if not len(hit):
            out[key] = None
            continue
        it = max(int(hit[0]), 1)
        if single:
            out[key] = dict(iterations=it, seconds=None, reached=float(k[it]))
            continue
        capped = {**params, cap: it, **({"tol": 0.0} if args.method == "ci" else {})}
        pre = int(res.history.get("presmooth") or 0)  # sweeps run (the Laplacian may stop before presmooth)
        if pre:  # the history starts with the smart-Laplace sweeps: cap those, then the solver's steps (at least
            # one: a threshold reached within the sweeps is timed with one solver step more)
            capped.update(presmooth=min(pre, it), max_steps=max(it - pre, 1))
        smooth(mesh, args.method, dtype=args.dtype, **capped)  # the cap may be a static argument: compile
        dt, r2 = _fastest(lambda capped=capped: smooth(mesh, args.method, dtype=args.dtype, **capped), args.repeats)
        out[key] = dict(iterations=it, seconds=dt, reached=r2.after.max_condition)
    out["objective_mcorners_per_s"] = None
    if res.plan.engine == "jax":
        out["objective_mcorners_per_s"] = _kernel_rate(mesh, args.dtype, res.plan)
    out["cpus"] = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    if res.plan.engine == "jax" and res.plan.device == "cpu":
        # XLA:CPU's intra-op pool: max(cores or NPROC, device count) threads, so forced devices beyond the cores
        # oversubscribe them (docs/sharding.md)
        from jaxci.optim.sharding import xla_cpu_threads

        out["xla_cpu_threads"] = xla_cpu_threads()
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["peak_rss_bytes_per_hex"] = out["peak_rss_mb"] * 2**20 / mesh.n_hexes
    return out


def _kernel_rate(mesh, dtype: str, plan) -> float:
    """The objective kernel alone, warm, on the device the run's `plan` used: millions of corners per second."""
    import jax
    import jax.numpy as jnp

    from jaxci.metrics import hexahedron as q

    dt = jnp.float32 if dtype == "float32" else jnp.float64
    with jax.enable_x64(dtype == "float64"), plan.context():
        pts = jnp.asarray(mesh.points, dt)
        conn = q.transposed(mesh.hexes)
        jax.block_until_ready(q.objective_t(pts, conn))
        reps, t0 = 0, time.perf_counter()
        while reps < 3 or time.perf_counter() - t0 < 0.5:
            jax.block_until_ready(q.objective_t(pts, conn))
            reps += 1
        return 8 * mesh.n_hexes * reps / (time.perf_counter() - t0) / 1e6


def _write(args, rows) -> None:
    """Write the JSON atomically."""
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    tmp = args.out + ".tmp"
    with open(tmp, "w") as f:
        json.dump(dict(benchmark="scaling", command=" ".join(sys.argv), date=time.strftime("%Y-%m-%d"),
                       amplitude=args.amplitude, seed=args.seed, dtype=args.dtype, engines=args.engines,
                       full_upto=args.full_upto, devices=args.devices, cpu_count=os.cpu_count(), rows=rows), f,
                  indent=1)
    os.replace(tmp, args.out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 20, 30, 60])
    ap.add_argument("--methods", nargs="+", default=["lbfgs", "ci", "smart-laplace"])
    ap.add_argument("--amplitude", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    ap.add_argument("--device", choices=["cpu", "gpu", "auto"], default="auto")
    ap.add_argument("--params", default="", help="JSON dict of method parameters (applied to every method)")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per (size, method)")
    ap.add_argument("--full-upto", type=int, default=60,
                    help="sizes above this are run once (cold: compile + run; iterations to each threshold, no "
                         "re-timed capped runs)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="each warm time (and each time to a threshold) is the fastest of this many runs")
    ap.add_argument("--out", default="results/benchmark.json")
    ap.add_argument("--hugepages", choices=["on", "off"], default="on",
                    help="run the children with GLIBC_TUNABLES=glibc.malloc.hugetlb=1 where it applies "
                         "(jaxci.runtime.process)")
    ap.add_argument("--devices", type=int, nargs="+", default=None, metavar="N",
                    help="device counts to run each (size, method) on, sharded (forced CPU devices on a CPU); "
                         "default: one device, unsharded")
    ap.add_argument("--engines", nargs="+", choices=["auto", "host", "jax"], default=["host", "jax"],
                    help="engines to run each (size, method) on, side by side (default: host jax)")
    ap.add_argument("--engine", default="auto", help=argparse.SUPPRESS)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--method", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        args.devices = args.devices[0] if args.devices else None
        from jaxci.errors import JaxciError

        try:
            print("RESULT " + json.dumps(child(args)), flush=True)
        except JaxciError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        return
    from jaxci.runtime.process import cpu_device_flags, hugepage_environment

    rows = []
    head = (f"{'n^3':>5} {'hexes':>8} {'method':>14} {'engine':>10} {'dev':>4} {'cold s':>8} {'warm s':>8} {'it':>5} "
            f"{'final k/3':>10} {'t(1.01) s':>10} {'t(1.0001) s':>12} {'peak MB':>8} {'Mcorner/s':>10} "
            f"{'threads/cpus':>12}")
    print(head)
    combos = [(n, m, e, d) for n in args.sizes for m in args.methods for e in args.engines
              for d in args.devices or [None] if not (d and e == "host")]
    for n, method, engine, devices in combos:
        cmd = [sys.executable, __file__, "--child", "--size", str(n), "--method", method, "--engine", engine,
               "--amplitude",
               str(args.amplitude), "--seed", str(args.seed), "--dtype", args.dtype, "--device", args.device,
               "--params", args.params, "--full-upto", str(args.full_upto), "--repeats", str(args.repeats)]
        cmd += ["--devices", str(devices)] if devices else []
        try:
            env = (hugepage_environment() if args.hugepages == "on" else None) or {**os.environ}
            if args.hugepages == "off":  # also drop the tunable if this process was started with it
                kept = [t for t in env.get("GLIBC_TUNABLES", "").split(":") if t and "malloc.hugetlb" not in t]
                env["GLIBC_TUNABLES"] = ":".join(kept)
            if devices:  # read when JAX starts in the child: a CPU gets this many devices
                env["XLA_FLAGS"] = " ".join(filter(None, [env.get("XLA_FLAGS"), "--xla_force_host_platform_"
                                                           f"device_count={devices}"]))
                # more devices than cores: no per-fusion partitions (jaxci.runtime.process.cpu_device_flags;
                # docs/sharding.md)
                env["XLA_FLAGS"] = cpu_device_flags(env) or env["XLA_FLAGS"]
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout, env=env)
            line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
            row = json.loads(line[-1][7:]) if line else dict(size=n, method=method, engine_asked=engine,
                                                             devices=devices, error=p.stderr[-2000:])
        except subprocess.TimeoutExpired:
            row = dict(size=n, method=method, engine_asked=engine, devices=devices,
                       error=f"timed out after {args.timeout} s")
        rows.append(row)
        _write(args, rows)  # after every row: a long run interrupted later keeps what it measured
        if "error" in row:
            last = row["error"].strip().splitlines()[-1][:80]
            print(f"{n:>5} {'':>8} {method:>14} {engine:>10} {devices or '-':>4}  FAILED: {last}", flush=True)
            continue

        def t(key, row=row):
            v = row.get(key)
            if not v:
                return "-"
            return f"({v['iterations']} it)" if v["seconds"] is None else f"{v['seconds']:.2f}"

        warm = "-" if row["warm_s"] is None else f"{row['warm_s']:.2f}"
        e = row["engine"]
        rate = "-" if row["objective_mcorners_per_s"] is None else f"{row['objective_mcorners_per_s']:.0f}"
        print(f"{n:>5} {row['hexes']:>8} {method:>14} {e['name'] + '/' + e['device']:>10} {devices or '-':>4} "
              f"{row['cold_s']:>8.2f} {warm:>8} "
              f"{row['iterations']:>5} {row['after_max_condition']:>10.6f} {t('to_1.01'):>10} "
              f"{t('to_1.0001'):>12} {row['peak_rss_mb']:>8.0f} {rate:>10} "
              f"{str(row.get('xla_cpu_threads')) + '/' + str(row.get('cpus')):>12}", flush=True)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
