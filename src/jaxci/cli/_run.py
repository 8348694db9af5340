"""`jaxci run CONFIG [--out DIR] [--force] [--seeds N] [--quiet]`: run an experiment config (`jaxci.experiment`).

Exit codes: 0 all runs done, 1 some runs failed (listed on stderr, recorded in the summary), 2 a bad config or
output folder (nothing written), 130 interrupted (the finished runs are written, marked ``"partial": true``).
"""

from __future__ import annotations

import sys


def add_args(p) -> None:
    p.add_argument("config", help="experiment config (YAML); see configs/ and jaxci.config")
    p.add_argument("--out", metavar="DIR", help="output folder (default: the config's output, else "
                   "results/<config name>)")
    p.add_argument("--force", action="store_true", help="replace DIR if it exists (once the new one is complete)")
    p.add_argument("--seeds", type=int, metavar="N", help="run seeds 0..N-1 instead of the config's")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary lines")


def _progress_bar(enabled: bool):
    """A rich progress bar on stderr (a no-op context when disabled) and its `progress(done, total, text)`."""
    import contextlib

    if not enabled:
        return contextlib.nullcontext(), None
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                   console=Console(stderr=True), transient=True)
    task = bar.add_task("runs", total=None)

    def update(done: int, total: int, text: str) -> None:
        bar.update(task, completed=done, total=total, description=text)

    return bar, update


def run(args) -> int:
    from ..experiment import load_config, run_experiment

    exp = load_config(args.config)
    ctx, update = _progress_bar(not args.quiet and sys.stderr.isatty())
    try:
        with ctx:
            res = run_experiment(exp, args.out, force=args.force, seeds=args.seeds, progress=update,
                                 strict=getattr(args, "debug", False))
    except KeyboardInterrupt as e:
        partial = e.args[0] if e.args else None
        if partial is not None and hasattr(partial, "out"):
            print(f"jaxci: interrupted: {len(partial.records)} finished runs written to {partial.out} "
                  f"(partial)", file=sys.stderr)
        raise
    for r in res.failed:
        print(f"jaxci: run failed: {r.mesh} / {r.label} / seed {r.seed}: {r.error}", file=sys.stderr)
    if not args.quiet:
        n = len(res.records)
        print(f"wrote {res.out}: {n} runs ({len(res.failed)} failed) in {res.summary['elapsed']:.1f} s; "
              f"see {res.out / 'report.md'}")
        for a in res.summary["aggregates"]:
            if a["mean_max_condition"] is not None:
                print(f"  {a['mesh']:<14} {a['method']:<24} max kappa/3 worst {a['worst_max_condition']:.4f} "
                      f"best {a['best_max_condition']:.4f} mean {a['mean_max_condition']:.4f}  "
                      f"median {a['median_wall_time']:.2f} s")
    return 1 if res.failed else 0
