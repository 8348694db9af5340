"""One file of `jaxci smooth`, as both of its forms run it: `smooth_options` (the command's options as
`jaxci.smooth`'s arguments, the same for every file), `smooth_file` (read, check the files read against the
output, smooth, write), `summary` (the ``--json`` object of one file) and `exit_status`. `_smooth` runs one file
with them and prints its report; `_batch` runs many over a pool of worker processes.
"""

from __future__ import annotations

import dataclasses
import json


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


@dataclasses.dataclass(frozen=True)
class Settings:
    """What the options ask of `jaxci.smooth`, the same for every file: the `method`, its keyword arguments
    (`kwargs`) and the method's hyperparameters (`params`: ``--param``, ``--untangle-budget``, ``--objective``)."""

    method: str
    kwargs: dict
    params: dict


def smooth_options(args) -> Settings:
    """The command's options as `Settings` (a `ConfigError` for a bad ``--param``, ``--devices`` or ``--objective``)."""
    params = _parse_params(args.param)
    devices = _devices(args.devices)
    if args.untangle_budget is not None:
        params["untangle_time_budget"] = args.untangle_budget
    if args.objective is not None:
        if params.get("objective", args.objective) != args.objective:
            from ..errors import ConfigError

            raise ConfigError(f"--objective {args.objective} and --param objective={params['objective']} disagree")
        params["objective"] = args.objective
    kwargs = dict(seed=args.seed, dtype=args.dtype, feature_angle=args.feature_angle, fix_boundary=args.fix_boundary,
                  fixed_sets=args.fixed_set, untangle=args.untangle, untangle_boundary=args.untangle_boundary,
                  merge_coincident=args.merge_coincident, keep_worst=not args.allow_worse_worst, devices=devices,
                  engine=args.engine, device=args.device)
    return Settings(args.method, kwargs, params)


def smooth_file(path, out, settings: Settings, clock, report=None, title: str = ""):
    """Smooth one file: read `path`, refuse an output (`out`, checked by `_files.check_output`) or `report` that is
    one of the files read, smooth it as `settings` say, draw the report, write the mesh (atomically; nothing else
    is replaced: `_files.Output.write`). Each step timed as a phase of `clock`. Returns ``(mesh, result)``."""
    from ..interface.smooth import smooth
    from ..io import read_mesh

    with clock.phase("read"):
        mesh = read_mesh(path)
    out.check_inputs(mesh)  # the files read through it too (includes, XDMF data), before the smoothing
    if report is not None:
        report.check_inputs(mesh)
    res = smooth(mesh, settings.method, clock=clock, **settings.kwargs, **settings.params)
    picture = None
    if report is not None:
        from ..experiments.smooth_report import render
        from ._report import report_format

        with clock.phase("draw"):
            picture = render(mesh, res, report_format(report.path), title)
    with clock.phase("write"):
        out.write(res.mesh)  # replaces only what check_output saw (nothing, without --force)
        if picture is not None:
            from ._report import write_report

            write_report(report, picture, mesh)
    return mesh, res


def summary(res, phases: dict, input, output, report=None) -> dict:
    """The ``--json`` object of one file: the result's summary, the phases, the input and output (and report)."""
    return {**res.summary(), "phases": phases, "input": str(input), "output": str(output),
            **({"report": str(report)} if report is not None else {})}


#: Exit status of ``--untangle partial`` when elements stayed inverted (the mesh was written with them).
INVERTED_LEFT = 3


def exit_status(res) -> tuple[int, str | None]:
    """The exit status of a written result and its line for stderr (None when 0)."""
    if res.after.inverted_elements or res.after.inverted_corners:
        return INVERTED_LEFT, (f"{res.after.inverted_elements} elements are still inverted in the output "
                               f"(--untangle partial); exit status {INVERTED_LEFT}")
    return 0, None
