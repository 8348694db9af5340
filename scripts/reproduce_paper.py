"""Reproduce the paper's Tables 1-3: run an experiment config and print the tables of its report.md.

    python scripts/reproduce_paper.py                                   # configs/paper.yaml -> results/paper
    python scripts/reproduce_paper.py --config configs/paper_quick.yaml --out results/paper_quick --force

A thin wrapper around ``jaxci run`` (`jaxci.cli.main`): same output folder (summary.json, runs.csv, history.json,
report.md, figures/, meshes/), same exit codes (0, 1 if some runs failed, 2 bad config, 130 interrupted).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(REPO / "configs" / "paper.yaml"), help="experiment config")
    parser.add_argument("--out", help="output folder (default: the config's output)")
    parser.add_argument("--force", action="store_true", help="replace the output folder if it exists")
    parser.add_argument("--seeds", type=int, metavar="N", help="run seeds 0..N-1 instead of the config's")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    from jaxci.cli import main as jaxci_main
    from jaxci.experiments.runner import load_config, resolve_output

    argv_run = ["run", args.config, "--quiet"]
    if args.out:
        argv_run += ["--out", args.out]
    if args.force:
        argv_run.append("--force")
    if args.seeds:
        argv_run += ["--seeds", str(args.seeds)]
    if not args.quiet and sys.stderr.isatty():
        argv_run.remove("--quiet")
    code = jaxci_main(argv_run)
    if code == 2:
        return code
    out, _ = resolve_output(load_config(args.config), args.out)
    report = out / "report.md"
    if report.is_file():
        print(report.read_text())
    return code


if __name__ == "__main__":
    sys.exit(main())
