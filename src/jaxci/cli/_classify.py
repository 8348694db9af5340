"""`jaxci classify MESH OUT.vtu [--force]`: write the node classes (interior/surface/edge/corner) as point data.

OUT is checked first (`_files.check_output`: never MESH, an existing file only with ``--force``).
"""

from __future__ import annotations

import dataclasses
import json


def add_args(p) -> None:
    p.add_argument("mesh", help="input mesh file")
    p.add_argument("output", help="output mesh (e.g. .vtu for ParaView) with point data 'node_class'")
    p.add_argument("--feature-angle", type=float, default=40.0, help="degrees (default 40)")
    p.add_argument("--json", action="store_true", help="print the counts as JSON")
    p.add_argument("--force", action="store_true", help="overwrite OUTPUT if it is an existing file (never the "
                   "input)")


def run(args) -> int:
    import numpy as np

    from ..geometry.boundary import classify_boundary
    from ..io import read_mesh
    from ._files import check_output

    out = check_output(args.output, [args.mesh], force=args.force)
    mesh = read_mesh(args.mesh)
    out.check_inputs(mesh)  # the files read through it too (includes, XDMF data), before any work
    info = classify_boundary(mesh, feature_angle=args.feature_angle)
    pd = dict(mesh.point_data)
    for key in ("node_class", "patch_id", "curve_id"):
        pd[key] = np.asarray(getattr(info, key), dtype=np.int32)
    out.write(dataclasses.replace(mesh, point_data=pd, fix_orientation=False, notes=()))  # source, input_files kept
    counts = {f"{k}_nodes": v for k, v in info.counts.items()}
    if args.json:
        print(json.dumps({**counts, "patches": info.n_patches, "curves": info.n_curves, "notes": list(info.notes)}))
    else:
        for note in info.notes:
            print(f"note: {note}")
        print(f"wrote {args.output}: " + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in counts.items())
              + f"; {info.n_patches} surface patches, {info.n_curves} feature curves")
    return 0
