"""A picture of what smoothing did to one mesh (``jaxci smooth IN OUT --report report.html``, or ``.png``).

- the corner condition numbers before and after: a histogram of every corner's kappa/3 on log bins (inverted
  corners a bar of their own);
- the worst elements before and after: their ids (the file's, `jaxci.metrics.objective.cell_label`), types,
  kappa/3 before and after (max corner kappa/3 of the cell, `jaxci.metrics.guard.cell_worst`) and positions
  (centroids);
- the boundary surface before and after, each face coloured by the condition of the element it bounds, the worst
  elements marked (above `MAX_SURFACE_FACES` faces, the faces of the worst elements only, and the title says so).

`render` returns the file's bytes: one PNG, or an HTML page whose images are PNGs embedded as base64 data URIs
(it opens without network access). Everything is measured in numpy float64 (no compilation) and drawn with
matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import math

import numpy as np

from ..cells import element_blocks
from ..geometry.topology import FACE_CELL_TYPES, boundary_topology
from ..metrics import elements as E
from ..metrics.guard import cell_worst
from ..metrics.objective import cell_label
from .plots import MAX_SURFACE_FACES, draw_surface, pyplot

#: How many of the worst elements are listed (and, the first `MARKED` of them, marked on the surface).
WORST = 10
MARKED = 3
#: Log-spaced bins of the corner histogram.
BINS = 40
#: The surface view's colour scale ends here (elements worse than this, but valid: one colour).
CAP = 10.0


@dataclasses.dataclass(frozen=True)
class WorstElement:
    """One of the worst elements: `label` (its id in the file, ``"17 (index 16)"``, else its index),
    `cell_type`, `index` (within its type, `jaxci.cells.element_blocks` order), kappa/3 `before` and `after`
    (``inf``: inverted) and `centroid` (the mean of its nodes, at the points it was ranked by)."""

    label: str
    cell_type: str
    index: int
    before: float
    after: float
    centroid: tuple[float, float, float]


def worst_elements(mesh, before, after, n: int = WORST) -> tuple[list[WorstElement], list[WorstElement]]:
    """The `n` worst elements of `mesh` at the coordinates `before` and at `after` (each list worst first), every
    cell type ranked together."""
    blocks = element_blocks(mesh)
    kb, ka = cell_worst(mesh, before), cell_worst(mesh, after)
    out = []
    for ranked, pts in ((kb, before), (ka, after)):
        types = list(ranked)
        values = np.concatenate([ranked[t] for t in types]) if types else np.zeros(0)
        owner = np.concatenate([np.full(len(ranked[t]), i) for i, t in enumerate(types)]) if types else values
        start = np.cumsum([0] + [len(ranked[t]) for t in types])
        order = np.argsort(-values, kind="stable")[:n]
        rows = []
        for j in order:
            t = types[int(owner[j])]
            k = int(j - start[int(owner[j])])
            c = np.asarray(pts, np.float64)[blocks[t][k]].mean(axis=0)
            rows.append(WorstElement(_label(mesh, t, k), t, k, float(kb[t][k]), float(ka[t][k]),
                                     (float(c[0]), float(c[1]), float(c[2]))))
        out.append(rows)
    return out[0], out[1]


def _label(mesh, cell_type: str, k: int) -> str:
    if cell_type == "hexahedron":
        return mesh.hex_label(k)
    return cell_label(mesh, cell_type, k).split(" element ", 1)[1]


def corner_histogram(mesh, points, edges: np.ndarray) -> tuple[np.ndarray, int]:
    """Counts of the corners' kappa/3 in the bins `edges` (the last bin closed; values above it counted in it)
    and the number of inverted corners (kappa/3 infinite), over every cell type, block by block."""
    counts = np.zeros(len(edges) - 1, np.int64)
    inverted = 0
    for t, cells in element_blocks(mesh).items():
        for lo in range(0, len(cells), E.CELL_CHUNK):
            k = E.corner_condition(points, cells[lo:lo + E.CELL_CHUNK], t).ravel()
            finite = np.isfinite(k)
            inverted += int((~finite).sum())
            counts += np.histogram(np.clip(k[finite], edges[0], edges[-1]), bins=edges)[0]
    return counts, inverted


def _surface_faces(mesh):
    """``(faces, cell_type of each, index of its cell)`` of the boundary of `mesh`."""
    blocks = element_blocks(mesh)
    hexes = blocks.get("hexahedron", np.zeros((0, 8), np.int64))
    others = {t: c for t, c in blocks.items() if t != "hexahedron"}
    topo = boundary_topology(hexes, mesh.n_nodes, others or None)
    types = np.asarray(FACE_CELL_TYPES)[topo.face_type]
    return topo.faces, types, topo.face_cell


def _face_values(values: dict, types: np.ndarray, cells: np.ndarray) -> np.ndarray:
    out = np.empty(len(cells))
    for t, v in values.items():
        sel = types == t
        out[sel] = v[cells[sel]]
    return out


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    return buf.getvalue()


def histogram_figure(mesh, before, after, result):
    """The corner kappa/3 histograms before and after on shared log bins (a matplotlib figure)."""
    plt = pyplot()
    tops = [r.max_condition for r in (result.before, result.after) if r.max_condition is not None]
    top = max(max(tops, default=2.0), 1.01)
    edges = np.geomspace(1.0, top * (1 + 1e-9), BINS + 1)
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    for pts, label, colour in ((before, "before", "tab:red"), (after, "after", "tab:blue")):
        counts, inv = corner_histogram(mesh, pts, edges)
        ax.stairs(counts, edges, label=f"{label}" + (f" ({inv} inverted corners)" if inv else ""), color=colour,
                  fill=label == "before", alpha=0.35 if label == "before" else 1.0, linewidth=1.6)
    ax.set_xscale("log")
    ax.set_yscale("symlog", linthresh=1)
    ax.set_xlabel("corner kappa/3 (1: an ideal corner)")
    ax.set_ylabel("corners")
    ax.set_title("corner condition numbers")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def surface_figure(mesh, before, after, worst: tuple[list, list], title: str = ""):
    """The boundary surface before and after, coloured by element condition, the `MARKED` worst elements of
    each marked with their ids (a matplotlib figure)."""
    from matplotlib.colors import LogNorm

    plt = pyplot()
    faces, types, cells = _surface_faces(mesh)
    vals = [_face_values(cell_worst(mesh, pts), types, cells) for pts in (before, after)]
    note = ""
    if len(faces) > MAX_SURFACE_FACES:  # the faces of the worst elements only (mplot3d draws ~10^4 faces/s)
        keep = np.sort(np.argsort(-np.maximum(*vals), kind="stable")[:MAX_SURFACE_FACES])
        note = f" (the {MAX_SURFACE_FACES} faces of the worst elements of {len(faces)})"
        faces, vals = faces[keep], [v[keep] for v in vals]
    finite = np.concatenate([v[np.isfinite(v)] for v in vals])
    # a scale that shows the result's elements apart: up to the worst finite value, at most `CAP` (beyond: orange)
    vmax = min(max(float(finite.max()) if finite.size else 2.0, 1.0 + 1e-3), CAP)
    norm = LogNorm(vmin=1.0, vmax=vmax)
    cmap = plt.get_cmap("viridis").with_extremes(over="orange")
    lo = np.minimum(np.min(before, axis=0), np.min(after, axis=0))
    hi = np.maximum(np.max(before, axis=0), np.max(after, axis=0))
    fig = plt.figure(figsize=(11, 5))
    for i, (v, lab, rows) in enumerate(zip(vals, ("before", "after"), worst, strict=True)):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        worst_v = max((r.before if i == 0 else r.after for r in rows), default=math.nan)
        draw_surface(ax, before if i == 0 else after, faces, v, norm, cmap, (lo, hi),
                     f"{lab}: worst element kappa/3 {_num(worst_v)}{note}")
        for rank, r in enumerate(rows[:MARKED]):  # the worst elements, by id (labels drawn above the surface)
            ax.text(*r.centroid, f"#{r.label.split()[0]}", color="black", fontsize=7, ha="center", va="center",
                    zorder=20 - rank, bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "red", "lw": 0.8})
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    over = bool(finite.size and finite.max() > vmax)
    fig.colorbar(sm, ax=fig.axes, shrink=0.7, extend="max" if over else "neither",
                 label="element condition (max corner kappa/3)")
    fig.text(0.5, 0.02, f"red: inverted{f'; orange: kappa/3 above {CAP:g}' if over else ''}; labelled: the "
             f"{MARKED} worst elements by id", ha="center", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def _num(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return "inverted" if math.isinf(v) else f"{v:.6g}"


def _xyz(c) -> str:
    return ", ".join(f"{x:.6g}" for x in c)


def _summary_rows(result) -> list[tuple[str, str, str]]:
    b, a = result.before, result.after
    return [
        ("elements", str(b.n_elements + sum((b.other_cells or {}).values())), ""),
        ("inverted elements", str(b.inverted_elements), str(a.inverted_elements)),
        ("inverted corners", str(b.inverted_corners), str(a.inverted_corners)),
        ("max kappa/3", _num(b.max_condition), _num(a.max_condition)),
        ("mean kappa/3", _num(b.mean_condition), _num(a.mean_condition)),
        ("F (mean of (kappa/3)^2 - 1)", _num(b.objective), _num(a.objective)),
        ("min scaled Jacobian", _num(b.min_scaled_jacobian), _num(a.min_scaled_jacobian)),
    ]


def _what(result) -> str:
    label = result.params.get("pipeline", result.method) if result.method == "auto" else result.method
    where = f"; {result.plan.describe()}" if result.plan is not None else ""
    return f"{label}, {result.iterations} iterations, {result.wall_time:.2f} s{where}"


def _html(title: str, result, worst, images: dict[str, bytes]) -> bytes:
    e = html.escape

    def img(name, alt):
        data = base64.b64encode(images[name]).decode("ascii")
        return f'<img alt="{e(alt)}" src="data:image/png;base64,{data}">'

    def worst_table(rows, ranked_by):
        head = ("<tr><th>#</th><th>element</th><th>type</th><th>kappa/3 before</th><th>kappa/3 after</th>"
                f"<th>centroid ({ranked_by})</th></tr>")
        body = "".join(f"<tr><td>{i + 1}</td><td>{e(r.label)}</td><td>{e(r.cell_type)}</td>"
                       f"<td>{_num(r.before)}</td><td>{_num(r.after)}</td><td>{_xyz(r.centroid)}</td></tr>"
                       for i, r in enumerate(rows))
        return f"<table>{head}{body}</table>"

    summary = "".join(f"<tr><td>{e(k)}</td><td>{e(b)}</td><td>{e(a)}</td></tr>" for k, b, a in _summary_rows(result))
    notes = "".join(f"<li>{e(n)}</li>" for n in result.notes)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{e(title)}</title>
<style>body{{font-family:sans-serif;max-width:1150px;margin:1em auto;padding:0 1em}}
table{{border-collapse:collapse;margin:.5em 0}}td,th{{border:1px solid #bbb;padding:2px 8px;text-align:right}}
td:first-child,th:first-child{{text-align:left}}img{{max-width:100%}}</style></head>
<body><h1>{e(title)}</h1>
<p>{e(_what(result))}</p>
<table><tr><th></th><th>before</th><th>after</th></tr>{summary}</table>
<h2>Corner condition numbers</h2>{img("histogram", "corner kappa/3 histogram before and after")}
<h2>Surface coloured by element condition</h2>{img("surface", "boundary surface before and after")}
<h2>Worst elements after smoothing</h2>{worst_table(worst[1], "after")}
<h2>Worst elements before smoothing</h2>{worst_table(worst[0], "before")}
{f"<h2>Notes</h2><ul>{notes}</ul>" if notes else ""}
</body></html>
"""
    return page.encode("utf-8")


def _table_figure(plt, worst):
    fig, ax = plt.subplots(figsize=(11, 0.6 + 0.22 * (len(worst[1]) + 2)))
    ax.axis("off")
    rows = [[str(i + 1), r.label, r.cell_type, _num(r.before), _num(r.after), _xyz(r.centroid)]
            for i, r in enumerate(worst[1])]
    if rows:
        t = ax.table(cellText=rows, colLabels=["#", "element", "type", "kappa/3 before", "kappa/3 after",
                                               "centroid (after)"], loc="center", cellLoc="left",
                     colWidths=[0.04, 0.2, 0.12, 0.13, 0.13, 0.38])
        t.auto_set_font_size(False)
        t.set_fontsize(8)
    ax.set_title("worst elements after smoothing", fontsize=10)
    return fig


def render(mesh, result, fmt: str, title: str = "jaxci smooth") -> bytes:
    """The report of smoothing `mesh` (the input `HexMesh`) into `result` (its `jaxci.SmoothResult`), as the
    bytes of a ``"png"`` or an ``"html"`` file (`fmt`)."""
    if fmt not in ("png", "html"):
        raise ValueError(f"render: fmt must be 'png' or 'html', got {fmt!r}")
    plt = pyplot()
    before = np.asarray(mesh.points, np.float64)
    after = np.asarray(result.mesh.points, np.float64)
    worst = worst_elements(mesh, before, after)
    figs = {"histogram": histogram_figure(mesh, before, after, result),
            "surface": surface_figure(mesh, before, after, worst)}
    try:
        if fmt == "html":
            return _html(title, result, worst, {k: _png(f) for k, f in figs.items()})
        figs["table"] = _table_figure(plt, worst)
        return _stack([_png(figs[k]) for k in ("histogram", "surface", "table")], title)
    finally:
        for f in figs.values():
            plt.close(f)


def _stack(pngs: list[bytes], title: str) -> bytes:
    """The PNG images one above the other, under `title`, as one PNG."""
    plt = pyplot()
    images = [plt.imread(io.BytesIO(p)) for p in pngs]
    width = max(im.shape[1] for im in images)
    heights = [im.shape[0] for im in images]
    total = sum(heights) + 40  # pixels: the images and the title's band
    dpi = 100
    fig = plt.figure(figsize=(width / dpi, total / dpi), dpi=dpi)
    fig.suptitle(title, fontsize=11, y=1 - 10 / total)
    top = 1 - 40 / total
    for im, h in zip(images, heights, strict=True):
        ax = fig.add_axes((0, top - h / total, im.shape[1] / width, h / total))
        ax.imshow(im)
        ax.axis("off")
        top -= h / total
    try:
        return _png(fig)
    finally:
        plt.close(fig)
