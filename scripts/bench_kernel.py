"""F + gradient corners per second in each kernel form, on the device JAX computes on.

The JAX engine's closed-form F + gradient (`jaxci.metrics.hexahedron.objective_terms_and_grad`) sums its
per-element gradient into the nodes in one of the forms of `jaxci.metrics.incidence` (``scatter``: 24
scatter-adds; ``gather``: a gather over the node incidences; ``segment``: one sorted segment sum); on CPU devices
the C kernel (``ffi``, `jaxci.metrics.native_grad`) replaces the XLA kernel where it is built. This script times
each, on perturbed boxes (`jaxci.mesh.generate.perturb_box`), float32 and float64, as the engine runs it (64-bit
integers and floats only for float64): warm, the forms called in turn round after round, the median of the
rounds. Corners per second = 8 x hexahedra / seconds per call. It prints a table and writes JSON.

    python scripts/bench_kernel.py --out results/bench_kernel.json          # 10^5 and 10^6 hexahedra
    python scripts/bench_kernel.py --small --out small.json                 # seconds: a check of the script

`run(sizes, dtypes)` is what scripts/bench_gpu.py calls (the same figures on its accelerator).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

#: The kernels timed: the XLA kernel's forms, and the C kernel through XLA's FFI (CPU devices only).
KERNELS = ("scatter", "gather", "segment", "ffi")
SIZES = (100_000, 1_000_000)
SMALL_SIZES = (1_000,)
ROUNDS, SMALL_ROUNDS = 7, 3


def machine() -> dict:
    """The machine the figures come from: the CPU, its cores, and the device JAX computes on."""
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu)
    except OSError:
        pass
    dev = jax.devices()[0]
    return {"cpu": cpu, "cpus": os.cpu_count(), "device": f"{dev.platform}: {dev.device_kind}",
            "jax": jax.__version__}


def _kernel(name: str):
    """``fn(x, conn, incidence) -> (F, max kappa/3, grad)`` jitted, for kernel `name`."""
    import jax

    from jaxci.metrics import native_grad
    from jaxci.metrics.hexahedron import objective_terms_and_grad

    if name == "ffi":
        return jax.jit(lambda x, conn, inc: native_grad.terms_and_grad(x, conn))
    return jax.jit(lambda x, conn, inc: objective_terms_and_grad(x, conn, incidence=inc))


def _time(fn, *args) -> float:
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def measure(hexes: int, dtype: str, rounds: int = ROUNDS, kernels=KERNELS) -> list[dict]:
    """One row per kernel of `kernels` on a perturbed box of about `hexes` hexahedra in `dtype`: seconds per
    call (median of `rounds` warm rounds, each calling every kernel once in turn), corners/s, the first call
    (compilation included) and, for ``gather`` and ``segment``, the incidences' build (once per problem: first
    and warm)."""
    import jax
    import numpy as np

    from jaxci.mesh.generate import perturb_box
    from jaxci.metrics import native_grad
    from jaxci.metrics.hexahedron import grad_block, transposed
    from jaxci.metrics.incidence import node_incidence

    n = max(2, round(hexes ** (1 / 3)))
    mesh = perturb_box(n, amplitude=0.3, seed=0)
    platform_ = jax.devices()[0].platform
    names = [k for k in kernels if k != "ffi" or native_grad.available(platform_)]
    rows = {}
    with jax.enable_x64(dtype == "float64"):
        x = jax.device_put(np.asarray(mesh.points, dtype))
        conn = transposed(mesh.hexes)
        calls = {}
        for name in names:
            inc, build = None, [None, None]
            if name in ("gather", "segment"):  # the first build compiles, the second is the warm build
                for i in range(2):
                    t0 = time.perf_counter()
                    inc = jax.block_until_ready(node_incidence(conn, x.shape[0], form=name))
                    build[i] = time.perf_counter() - t0
            fn = _kernel(name)
            calls[name] = (fn, inc)
            rows[name] = {"kernel": name, "hexes": mesh.n_hexes, "dtype": dtype, "incidence_first_s": build[0],
                          "incidence_warm_s": build[1], "first_call_s": _time(fn, x, conn, inc), "times": []}
        for _ in range(rounds):  # alternated: a load on the machine weighs on every kernel alike
            for name, (fn, inc) in calls.items():
                rows[name]["times"].append(_time(fn, x, conn, inc))
    block = grad_block(mesh.n_hexes)
    out = []
    for row in rows.values():
        t = float(np.median(row["times"]))
        out.append(row | {"seconds": t, "corners_per_s": 8 * mesh.n_hexes / t, "block": block,
                          "times": [round(s, 6) for s in row["times"]]})
    return out


def run(sizes=SIZES, dtypes=("float32", "float64"), rounds: int = ROUNDS, kernels=KERNELS) -> dict:
    """Every kernel at every size (hexahedra, rounded to a cube) and dtype: ``{"machine": ..., "rows": [...]}``
    (rows as `measure`)."""
    rows = [r for n in sizes for dt in dtypes for r in measure(n, dt, rounds, kernels)]
    return {"machine": machine(), "rounds": rounds, "rows": rows}


def table(rows: list[dict]) -> str:
    """The rows as a text table: M corners/s per kernel (columns) for each size and dtype (lines)."""
    kernels = [k for k in KERNELS if any(r["kernel"] == k for r in rows)]
    lines = [f"{'hexahedra':>10} {'dtype':>8} " + " ".join(f"{k:>9}" for k in kernels) + "   (M corners/s)"]
    for key in dict.fromkeys((r["hexes"], r["dtype"]) for r in rows):
        got = {r["kernel"]: r["corners_per_s"] / 1e6 for r in rows if (r["hexes"], r["dtype"]) == key}
        lines.append(f"{key[0]:>10,} {key[1]:>8} " + " ".join(f"{got[k]:9.2f}" if k in got else f"{'-':>9}"
                                                               for k in kernels))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", help="hexahedra (rounded to cubes; default 100000 1000000)")
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    ap.add_argument("--kernels", nargs="+", default=list(KERNELS), choices=KERNELS)
    ap.add_argument("--rounds", type=int, help=f"warm rounds (default {ROUNDS}; --small {SMALL_ROUNDS})")
    ap.add_argument("--small", action="store_true", help="a 1000-hexahedron box, 3 rounds: a check of the script")
    ap.add_argument("--out", type=Path, help="JSON path")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_stamp import stamp

    sizes = args.sizes or (SMALL_SIZES if args.small else SIZES)
    rounds = args.rounds or (SMALL_ROUNDS if args.small else ROUNDS)
    data = stamp() | run(sizes, args.dtypes, rounds, args.kernels)
    print(table(data["rows"]))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
