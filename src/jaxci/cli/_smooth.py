"""`jaxci smooth IN OUT [--method M] [--engine E] [--device D] [--seed S] [--devices N|all] [--json] [--verbose]
[--quiet] [--report FILE] [--force]`: smooth a mesh, write it as OUT. ``jaxci smooth IN... --out-dir DIR [--jobs N]
[options]`` smooths many (`_batch`: each IN a mesh file or a folder of them, each written to DIR under its own
name, over a pool of worker processes; exit status 0 if every file succeeded, else the largest per-file status).

The per-file work (read, check the files read against the output, smooth, write) is `_smooth_file.smooth_file`,
with `_smooth_file.smooth_options` (the options as `jaxci.smooth`'s arguments), `_smooth_file.summary` (the
``--json`` object) and `_smooth_file.exit_status`: both forms call them.

``--engine auto|host|jax`` and ``--device auto|cpu|gpu`` are `jaxci.smooth`'s ``engine`` and ``device``: one
decision (`jaxci.interface.engine.resolve_plan`), printed with the result (``engine:`` line; ``--json``: the ``engine``
object with its name, device, dtype and kernel; ``--verbose``: as the run starts).

Without ``--method`` the default pipeline runs (``auto``: `jaxci.interface.smooth.auto_pipeline`), and the output says
which. ``--json`` reports the time of each phase (``phases``: ``startup`` (process start, imports and JAX set-up),
``read``, then `jaxci.smooth`'s ``validate``, ``report``, ``untangle``, ``setup``, ``smooth``, ``checks``, and
``write``; each with its compilation seconds and count); ``--verbose`` prints one line per phase on stderr as it
ends, and one per stage inside it (an untangling round, a solver's restart). On a terminal, stderr shows one line
of progress redrawn in place (phase, stage, step, F, the worst element, elapsed time: `_progress`), erased before
the result is printed; nothing when stderr is not a terminal or with ``--quiet``. ``--report FILE`` (``.html`` or
``.png``) draws what the smoothing did (`jaxci.experiments.smooth_report`), an output checked and written as OUT is
(`_report`). ``--devices`` shards the elements over several devices
(`jaxci.smooth`'s ``devices``; on a CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` makes N; with
more N than cores the command also turns XLA's per-fusion split off: `jaxci.runtime.process.cpu_device_flags`).

OUT is checked before the smoothing (`_files.check_output`: never the input, an existing file only with
``--force``) and written atomically; an interrupt leaves no OUT and no temporary file.
"""

from __future__ import annotations

import json
import sys


def add_args(p) -> None:
    from ..interface.smooth import METHODS

    p.intermixed = True  # IN --method M OUT, IN1 IN2 --out-dir D IN3: options anywhere (`jaxci.cli._Parser`)
    p.usage = ("jaxci smooth [options] IN OUT\n       jaxci smooth [options] IN [IN ...] --out-dir DIR "
               "[--jobs N]")
    p.add_argument("paths", nargs="+", metavar="PATH",
                   help="IN OUT: the input mesh file (never modified) and the output file, whose extension picks "
                        "the format; with --out-dir, every PATH is an input: a mesh file or a folder (each mesh "
                        "file in it jaxci reads and writes, by extension; not its subfolders)")
    p.add_argument("--out-dir", metavar="DIR", default=None,
                   help="smooth every input and write each as DIR/<its file name>, in its own format (DIR is made "
                        "if missing); the options apply to each file. Exit status 0 if every file succeeded, else "
                        "the largest of the files' statuses (each as the one-file form would return it)")
    p.add_argument("--jobs", "-j", type=int, default=None, metavar="N",
                   help="with --out-dir: worker processes, each smoothing one file after another (default: the "
                        "cores this process may use, at most the number of files); 1 runs them in this process")
    p.add_argument("--method", default="auto", choices=METHODS,
                   help="smoothing method (default auto: untangle if needed, then L-BFGS, with smart-Laplace sweeps "
                        "first on large meshes; the output says which)")
    p.add_argument("--engine", choices=["auto", "host", "jax"], default="auto",
                   help="auto (default: the JAX engine on an accelerator where JAX sees one and the mesh is large "
                        "enough, else the host engine where it runs the method, else JAX on the CPU), host (numpy "
                        "and C kernels, float64, CPU) or jax (compiled JAX programs)")
    p.add_argument("--device", choices=["auto", "cpu", "gpu"], default="auto",
                   help="auto (default), cpu, or gpu (any accelerator JAX sees; the JAX engine runs on it)")
    p.add_argument("--seed", type=int, default=0, help="random seed of stochastic methods (default 0)")
    p.add_argument("--dtype", choices=["float32", "float64"], default="float32",
                   help="the JAX engine's arithmetic (default float32; the host engine is float64)")
    p.add_argument("--feature-angle", type=float, default=40.0, help="degrees (default 40)")
    p.add_argument("--fix-boundary", action="store_true", help="fix every boundary node")
    p.add_argument("--fixed-set", action="append", default=[], metavar="NAME",
                   help="fix the nodes of this named node set of the file (repeatable)")
    p.add_argument("--untangle", choices=["auto", "always", "never", "partial"], default="auto",
                   help="auto: untangle inverted input first (default); always: also lift corners below the "
                        "untangling margin; never: refuse inverted input; partial: untangle what can be untangled "
                        "and, if elements stay inverted, write the mesh with them (no shape improvement) and exit "
                        "with status 3")
    p.add_argument("--untangle-boundary", action="store_true",
                   help="let the corner and edge nodes of inverted elements slide on a boundary surface while "
                        "untangling, where only the boundary's shape holds them (never --fix-boundary or "
                        "--fixed-set nodes): for inverted elements at the boundary's corners that nothing else "
                        "can untangle")
    p.add_argument("--untangle-budget", type=float, default=None, metavar="SECONDS",
                   help="stop the untangling stage after this many seconds (meshes up to 60,000 hexahedra; "
                        "larger ones are bounded by --param untangle_max_rounds / untangle_inner_steps)")
    p.add_argument("--merge-coincident", action="store_true",
                   help="merge coincident nodes (an unmerged interface) before smoothing; without it each set "
                        "moves as one node on the interface and is written back unmerged, exactly coincident")
    p.add_argument("--allow-worse-worst", action="store_true",
                   help="return the method's result even if its worst cell is worse than the input's (by default "
                        "the nodes of such cells are put back: jaxci.metrics.guard)")
    p.add_argument("--objective", choices=["mean", "pmean"], default=None,
                   help="what the gradient methods minimise: mean (F, Eq. 3.1: the default) or pmean (the p-mean "
                        "of the corner excesses, --param p=2 by default: pulls the worst element harder)")
    p.add_argument("--devices", default=None, metavar="N|all",
                   help="run on N devices (or all), the elements sharded over them: L-BFGS (and the default "
                        "pipeline), BFGS, CG, the Laplacians and local CI; global CI's trial meshes; compiled; "
                        "default: one device")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="method hyperparameter, e.g. --param cohort=8 (repeatable)")
    p.add_argument("--json", action="store_true", help="print one JSON summary object (with phase timings)")
    p.add_argument("--verbose", "-v", action="store_true", help="one line per phase on stderr (time, compilation)")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress line on stderr (shown only where stderr is a terminal)")
    p.add_argument("--report", metavar="FILE", default=None,
                   help="also write a report of the smoothing: FILE.html (opens offline: images embedded) or "
                        "FILE.png; corner kappa/3 histograms before and after, the worst elements (ids, "
                        "positions), the surface coloured by element condition. Checked like OUTPUT")
    p.add_argument("--force", action="store_true", help="overwrite OUTPUT if it is an existing file (never the "
                   "input)")
    p.epilog = ("exit status: 0 success; 2 an error the user can fix (bad file, option or mesh; an output that exists "
                "without --force or is an input: nothing written); 3 elements left inverted (--untangle partial); 1 "
                "an internal error; 130 on SIGINT, 143 on SIGTERM (no partial output left). With --out-dir: 0 if "
                "every file succeeded, else the largest status of its files (each reported with its error line); "
                "two inputs with the same file name, or an output that is an input, refuse the whole command (2)")


def run(args) -> int:
    import time

    from ..errors import ConfigError
    from ..runtime.phases import process_age
    from ._progress import Display, wanted

    if args.out_dir is not None:
        from ._batch import run_batch

        return run_batch(args)
    if len(args.paths) != 2 or args.jobs is not None:
        got = "--jobs" if len(args.paths) == 2 else f"{len(args.paths)} path{'s' if len(args.paths) != 1 else ''}"
        raise ConfigError(f"jaxci smooth: expects IN OUT (one mesh), or IN... --out-dir DIR [--jobs N] (many); "
                          f"got {got} without --out-dir (see jaxci smooth --help)")
    args.input, args.output = args.paths
    age = process_age()
    display = Display(live=wanted(args.quiet), verbose=args.verbose, started=time.perf_counter() - (age or 0.0))
    try:
        return _smooth(args, display, age)
    finally:
        display.close()


def _smooth(args, display, age) -> int:
    from ..runtime.phases import PhaseClock

    clock = PhaseClock(display.on_event if display.live or display.verbose else None)
    if age is not None:
        clock.add("startup", age)
        if clock.on_event is not None:
            clock.on_event("end", "startup", clock.as_dict()["startup"])
    from ._files import check_output
    from ._quality import format_table
    from ._smooth_file import smooth_file, smooth_options, summary

    settings = smooth_options(args)
    out = check_output(args.output, [args.input], force=args.force)
    report = None
    if args.report is not None:
        from ._report import check_report

        report = check_report(args.report, [args.input], out, force=args.force)
    mesh, res = smooth_file(args.input, out, settings, clock, report, f"jaxci smooth {args.input} -> {args.output}")
    display.close()  # the progress line erased before the result is printed
    phases = clock.as_dict()
    if args.verbose:
        t = phases["total"]
        print(f"jaxci: total     {t['seconds']:8.2f} s (compilation {t['compile_seconds']:.2f} s, {t['compiled']} "
              f"compiled, {t['cache_hits']} from the compilation cache)", file=sys.stderr)
    if args.json:
        print(json.dumps(summary(res, phases, args.input, args.output, args.report if report is not None else None)))
        return _status(res)
    for note in (*mesh.notes, *res.notes):
        print(f"note: {note}")
    b, a = res.before.to_dict(), res.after.to_dict()
    print(format_table(b, f"before: {args.input}"))
    label = res.params.get("pipeline", res.method) if res.method == "auto" else res.method
    if res.params.get("solver") == "newton":  # the gradient methods' solver (GradientParams.solver)
        label += ", truncated Newton"
    print(format_table(a, f"after ({label}, {res.iterations} iterations, {res.wall_time:.2f} s): {args.output}"))
    from ..metrics.report import limited_note

    limited = limited_note(res.after)
    if limited is not None:
        print(f"note: {limited}")
    if res.plan is not None:
        print(f"engine: {res.plan.describe()}")
    return _status(res)


def _status(res) -> int:
    from ._smooth_file import exit_status

    code, line = exit_status(res)
    if line is not None:
        print(f"jaxci: {line}", file=sys.stderr)
    return code
