"""The quality report of a mesh (`quality_report`, what ``jaxci quality`` prints): every figure in float64.

The hexahedra's figures (the paper's: kappa/3 per corner, inverted corners and elements, F of Eq. 3.1, the
scaled Jacobian and Table 1's histogram) come from the numpy kernel of `jaxci.metrics.elements` (no compilation),
over blocks of `REPORT_CHUNK` hexahedra whose counts, sums and extremes are added up; every
cell type's figures (`QualityReport.by_type`, `QualityReport.overall`) from `jaxci.metrics.elements.corner_figures`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..cells import element_blocks
from ..errors import MeshError
from ..mesh import HexMesh, as_hex_mesh, to_unit, unit_frame
from .elements import corner_figures, hex_corner_measures, summary

#: Bin edges of the paper's Table 1 histogram of corners over kappa/3.
HISTOGRAM_EDGES = (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 8.0, math.inf)


@dataclasses.dataclass(frozen=True)
class QualityReport:
    """What `jaxci quality` prints: counts, inverted corners/elements, condition figures, Table 1 histogram.

    Condition figures are kappa/3 (Frobenius, Verdict convention) over VALID corners and elements only;
    `objective` is F (Eq. 3.1) over the valid corners, None if there are none. All these keys (and
    `n_elements`) are about the HEXAHEDRA only, as they always were.

    Every volume cell type (`jaxci.metrics.elements`: hexahedron, wedge, pyramid, tetra; quadratic cells by their
    corner nodes) is in:

    - `by_type`: type -> {``count``, ``inverted`` (cells), ``max_condition``, ``mean_condition`` (corner kappa/3
      relative to the type's ideal cell, over the corners of valid cells), ``min_scaled_jacobian`` (Verdict's
      element scaled Jacobian; for hexahedra the min corner one, as `min_scaled_jacobian`),
      ``verdict_condition`` (max of VTK's ``HexCondition`` / ``WedgeCondition`` / ``TetCondition`` over valid
      cells; pyramids: max corner kappa/3), ``objective`` (the type's mean of (kappa/3)^2 - 1 over its valid
      corners)};
    - `overall`: the same over all cells (no ``verdict_condition``); its ``objective`` is Eq. 3.1 over every
      valid element corner, `jaxci.metrics.elements.mixed_objective` when no corner is inverted (on a hexahedral mesh:
      `objective`).
    - `worst_elements`: after smoothing (`jaxci.smooth`), the `WORST_LISTED` worst cells and what limits each
      (`worst_elements`); None elsewhere (and then not in `to_dict`).
    """

    n_nodes: int
    n_elements: int
    inverted_corners: int
    inverted_elements: int
    max_condition: float | None
    mean_condition: float | None
    objective: float | None
    min_scaled_jacobian: float | None
    histogram: tuple[tuple[float, float, int], ...]
    worst_element: int | None = None
    other_cells: dict | None = None
    by_type: dict | None = None
    overall: dict | None = None
    worst_elements: tuple | None = None

    def to_dict(self) -> dict:
        """The JSON object of ``jaxci quality --json`` (histogram as a list of {low, high, count})."""
        d = dataclasses.asdict(self)
        if self.worst_elements is None:
            d.pop("worst_elements")
        else:
            d["worst_elements"] = [dict(w) for w in self.worst_elements]
        d["histogram"] = [
            {"low": lo, "high": (None if math.isinf(hi) else hi), "count": c} for lo, hi, c in self.histogram
        ]
        return d


def corner_histogram(kappa3: np.ndarray) -> tuple[tuple[float, float, int], ...]:
    """Counts of corner kappa/3 values (finite ones) in the paper's Table 1 bins `HISTOGRAM_EDGES`."""
    k = np.asarray(kappa3, dtype=np.float64).ravel()
    k = k[np.isfinite(k)]
    edges = np.asarray(HISTOGRAM_EDGES)
    # values a rounding error below 1 belong to the first bin
    idx = np.clip(np.searchsorted(edges, k, side="right") - 1, 0, len(edges) - 2)
    counts = np.bincount(idx, minlength=len(edges) - 1)
    return tuple((float(edges[i]), float(edges[i + 1]), int(counts[i])) for i in range(len(edges) - 1))


def quality_report(mesh: HexMesh, points=None) -> QualityReport:
    """The quality report of `mesh` (or of `mesh` with node coordinates `points` of shape ``(n, 3)``).

    Measured in float64 on the host (`jaxci.metrics.elements.hex_corner_measures`: the threaded C pass of
    `jaxci.native`, else numpy; no compilation, which cost 0.4 s of a 729-element cold start), over blocks of
    `REPORT_CHUNK` hexahedra (`_HexFigures`). The coordinates are
    measured in the unit frame of `jaxci.mesh.unit_frame` (the metrics are scale-invariant): a mesh in metres,
    nanometres or light years gives the same report, without overflow or underflow.

    **Arguments:** `mesh` a `HexMesh` (a `meshio.Mesh` is converted; anything else raises `UsageError`);
    `points` optional coordinates of shape ``(n_nodes, 3)``, finite (`MeshError` otherwise).
    """
    mesh = as_hex_mesh(mesh, "quality_report")
    if points is None:
        pts = mesh.points
    else:
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape != mesh.points.shape:
            raise MeshError(f"quality_report: points have shape {pts.shape}, the mesh has {mesh.points.shape}")
        if not np.isfinite(pts).all():
            k = int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
            raise MeshError(f"quality_report: node {mesh.node_label(k)} has non-finite coordinates "
                            f"{pts[k].tolist()}")
    pts = to_unit(pts, unit_frame(pts))
    hexes = mesh.hexes
    acc = _HexFigures()
    for lo in range(0, mesh.n_hexes, REPORT_CHUNK):
        acc.add(pts, hexes[lo:lo + REPORT_CHUNK], lo)
    return QualityReport(
        n_nodes=mesh.n_nodes,
        n_elements=mesh.n_hexes,
        inverted_corners=acc.inverted_corners,
        inverted_elements=acc.inverted,
        max_condition=acc.max_ok,
        mean_condition=acc.sum_ok / acc.n_ok if acc.n_ok else None,
        objective=acc.sq_sum / acc.n_valid - 1.0 if acc.n_valid else None,
        min_scaled_jacobian=acc.sj_min,
        histogram=tuple((float(lo), float(hi), int(c)) for lo, hi, c in
                        zip(HISTOGRAM_EDGES[:-1], HISTOGRAM_EDGES[1:], acc.hist, strict=True)),
        worst_element=acc.worst,
        other_cells={t: int(sum(len(b.data) for b in mesh.cells if b.type == t)) for t in mesh.other_cell_types}
        or None,
        **_by_type(mesh, pts, acc),
    )


#: `quality_report` measures the hexahedra in blocks of this many (numpy float64), adding up counts, sums,
#: extremes and histogram bins: a block's corner arrays (~0.6 kB per hexahedron) are live, not the mesh's.
#: Measured at 10^6 hexahedra: see docs/sharding.md, "Memory".
REPORT_CHUNK = 65_536


class _HexFigures:
    """The hexahedra's report figures, accumulated block by block (`add`)."""

    def __init__(self):
        self.count = self.inverted = self.inverted_corners = self.n_ok = self.n_valid = 0
        self.sum_ok = self.sq_sum = 0.0
        self.max_ok = self.sj_min = self.worst = None
        self.hist = np.zeros(len(HISTOGRAM_EDGES) - 1, np.int64)

    def add(self, pts, hexes, offset: int) -> None:
        """The figures of hexahedra `hexes` (``(B, 8)``), the first of which is hexahedron `offset`."""
        kappa3, sj = hex_corner_measures(pts, hexes)
        valid = np.isfinite(kappa3)  # inf exactly where det <= 0
        inv_el = ~valid.all(axis=1)
        elem_max = kappa3.max(axis=1)
        ok = ~inv_el
        self.count += len(hexes)
        self.inverted += int(inv_el.sum())
        self.inverted_corners += int((~valid).sum())
        if ok.any():
            k = int(np.argmax(np.where(ok, elem_max, -np.inf)))
            if self.max_ok is None or elem_max[k] > self.max_ok:
                self.max_ok, self.worst = float(elem_max[k]), offset + k
            self.sum_ok += float(kappa3[ok].sum())
            self.n_ok += int(ok.sum()) * 8
        kv = kappa3[valid]
        self.sq_sum += float(np.sum(kv * kv))
        self.n_valid += len(kv)
        self.hist += np.asarray([c for _, _, c in corner_histogram(kv)], np.int64)
        m = float(sj.min())
        self.sj_min = m if self.sj_min is None else min(self.sj_min, m)

    def summary(self) -> dict:
        """`jaxci.metrics.elements.summary` of the hexahedra, plus ``verdict_condition`` (max element kappa/3)."""
        return {"count": self.count, "inverted": self.inverted, "max_condition": self.max_ok,
                "mean_condition": self.sum_ok / self.n_ok if self.n_ok else None, "min_scaled_jacobian": self.sj_min,
                "objective": self.sq_sum / self.n_valid - 1.0 if self.n_valid else None,
                "verdict_condition": self.max_ok}


def _by_type(mesh: HexMesh, points, hexa: _HexFigures) -> dict:
    """The `by_type` and `overall` fields of `quality_report`: the hexahedra's from `hexa` (accumulated above),
    `jaxci.metrics.elements.corner_figures` for the other types."""
    by_type = {}
    parts = []
    for t, cells in element_blocks(mesh).items():
        if t == "hexahedron":
            by_type[t] = hexa.summary()
            parts.append(hexa)
            continue
        f = corner_figures(points, cells, t)
        ok = ~f["inverted"]
        by_type[t] = {**summary([f]), "verdict_condition": float(f["verdict_condition"][ok].max()) if ok.any()
                      else None}
        parts.append(f)
    return {"by_type": by_type, "overall": _overall(parts)}


def _overall(parts: list) -> dict:
    """`jaxci.metrics.elements.summary` over every cell: the hexahedra's accumulated figures (`_HexFigures`) and
    the other types' `corner_figures`."""
    figs = [p for p in parts if isinstance(p, dict)]
    hexa = [p for p in parts if isinstance(p, _HexFigures)]
    if not hexa:
        return summary(figs)
    h = hexa[0]
    if not figs:
        s = h.summary()
        s.pop("verdict_condition")
        return s
    k3_ok = np.concatenate([f["kappa3"][~f["inverted"]].ravel() for f in figs])
    k3 = np.concatenate([f["kappa3"].ravel() for f in figs])
    k3 = k3[np.isfinite(k3)]
    sj = np.concatenate([f["scaled_jacobian"] for f in figs])
    n_ok, n_fin = h.n_ok + len(k3_ok), h.n_valid + len(k3)
    maxes = [m for m in (h.max_ok, float(k3_ok.max()) if len(k3_ok) else None) if m is not None]
    sjs = [m for m in (h.sj_min, float(sj.min()) if len(sj) else None) if m is not None]
    return {
        "count": h.count + int(sum(len(f["inverted"]) for f in figs)),
        "inverted": h.inverted + int(sum(f["inverted"].sum() for f in figs)),
        "max_condition": max(maxes) if maxes else None,
        "mean_condition": (h.sum_ok + float(k3_ok.sum())) / n_ok if n_ok else None,
        "min_scaled_jacobian": min(sjs) if sjs else None,
        "objective": (h.sq_sum + float(np.sum(k3 * k3))) / n_fin - 1.0 if n_fin else None,
    }


# ---------------------------------------------------------------------------------------------- worst elements
#: How many of the worst cells a smoothing result lists (`worst_elements`).
WORST_LISTED = 10

#: What can hold an element back, as `worst_elements` names it (``limits``), with the sentence that explains it.
LIMITS = {
    "fixed corner": "the four nodes of its worst corner are fixed (boundary corners, fixed sets or --fix-boundary)",
    "boundary corner": "the four nodes of its worst corner all lie on the boundary (fixed, or sliding on it)",
    "feature edge": "its worst corner has an edge on a feature curve (--feature-angle decides which edges are)",
    "coincident nodes": "it has coincident nodes (an unmerged interface), which move together",
}


def worst_elements(mesh: HexMesh, points, node_class=None, feature_edges=None, coincident=None,
                   n: int = WORST_LISTED) -> tuple[dict, ...]:
    """The `n` worst cells of every type at `points` (by their worst corner's kappa/3, worst first), each with what
    limits it.

    **Arguments:** `mesh`; `points` ``(n_nodes, 3)``; `node_class` (optional) every node's class
    (`jaxci.geometry.boundary`: 3 is fixed, 1-2 on the boundary); `feature_edges` (optional) ``(k, 2)`` node
    pairs; `coincident` (optional) the nodes in coincident sets.

    **Returns:** dicts ``{"element": label (the file's id), "type", "index" (within its type), "kappa3" (the
    cell's worst corner kappa/3, inf if inverted), "corner" (that corner's local node), "nodes" (the corner's
    node and its three edge neighbours, indices), "limits": [names of `LIMITS` that apply]}``.
    """
    from ..cells import CORNERS
    from .elements import corner_condition
    from .objective import cell_label

    pts = np.asarray(points, np.float64)
    found = []
    for t, cells in element_blocks(mesh).items():
        k = corner_condition(pts, cells, t)
        k = np.where(np.isnan(k), np.inf, k)
        worst = k.max(axis=1)
        top = np.argsort(-worst, kind="stable")[:n]
        found += [(float(worst[e]), t, int(e), int(np.argmax(k[e])), cells[e]) for e in top]
    found.sort(key=lambda f: -f[0])
    cls = None if node_class is None else np.asarray(node_class)
    edges = set()
    if feature_edges is not None and len(feature_edges):
        fe = np.sort(np.asarray(feature_edges, np.int64), axis=1)
        edges = set(map(tuple, fe.tolist()))
    shared = np.zeros(len(pts), bool)
    if coincident is not None:
        shared[np.asarray(coincident, np.int64)] = True
    out = []
    for kappa, t, e, c, cell in found[:n]:
        row = CORNERS[t][c]
        nodes = [int(cell[j]) for j in row]
        limits = []
        if cls is not None:
            if (cls[nodes] == 3).all():
                limits.append("fixed corner")
            elif (cls[nodes] >= 1).all():
                limits.append("boundary corner")
        if any(tuple(sorted((nodes[0], b))) in edges for b in nodes[1:]):
            limits.append("feature edge")
        if shared[np.asarray(cell, np.int64)].any():
            limits.append("coincident nodes")
        label = f"element {mesh.hex_label(e)}" if t == "hexahedron" else cell_label(mesh, t, e)
        out.append({"element": label, "type": t, "index": e, "kappa3": kappa, "corner": int(row[0]), "nodes": nodes,
                    "limits": limits})
    return tuple(out)


def limited_note(report: QualityReport) -> str | None:
    """One sentence where the worst element of `report` (its `worst_elements`) is held back by what cannot move,
    else None."""
    worst = report.worst_elements
    if not worst or not worst[0]["limits"]:
        return None
    w = worst[0]
    why = "; ".join(LIMITS[k] for k in w["limits"])
    return f"the worst element, {w['element']} (kappa/3 {w['kappa3']:.4g}), is limited: {why}"
