"""`jaxci run CONFIG [--out DIR] [--force] [--seeds N] [--quiet]`: run an experiment config
(`jaxci.experiments.runner`). On a terminal (and without ``--quiet``), stderr shows one line of progress redrawn
in place: the run (k of n: mesh / method / seed), its phase, stage, step, F, worst element and the elapsed time
(`_progress`).

Exit codes: 0 all runs done, 1 some runs failed (listed on stderr, recorded in the summary), 2 a bad config or
output folder (nothing written), or an output folder that appeared or changed while the experiment ran (the
results are then beside it, ``DIR.new-N``, and the line says so), 130 on SIGINT (Ctrl-C) and 143 on SIGTERM: the
finished runs are written, marked ``"partial": true``, even when the signal comes during a long computation
(`_interrupt`).

DIR (`jaxci.experiments.results`): a new folder, or with ``--force`` an empty one or earlier jaxci results (marker file
``.jaxci-results``) holding nothing else; never the current folder or one holding an input (the config, its mesh
files, the files read through them). Earlier results are replaced only by a complete run: an interrupted run, or
one where every run failed, is written beside them to ``DIR.partial-N`` / ``DIR.failed-N`` (first free N) and
stderr says so. Checked again when the results are moved in: nothing that appeared at DIR meanwhile is replaced.
"""

from __future__ import annotations

import sys


def add_args(p) -> None:
    p.add_argument("config", help="experiment config (YAML); see configs/ and jaxci.experiments.config")
    p.add_argument("--out", metavar="DIR", help="output folder (default: the config's output, else "
                   "results/<config name>)")
    p.add_argument("--force", action="store_true",
                   help="replace DIR if it holds earlier jaxci results and nothing else (or is empty); they are "
                   "replaced only once the new run is complete, else it goes to DIR.partial-N / DIR.failed-N")
    p.add_argument("--seeds", type=int, metavar="N", help="run seeds 0..N-1 instead of the config's")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress line on stderr (shown only where stderr is a terminal) and no summary lines")
    p.epilog = ("exit codes: 0 all runs done; 1 some runs failed; 2 bad config or output folder (nothing written); "
                "130 on SIGINT, 143 on SIGTERM (finished runs written, marked partial, beside earlier results: "
                "DIR.partial-N)")


def _progress(enabled: bool):
    """The progress line on stderr (`_progress.Display`; a no-op context when disabled): ``(context, update)``,
    `update(done, total, text)` for `run_experiment`; inside the context each run's `jaxci.smooth` reports its
    phases, stages and steps to the line (`jaxci.runtime.phases.listening`)."""
    import contextlib

    if not enabled:
        return contextlib.nullcontext(), None
    from ..runtime.phases import listening
    from ._progress import Display

    display = Display(live=True)

    def update(done: int, total: int, text: str) -> None:
        display.set_context(f"run {min(done + 1, total)}/{total}: {text}" if done < total else text)

    @contextlib.contextmanager
    def shown():
        try:
            with listening(display.on_event):
                yield
        finally:
            display.close()

    return shown(), update


def _kept_line(res) -> str:
    """What an interrupted `run_experiment` wrote, for the stderr line."""
    if res is None:
        return "the finished runs could not be written in time (a temporary folder may remain)"
    s = res.summary
    done = f"{s['runs_done']} of {s['runs_planned']} runs" if s else f"{len(res.records)} runs"
    line = f"{done} finished, written to {res.out}" + (" (partial)" if res.partial else " (complete)")
    if res.taken is not None:
        line += f"; {res.taken}: left as it is"
    elif res.kept is not None:
        line += f"; earlier results in {res.kept} untouched"
    return line


def run(args) -> int:
    from ..errors import ConfigError, MeshReadError
    from ..experiments.runner import ExperimentResult, load_config, run_experiment
    from ..io._paths import check_regular
    from ._interrupt import completed, on_interrupt
    from ._progress import wanted

    try:  # a FIFO or a device would make reading the config wait forever
        check_regular(args.config, "config file (YAML)")
    except MeshReadError as e:
        raise ConfigError(str(e).replace(": no such file", ": no such config file")) from None
    exp = load_config(args.config)
    ctx, update = _progress(wanted(args.quiet))
    abort = []  # run_experiment's finish-now function, for the interrupt watchdog

    def emergency():
        return _kept_line(abort[0]()) if abort else None

    try:
        with on_interrupt(emergency), ctx:
            res = run_experiment(exp, args.out, force=args.force, seeds=args.seeds, progress=update,
                                 strict=args.debug, on_start=abort.append)
    except KeyboardInterrupt as e:
        partial = e.args[0] if e.args else None
        if not isinstance(partial, ExperimentResult) and abort:  # the results were written as it returned?
            partial = abort[0](write=False)
        if isinstance(partial, ExperimentResult):
            raise KeyboardInterrupt(_kept_line(partial)) from None
        raise
    completed(_kept_line(res))  # an interrupt from here on says where the results are, complete
    for r in res.failed:
        print(f"jaxci: run failed: {r.mesh} / {r.label} / seed {r.seed}: {r.error}", file=sys.stderr)
    if res.taken is not None:
        raise ConfigError(f"{res.taken}; left as it is: the results ({len(res.records)} runs) are in "
                          f"{res.out}")
    if res.kept is not None:
        print(f"jaxci: every run failed: written to {res.out}; earlier results in {res.kept} kept", file=sys.stderr)
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
