"""The quality figures and checks of a hexahedral mesh from its arrays on a device (the JAX engine), in float64.

A run on the JAX engine keeps the node coordinates ``points`` ``(n, 3)`` and the transposed hexahedra ``conn``
``(8, N)`` (`jaxci.metrics.hexahedron.transposed`) on the device from upload to download. What the host
functions measure over every corner (`jaxci.metrics.report.quality_report`, `worst_elements`, the validity and
volume checks, the final checks of `jaxci.interface.invariants.enforce`) is measured there, by the jitted programs of
this module (each an entry point timed by `jaxci.runtime.transfer.program`), and only their few figures come down,
in one `jaxci.runtime.transfer.to_host` per call: O(1), or O(k) for the k worst elements, never O(mesh).

- `quality_report_device`: the `QualityReport` of `quality_report` (measured in the unit frame, as there);
- `worst_elements_device`: the list of `worst_elements` (a `jax.lax.top_k` of the cells' worst corners);
- `inverted_hexes`: the count and first index of inverted hexahedra (`jaxci.metrics.objective.inverted_cells`);
- `volume_moments`: the moment matrix `jaxci.mesh.check_volume` decides from;
- `final_figures`: the figures `jaxci.interface.invariants.enforce_device` decides from (newly inverted cells, F or
  the p-mean, the worst cells, `jaxci.metrics.guard.keep_worst`'s put-back as a device mask).

Every function here runs inside ``jax.enable_x64(True)`` and measures in float64 (coordinates of another dtype are
converted on the device). The report's figures are `jaxci.metrics.report.figure_totals`, written once for numpy
and `jax.numpy`; the corner algebra is `jaxci.cells.corner_invariants` and `jaxci.metrics.hexahedron`'s. XLA may
contract products and sums into fused multiply-adds, so values agree with the host's to rounding (a few ulp of
each corner's measures, ~1e-13 relative of kappa/3) and counts exactly, except for corners whose det is within
rounding of 0, which either side may call inverted.

Hexahedral meshes only (`hex_only`): a mesh with wedges, pyramids or tetrahedra keeps the host functions.
"""

from __future__ import annotations

import numpy as np

from ..cells import ELEMENT_TYPES, corner_invariants, edge_lengths2, pmean_weights, scaled_ratio
from ..errors import UsageError
from ..mesh import HexMesh
from ..mesh.frame import box_frame
from ..runtime._lazy import enable_x64, jax, jit, jnp
from ..runtime.transfer import program, to_device, to_host
from .guard import KEEP_WORST_RTOL
from .hexahedron import condition_from_invariants, corner_columns, squared_condition_from_invariants
from .report import (
    WORST_LISTED,
    HexFigures,
    QualityReport,
    build_report,
    check_report_points,
    figure_totals,
    listed_worst,
    non_finite_error,
)


def hex_only(mesh: HexMesh, caller: str) -> None:
    """`UsageError` unless the measured cells of `mesh` are hexahedra only (the device functions' domain)."""
    other = sorted({b.type for b in mesh.cells if b.type in ELEMENT_TYPES[1:] and len(b.data)})
    if other:
        raise UsageError(f"{caller} measures hexahedral meshes only; this one has {', '.join(other)} cells (use "
                         f"the host function)")


# ---------------------------------------------------------------------------------------------- kernels
def _corners(points, conn):
    """Every corner's ``(det, kappa3, sj, term)``, each ``(8, N)`` float64: det A, kappa/3 (``inf`` where
    det <= 0), the scaled Jacobian det / (|a| |b| |c|) (0 for an edge of length 0) and (kappa/3)^2 (``inf`` where
    det <= 0)."""
    g = points.astype(jnp.float64)[conn]  # (8, N, 3): one gather of rows (on a CPU 2x faster than 24 of scalars)
    cols = corner_columns(g[..., 0], g[..., 1], g[..., 2])
    det, fro2, adj2 = corner_invariants(*cols)
    sj = scaled_ratio(jnp, det, edge_lengths2(*cols))
    return det, condition_from_invariants(det, fro2, adj2), sj, squared_condition_from_invariants(det, fro2, adj2)


def reduce_rows(fields: dict, axis: int) -> dict:
    """`jaxci.metrics.report.reduce_rows_np` as ONE variadic `jax.lax.reduce`: name -> ``(array, "sum" | "max" |
    "min")`` -> name -> the array reduced over `axis`. Several reductions of one corner computation written
    apart make XLA:CPU form the corners once per reduction, or store their columns (measured at 10^6
    hexahedra on the shared 2-core CPU: the report's figures 2.9 s apart, 1.1 s as one reduction; the max kappa/3
    alone 0.56 s)."""

    def identity(op, dtype):
        if op == "sum":
            return jnp.zeros((), dtype)
        big = jnp.inf if jnp.issubdtype(dtype, jnp.floating) else jnp.iinfo(dtype).max
        return jnp.asarray(-big if op == "max" else big, dtype)

    combine = {"sum": jax.lax.add, "max": jax.lax.max, "min": jax.lax.min}
    names = list(fields)
    arrays = tuple(fields[n][0] for n in names)
    fns = [combine[fields[n][1]] for n in names]
    inits = tuple(identity(fields[n][1], a.dtype) for n, a in zip(names, arrays, strict=True))
    out = jax.lax.reduce(arrays, inits, lambda a, b: tuple(f(x, y) for f, x, y in zip(fns, a, b, strict=True)),
                         (axis,))
    return dict(zip(names, out, strict=True))


def _cell_worst(kappa3):
    """Each cell's max corner kappa/3, ``inf`` where a corner is inverted (NaN counted as inverted), ``(N,)``."""
    return jnp.max(jnp.where(jnp.isnan(kappa3), jnp.inf, kappa3), axis=0)


def _unit(points):
    """`points` in the unit frame of `jaxci.mesh.unit_frame` (the same numbers: the frame's scale is a power of
    two), on the device."""
    centre, scale = box_frame(jnp, points.min(axis=0), points.max(axis=0))
    return (points - centre) / scale


# ---------------------------------------------------------------------------------------------- quality report
@program
@jit
def report_figures(points, conn) -> dict:
    """`jaxci.metrics.report.figure_totals` of the hexahedra `conn` ``(8, N)`` at `points` ``(n, 3)`` in their
    unit frame, plus ``n_bad`` (nodes with a non-finite coordinate), ``first_bad`` and ``bad_row`` (the first such
    node and its coordinates, ``(3,)``): a dict of device scalars."""
    p = points.astype(jnp.float64)
    bad = ~jnp.all(jnp.isfinite(p), axis=1)
    first = jnp.argmax(bad)
    _, kappa3, sj, _ = _corners(_unit(p), conn)
    return {**figure_totals(jnp, kappa3, sj, axis=0, reduce_rows=reduce_rows), "n_bad": jnp.sum(bad),
            "first_bad": first, "bad_row": p[first]}


def quality_report_device(mesh: HexMesh, points, conn) -> QualityReport:
    """`jaxci.metrics.report.quality_report(mesh, points)` from device arrays: the same `QualityReport`.

    **Arguments:** `mesh` the `HexMesh` (hexahedra only: its counts, labels and cell types, no O(mesh) host
    work); `points` ``(n_nodes, 3)`` its coordinates on the device (float64; another float dtype is converted
    there); `conn` ``(8, N)`` its transposed hexahedra on the device (`jaxci.metrics.hexahedron.transposed`).

    **Returns:** the `QualityReport` (`worst_elements` None). `MeshError` as `quality_report` for points of
    another shape or non-finite coordinates. One program, one `to_host` of ~20 scalars.
    """
    hex_only(mesh, "quality_report_device")
    check_report_points(mesh, points.shape)
    with enable_x64():
        t = to_host(report_figures(points, conn))
    if t["n_bad"]:
        raise non_finite_error(mesh, int(t["first_bad"]), t["bad_row"])
    acc = HexFigures()
    acc.add(t, 0)
    return build_report(mesh, acc, None)


# ---------------------------------------------------------------------------------------------- worst elements
#: `top_k`'s block: the k largest values lie in the k blocks of this many with the largest maxima.
TOP_K_BLOCK = 1024


def top_k(values, k: int):
    """``(values, indices)`` of the `k` largest of `values` ``(N,)`` (no NaN), largest first, equal values by
    lower index first: `jax.lax.top_k`'s answer, in two small ones (measured on a CPU at 10^6 values: 1 s for
    `jax.lax.top_k`): the block maxima's top k, then the top k of those k blocks' values. Exact: a value outside
    those blocks has k block maxima ahead of it, each a value ahead of it."""
    n = values.shape[0]
    if n <= 4 * TOP_K_BLOCK:
        return jax.lax.top_k(values, k)
    m = -(-n // TOP_K_BLOCK)
    blocks = jnp.pad(values, (0, m * TOP_K_BLOCK - n), constant_values=-jnp.inf).reshape(m, TOP_K_BLOCK)
    chosen = jnp.sort(jax.lax.top_k(blocks.max(axis=1), min(k, m))[1])  # in index order: ties stay by index
    vals, pos = jax.lax.top_k(blocks[chosen].ravel(), k)
    return vals, chosen[pos // TOP_K_BLOCK] * TOP_K_BLOCK + pos % TOP_K_BLOCK


@program
@jit(static_argnames=("k",))
def worst_rows(points, conn, node_class, k: int) -> dict:
    """The `k` cells of `conn` ``(8, N)`` with the worst corner kappa/3 at `points` (``inf`` if inverted), worst
    first (ties: the lower index first, as a stable sort): ``kappa3`` ``(k,)``, ``index`` ``(k,)``, ``corner``
    ``(k,)`` (the first worst corner's local node), ``cells`` ``(k, 8)`` (their nodes) and, where `node_class`
    ``(n,)`` is given, ``classes`` ``(k, 8)`` (the classes of those nodes)."""
    vals, idx = top_k(_cell_worst(_corners(points, conn)[1]), k)
    cells = conn[:, idx]
    k3 = _corners(points, cells)[1]  # the k cells' corners again (a second use of the mesh's would store them)
    corner = jnp.argmax(jnp.where(jnp.isnan(k3), jnp.inf, k3), axis=0)
    out = {"kappa3": vals, "index": idx, "corner": corner, "cells": cells.T}
    if node_class is not None:
        out["classes"] = node_class[cells.T]
    return out


def worst_elements_device(mesh: HexMesh, points, conn, node_class=None, feature_edges=None, coincident=None,
                          n: int = WORST_LISTED) -> tuple[dict, ...]:
    """`jaxci.metrics.report.worst_elements(mesh, points, node_class, feature_edges, coincident, n)` from device
    arrays: the same list of dicts.

    **Arguments:** `mesh` (hexahedra only); `points` ``(n_nodes, 3)`` and `conn` ``(8, N)`` on the device, as for
    `quality_report_device` (measured as given, not in the unit frame, as `worst_elements` does); `node_class`
    None, or every node's class ``(n_nodes,)``: on the device (gathered there for the listed cells' nodes) or a
    numpy array (indexed on the host for them); `feature_edges` ``(k, 2)`` and `coincident` (node indices) on the
    host (O(boundary)), as `worst_elements` takes them.

    **Returns:** the `n` worst hexahedra's dicts (`jaxci.metrics.report.listed_worst`). One program, one
    `to_host` of O(n) values.
    """
    hex_only(mesh, "worst_elements_device")
    k = min(int(n), int(conn.shape[1]))
    on_device = node_class is not None and not isinstance(node_class, np.ndarray)
    with enable_x64():
        rows = to_host(worst_rows(points, conn, node_class if on_device else None, k=k))
    cells = np.asarray(rows["cells"], np.int64)
    found = [(float(v), "hexahedron", int(e), int(c), cell)
             for v, e, c, cell in zip(rows["kappa3"], rows["index"], rows["corner"], cells, strict=True)]
    if node_class is None:
        classes = None
    else:
        classes = rows["classes"] if on_device else np.asarray(node_class)[cells]
    return listed_worst(mesh, found, classes, feature_edges, coincident)


# ---------------------------------------------------------------------------------------------- validation
@program
@jit
def _inverted_program(points, conn):
    det = _corners(points, conn)[0]
    bad = jnp.any(det <= 0, axis=0)
    return jnp.sum(bad), jnp.argmax(bad)


def inverted_hexes(points, conn) -> tuple[int, int | None]:
    """``(count, first)``: how many hexahedra of `conn` ``(8, N)`` have a corner with det <= 0 at `points`
    ``(n, 3)`` (both on the device) and the index of the first (None if none): `jaxci.metrics.objective.
    inverted_cells`'s hexahedra, counted on the device (one `to_host` of two integers)."""
    with enable_x64():
        count, first = (int(v) for v in to_host(_inverted_program(points, conn)))
    return count, (first if count else None)


@program
@jit
def _moments_program(points, conn):
    p = points.astype(jnp.float64)
    used = jnp.zeros(p.shape[0], bool).at[conn].set(True)  # the nodes of the hexahedra
    count = jnp.sum(used)
    u = used[:, None]
    centre, scale = box_frame(jnp, jnp.where(u, p, jnp.inf).min(axis=0), jnp.where(u, p, -jnp.inf).max(axis=0))
    q = jnp.where(u, (p - centre) / scale, 0.0)
    q = jnp.where(u, q - q.sum(axis=0) / count, 0.0)
    return jnp.einsum("ij,ik->jk", q, q, precision=jax.lax.Precision.HIGHEST), count


def volume_moments(points, conn) -> tuple[np.ndarray, int]:
    """``(m, count)``: the 3 x 3 moment matrix of the nodes of the hexahedra `conn` ``(8, N)`` about their mean,
    in their unit frame, and how many nodes they are, from `points` ``(n, 3)``; both on the device, reduced
    there (one `to_host` of 10 numbers): what `jaxci.mesh.check_volume` decides from."""
    with enable_x64():
        m, count = to_host(_moments_program(points, conn))
    return np.asarray(m, np.float64), int(count)


# ---------------------------------------------------------------------------------------------- final checks
def _state(points, conn, power):
    """Of coordinates `points`: each cell inverted ``(N,)``, each cell's worst kappa/3 ``(N,)`` and the objective
    (F, or the p-mean of power `power`; ``inf`` if a corner is inverted)."""
    det, kappa3, _, term = _corners(points, conn)
    fields = {"inverted": ((det <= 0).astype(jnp.int32), "max"),
              "worst": (jnp.where(jnp.isnan(kappa3), jnp.inf, kappa3), "max")}
    if power is None:
        fields["excess"] = (term - 1.0, "sum")
    cell = reduce_rows(fields, 0)  # one pass over the corners (`reduce_rows`)
    if power is None:
        f = jnp.sum(cell["excess"]) / term.size
    else:  # two passes: the p-mean is scaled by the largest excess
        f = pmean_weights(jnp, term - 1.0, None, float(power))[0]
    return cell["inverted"] > 0, cell["worst"], f


def _put_back(conn, before, after, cell_worst, limit, run):
    """`jaxci.metrics.guard.keep_worst`'s loop on the device: while some cell is worse than `limit`, the nodes of
    those cells not yet put back take their `before` coordinates. `cell_worst` ``(N,)`` at `after`; `run` a
    boolean scalar (False: nothing is put back). Returns ``(points, back (n,), cell_worst at points)``."""
    n = before.shape[0]

    def body(carry):
        x, back, cw, _ = carry
        hit = jnp.zeros(n, bool).at[jnp.where(cw > limit, conn, n)].set(True, mode="drop")
        new = hit & ~back
        moved = jnp.any(new)
        x = jnp.where(new[:, None], before, x)
        cw = jax.lax.cond(moved, lambda: _cell_worst(_corners(x, conn)[1]), lambda: cw)
        return x, back | new, cw, moved

    start = (after, jnp.zeros(n, bool), cell_worst, run & (jnp.max(cell_worst) > limit))
    x, back, cw, _ = jax.lax.while_loop(lambda c: c[3], body, start)
    return x, back, cw


@program
@jit(static_argnames=("keep_worst", "power"))
def final_figures(conn, start, x, worst_start, keep_worst: bool, power: float | None) -> tuple:
    """The figures `jaxci.interface.invariants.enforce_device` decides from, of the method's result `x`
    ``(n, 3)`` against `start` ``(n, 3)`` (float64 on the device; `conn` ``(8, N)``).

    `worst_start`: a float64 device scalar, the start's worst cell where the caller has it, else NaN (computed
    here); `keep_worst` (static): run the put-back of `jaxci.metrics.guard.keep_worst`; `power` (static): the
    p-mean's power, None for F.

    **Returns:** ``(y, figures)``: `x` with the put-back applied (float64, on the device) and a dict of device
    scalars: ``new`` (cells valid at `start`, inverted at `x`), ``f0``, ``f1`` (the objective at both), ``w0``
    (the start's worst), ``w1`` (the worst at `x`), ``n_back`` (nodes put back), ``f2`` and ``wy`` (the objective
    and the worst at `y`). Nothing is put back where `x` has newly inverted cells or a non-finite objective.
    """
    start, x = start.astype(jnp.float64), x.astype(jnp.float64)
    inv0, cw0, f0 = _state(start, conn, power)
    inv1, cw1, f1 = _state(x, conn, power)
    new = jnp.sum(inv1 & ~inv0)
    w0 = jnp.where(jnp.isnan(worst_start), jnp.max(cw0), worst_start)
    w1 = jnp.max(cw1)
    figures = {"new": new, "f0": f0, "f1": f1, "w0": w0, "w1": w1, "n_back": jnp.zeros((), new.dtype), "f2": f1,
               "wy": w1}
    if not keep_worst:
        return x, figures
    run = (new == 0) & jnp.isfinite(f1)
    y, back, cw = _put_back(conn, start, x, cw1, w0 * (1.0 + KEEP_WORST_RTOL), run)
    n_back = jnp.sum(back)
    f2 = jax.lax.cond(n_back > 0, lambda: _state(y, conn, power)[2], lambda: f1)
    return y, {**figures, "n_back": n_back, "f2": f2, "wy": jnp.max(cw)}


def final_checks(conn, start, x, *, keep_worst: bool, worst_start: float | None, power: float | None
                 ) -> tuple[object, dict]:
    """`final_figures` called (float64) and its figures brought down in one `to_host`: ``(y, figures)`` with `y`
    on the device and the figures as Python numbers."""
    with enable_x64():
        ws = to_device(np.float64(np.nan if worst_start is None else worst_start))
        y, figs = final_figures(conn, start, x, ws, keep_worst=bool(keep_worst),
                                power=None if power is None else float(power))
        figs = to_host(figs)
    return y, {k: (int(v) if k in ("new", "n_back") else float(v)) for k, v in figs.items()}
