"""Many small meshes: one ``jaxci smooth DIR --out-dir OUT`` call against Mesquite's msqshape on each file in turn.

The corpus (``--count`` meshes of ``--min-hexes`` to ``--max-hexes`` hexahedra, legacy ASCII VTK 4.2, which both
read) is first every real mesh of that size in ``shared/data/mesquite`` (read there, copied only into the temporary
folder: ``large_box_hex_1000``, ``1000hex-block-internal-bias``, ``pave3.e``), then perturbed boxes made here to
make up the count (`jaxci.perturb_box`, interior nodes moved by 0.1-0.35 of the spacing, inverted draws redrawn;
nx, ny, nz of 4-30 and element aspect ratios of 1-2.5, from ``numpy.random.default_rng(--seed)``).

Timed, each in fresh processes, wall clock (``--repeat`` times, alternating; the median is the headline):

- ``batch``: one ``jaxci smooth DIR --out-dir OUT --engine auto --json`` (the default method; every worker
  process it starts included);
- ``msqshape``: ``msqshape -s IN OUT`` (every skin vertex fixed, as `bench_realmesh.py` runs it) on each file, one
  after another;
- ``batch_fixed``: the batch with ``--fix-boundary``, the problem msqshape -s solves (``--no-fixed`` skips it);
- ``single`` (``--single``): ``jaxci smooth IN OUT --engine auto`` on each file, one after another.

The worst element (max kappa/3) of each output is read back with `jaxci.metrics.report.quality_report`, msqshape's
and jaxci's alike. Prints the figures, writes the JSON (date, commit, machine, command, per-file rows) and with
``--md`` the results page.

    python scripts/bench_batch.py [--count 100] [--repeat 3] [--single] [--out docs/results/bench_batch.json]
        [--md docs/results/bench_batch.md]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import realmesh_corpus as corpus  # noqa: E402
from bench_compile import machine  # noqa: E402
from bench_realmesh import MSQSHAPE, last_json, run_child  # noqa: E402
from bench_stamp import stamp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
JAXCI = [sys.executable, "-m", "jaxci"]


def real_meshes(lo: int, hi: int) -> list[tuple[str, Path, int]]:
    """``(name, path, hexahedra)`` of the Mesquite meshes with `lo` to `hi` hexahedra."""
    from jaxci.io import read_mesh

    out = []
    for path in sorted(corpus.MESQUITE.glob("*.vtk")):
        n = read_mesh(path).n_hexes
        if lo <= n <= hi:
            out.append((path.name, path, n))
    return out


def boxes(count: int, lo: int, hi: int, seed: int):
    """`count` perturbed boxes of `lo` to `hi` hexahedra: ``(name, mesh, recipe)``."""
    from jaxci import perturb_box

    rng = np.random.default_rng(seed)
    made = 0
    while made < count:
        nx, ny, nz = (int(v) for v in rng.integers(4, 31, size=3))
        if not lo <= nx * ny * nz <= hi:
            continue
        spacing = rng.uniform(1.0, 2.5, size=3)
        amplitude = float(rng.uniform(0.1, 0.35))
        box_seed = int(rng.integers(0, 2**31))
        size = tuple(float(v) for v in np.array([nx, ny, nz]) * spacing / max(nx, ny, nz))
        mesh = perturb_box(nx, ny, nz, amplitude=amplitude, seed=box_seed, which="interior", size=size)
        recipe = dict(nx=nx, ny=ny, nz=nz, size=[round(s, 6) for s in size], amplitude=round(amplitude, 4),
                      seed=box_seed, which="interior")
        made += 1
        yield f"box{made:03d}_{nx}x{ny}x{nz}.vtk", mesh, recipe


def make_corpus(folder: Path, args) -> list[dict]:
    """Write the corpus into `folder`; one row per mesh (name, source, hexahedra, worst element before)."""
    from jaxci.io import read_mesh
    from jaxci.metrics.report import quality_report

    rows = []
    for name, path, n in real_meshes(args.min_hexes, args.max_hexes)[: args.count]:
        shutil.copyfile(path, folder / name)
        rows.append(dict(name=name, source="real (shared/data/mesquite)", hexes=n))
    for name, mesh, recipe in boxes(args.count - len(rows), args.min_hexes, args.max_hexes, args.seed):
        corpus.write_vtk(folder / name, np.asarray(mesh.points), np.asarray(mesh.hexes))
        rows.append(dict(name=name, source="generated (perturb_box)", hexes=mesh.n_hexes, recipe=recipe))
    for row in rows:
        rep = quality_report(read_mesh(folder / row["name"]))
        row["before"] = dict(max_condition=rep.max_condition, mean_condition=rep.mean_condition,
                             inverted_elements=rep.inverted_elements)
    return rows


def worst(path: Path) -> dict:
    """The worst and mean element (and inverted count) of a written mesh, by jaxci's quality report."""
    from jaxci.io import read_mesh
    from jaxci.metrics.report import quality_report

    try:
        rep = quality_report(read_mesh(path))
    except Exception as e:  # noqa: BLE001 - a broken output is a result
        return dict(error=f"{type(e).__name__}: {e}")
    return dict(max_condition=rep.max_condition, mean_condition=rep.mean_condition,
                inverted_elements=rep.inverted_elements)


def run_batch(src: Path, out: Path, extra: list[str], timeout: float) -> dict:
    """One ``jaxci smooth SRC --out-dir OUT`` process: wall, CPU, its JSON totals and per-file rows."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [*JAXCI, "smooth", str(src), "--out-dir", str(out), "--engine", "auto", "--json", "-q", *extra]
    r = run_child(cmd, timeout=timeout)
    doc = last_json(r.pop("stdout")) or {}
    files = {Path(f["input"]).name: f for f in doc.get("files", [])}
    rows = {name: dict(exit_code=f["exit_code"], seconds=f["seconds"], **worst(out / name))
            for name, f in files.items()}
    return dict(cmd=_shown(cmd, src, out), rc=r["rc"], wall_s=r["wall_s"], cpu_s=r["cpu_s"],
                totals=doc.get("totals"), files=rows, stderr_tail=r["stderr_tail"][-600:])


def run_each(names: list[str], src: Path, out: Path, make_cmd, timeout: float) -> dict:
    """`make_cmd(input, output)` for each file, one process after another: the wall of the whole loop."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    rows, cpu = {}, 0.0
    t0 = time.perf_counter()
    for name in names:
        r = run_child(make_cmd(src / name, out / name), timeout=timeout)
        cpu += r["cpu_s"] or 0.0
        rows[name] = dict(exit_code=r["rc"], seconds=r["wall_s"])
    wall = time.perf_counter() - t0
    for name in names:
        rows[name].update(worst(out / name) if (out / name).exists() else dict(error="no output"))
    return dict(cmd=_shown(make_cmd(Path("IN"), Path("OUT")), src, out), wall_s=wall, cpu_s=cpu,
                files=rows)


def _shown(cmd: list, src: Path, out: Path) -> str:
    """`cmd` as the results show it: ``jaxci`` for this Python's ``-m jaxci``, ``msqshape`` for its path, DIR and
    OUT for the corpus and output folders."""
    words = [str(c) for c in cmd]
    if words[:3] == JAXCI:
        words = ["jaxci", *words[3:]]
    names = {str(MSQSHAPE): "msqshape", str(src): "DIR", str(out): "OUT"}
    return " ".join(names.get(w, w) for w in words)


def summarise(run: dict, rows: list[dict]) -> dict:
    """Files done, the largest and mean worst element over the files."""
    got = [run["files"].get(r["name"], {}) for r in rows]
    ok = [g for g in got if g.get("exit_code") == 0 and g.get("max_condition") is not None]
    kmax = [g["max_condition"] for g in ok]
    return dict(files_ok=len(ok), files=len(rows), worst_max_condition=max(kmax, default=None),
                mean_max_condition=statistics.fmean(kmax) if kmax else None,
                inverted_outputs=sum(1 for g in ok if g.get("inverted_elements")))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=100, help="meshes in the corpus (default %(default)s)")
    ap.add_argument("--min-hexes", type=int, default=500)
    ap.add_argument("--max-hexes", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0, help="seed of the generated boxes (default %(default)s)")
    ap.add_argument("--repeat", type=int, default=1, help="timed rounds of each run (default %(default)s)")
    ap.add_argument("--single", action="store_true", help="also the single form on each file in turn")
    ap.add_argument("--no-fixed", action="store_true", help="skip the batch with --fix-boundary")
    ap.add_argument("--jobs", type=int, default=None, help="--jobs of the batch (default: its own default)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per process (default %(default)s)")
    ap.add_argument("--work-dir", help="keep the corpus and outputs here (default: a temporary folder)")
    ap.add_argument("--out", help="write the JSON here (e.g. docs/results/bench_batch.json)")
    ap.add_argument("--md", help="write the results page here (e.g. docs/results/bench_batch.md)")
    ap.add_argument("--from-json", metavar="JSON", help="measure nothing: write the --md page of this JSON")
    args = ap.parse_args(argv)
    if args.from_json:
        Path(args.md).write_text(page(json.loads(Path(args.from_json).read_text())))
        print(f"wrote {args.md}")
        return 0

    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="jaxci-batch-"))
    src = work / "in"
    shutil.rmtree(src, ignore_errors=True)
    src.mkdir(parents=True)
    rows = make_corpus(src, args)
    names = [r["name"] for r in rows]
    real = [r["name"] for r in rows if r["source"].startswith("real")]
    print(f"{len(rows)} meshes in {src}: {len(real)} real ({', '.join(real) or 'none'}), "
          f"{len(rows) - len(real)} generated; {sum(r['hexes'] for r in rows)} hexahedra in all", flush=True)
    jobs = [] if args.jobs is None else ["--jobs", str(args.jobs)]
    plans = {"batch": lambda: run_batch(src, work / "out_batch", jobs, args.timeout)}
    if MSQSHAPE.exists():
        plans["msqshape"] = lambda: run_each(names, src, work / "out_msq",
                                             lambda i, o: [str(MSQSHAPE), "-s", str(i), str(o)], args.timeout)
    if not args.no_fixed:
        plans["batch_fixed"] = lambda: run_batch(src, work / "out_fixed", [*jobs, "--fix-boundary"], args.timeout)
    if args.single:
        plans["single"] = lambda: run_each(names, src, work / "out_single",
                                           lambda i, o: [*JAXCI, "smooth", str(i), str(o), "--engine", "auto", "-q"],
                                           args.timeout)
    runs: dict[str, list[dict]] = {k: [] for k in plans}
    for round_ in range(args.repeat):
        for key, plan in plans.items():
            load = _load()
            r = plan()
            r["load_before"] = load
            runs[key].append(r)
            print(f"round {round_ + 1}: {key:<12} {r['wall_s']:8.2f} s wall, {r['cpu_s']:8.2f} s CPU (1-minute load "
                  f"average before: {load})", flush=True)
    result = {}
    for key, rs in runs.items():
        walls = [r["wall_s"] for r in rs]
        result[key] = dict(cmd=rs[-1]["cmd"], wall_s=walls, median_wall_s=statistics.median(walls),
                           cpu_s=[r["cpu_s"] for r in rs], load_before=[r["load_before"] for r in rs],
                           **summarise(rs[-1], rows),
                           **({"totals": rs[-1]["totals"]} if "totals" in rs[-1] else {}))
    for row in rows:
        for key, rs in runs.items():
            row[key] = rs[-1]["files"].get(row["name"])
    doc = {**stamp(), "machine": machine(), "benchmark": "bench_batch", "msqshape": str(MSQSHAPE),
           "corpus": dict(count=len(rows), real=real, min_hexes=args.min_hexes, max_hexes=args.max_hexes,
                          seed=args.seed, hexes=sum(r["hexes"] for r in rows)),
           "notes": ["wall clock of fresh processes (the per-file loops: every process start included); worst "
                     "element = max kappa/3 of each output by jaxci.metrics.report.quality_report",
                     "msqshape -s fixes every skin vertex; jaxci's default lets boundary nodes slide on the "
                     "boundary (batch_fixed: --fix-boundary, the same problem as msqshape -s)"],
           "results": result, "meshes": rows}
    print()
    print(f"{'run':<12} {'median wall s':>14} {'files ok':>9} {'worst max k/3':>14} {'mean max k/3':>13}")
    for key, r in result.items():
        print(f"{key:<12} {r['median_wall_s']:14.2f} {r['files_ok']:>5}/{r['files']:<3} "
              f"{_f(r['worst_max_condition']):>14} {_f(r['mean_max_condition']):>13}")
    for row in rows:
        if row["name"] in real:
            cells = "  ".join(f"{k} {_f((row.get(k) or {}).get('max_condition'))}" for k in runs)
            print(f"  {row['name']}: {row['hexes']} hexes, before {_f(row['before']['max_condition'])}; {cells}")
    if args.out:
        Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.out}")
    if args.md:
        Path(args.md).write_text(page(doc))
        print(f"wrote {args.md}")
    if not args.work_dir:
        shutil.rmtree(work, ignore_errors=True)
    return 0


def _load() -> float | None:
    """The 1-minute load average (None where there is none): the machine may be shared."""
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def _f(x, fmt: str = ".5g") -> str:
    return "-" if x is None else format(x, fmt)


def _as_good(doc: dict, key: str) -> str:
    """How many files `key`'s worst element is at most msqshape's on (to 1e-9), of those both did."""
    if key == "msqshape":
        return "-"
    pairs = [(row.get(key) or {}, row.get("msqshape") or {}) for row in doc["meshes"]]
    pairs = [(a["max_condition"], b["max_condition"]) for a, b in pairs
             if a.get("max_condition") is not None and b.get("max_condition") is not None]
    if not pairs:
        return "-"
    return f"{sum(a <= b * (1 + 1e-9) for a, b in pairs)}/{len(pairs)}"


def _loads(res: dict) -> str:
    loads = [x for r in res.values() for x in r.get("load_before", []) if x is not None]
    return f"{min(loads):.1f}-{max(loads):.1f}" if loads else "not known"


def page(doc: dict) -> str:
    """The results page: the headline table, the real meshes' rows, how it was made."""
    res, c = doc["results"], doc["corpus"]
    m = doc["machine"]
    lines = ["# Many small meshes: one `jaxci smooth --out-dir` call against msqshape on each", "",
             f"Measured {doc['date']} at commit {doc['commit']} on {m['cpu']} ({m['cpus']} cores), with "
             f"`python scripts/{doc['command']}`.", "",
             f"{c['count']} meshes of {c['min_hexes']}-{c['max_hexes']} hexahedra ({c['hexes']:,} in all), legacy "
             f"ASCII VTK: {len(c['real'])} real meshes of that size from Mesquite's meshFiles "
             f"({', '.join(c['real'])}), the rest perturbed boxes (`perturb_box`, seed {c['seed']}: sizes, element "
             f"aspect and amplitude drawn per box). Wall clock of fresh processes; median of "
             f"{len(next(iter(res.values()))['wall_s'])} rounds, the runs alternating. Worst element = max kappa/3 "
             f"of each output (jaxci's quality report, msqshape's outputs included). The machine was shared: the "
             f"1-minute load average before each run was {_loads(res)}.", "",
             "| run | command | wall s (median) | wall s (rounds) | files ok | worst max k/3 over files | mean of the "
             "files' max k/3 | files with a worst element no worse than msqshape's |", "|---" * 8 + "|"]
    for key, r in res.items():
        rounds = ", ".join(f"{w:.1f}" for w in r["wall_s"])
        lines.append(f"| {key} | `{r['cmd']}` | {r['median_wall_s']:.1f} | {rounds} | {r['files_ok']}/{r['files']} "
                     f"| {_f(r['worst_max_condition'])} | {_f(r['mean_max_condition'])} | {_as_good(doc, key)} |")
    if "batch" in res and "msqshape" in res:
        b, m = res["batch"]["median_wall_s"], res["msqshape"]["median_wall_s"]
        single = f", {res['single']['median_wall_s'] / b:.1f}x faster than the one-file form on each file in turn" \
            if "single" in res else ""
        lines += ["", f"The one `jaxci smooth --out-dir` call took {b:.1f} s, {m / b:.1f}x faster than msqshape -s on "
                      f"each file in turn ({m:.1f} s){single}."]
    keys = list(res)
    lines += ["", "The real meshes (max kappa/3 before and after):", "",
              "| mesh | hexahedra | before | " + " | ".join(keys) + " |", "|---|---|---|" + "---|" * len(keys)]
    for row in doc["meshes"]:
        if row["name"] in c["real"]:
            cells = " | ".join(_f((row.get(k) or {}).get("max_condition")) for k in keys)
            lines.append(f"| {row['name']} | {row['hexes']} | {_f(row['before']['max_condition'])} | {cells} |")
    lines += ["", "Notes:", "", *(f"- {n}" for n in doc.get("notes", []))]
    lines += ["", "msqshape `-s` fixes every skin vertex; jaxci's default lets boundary nodes slide on the boundary, "
              "so its worst elements can be lower: `batch_fixed` (`--fix-boundary`) solves msqshape's problem. "
              "Per-file rows (seconds, worst and mean element, exit status) are in "
              "[bench_batch.json](bench_batch.json).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
