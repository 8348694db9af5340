"""What the JAX engine's compiled programs hold on the device, per hexahedron, on any platform (a CPU too).

The default pipeline on the JAX engine, where the mesh lives on the device (from 100,000 hexahedra), runs two
large compiled programs: the smart-Laplace presmoothing sweeps (`jaxci.optim.laplace`) and the L-BFGS loop
(`jaxci.optim.lbfgs.lbfgs_loop`; asked for by name, ``solver="lbfgs"``, so that a smaller mesh, whose default
solver is truncated Newton, runs the same two). For each, at its call, this
prints and writes (JSON) the bytes per hexahedron of the arrays alive on the device (`jax.live_arrays`) and
XLA's memory analysis of the compiled program (arguments, outputs, temporaries): the device's peak is about the
largest of live + temporaries. A GPU's own peak is `scripts/bench_gpu.py`'s ``device_bytes_per_hex``; this is the
breakdown, and it runs without one.

    python scripts/bench_device_memory.py --hexes 216000 --out device_memory.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def run(hexes: int, max_steps: int = 3) -> dict:
    """`jaxci.smooth` (default pipeline, JAX engine) on a perturbed box of about `hexes` hexahedra, the two
    programs measured at their calls: the JSON row."""
    import jax

    import jaxci.optim.laplace as laplace
    import jaxci.optim.lbfgs as solve
    from jaxci.interface.smooth import smooth
    from jaxci.mesh.generate import perturb_box

    n = max(2, round(hexes ** (1 / 3)))
    mesh = perturb_box(n, amplitude=0.3, seed=0)
    per = float(mesh.n_hexes)
    rows: dict = {}

    def measure(name, jitted, args, kwargs):
        live = sum(a.nbytes for a in jax.live_arrays())
        compiled = jitted.lower(*args, **kwargs).compile()
        m = getattr(compiled, "compiled", compiled).memory_analysis()  # equinox wraps jax's Compiled
        row = {"live": live / per}
        if m is not None:
            row |= {"arguments": m.argument_size_in_bytes / per, "outputs": m.output_size_in_bytes / per,
                    "temporaries": m.temp_size_in_bytes / per}
            row["peak_estimate"] = row["live"] + row["temporaries"]
        rows.setdefault(name, row)  # the first call (a restart would repeat it)

    real_solve, real_sweeps = solve.lbfgs_loop, laplace._laplace_run
    sweeps_jit = jax.jit(real_sweeps.__wrapped__, static_argnames=("smart", "p"))

    def lbfgs_loop(*a, **k):
        measure("lbfgs", real_solve, a, k)
        return real_solve(*a, **k)

    def sweeps(*a, **k):
        measure("presmoothing", sweeps_jit, a, k)
        return real_sweeps(*a, **k)

    solve.lbfgs_loop, laplace._laplace_run = lbfgs_loop, sweeps
    try:
        res = smooth(mesh, engine="jax", max_steps=max_steps, solver="lbfgs")
    finally:
        solve.lbfgs_loop, laplace._laplace_run = real_solve, real_sweeps
    return {"hexes": mesh.n_hexes, "engine": res.plan.to_dict(), "bytes_per_hex": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hexes", type=int, default=216_000, help="box size (rounded to a cube; default 216,000)")
    ap.add_argument("--out", type=Path, help="JSON path")
    args = ap.parse_args(argv)
    out = run(args.hexes)
    from bench_stamp import stamp

    out |= stamp()
    print(f"{out['hexes']:,} hexahedra, {out['engine']['device_kind']} ({out['engine']['dtype']}), bytes per "
          f"hexahedron:")
    for name, row in out["bytes_per_hex"].items():
        print(f"  {name:13s} " + ", ".join(f"{k} {v:.0f}" for k, v in row.items()))
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
