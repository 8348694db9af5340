"""`jaxci smooth IN OUT [--method M] [--engine E] [--device D] [--seed S] [--devices N|all] [--json] [--verbose]
[--quiet] [--report FILE] [--force]`: smooth a mesh, write it as OUT.

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

    p.add_argument("input", help="input mesh file (never modified)")
    p.add_argument("output", help="output mesh file; its extension picks the format")
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


def _parse_params(items: list[str]) -> dict:
    from ..errors import ConfigError

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--param expects KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _devices(text: str | None):
    """``--devices`` as `jaxci.smooth`'s ``devices``: None, ``"all"`` or a positive int (`ConfigError` else)."""
    if text is None or text == "all":
        return text
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        from ..errors import ConfigError

        raise ConfigError(f"--devices expects a positive number of devices or 'all', got {text!r}")
    return n


def run(args) -> int:
    import time

    from ..runtime.phases import process_age
    from ._progress import Display, wanted

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
    from ..interface.smooth import smooth
    from ..io import read_mesh
    from ._files import check_output
    from ._quality import format_table

    params = _parse_params(args.param)
    devices = _devices(args.devices)
    if args.untangle_budget is not None:
        params["untangle_time_budget"] = args.untangle_budget
    if args.objective is not None:
        if params.get("objective", args.objective) != args.objective:
            from ..errors import ConfigError

            raise ConfigError(f"--objective {args.objective} and --param objective={params['objective']} disagree")
        params["objective"] = args.objective
    out = check_output(args.output, [args.input], force=args.force)
    report = None
    if args.report is not None:
        from ._report import check_report

        report = check_report(args.report, [args.input], out, force=args.force)
    with clock.phase("read"):
        mesh = read_mesh(args.input)
    out.check_inputs(mesh)  # the files read through it too (includes, XDMF data), before the smoothing
    if report is not None:
        report.check_inputs(mesh)
    res = smooth(mesh, args.method, seed=args.seed, dtype=args.dtype, feature_angle=args.feature_angle,
                 fix_boundary=args.fix_boundary, fixed_sets=args.fixed_set, untangle=args.untangle,
                 untangle_boundary=args.untangle_boundary,
                 merge_coincident=args.merge_coincident, keep_worst=not args.allow_worse_worst, clock=clock,
                 devices=devices, engine=args.engine, device=args.device, **params)
    picture = None
    if report is not None:
        from ..experiments.smooth_report import render
        from ._report import report_format, write_report

        with clock.phase("draw"):
            picture = render(mesh, res, report_format(report.path), f"jaxci smooth {args.input} -> {args.output}")
    with clock.phase("write"):
        out.write(res.mesh)  # replaces only what check_output saw (nothing, without --force)
        if picture is not None:
            write_report(report, picture, mesh)
    display.close()  # the progress line erased before the result is printed
    phases = clock.as_dict()
    if args.verbose:
        t = phases["total"]
        print(f"jaxci: total     {t['seconds']:8.2f} s (compilation {t['compile_seconds']:.2f} s, {t['compiled']} "
              f"compiled, {t['cache_hits']} from the compilation cache)", file=sys.stderr)
    if args.json:
        print(json.dumps({**res.summary(), "phases": phases, "input": args.input, "output": args.output,
                          **({"report": args.report} if report is not None else {})}))
        return _status(res)
    for note in (*mesh.notes, *res.notes):
        print(f"note: {note}")
    b, a = res.before.to_dict(), res.after.to_dict()
    print(format_table(b, f"before: {args.input}"))
    label = res.params.get("pipeline", res.method) if res.method == "auto" else res.method
    print(format_table(a, f"after ({label}, {res.iterations} iterations, {res.wall_time:.2f} s): {args.output}"))
    from ..metrics.report import limited_note

    limited = limited_note(res.after)
    if limited is not None:
        print(f"note: {limited}")
    if res.plan is not None:
        print(f"engine: {res.plan.describe()}")
    return _status(res)


#: Exit status of ``--untangle partial`` when elements stayed inverted (the mesh was written with them).
INVERTED_LEFT = 3


def _status(res) -> int:
    if res.after.inverted_elements or res.after.inverted_corners:
        print(f"jaxci: {res.after.inverted_elements} elements are still inverted in the output (--untangle "
              f"partial); exit status {INVERTED_LEFT}", file=sys.stderr)
        return INVERTED_LEFT
    return 0
