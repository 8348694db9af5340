"""Peak resident memory of `jaxci smooth` on the host, beside Mesquite's msqshape: one fresh process each.

Runs ``jaxci smooth IN OUT --force -q --json`` (the host engine on a CPU: numpy and C, no JAX import) as a child
of `bench_realmesh.run_child` (GNU time's maximum resident set size, else the child's ``ru_maxrss``) and records
its peak memory, wall and CPU seconds, and the peak bytes per hexahedron; with ``--msqshape``, also ``msqshape -s
IN OUT`` (every skin vertex fixed; ``shared/peers/msqshape``) the same way. The default input is ``cube60_pert``
(`scripts/realmesh_corpus.py`: the unit cube of 60^3 hexahedra, interior perturbed by 0.3 h, 1838 inverted: made
once, about 3 s, into ``~/.cache/jaxci/realmesh``). jaxci alone takes about 10-25 s on a 2-core machine; msqshape
about 5-8 minutes on cube60_pert (so it is opt-in). The figures are printed and written as JSON (``--out``). The
peak of jaxci includes its imports (about 40 MB). As `bench_realmesh` does, it first writes the bytecode of the
jaxci package (`bench_realmesh.ensure_bytecode`; ``--no-bytecode``: as found): a process that compiles its modules
at every start, as where ``PYTHONDONTWRITEBYTECODE`` is set and the sources were never compiled, needs about 0.15 s
and a few MB more.

With ``--stages`` (Linux), one more fresh process runs the same command in process and records the peak resident
set of each of its phases (read, validate, report, untangle, setup, smooth, checks, write): the kernel's high-water
mark at the end of each phase, reset there (``/proc/self/clear_refs``), so each figure is the peak from the end of
the phase before to the end of this one. That process is not the one timed: a reset peak is not its whole run's.

    python scripts/bench_memory.py                                  # jaxci on cube60_pert
    python scripts/bench_memory.py --msqshape --out memory.json     # and msqshape -s beside it
    python scripts/bench_memory.py --stages                         # and the peak of each phase
    python scripts/bench_memory.py --mesh part.vtk --jaxci-args=--fix-boundary
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import bench_realmesh as realmesh  # noqa: E402
import realmesh_corpus as corpus  # noqa: E402

MSQSHAPE = corpus.PEERS / "msqshape"


def timed(cmd: list[str], env: dict | None = None, timeout: float = 3600.0) -> dict:
    """Run `cmd` in a fresh process (`bench_realmesh.run_child`): ``peak_mb`` (MiB: kB / 1024, as msqshape's
    133 MB was quoted), ``peak_kb``, ``wall_s``, ``cpu_s`` (user + system), ``status``, the command's stdout, and
    its stderr's tail where it failed."""
    r = realmesh.run_child(cmd, env=env, timeout=timeout)
    if r["peak_rss_mb"] is None:
        raise SystemExit(f"no peak memory for {shlex.join(cmd)}: {r.get('error') or r['stderr_tail'][-2000:]}")
    row = {"command": shlex.join(cmd), "status": r["rc"], "peak_kb": round(r["peak_rss_mb"] * 1024),
           "peak_mb": round(r["peak_rss_mb"], 1), "wall_s": round(r["wall_s"], 2), "cpu_s": round(r["cpu_s"], 2),
           "stdout": r["stdout"]}
    if r["rc"]:
        row["stderr_tail"] = r["stderr_tail"][-2000:]
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


#: The ``--stages`` child: ``python -c STAGES_CHILD RECORDS jaxci-arguments...`` runs the jaxci command in process
#: and writes one JSON line to RECORDS at the end of each phase (`jaxci.runtime.phases.listening`): the phase and the
#: peak resident set since the last phase's end, in kB (VmHWM, then reset).
STAGES_CHILD = """
import json, runpy, sys
from jaxci.runtime.phases import listening

records = open(sys.argv[1], "w")


def on_event(kind, name, record):
    if kind != "end":
        return
    with open("/proc/self/status") as f:
        peak = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    records.write(json.dumps({"phase": name, "peak_kb": peak}) + "\\n")
    records.flush()
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


sys.argv = ["jaxci", *sys.argv[2:]]
with listening(on_event):
    runpy.run_module("jaxci", run_name="__main__", alter_sys=True)
"""


def run_stages(mesh: Path, out: Path, extra: list[str], tmp: Path) -> dict:
    """The peak resident set of each phase of `jaxci smooth` (`STAGES_CHILD`, in a fresh process with the
    environment the jaxci command gives itself: `jaxci.runtime.process.hugepage_environment`): ``{phase: kB}`` (a
    phase run twice: its larger peak)."""
    from jaxci.runtime.process import hugepage_environment

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), *filter(None, [env.get("PYTHONPATH")])])
    env = hugepage_environment(env) or env
    records = tmp / "stages.jsonl"
    r = subprocess.run([sys.executable, "-c", STAGES_CHILD, str(records), "smooth", str(mesh), str(out), "--force",
                        "-q", *extra], env=env, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"the --stages run failed ({r.returncode}): {r.stderr[-2000:]}")
    peaks: dict[str, int] = {}
    for line in records.read_text().splitlines():
        rec = json.loads(line)
        peaks[rec["phase"]] = max(peaks.get(rec["phase"], 0), rec["peak_kb"])
    return peaks


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
    ap.add_argument("--no-bytecode", action="store_true", help="do not write jaxci's bytecode first")
    ap.add_argument("--stages", action="store_true", help="also the peak memory of each phase (another process)")
    args = ap.parse_args(argv)
    import jaxci

    bytecode = "as found" if args.no_bytecode else realmesh.ensure_bytecode(Path(jaxci.__file__).parent)
    if args.mesh is None:
        entry = next(e for e in corpus.entries() if e.name == "cube60_pert")
        mesh, name = entry.ensure(), entry.name
    else:
        mesh, name = args.mesh, args.mesh.stem
    rows = {}
    with tempfile.TemporaryDirectory(prefix="jaxci-bench-memory-") as tmp:
        rows["jaxci"] = run_jaxci(mesh, Path(tmp) / f"jaxci{mesh.suffix}", shlex.split(args.jaxci_args))
        hexes = rows["jaxci"].get("hexahedra")
        if args.stages:
            rows["jaxci"]["stages_kb"] = run_stages(mesh, Path(tmp) / f"stages{mesh.suffix}",
                                                    shlex.split(args.jaxci_args), Path(tmp))
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
              "load_avg": [round(x, 2) for x in os.getloadavg()], "bytecode": bytecode}
    print(f"{name}: {hexes} hexahedra (commit {commit}, load {result['load_avg'][0]})")
    print(f"  {'':10} {'peak MB':>8} {'wall s':>7} {'cpu s':>7} {'B/hex':>7}  status")
    for who, row in rows.items():
        if "peak_kb" not in row:
            print(f"  {who:10} {row.get('skipped', '')}")
            continue
        print(f"  {who:10} {row['peak_mb']:8.1f} {row['wall_s']:7.2f} {row['cpu_s']:7.2f} "
              f"{row.get('bytes_per_hex', 0):7d}  {row['status']}")
        if "stages_kb" in row:
            print("    peak MB by phase: " + ", ".join(f"{k} {v / 1024:.1f}" for k, v in row["stages_kb"].items()))
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0 if all(r.get("status", 0) == 0 for r in rows.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
