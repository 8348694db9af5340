"""The presmoothing's data and the parametrisation of the JAX engine, built on the host (numpy, then uploaded)
against built on the device (`jaxci.optim.device_stars`, `jaxci.optim.device_parametrisation`).

On a perturbed box of ``size^3`` hexahedra, float32 as the JAX engine runs, each of the two is timed twice,
alternated (old, new, old, new; the first of each pays its compilation):

- the presmoothing: colouring, stars, neighbours, padding and upload, then 3 smart-Laplace sweeps (old: the
  host's first-fit colouring, `coloured_stars`, `coloured_neighbours`, `laplace`; new: `sweep_data` with the
  device's colouring, `laplace_device`, its two parts also timed alone; with the stars as incidences, and as
  node lists relabelled once, ``_lists``);
- the parametrisation with its padding to the size class (old: `make_parametrisation`, then the copy back and
  `pad_parametrisation` in numpy as `minimise` did; new: `make_parametrisation_device`, `pad_problem_device`).

For each: wall seconds, seconds compiling, seconds inside compiled programs (``device_s``), the rest
(``host_s``), and the bytes each way (`jaxci.runtime.transfer`); and F after the sweeps with each colouring.

    python scripts/bench_device_prep.py --size 100 --out device_prep.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def _measure(fn) -> tuple[dict, object]:
    """``(figures, result)`` of `fn()`: wall, compile, device and host seconds, bytes each way."""
    from jaxci.runtime import transfer
    from jaxci.runtime.phases import compile_totals

    c0, t0 = compile_totals(), transfer.totals()
    w0 = time.perf_counter()
    out = fn()
    wall = time.perf_counter() - w0
    c1, t1 = compile_totals(), transfer.totals()
    compile_s = sum(c1[k] - c0[k] for k in ("trace", "lower", "backend"))
    device_s = t1["device_s"] - t0["device_s"]
    return {"wall_s": round(wall, 3), "compile_s": round(compile_s, 3), "device_s": round(device_s, 3),
            "host_s": round(wall - compile_s - device_s, 3), "h2d_bytes": t1["h2d_bytes"] - t0["h2d_bytes"],
            "d2h_bytes": t1["d2h_bytes"] - t0["d2h_bytes"]}, out


def run(size: int) -> dict:
    import jax

    from jaxci.geometry.topology import colour_nodes
    from jaxci.interface.methods import build_problem
    from jaxci.mesh.generate import perturb_box
    from jaxci.optim import laplace as L
    from jaxci.optim._buckets import bucket, padded_connectivity, to_device
    from jaxci.optim._moves import coloured_stars
    from jaxci.optim.device_parametrisation import make_parametrisation_device
    from jaxci.optim.device_stars import sweep_data
    from jaxci.optim.parametrisation import make_parametrisation, pad_parametrisation, pad_problem_device
    from jaxci.runtime.transfer import to_host

    mesh = perturb_box(size, amplitude=0.3, seed=0)
    pr = build_problem(mesh, dtype=np.float32)
    faces, info = pr.info.topology.faces, pr.info
    p = L.LaplaceParams(max_sweeps=3)
    hexes = mesh.hexes

    def old_presmooth():
        colour = colour_nodes(np.array(hexes), mesh.n_nodes).colour  # a fresh array: no cached colouring
        cs = coloured_stars(hexes, pr.cons, colour, faces, place=False)
        nbr, nmask = L.coloured_neighbours(cs, hexes, mesh.n_nodes, place=False)
        x, sweeps, hist, _ = L.laplace(pr.x0, pr.conn, cs, nbr, nmask, pr.cons, p, smart=True)
        return jax.block_until_ready(x), hist, int(colour.max()) + 1, {}

    def new_presmooth(lists=False):
        build, data = _measure(lambda: jax.block_until_ready(sweep_data(pr.x0, pr.conn, pr.cons, faces, lists=lists)))
        sweeps, (x, _, hist, _) = _measure(lambda: jax.block_until_ready(L.laplace_device(data, p, smart=True)))
        rows = int(to_host(data.n_colours))
        return x, hist, data.colours, {"build": build, "sweeps": sweeps, "rows": rows,
                                       "slots": rows * int(data.cs.nodes.shape[1])}

    points64 = to_device(np.asarray(mesh.points, np.float64))
    n_el = bucket(mesh.n_hexes)

    def old_parametrisation():
        par = make_parametrisation(mesh, info, pr.cons, dtype=np.float32)
        padded, _ = pad_parametrisation(to_host(par))  # the copy back `_bucketed` made
        c, w = padded_connectivity(np.asarray(pr.conn).T, n_el)
        return jax.block_until_ready((padded, to_device(c, np.int32), to_device(w, np.float32)))

    def new_parametrisation():
        with jax.enable_x64(True):
            par = make_parametrisation_device(points64, pr.conn, faces, info.feature_edges, pr.cons,
                                              dtype=np.float32)
            padded, _, c, w = pad_problem_device(par, pr.conn, n_el)
        return jax.block_until_ready((padded, c, w))

    rows = {}
    for rep in ("cold", "warm"):
        for name, fn in (("presmooth_host", old_presmooth), ("presmooth_device", new_presmooth),
                         ("presmooth_device_lists", lambda: new_presmooth(lists=True)),
                         ("parametrisation_host", old_parametrisation),
                         ("parametrisation_device", new_parametrisation)):
            figures, out = _measure(fn)
            if name.startswith("presmooth"):
                _, hist, colours, parts = out
                figures.update(colours=colours, objective=[float(v) for v in hist["objective"]],
                               max_condition=[float(v) for v in hist["max_condition"]], **parts)
            rows.setdefault(name, {})[rep] = figures
            print(name, rep, figures, flush=True)
    from bench_stamp import stamp

    mesh_bytes = mesh.points.nbytes + 4 * hexes.size
    return {**stamp(), "hexes": mesh.n_hexes, "nodes": mesh.n_nodes, "mesh_bytes": int(mesh_bytes),
            "device": str(jax.devices()[0]), "rows": rows}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=100, help="box edge in hexahedra (default 100: 10^6 hexahedra)")
    ap.add_argument("--out", default=None, help="JSON output file")
    args = ap.parse_args(argv)
    data = run(args.size)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(data, f, indent=1)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
