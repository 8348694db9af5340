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

from ..cells import CORNERS, ELEMENT_TYPES, element_blocks
from ..errors import MeshError
from ..mesh import HexMesh, as_hex_mesh, to_unit, unit_frame
from .elements import corner_condition, corner_figures, hex_corner_measures, summary
from .objective import cell_label

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


def quality_report(mesh: HexMesh, points=None) -> QualityReport:
    """The quality report of `mesh` (or of `mesh` with node coordinates `points` of shape ``(n, 3)``).

    Measured in float64 on the host (`jaxci.metrics.elements.hex_corner_measures`: the threaded C pass of
    `jaxci.native`, else numpy; no compilation, which cost 0.4 s of a 729-element cold start), over blocks of
    `REPORT_CHUNK` hexahedra (`HexFigures`). The coordinates are
    measured in the unit frame of `jaxci.mesh.unit_frame` (the metrics are scale-invariant): a mesh in metres,
    nanometres or light years gives the same report, without overflow or underflow. The same report from
    coordinates on a device: `jaxci.metrics.device.quality_report_device`.

    **Arguments:** `mesh` a `HexMesh` (a `meshio.Mesh` is converted; anything else raises `UsageError`);
    `points` optional coordinates of shape ``(n_nodes, 3)``, finite (`MeshError` otherwise).
    """
    mesh = as_hex_mesh(mesh, "quality_report")
    if points is None:
        pts = mesh.points
    else:
        pts = np.asarray(points, dtype=np.float64)
        check_report_points(mesh, pts.shape)
        if not np.isfinite(pts).all():
            k = int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
            raise non_finite_error(mesh, k, pts[k])
    pts = to_unit(pts, unit_frame(pts))
    hexes = mesh.hexes
    acc = HexFigures()
    for lo in range(0, mesh.n_hexes, REPORT_CHUNK):
        kappa3, sj = hex_corner_measures(pts, hexes[lo:lo + REPORT_CHUNK])
        acc.add(figure_totals(np, kappa3, sj, axis=1), lo)
    return build_report(mesh, acc, pts)


def check_report_points(mesh: HexMesh, shape: tuple) -> None:
    """`MeshError` unless coordinates of shape `shape` fit `mesh` (``(n_nodes, 3)``)."""
    if tuple(shape) != mesh.points.shape:
        raise MeshError(f"quality_report: points have shape {tuple(shape)}, the mesh has {mesh.points.shape}")


def non_finite_error(mesh: HexMesh, k: int, row) -> MeshError:
    """The `MeshError` of `quality_report` for node `k` (the first with a non-finite coordinate, at `row`)."""
    return MeshError(f"quality_report: node {mesh.node_label(k)} has non-finite coordinates "
                     f"{np.asarray(row, np.float64).tolist()}")


def build_report(mesh: HexMesh, acc: HexFigures, pts) -> QualityReport:
    """The `QualityReport` of `mesh` from its hexahedra's figures `acc` and, for its other cell types, the unit
    frame coordinates `pts` ``(n, 3)`` (unused, and may be None, on a hexahedral mesh)."""
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
#: extremes and histogram bins: a block's corner arrays (~0.6 kB per hexahedron: 10 MB) are live, not the mesh's.
#: 65,536 held 40 MB of them, the peak of the final checks at 216,000 hexahedra; 16,384 takes the same time (the
#: input report of cube60_pert 0.044-0.047 s against 0.050 s, 2026-11-30; the sums' last bits differ).
REPORT_CHUNK = 16_384


def figure_totals(xp, kappa3, sj, axis: int, reduce_rows=None) -> dict:
    """The report's figures of a set of hexahedra, with the array module `xp` (numpy for a block on the host,
    `jax.numpy` for the whole mesh on a device: `jaxci.metrics.device`).

    **Arguments:** `kappa3` every corner's kappa/3 (``inf`` where det <= 0) and `sj` its scaled Jacobian, float64,
    the 8 corners of a hexahedron along `axis` (1: ``(B, 8)``; 0: ``(8, B)``); `reduce_rows` how the per-corner
    figures are reduced over each element's corners: a function ``(fields, axis)`` -> per-element arrays, `fields`
    name -> ``(array, "sum" | "max" | "min")`` (default `reduce_rows_np`; on a device
    `jaxci.metrics.device.reduce_rows`, one variadic reduction: XLA forms the corners once for all of them).

    **Returns:** a dict of scalars (`xp` arrays): ``count``, ``inverted`` (elements), ``inverted_corners``,
    ``n_ok`` (corners of valid elements) and ``sum_ok`` (their kappa/3 summed), ``n_valid`` (valid corners) and
    ``sq_sum`` (their (kappa/3)^2 summed), ``max_ok`` (max element kappa/3 over valid elements, ``-inf`` if none)
    and ``worst`` (its first element), ``sj_min`` and ``hist`` (Table 1's bins `HISTOGRAM_EDGES` of the valid
    corners, ``(7,)``; a value a rounding error below 1 counts in the first bin).
    """
    valid = xp.isfinite(kappa3)  # inf exactly where det <= 0
    kv = xp.where(valid, kappa3, 0.0)
    one = xp.int32
    fields = {"n_valid": (valid.astype(one), "sum"), "k_max": (kappa3, "max"), "k_sum": (kv, "sum"),
              "k_sq": (kv * kv, "sum"), "sj_min": (sj, "min")}
    inner = HISTOGRAM_EDGES[1:-1]
    fields.update({f"above{i}": ((kv >= e).astype(one), "sum") for i, e in enumerate(inner)})  # valid corners
    el = (reduce_rows or reduce_rows_np)(fields, axis)  # per element, (B,) each
    corners = kappa3.shape[axis]
    ok = el["n_valid"] == corners
    elem_max = xp.where(ok, el["k_max"], -xp.inf)
    worst = xp.argmax(elem_max)
    n_valid = xp.sum(el["n_valid"], dtype=xp.int64)
    above = [xp.sum(el[f"above{i}"], dtype=xp.int64) for i in range(len(inner))]
    hist = xp.stack([n_valid - above[0], *(a - b for a, b in zip(above[:-1], above[1:], strict=True)), above[-1]])
    count = ok.shape[0]
    n_ok = xp.sum(ok, dtype=xp.int64)
    return {"count": xp.asarray(count), "inverted": count - n_ok, "inverted_corners": corners * count - n_valid,
            "n_ok": corners * n_ok, "sum_ok": xp.sum(xp.where(ok, el["k_sum"], 0.0)), "n_valid": n_valid,
            "sq_sum": xp.sum(el["k_sq"]), "max_ok": elem_max[worst], "worst": worst, "sj_min": xp.min(el["sj_min"]),
            "hist": hist}


def reduce_rows_np(fields: dict, axis: int) -> dict:
    """`figure_totals`' per-element reductions in numpy: name -> ``(array, op)`` -> name -> the array reduced
    over `axis` by ``np.sum`` / ``np.max`` / ``np.min``."""
    return {name: getattr(np, op)(a, axis=axis) for name, (a, op) in fields.items()}


class HexFigures:
    """The hexahedra's report figures, accumulated block by block (`add`)."""

    def __init__(self):
        self.count = self.inverted = self.inverted_corners = self.n_ok = self.n_valid = 0
        self.sum_ok = self.sq_sum = 0.0
        self.max_ok = self.sj_min = self.worst = None
        self.hist = np.zeros(len(HISTOGRAM_EDGES) - 1, np.int64)

    def add(self, totals: dict, offset: int) -> None:
        """Add the `figure_totals` of hexahedra (numpy values) the first of which is hexahedron `offset`."""
        t = totals
        for key in ("count", "inverted", "inverted_corners", "n_ok", "n_valid"):
            setattr(self, key, getattr(self, key) + int(t[key]))
        self.sum_ok += float(t["sum_ok"])
        self.sq_sum += float(t["sq_sum"])
        if int(t["n_ok"]) and (self.max_ok is None or float(t["max_ok"]) > self.max_ok):
            self.max_ok, self.worst = float(t["max_ok"]), offset + int(t["worst"])
        if int(t["count"]):
            m = float(t["sj_min"])
            self.sj_min = m if self.sj_min is None else min(self.sj_min, m)
        self.hist += np.asarray(t["hist"], np.int64)

    def summary(self) -> dict:
        """`jaxci.metrics.elements.summary` of the hexahedra, plus ``verdict_condition`` (max element kappa/3)."""
        return {"count": self.count, "inverted": self.inverted, "max_condition": self.max_ok,
                "mean_condition": self.sum_ok / self.n_ok if self.n_ok else None, "min_scaled_jacobian": self.sj_min,
                "objective": self.sq_sum / self.n_valid - 1.0 if self.n_valid else None,
                "verdict_condition": self.max_ok}


def _by_type(mesh: HexMesh, points, hexa: HexFigures) -> dict:
    """The `by_type` and `overall` fields of `quality_report`: the hexahedra's from `hexa` (accumulated above),
    `jaxci.metrics.elements.corner_figures` for the other types (measured at `points`; unused on a mesh of
    hexahedra only, whose blocks are then not concatenated)."""
    by_type = {"hexahedron": hexa.summary()}
    figs = []
    others = [t for t in ELEMENT_TYPES[1:] if any(b.type == t and len(b.data) for b in mesh.cells)]
    blocks = element_blocks(mesh) if others else {}
    for t in others:
        f = corner_figures(points, blocks[t], t)
        ok = ~f["inverted"]
        by_type[t] = {**summary([f]), "verdict_condition": float(f["verdict_condition"][ok].max()) if ok.any()
                      else None}
        figs.append(f)
    return {"by_type": by_type, "overall": _overall(hexa, figs)}


def _overall(h: HexFigures, figs: list) -> dict:
    """`jaxci.metrics.elements.summary` over every cell: the hexahedra's accumulated figures `h` and the other
    types' `corner_figures` `figs`."""
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
    pts = np.asarray(points, np.float64)
    found = []
    for t, cells in element_blocks(mesh).items():
        # each cell's worst corner, `REPORT_CHUNK` cells at a time (every corner's kappa/3 at once, with the
        # scaled Jacobians the kernel makes beside them and a copy: 40 MB at 216,000 hexahedra)
        worst, corner = np.empty(len(cells)), np.empty(len(cells), np.int64)
        for lo in range(0, len(cells), REPORT_CHUNK):
            k = corner_condition(pts, cells[lo:lo + REPORT_CHUNK], t)
            k[np.isnan(k)] = np.inf
            worst[lo:lo + len(k)] = k.max(axis=1)
            corner[lo:lo + len(k)] = np.argmax(k, axis=1)
        top = np.argsort(-worst, kind="stable")[:n]
        found += [(float(worst[e]), t, int(e), int(corner[e]), cells[e]) for e in top]
    found.sort(key=lambda f: -f[0])
    found = found[:n]
    cls = None if node_class is None else np.asarray(node_class)
    classes = None if cls is None else [cls[np.asarray(f[4], np.int64)] for f in found]
    return listed_worst(mesh, found, classes, feature_edges, coincident)


def listed_worst(mesh: HexMesh, found: list, classes, feature_edges, coincident) -> tuple[dict, ...]:
    """The dicts of `worst_elements` for the worst cells `found`, worst first: rows ``(kappa3, type, index,
    corner (the worst corner's row of `jaxci.cells.CORNERS`), cell (its nodes, ``(k,)``))``; `classes` None or,
    per row, the node classes of its cell's nodes (``(k,)``, aligned with the cell); `feature_edges` and
    `coincident` as `worst_elements` takes them (O(boundary), on the host)."""
    edges = set()
    if feature_edges is not None and len(feature_edges):
        fe = np.sort(np.asarray(feature_edges, np.int64), axis=1)
        edges = set(map(tuple, fe.tolist()))
    shared = np.zeros(0, np.int64) if coincident is None else np.asarray(coincident, np.int64)
    out = []
    for i, (kappa, t, e, c, cell) in enumerate(found):
        row = CORNERS[t][c]
        cell = np.asarray(cell, np.int64)
        nodes = [int(cell[j]) for j in row]
        limits = []
        if classes is not None:
            cls = np.asarray(classes[i])[row]
            if (cls == 3).all():
                limits.append("fixed corner")
            elif (cls >= 1).all():
                limits.append("boundary corner")
        if any(tuple(sorted((nodes[0], b))) in edges for b in nodes[1:]):
            limits.append("feature edge")
        if np.isin(cell, shared).any():
            limits.append("coincident nodes")
        label = f"element {mesh.hex_label(e)}" if t == "hexahedron" else cell_label(mesh, t, e)
        out.append({"element": label, "type": t, "index": e, "kappa3": float(kappa), "corner": int(row[0]),
                    "nodes": nodes, "limits": limits})
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
