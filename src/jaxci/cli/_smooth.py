"""`jaxci smooth IN OUT --method ci [--seed S] [--json] [--force]`: smooth a mesh and write it in the format of OUT.

OUT is checked before the smoothing (`_files.check_output`: never the input, an existing file only with
``--force``) and written atomically; an interrupt leaves no OUT and no temporary file.
"""

from __future__ import annotations

import json


def add_args(p) -> None:
    from ..smooth import METHODS

    p.add_argument("input", help="input mesh file (never modified)")
    p.add_argument("output", help="output mesh file; its extension picks the format")
    p.add_argument("--method", default="ci", choices=METHODS, help="smoothing method (default ci: local CI)")
    p.add_argument("--seed", type=int, default=0, help="random seed of stochastic methods (default 0)")
    p.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    p.add_argument("--feature-angle", type=float, default=40.0, help="degrees (default 40)")
    p.add_argument("--fix-boundary", action="store_true", help="fix every boundary node")
    p.add_argument("--fixed-set", action="append", default=[], metavar="NAME",
                   help="fix the nodes of this named node set of the file (repeatable)")
    p.add_argument("--untangle", choices=["auto", "always", "never"], default="auto")
    p.add_argument("--merge-coincident", action="store_true",
                   help="merge coincident nodes (an unmerged interface) before smoothing; without it they are "
                        "kept fixed, so they stay exactly coincident")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="method hyperparameter, e.g. --param cohort=8 (repeatable)")
    p.add_argument("--json", action="store_true", help="print one JSON summary object")
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


def run(args) -> int:
    from ..io import read_mesh, write_mesh
    from ..smooth import smooth
    from ._files import check_output
    from ._interrupt import removing_temporaries
    from ._quality import format_table

    check_output(args.output, [args.input], force=args.force)
    mesh = read_mesh(args.input)
    res = smooth(mesh, args.method, seed=args.seed, dtype=args.dtype, feature_angle=args.feature_angle,
                 fix_boundary=args.fix_boundary, fixed_sets=args.fixed_set, untangle=args.untangle,
                 merge_coincident=args.merge_coincident,
                 **_parse_params(args.param))
    with removing_temporaries(args.output):
        write_mesh(res.mesh, args.output)
    if args.json:
        print(json.dumps({**res.summary(), "input": args.input, "output": args.output}))
        return 0
    for note in (*mesh.notes, *res.notes):
        print(f"note: {note}")
    b, a = res.before.to_dict(), res.after.to_dict()
    print(format_table(b, f"before: {args.input}"))
    print(format_table(a, f"after ({args.method}, {res.iterations} iterations, {res.wall_time:.2f} s): "
                          f"{args.output}"))
    return 0
