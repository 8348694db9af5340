"""What `jaxci.smooth` guarantees on return, checked in float64 (not assumed) after the method ran.

From the start the method ran from (the input, or the untangling stage's result):

- every boundary node lies on the ORIGINAL boundary (an exact float64 projection, `jaxci.geometry.projection.
  project_np`, unless the host solver projected it so already);
- no cell of any type is inverted that was valid at the start;
- with `keep_worst` (the input, valid), the worst cell is no worse than the input's (`jaxci.metrics.guard.
  keep_worst` puts back the nodes of cells that ended worse);
- the objective the method minimised (F over every corner, or its p-mean) did not rise, or, where the method
  weighs the worst element first (the default pipeline's worst-element polish), rose only while the worst cell
  fell (`jaxci.metrics.guard.worst_first`).

Otherwise the start is returned, with a note saying why.
"""

from __future__ import annotations

import numpy as np

from .geometry.projection import Constraints, project_np
from .mesh import HexMesh
from .metrics import objective as mixed
from .metrics.elements import checked_objective
from .metrics.guard import keep_worst as guard
from .metrics.guard import worst_first as keep_lower_worst


def enforce(mesh: HexMesh, cons: Constraints, start: np.ndarray, x: np.ndarray, *, untangled: bool = False,
            keep_worst: bool = False, worst_start: float | None = None, power: float | None = None,
            projected: bool = False, worst_first: bool = False) -> tuple[np.ndarray, list[str]]:
    """The method's result `x` held to the guarantees of this module against `start`.

    **Arguments:** `mesh` (its cells; the mesh the method smoothed); `cons` its numpy float64 `Constraints` (the
    original boundary); `start` ``(n, 3)``: the input (`untangled` False) or the untangling stage's result
    (`untangled` True); `x` ``(n, 3)``: the method's result; `keep_worst`: the worst-cell guard (the input's
    worst cell `worst_start` where the caller has it); `power`: the p-mean's power where the method minimised
    it (else F); `projected`: `x` is on the original boundary already (the host solver's float64 projection);
    `worst_first`: a higher objective is kept where the worst cell fell.

    **Returns:** ``(points, notes)``: the checked coordinates (`x`, its guarded form, or a copy of `start`) and
    the sentences for `jaxci.smooth.SmoothResult.notes`.
    """
    what = "the untangled mesh" if untangled else "the input"
    if not projected:
        x = project_np(cons, x)
    new = mixed.newly_inverted(mesh, start, x)
    objective = checked_objective(mesh, power)  # F, or the p-mean the method minimised (`power`)
    f0, f1 = objective(start), objective(x)
    if new or not np.isfinite(f1):
        cells = ", ".join(f"{k} {t}" for t, k in new.items()) or "non-finite objective"
        return np.array(start), [f"the result had newly inverted elements ({cells}); {what} is returned"]
    notes = []
    if keep_worst:
        y, n_back, worst_start, w1 = guard(mesh, start, x, worst_before=worst_start)
        if n_back:
            f2 = objective(y)
            notes.append(f"worst cell kept no worse than the input's (max kappa/3 {worst_start:.6g}; the method's "
                         f"result had {w1:.6g}): {n_back} nodes put back where they were, F {f1:.6g} -> {f2:.6g} "
                         f"(keep_worst=False / --allow-worse-worst returns the method's result)")
            x, f1 = y, f2
    if f1 > f0:
        kept = keep_lower_worst(mesh, start, x, f0, f1, worst_start=worst_start) if worst_first else None
        if kept is None:
            return np.array(start), [*notes, f"the objective rose from {f0:.6g} to {f1:.6g}; {what} is returned"]
        notes.append(kept)
    return x, notes
