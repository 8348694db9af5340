"""`jaxci classify MESH OUT.vtu`: write the node classes (interior/surface/edge/corner) as point data."""

from __future__ import annotations

import dataclasses
import json


def add_args(p) -> None:
    p.add_argument("mesh", help="input mesh file")
    p.add_argument("output", help="output mesh (e.g. .vtu for ParaView) with point data 'node_class'")
    p.add_argument("--feature-angle", type=float, default=40.0, help="degrees (default 40)")
    p.add_argument("--json", action="store_true", help="print the counts as JSON")


def run(args) -> int:
    import numpy as np

    from ..boundary import classify_boundary
    from ..io import read_mesh, write_mesh

    mesh = read_mesh(args.mesh)
    info = classify_boundary(mesh, feature_angle=args.feature_angle)
    pd = dict(mesh.point_data)
    pd["node_class"] = np.asarray(info.node_class, dtype=np.int32)
    pd["patch_id"] = np.asarray(info.patch_id, dtype=np.int32)
    pd["curve_id"] = np.asarray(info.curve_id, dtype=np.int32)
    write_mesh(dataclasses.replace(mesh, point_data=pd, fix_orientation=False, notes=(), source=None), args.output)
    counts = {f"{k}_nodes": v for k, v in info.counts.items()}
    if args.json:
        print(json.dumps({**counts, "patches": info.n_patches, "curves": info.n_curves, "notes": list(info.notes)}))
    else:
        for note in info.notes:
            print(f"note: {note}")
        print(f"wrote {args.output}: " + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in counts.items())
              + f"; {info.n_patches} surface patches, {info.n_curves} feature curves")
    return 0
