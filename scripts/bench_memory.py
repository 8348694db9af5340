"""Peak resident memory of `jaxci smooth` on the host, beside Mesquite's msqshape: one fresh process each.

Runs ``jaxci smooth IN OUT --force -q --json`` (the host engine on a CPU: numpy and C, no JAX import) under
``/usr/bin/time -v`` and records its "Maximum resident set size", wall and CPU seconds, and the peak bytes per
hexahedron; with ``--msqshape``, also ``msqshape -s IN OUT`` (every skin vertex fixed; ``shared/peers/msqshape``)
the same way. The default input is ``cube60_pert`` (`scripts/realmesh_corpus.py`: the unit cube of 60^3
hexahedra, interior perturbed by 0.3 h, 1838 inverted: made once, about 3 s, into ``~/.cache/jaxci/realmesh``).
jaxci alone takes about 10-25 s on a 2-core machine; msqshape about 5-8 minutes on cube60_pert (so it is opt-in).
The figures are printed and written as JSON (``--out``). The peak of jaxci includes its imports (about 40 MB).

    python scripts/bench_memory.py                                  # jaxci on cube60_pert
    python scripts/bench_memory.py --msqshape --out memory.json     # and msqshape -s beside it
    python scripts/bench_memory.py --mesh part.vtk --jaxci-args=--fix-boundary
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import realmesh_corpus as corpus  # noqa: E402

TIME = "/usr/bin/time"
MSQSHAPE = corpus.PEERS / "msqshape"
#: What ``/usr/bin/time -v`` prints that is kept, by key.
_FIELDS = {"peak_kb": r"Maximum resident set size \(kbytes\): (\d+)",
           "user_s": r"User time \(seconds\): ([\d.]+)",
           "system_s": r"System time \(seconds\): ([\d.]+)",
           "wall": r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)"}


def _seconds(text: str) -> float:
    """``h:mm:ss`` or ``m:ss.ss`` as seconds."""
    out = 0.0
    for part in text.split(":"):
        out = out * 60 + float(part)
    return out


def timed(cmd: list[str], env: dict | None = None, timeout: float | None = None) -> dict:
    """Run `cmd` under ``/usr/bin/time -v``: ``peak_mb`` (MiB: kB / 1024, as msqshape's 133 MB was quoted),
    ``peak_kb``, ``wall_s``, ``cpu_s`` (user + system), ``status``, the command's stdout, and its stderr's tail
    where it failed."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as rep:
        p = subprocess.run([TIME, "-v", "-o", rep.name, *cmd], capture_output=True, text=True, env=env,
                           timeout=timeout)
        text = Path(rep.name).read_text()
    got = {k: m.group(1) for k, rx in _FIELDS.items() if (m := re.search(rx, text))}
    if "peak_kb" not in got:
        raise SystemExit(f"{TIME} -v gave no peak for {shlex.join(cmd)}:\n{text}{p.stderr[-2000:]}")
    row = {"command": shlex.join(cmd), "status": p.returncode, "peak_kb": int(got["peak_kb"]),
           "peak_mb": round(int(got["peak_kb"]) / 1024, 1), "wall_s": round(_seconds(got["wall"]), 2),
           "cpu_s": round(float(got["user_s"]) + float(got["system_s"]), 2), "stdout": p.stdout}
    if p.returncode:
        row["stderr_tail"] = p.stderr[-2000:]
    return row


def run_jaxci(mesh: Path, out: Path, extra: list[str]) -> dict:
    """`jaxci smooth` in a fresh process (this checkout's package: ``src`` first on ``PYTHONPATH``)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), *filter(None, [env.get("PYTHONPATH")])])
    row = timed([sys.executable, "-m", "jaxci", "smooth", str(mesh), str(out), "--force", "-q", "--json", *extra],
                env=env)
    summary = json.loads(row.pop("stdout") or "{}") if row["status"] == 0 else {}
    if summary:
        row["hexahedra"] = int(summary["before"]["n_elements"])
        row["engine"] = summary.get("engine")
        row["phases_s"] = {k: round(v["seconds"], 2) for k, v in summary.get("phases", {}).items()
                           if isinstance(v, dict) and "seconds" in v}
        row["after"] = {k: summary["after"][k] for k in ("inverted_elements", "max_condition", "mean_condition")}
    return row


def run_msqshape(mesh: Path, out: Path, timeout: float) -> dict:
    """``msqshape -s`` (every skin vertex fixed) in a fresh process."""
    row = timed([str(MSQSHAPE), "-s", str(mesh), str(out)], timeout=timeout)
    row.pop("stdout")
    return row


def _per_hex(row: dict, hexes: int | None) -> None:
    if hexes:
        row["bytes_per_hex"] = round(row["peak_kb"] * 1024 / hexes)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", type=Path, help="input mesh (default: cube60_pert, made if missing)")
    ap.add_argument("--jaxci-args", default="", help="more options of jaxci smooth, one string")
    ap.add_argument("--msqshape", action="store_true", help=f"also run msqshape -s ({MSQSHAPE}; minutes)")
    ap.add_argument("--msq-timeout", type=float, default=900.0, help="seconds (default 900)")
    ap.add_argument("--out", type=Path, help="write the JSON here")
    args = ap.parse_args(argv)
    if not Path(TIME).exists():
        raise SystemExit(f"{TIME} not found (GNU time: apt-get install time)")
    if args.mesh is None:
        entry = next(e for e in corpus.entries() if e.name == "cube60_pert")
        mesh, name = entry.ensure(), entry.name
    else:
        mesh, name = args.mesh, args.mesh.stem
    rows = {}
    with tempfile.TemporaryDirectory(prefix="jaxci-bench-memory-") as tmp:
        rows["jaxci"] = run_jaxci(mesh, Path(tmp) / f"jaxci{mesh.suffix}", shlex.split(args.jaxci_args))
        hexes = rows["jaxci"].get("hexahedra")
        if args.msqshape:
            if MSQSHAPE.exists():
                rows["msqshape"] = run_msqshape(mesh, Path(tmp) / "msq.vtk", args.msq_timeout)
            else:
                rows["msqshape"] = {"skipped": f"{MSQSHAPE} not found"}
    for row in rows.values():
        if "peak_kb" in row:
            _per_hex(row, hexes)
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    result = {"mesh": name, "path": str(mesh), "hexahedra": hexes, "rows": rows,
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "commit": commit, "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.node()}",
              "load_avg": [round(x, 2) for x in os.getloadavg()]}
    print(f"{name}: {hexes} hexahedra (commit {commit}, load {result['load_avg'][0]})")
    print(f"  {'':10} {'peak MB':>8} {'wall s':>7} {'cpu s':>7} {'B/hex':>7}  status")
    for who, row in rows.items():
        if "peak_kb" not in row:
            print(f"  {who:10} {row.get('skipped', '')}")
            continue
        print(f"  {who:10} {row['peak_mb']:8.1f} {row['wall_s']:7.2f} {row['cpu_s']:7.2f} "
              f"{row.get('bytes_per_hex', 0):7d}  {row['status']}")
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0 if all(r.get("status", 0) == 0 for r in rows.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
