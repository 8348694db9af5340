"""`jaxci.experiments.plots`: the figures of an experiment, drawn with matplotlib's Agg backend (no display needed).

Per mesh: ``convergence_<mesh>.png`` (objective F and max kappa/3 per iteration, log scale, one colour per
method: the first seed bold, the other seeds faint), ``histogram_<mesh>.png`` (corners per Table 1 bin before
and after each method, first seed; the paper's Table 1 beside it for the 27-element case) and, per method,
``surface_<mesh>_<method>.png`` (the boundary quadrilaterals before and after, coloured by the condition of
the element they bound, like the paper's Figs. 2-3; skipped above `MAX_SURFACE_FACES` faces).
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np

from ..metrics.report import HISTOGRAM_EDGES

#: Surface plots are skipped for meshes with more boundary faces than this (matplotlib 3-D is slow).
MAX_SURFACE_FACES = 20000


def pyplot():
    """matplotlib's pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path, tight: bool = True) -> None:
    """Save `fig` as a PNG atomically (temporary file in the same folder, then `os.replace`), laid out tight
    first (`tight`), then close it."""
    if tight:
        fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110, metadata={"Software": None})
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    pyplot().close(fig)


def convergence_figure(path: Path, title: str, series: list[tuple[str, list[dict]]]) -> None:
    """Objective F (log y) and max kappa/3 - 1 (log y) against iteration.

    **Arguments:** `path` of the PNG; `title`; `series`: per method, ``(label, histories)`` with the history
    dicts of its seeds (first seed first), each with ``objective`` and ``max_condition`` lists.
    """
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, (label, hists) in enumerate(series):
        c = colours[j % len(colours)]
        ls = ("-", "--", ":", "-.")[j % 4]  # equal prefixes (stage 1 vs stage 2) stay visible
        for k, h in enumerate(hists):
            for ax, key, shift in ((axes[0], "objective", 0.0), (axes[1], "max_condition", 1.0)):
                y = np.array([np.nan if v is None else v for v in h.get(key, [])], dtype=float) - shift
                if not len(y):
                    continue
                y = np.where(np.isfinite(y), np.maximum(y, 1e-16), np.nan)
                ax.plot(np.arange(len(y)), y, color=c, ls=ls, lw=1.6 if k == 0 else 0.6, alpha=1.0 if k == 0 else 0.3,
                        label=label if k == 0 else None)
    axes[0].set_ylabel("objective F (Eq. 3.1)")
    axes[1].set_ylabel("max kappa/3 - 1")
    for ax in axes:
        ax.set_yscale("log")
        ax.set_xlabel("iteration (sweep / learning attempt / step)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    _save(fig, path)


def histogram_figure(path: Path, title: str, bars: list[tuple[str, list[int]]], paper=None) -> None:
    """Grouped bars of corner counts per Table 1 bin: ``bars`` is ``[(label, counts), ...]`` (before first);
    `paper` optional ``[(label, counts)]`` drawn hatched."""
    from .report import bin_labels

    plt = pyplot()
    allbars = [(lab, cnt, False) for lab, cnt in bars] + [(lab, cnt, True) for lab, cnt in (paper or [])]
    nb = len(HISTOGRAM_EDGES) - 1
    width = 0.85 / max(len(allbars), 1)
    fig, ax = plt.subplots(figsize=(max(7, 1.1 * nb + 0.3 * len(allbars)), 4.2))
    x = np.arange(nb)
    for i, (lab, cnt, hatched) in enumerate(allbars):
        ax.bar(x + (i - (len(allbars) - 1) / 2) * width, cnt, width, label=lab, hatch="//" if hatched else None,
               alpha=0.6 if hatched else 1.0, edgecolor="k", linewidth=0.4)
    ax.set_xticks(x, bin_labels())
    ax.set_xlabel("corner kappa/3")
    ax.set_ylabel("corners")
    ax.set_yscale("symlog", linthresh=10)
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(title)
    _save(fig, path)


def surface_figure(path: Path, title: str, hexes, points_before, points_after) -> bool:
    """Boundary quadrilaterals of a hex mesh before and after, coloured by element condition (log scale).

    **Returns:** False (and draws nothing) when the mesh has more than `MAX_SURFACE_FACES` boundary faces.
    """
    import jax
    from matplotlib.colors import LogNorm

    from ..geometry.topology import boundary_topology
    from ..metrics.hexahedron import element_condition

    hexes = np.asarray(hexes)
    topo = boundary_topology(hexes, len(points_before))
    if len(topo.faces) > MAX_SURFACE_FACES:
        return False
    plt = pyplot()
    vals = []
    with jax.enable_x64(True):
        for pts in (points_before, points_after):
            ec = np.asarray(element_condition(np.asarray(pts, np.float64), hexes), dtype=np.float64)
            vals.append(ec[topo.face_hex])
    finite = np.concatenate([v[np.isfinite(v)] for v in vals])
    vmax = max(float(finite.max()) if finite.size else 2.0, 1.0 + 1e-3)
    norm = LogNorm(vmin=1.0, vmax=vmax)
    cmap = plt.get_cmap("viridis").with_extremes(over="red")
    fig = plt.figure(figsize=(11, 5))
    lo = np.minimum(np.min(points_before, axis=0), np.min(points_after, axis=0))
    hi = np.maximum(np.max(points_before, axis=0), np.max(points_after, axis=0))
    for i, (pts, v, lab) in enumerate(zip((points_before, points_after), vals, ("before", "after"), strict=True)):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        worst = float(np.max(v)) if v.size else math.nan
        draw_surface(ax, pts, topo.faces, v, norm, cmap, (lo, hi), f"{lab}: max kappa/3 on the surface {worst:.4g}")
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=fig.axes, shrink=0.7, label="element condition (max corner kappa/3)")
    fig.suptitle(title)
    _save(fig, path, tight=False)
    return True


def draw_surface(ax, points, faces, values, norm, cmap, box, title: str) -> None:
    """Draw boundary `faces` ``(F, 4)`` (a triangle repeats its last node) of `points` on the 3-D axes `ax`,
    coloured by `values` ``(F,)`` through `norm` and `cmap` (non-finite values, inverted cells: red), in the
    bounding box ``box = (lo, hi)`` seen from the same angle as every other surface figure."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    pts = np.asarray(points, dtype=np.float64)
    lo, hi = box
    top = norm.vmax * 10 if norm.vmax is not None else 1e300
    finite = np.isfinite(values)
    colours = cmap(norm(np.where(finite, values, top)))
    colours[~finite] = (1.0, 0.0, 0.0, 1.0)  # inverted: red
    ax.add_collection3d(Poly3DCollection(pts[faces], facecolors=colours, edgecolors="k", linewidths=0.3))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-12)))
    ax.set_title(title, fontsize=9)
    ax.view_init(elev=25, azim=-55)


def write_figures(folder: Path, exp, records, results: dict) -> dict:
    """Draw every figure of an experiment into `folder`.

    **Arguments:** `folder`; `exp` the `jaxci.experiments.config.Experiment`; `records` its `RunRecord` list; `results`
    ``(input HexMesh, SmoothResult)`` of the first seed per ``(mesh name, method label)``.

    **Returns:** ``{"files": [relative paths], "skipped": [reasons]}`` for the summary.
    """
    from .report import PAPER_TABLE1, table1_choice

    files, skipped = [], []
    t1 = table1_choice(exp)
    for rm in exp.meshes:
        series = []
        for meth in exp.methods:
            hists = [r.history for r in records if r.mesh == rm.name and r.label == meth.label and r.history]
            if hists:
                series.append((meth.label, hists))
        if series:
            p = folder / f"convergence_{rm.slug}.png"
            convergence_figure(p, f"{rm.name}: convergence (first seed bold)", series)
            files.append(f"figures/{p.name}")
        firsts = [(meth, results.get((rm.name, meth.label))) for meth in exp.methods]
        firsts = [(m, r) for m, r in firsts if r is not None]
        if not firsts:
            continue
        before = firsts[0][1][1].before
        bars = [("before", [c for _, _, c in before.histogram])]
        bars += [(m.label, [c for _, _, c in r.after.histogram]) for m, (_, r) in firsts]
        paper = None
        if rm.name == t1["mesh"] and before.n_elements == 27:
            paper = [(f"paper {k}", list(v)) for k, v in PAPER_TABLE1.items()]
        p = folder / f"histogram_{rm.slug}.png"
        histogram_figure(p, f"{rm.name}: corners per kappa/3 bin (seed {exp.seeds[0]})", bars, paper)
        files.append(f"figures/{p.name}")
        for meth, (inp, res) in firsts:
            p = folder / f"surface_{rm.slug}_{meth.slug}.png"
            title = (f"{rm.name}, {meth.label} (seed {exp.seeds[0]}): mesh max kappa/3 "
                     f"{_num(res.before.max_condition)} -> {_num(res.after.max_condition)}")
            ok = surface_figure(p, title, inp.hexes, inp.points, res.mesh.points)
            if ok:
                files.append(f"figures/{p.name}")
            else:
                skipped.append(f"{p.name}: more than {MAX_SURFACE_FACES} boundary faces")
    return {"files": files, "skipped": skipped}


def _num(v) -> str:
    return "-" if v is None else f"{v:.4g}"
