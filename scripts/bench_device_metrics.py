"""The quality figures and final checks measured on the device (`jaxci.metrics.device`) against the host functions
they stand for, on one perturbed box.

For each pair (the quality report, the worst elements, the inverted-cell count, the volume check, the final
checks without and with the worst-cell guard): the device function's compilation (seconds of `jaxci.runtime.phases`'
compile totals on its first call), its seconds inside compiled programs (``device_s`` of `jaxci.runtime.transfer`) and
per call, and the host function's seconds per call; the minimum of `--repeats` calls, device and host
alternated (a shared machine's load falls on both alike). Printed, and written as JSON with `--out`.

    python scripts/bench_device_metrics.py --n 100 --out device_metrics.json   # 10^6 hexahedra
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def cases(mesh, points, conn, x, x_host, worst_start):
    """name -> (device call, host call) on `mesh` (coordinates `points`, `conn` and the result `x` on the device;
    `x_host` the same result in numpy)."""
    from jaxci.interface.invariants import enforce, enforce_device
    from jaxci.mesh import check_volume
    from jaxci.metrics import device as D
    from jaxci.metrics import objective as mixed
    from jaxci.metrics.report import quality_report, worst_elements

    guard = {"keep_worst": True, "worst_start": worst_start, "worst_first": True}
    return {
        "quality_report": (lambda: D.quality_report_device(mesh, points, conn), lambda: quality_report(mesh)),
        "worst_elements": (lambda: D.worst_elements_device(mesh, points, conn),
                           lambda: worst_elements(mesh, mesh.points)),
        "inverted_cells": (lambda: D.inverted_hexes(points, conn), lambda: mixed.inverted_cells(mesh, mesh.points)),
        "check_volume": (lambda: check_volume(mesh, D.volume_moments(points, conn)), lambda: check_volume(mesh)),
        "enforce": (lambda: enforce_device(mesh, conn, points, x),
                    lambda: enforce(mesh, None, mesh.points, x_host, projected=True)),
        "enforce_guarded": (lambda: enforce_device(mesh, conn, points, x, **guard),
                            lambda: enforce(mesh, None, mesh.points, x_host, projected=True, **guard)),
    }


def run(n: int, repeats: int = 3) -> dict:
    """The rows of a perturbed box of n^3 hexahedra (`jaxci.mesh.generate.perturb_box`, amplitude 0.3, seed 0); the
    method's result is the box with every node shaken by 1e-4 of the side."""
    import jax
    import numpy as np

    from jaxci.mesh.generate import perturb_box
    from jaxci.metrics.report import quality_report
    from jaxci.runtime import transfer
    from jaxci.runtime.phases import compile_totals

    jax.config.update("jax_enable_x64", True)
    mesh = perturb_box(n, amplitude=0.3, seed=0)
    x_host = mesh.points + np.random.default_rng(0).normal(scale=1e-4, size=mesh.points.shape)
    points, conn, x = (transfer.to_device(a) for a in (mesh.points, np.ascontiguousarray(mesh.hexes.T), x_host))
    worst_start = quality_report(mesh).max_condition

    def compiling() -> float:
        t = compile_totals()
        return t["trace"] + t["lower"] + t["backend"]

    rows = {}
    for name, (dev, host) in cases(mesh, points, conn, x, x_host, worst_start).items():
        c0 = compiling()
        dev()
        row = {"compile_s": compiling() - c0, "device_s": [], "call_s": [], "host_s": []}
        for _ in range(repeats):
            d0, t0 = transfer.totals()["device_s"], time.perf_counter()
            dev()
            row["call_s"].append(time.perf_counter() - t0)
            row["device_s"].append(transfer.totals()["device_s"] - d0)
            t0 = time.perf_counter()
            host()
            row["host_s"].append(time.perf_counter() - t0)
        rows[name] = {k: round(min(v) if isinstance(v, list) else v, 4) for k, v in row.items()}
        r = rows[name]
        print(f"{name:16s} compile {r['compile_s']:6.2f} s   device {r['device_s']:7.3f} s   call {r['call_s']:7.3f} s"
              f"   host function {r['host_s']:7.3f} s", flush=True)
    return {"hexes": mesh.n_hexes, "nodes": mesh.n_nodes, "platform": jax.default_backend(), "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100, help="box of n^3 hexahedra (default 100: 10^6)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="write the JSON here")
    args = ap.parse_args(argv)
    out = run(args.n, args.repeats)
    if args.out is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_stamp import stamp

        args.out.write_text(json.dumps(out | stamp(), indent=1))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
