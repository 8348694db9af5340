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

Otherwise the start is returned, with a note saying why. `enforce` checks numpy coordinates on the host;
`enforce_device` checks coordinates on a device (the JAX engine, hexahedral meshes), where the figures are reduced
(`jaxci.metrics.device.final_figures`); both decide by `checked`, from the figures alone.
"""

from __future__ import annotations

import numpy as np

from ..geometry.projection import Constraints, project_np
from ..mesh import HexMesh
from ..metrics import objective as mixed
from ..metrics.elements import checked_objective
from ..metrics.guard import keep_worst as guard
from ..metrics.guard import worst_first as keep_lower_worst
from ..metrics.guard import worst_first_note


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
    the sentences for `jaxci.interface.smooth.SmoothResult.notes`.
    """
    what = "the untangled mesh" if untangled else "the input"
    if not projected:
        x = project_np(cons, x)
    new = mixed.newly_inverted(mesh, start, x)
    objective = checked_objective(mesh, power)  # F, or the p-mean the method minimised (`power`)
    f0, f1 = objective(start), objective(x)

    def guarded():
        y, n_back, w0, w1 = guard(mesh, start, x, worst_before=worst_start)
        return y, n_back, w0, w1, (objective(y) if n_back else f1)

    def lower_worst(y, g0, g1, w0):
        return keep_lower_worst(mesh, start, y, g0, g1, worst_start=w0)

    points, notes = checked(what, start, x, new, f0, f1, guarded if keep_worst else None,
                            lower_worst if worst_first else None, worst_start)
    return (np.array(start) if points is start else points), notes


def enforce_device(mesh: HexMesh, conn, start, x, *, project=None, untangled: bool = False,
                   keep_worst: bool = False, worst_start: float | None = None, power: float | None = None,
                   worst_first: bool = False) -> tuple[object, list[str]]:
    """`enforce` on the device (the JAX engine, hexahedral meshes): the same points and notes from device arrays.

    **Arguments:** `mesh` the `HexMesh` (hexahedra only; its cells are `conn`); `conn` ``(8, N)`` its transposed
    hexahedra on the device; `start`, `x` ``(n, 3)`` on the device (float64; `x` in another float dtype is
    converted there); `project`: None where `x` is on the original boundary already (as `enforce`'s
    `projected=True`), else a function of device coordinates ``(n, 3)`` -> device coordinates that projects the
    boundary nodes onto the original boundary (exactly, in float64); the other arguments as `enforce`'s.

    **Returns:** ``(points, notes)``: the checked coordinates on the device (`x` in float64, its guarded form, or
    `start`) and the notes. The figures are reduced on the device (`jaxci.metrics.device.final_figures`: the
    guard's put-back is a node mask there) and come down in one `to_host` of ~8 scalars.
    """
    from ..metrics.device import final_checks, hex_only

    hex_only(mesh, "enforce_device")
    what = "the untangled mesh" if untangled else "the input"
    if project is not None:
        x = project(x)
    y, fig = final_checks(conn, start, x, keep_worst=keep_worst, worst_start=worst_start, power=power)
    new = {"hexahedron": fig["new"]} if fig["new"] else {}

    def lower_worst(_, g0, g1, w0):
        return worst_first_note(w0, fig["wy"], g0, g1)

    return checked(what, start, y, new, fig["f0"], fig["f1"],
                   (lambda: (y, fig["n_back"], fig["w0"], fig["w1"], fig["f2"])) if keep_worst else None,
                   lower_worst if worst_first else None, fig["w0"])


def checked(what: str, start, x, new: dict, f0: float, f1: float, guarded, lower_worst, worst_start
            ) -> tuple[object, list[str]]:
    """The decisions of `enforce` from its figures, whoever measured them (the host or the device).

    **Arguments:** `what` names the start in the notes; `start`, `x` the coordinates (returned as they are);
    `new` type -> cells newly inverted at `x`; `f0`, `f1` the objective at `start` and `x`; `guarded` None (no
    worst-cell guard) or a function -> ``(y, n_back, w0, w1, f2)``: the guarded coordinates, nodes put back, the
    start's and `x`'s worst cell and the objective at `y`; `lower_worst` None (no worst-first order) or a function
    ``(y, f0, f1, w0)`` -> note or None (`jaxci.metrics.guard.worst_first`); `worst_start` the start's worst cell
    where known (None: `lower_worst` measures it).

    **Returns:** ``(points, notes)``: `start`, `x` or the guarded coordinates, and the notes.
    """
    if new or not np.isfinite(f1):
        cells = ", ".join(f"{k} {t}" for t, k in new.items()) or "non-finite objective"
        return start, [f"the result had newly inverted elements ({cells}); {what} is returned"]
    notes = []
    if guarded is not None:
        y, n_back, worst_start, w1, f2 = guarded()
        if n_back:
            notes.append(f"worst cell kept no worse than the input's (max kappa/3 {worst_start:.6g}; the method's "
                         f"result had {w1:.6g}): {n_back} nodes put back where they were, F {f1:.6g} -> {f2:.6g} "
                         f"(keep_worst=False / --allow-worse-worst returns the method's result)")
            x, f1 = y, f2
    if f1 > f0:
        kept = lower_worst(x, f0, f1, worst_start) if lower_worst is not None else None
        if kept is None:
            return start, [*notes, f"the objective rose from {f0:.6g} to {f1:.6g}; {what} is returned"]
        notes.append(kept)
    return x, notes
