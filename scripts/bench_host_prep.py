"""The host-side work of one smoothing run, phase by phase and function by function.

On an accelerator the solver's steps are cheap and what the host does around them (numpy on one core: checking
the input, the quality reports, classifying the boundary, building the constraints and the parametrisation,
colouring and padding the presmoothing's stars, projecting the result exactly, the final checks) decides the
wall time of a large mesh. This benchmark runs `jaxci.smooth` on a perturbed box under cProfile, with the
solver's steps capped (``--max-steps``) so that the host's work is what is measured, and prints and writes (JSON)
the seconds of each phase (`jaxci.runtime.phases`) and the cumulative seconds of the host functions that matter
(`FUNCTIONS`; a function absent from the profile is reported as 0).

    python scripts/bench_host_prep.py --hexes 1000000 --engine jax --out host_prep.json

The figures include cProfile's overhead (small: these functions are whole-array numpy and C calls).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time
from pathlib import Path

#: (module path suffix, function name) of the host functions reported.
FUNCTIONS = (
    ("jaxci/mesh/__init__.py", "check_volume"),
    ("jaxci/mesh/__init__.py", "__post_init__"),
    ("jaxci/metrics/report.py", "quality_report"),
    ("jaxci/metrics/report.py", "worst_elements"),
    ("jaxci/metrics/guard.py", "keep_worst"),
    ("jaxci/geometry/boundary.py", "classify_boundary"),
    ("jaxci/geometry/topology.py", "boundary_topology"),
    ("jaxci/geometry/projection.py", "build_constraints"),
    ("jaxci/geometry/projection.py", "project_np"),
    ("jaxci/optim/parametrisation.py", "make_parametrisation"),
    ("jaxci/optim/parametrisation.py", "node_lengths"),
    ("jaxci/optim/_moves.py", "coloured_stars"),
    ("jaxci/optim/_moves.py", "planar_rings"),
    ("jaxci/optim/_moves.py", "pad_stars"),
    ("jaxci/optim/_moves.py", "pad_slots"),
    ("jaxci/optim/_local.py", "node_stars"),
    ("jaxci/optim/_local.py", "edge_neighbours"),
    ("jaxci/optim/polish.py", "polish"),
)


def _cumulative(stats: pstats.Stats) -> dict[str, float]:
    out = {_key(name): 0.0 for _, name in FUNCTIONS}
    for (file, _, func), (_, _, _, cum, _) in stats.stats.items():
        for path, name in FUNCTIONS:
            if func == name and file.replace("\\", "/").endswith(path):
                out[_key(name)] = max(out[_key(name)], cum)  # recursive entries: the outermost
    return {k: round(v, 6) for k, v in out.items()}


def _key(name: str) -> str:
    return "HexMesh.__post_init__" if name == "__post_init__" else name


def run(hexes: int, engine: str = "jax", max_steps: int = 5) -> dict:
    """`jaxci.smooth` on a perturbed box of about `hexes` hexahedra under cProfile: the JSON row (phases, host
    functions, the plan)."""
    from jaxci.interface.smooth import smooth
    from jaxci.mesh.generate import perturb_box

    n = max(2, round(hexes ** (1 / 3)))
    t0 = time.perf_counter()
    mesh = perturb_box(n, amplitude=0.3, seed=0)
    generate = time.perf_counter() - t0
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    try:
        res = smooth(mesh, engine=engine, max_steps=max_steps)
    finally:
        prof.disable()
    wall = time.perf_counter() - t0
    return {"hexes": mesh.n_hexes, "engine": res.plan.to_dict(), "describe": res.plan.describe(),
            "max_steps": max_steps, "generate_s": round(generate, 3), "wall_s": round(wall, 3),
            "phases": {k: round(v["seconds"], 3) for k, v in res.phases.items()},
            "functions": _cumulative(pstats.Stats(prof))}


def main(argv=None) -> int:
    from bench_stamp import stamp

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hexes", type=int, default=1_000_000, help="box size (rounded to a cube; default 10^6)")
    ap.add_argument("--engine", default="jax", choices=("jax", "host"), help="the engine (default jax)")
    ap.add_argument("--max-steps", type=int, default=5, help="the solver's step cap (default 5)")
    ap.add_argument("--out", type=Path, help="JSON path")
    args = ap.parse_args(argv)
    out = run(args.hexes, args.engine, args.max_steps)
    out |= stamp()
    print(f"{out['hexes']:,} hexahedra, {out['describe']}: {out['wall_s']:.2f} s")
    print("phases:", ", ".join(f"{k} {v:.2f}" for k, v in out["phases"].items()))
    for k, v in sorted(out["functions"].items(), key=lambda kv: -kv[1]):
        print(f"  {k:24s} {v:8.3f} s")
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
