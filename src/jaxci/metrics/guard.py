"""The worst-element guard: a smoothed mesh whose worst cell is no worse than the input's.

Every method minimises a MEAN (F, Eq. 3.1), and a mean can improve while the worst cell gets worse (seen on a hex
sphere from a FE package: max kappa/3 1.146 -> 1.154 with a better mean). A user smooths to fix the worst element
first, so `keep_worst` puts back, node by node, the input positions of the nodes of every cell that ended worse
than the input's worst cell, until none does: the cells whose nodes are all put back are input cells, so the loop
ends at the latest with the input itself. Checked in float64, over every cell type (max corner kappa/3 of each
cell, `jaxci.metrics.elements.corner_condition`; inverted cells count as infinitely bad).
"""

from __future__ import annotations

import numpy as np

from ..cells import element_blocks
from ..mesh import HexMesh
from . import elements as E


def cell_worst(mesh: HexMesh, points) -> dict[str, np.ndarray]:
    """Per measured cell type, each cell's max corner kappa/3 at `points` (``inf`` where a corner is inverted),
    float64 arrays of shape ``(N_type,)``."""
    out = {}
    for t, cells in element_blocks(mesh).items():
        k = E.max_corner_condition(points, cells, t)
        out[t] = np.where(np.isnan(k), np.inf, k)
    return out


def worst(mesh: HexMesh, points) -> float:
    """The max corner kappa/3 over every cell of `mesh` at `points` (``inf`` if a cell is inverted)."""
    return max((float(k.max()) for k in cell_worst(mesh, points).values() if len(k)), default=1.0)


#: `keep_worst`'s relative slack on the input's worst cell (float64 rounding).
KEEP_WORST_RTOL = 1e-12


def keep_worst(mesh: HexMesh, before, after, *, worst_before: float | None = None
               ) -> tuple[np.ndarray, int, float, float]:
    """`after` with the nodes of cells worse than the worst cell at `before` (`KEEP_WORST_RTOL`) put back to `before`.

    **Arguments:** `mesh` (its cells); `before`, `after`: node coordinates of shape ``(n_nodes, 3)``;
    `worst_before`: `worst` at `before` when the caller has it already (a quality report's max kappa/3 of a valid
    mesh), else computed.

    **Returns:** ``(points, n_put_back, worst_before, worst_after)``: the guarded coordinates (a new array), how
    many nodes were put back, the input's worst and the unguarded result's worst. Where the input has an
    inverted cell (worst ``inf``) there is nothing to guard and `after` is returned.
    """
    before, after = np.asarray(before, np.float64), np.asarray(after, np.float64)
    w0 = worst(mesh, before) if worst_before is None else float(worst_before)
    w1 = worst(mesh, after)
    limit = w0 * (1.0 + KEEP_WORST_RTOL)
    if not np.isfinite(w0) or w1 <= limit:
        return after.copy(), 0, w0, w1
    blocks = element_blocks(mesh)
    back = np.zeros(len(before), bool)
    x = after.copy()
    while True:
        bad = [blocks[t][k > limit] for t, k in cell_worst(mesh, x).items()]
        nodes = np.unique(np.concatenate([b.ravel() for b in bad])) if bad else np.zeros(0, np.int64)
        nodes = nodes[~back[nodes]]
        if not len(nodes):
            break
        back[nodes] = True
        x[nodes] = before[nodes]
    return x, int(back.sum()), w0, w1


#: `worst_first`'s relative margin: the worst cell must fall by more than this.
WORST_FIRST_RTOL = 1e-9


def worst_first(mesh: HexMesh, start, x, f0: float, f1: float, *, worst_start: float | None = None) -> str | None:
    """The worst-first order's verdict on a result `x` whose F (`f1`) rose above its start's (`f0`, at `start`):
    a note saying why it is kept where its worst cell fell (max kappa/3 below the start's by more than
    `WORST_FIRST_RTOL`, both in float64 over every cell type), else None (the start is to be returned).

    A run whose objective weighs the worst element first (the default pipeline's worst-element polish,
    `jaxci.optim.polish`) may trade a little of F for a lower worst element: the mesh a solver needs is judged
    by its worst element first, then by the mean. `worst_start`: `worst` at `start` where the caller has it.
    """
    w0 = worst(mesh, start) if worst_start is None else float(worst_start)
    return worst_first_note(w0, worst(mesh, x), f0, f1)


def worst_first_note(w0: float, w1: float, f0: float, f1: float) -> str | None:
    """`worst_first`'s verdict from the worst cells `w0` (start) and `w1` (result), F `f0` and `f1`: a note where
    the worst cell fell, else None (from device figures too: `jaxci.interface.invariants.enforce_device`)."""
    if not (np.isfinite(w0) and np.isfinite(w1) and w1 < w0 * (1.0 - WORST_FIRST_RTOL)):
        return None
    return (f"F rose from {f0:.6g} to {f1:.6g} (+{100.0 * (f1 - f0) / max(abs(f0), 1e-300):.2g}%) while the worst "
            f"element fell from {w0:.6g} to {w1:.6g} (max kappa/3): kept, the worst element first (--method lbfgs, "
            f"or polish=False, minimises F alone and never raises it)")
