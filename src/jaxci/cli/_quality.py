"""`jaxci quality MESH [--json]`: the mesh report of `jaxci.metrics.report.quality_report`.

The table gives the hexahedra's figures (the paper's: max/mean k/3, F of Eq. 3.1, min scaled Jacobian), then one
row per volume cell type and one for all of them (``by_type`` / ``overall`` of the JSON; k/3 relative to each
type's ideal cell, F the mixed objective of `jaxci.metrics.elements`), then the hexahedra's corner histogram.
"""

from __future__ import annotations

import json
import math


def add_args(p) -> None:
    p.add_argument("mesh", help="mesh file (any format jaxci reads: see the README's format table)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--feature-angle", type=float, default=40.0, help="for the node class counts (default 40)")


def report_dict(mesh, feature_angle: float = 40.0) -> dict:
    """The quality keys of a mesh, as `jaxci quality --json` prints them, with the node class counts."""
    from ..geometry.boundary import classify_boundary
    from ..metrics.report import quality_report

    d = quality_report(mesh).to_dict()
    counts = classify_boundary(mesh, feature_angle=feature_angle).counts
    d.update({f"{k}_nodes": counts[k] for k in ("corner", "edge", "surface", "interior")})
    return d


def format_table(d: dict, title: str = "") -> str:
    def f(v, fmt=".6g"):
        return "-" if v is None else format(v, fmt)

    lines = [title] if title else []
    lines += [  # the hexahedra's figures (the paper's); every cell type in the table "by element type" below
        f"  nodes                 {d['n_nodes']}",
        f"  hexahedra             {d['n_elements']}",
    ]
    if d.get("other_cells"):
        lines.append("  other cells           " + ", ".join(f"{k} {v}" for k, v in d["other_cells"].items()))
    lines += [
        f"  inverted corners      {d['inverted_corners']}",
        f"  inverted elements     {d['inverted_elements']}",
        f"  max condition k/3     {f(d['max_condition'])}",
        f"  mean condition k/3    {f(d['mean_condition'])}",
        f"  objective F (Eq 3.1)  {f(d['objective'])}",
        f"  min scaled Jacobian   {f(d['min_scaled_jacobian'])}",
    ]
    for key in ("corner_nodes", "edge_nodes", "surface_nodes", "interior_nodes"):
        if key in d:
            lines.append(f"  {key.replace('_', ' '):<22}{d[key]}")
    if d.get("by_type"):
        lines.append(f"  {'by element type':<18}{'count':>8}{'inverted':>10}{'max k/3':>12}{'mean k/3':>12}"
                     f"{'min SJ':>12}{'F':>12}")
        rows = list(d["by_type"].items()) + ([("all", d["overall"])] if d.get("overall") else [])
        for name, t in rows:
            lines.append(f"    {name:<16}{t['count']:>8}{t['inverted']:>10}{f(t['max_condition']):>12}"
                         f"{f(t['mean_condition']):>12}{f(t['min_scaled_jacobian']):>12}{f(t['objective']):>12}")
    lines.append("  corners by k/3:")
    for b in d["histogram"]:
        hi = "inf" if b["high"] is None or math.isinf(b["high"]) else f"{b['high']:g}"
        label = f"[{b['low']:g}, {hi})"
        lines.append(f"    {label:<12}{b['count']:>9}")
    return "\n".join(lines)


def run(args) -> int:
    from ..io import read_mesh

    mesh = read_mesh(args.mesh)
    d = report_dict(mesh, args.feature_angle)
    if args.json:
        print(json.dumps(d))
    else:
        for note in mesh.notes:
            print(f"note: {note}")
        print(format_table(d, f"{args.mesh}"))
    return 0
