"""`SmoothResult`: what `jaxci.smooth` returns, the smoothed mesh with its history, quality before and after,
notes, phases and the plan that ran it."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..mesh import HexMesh
from ..metrics.report import QualityReport
from .engine import Plan


@dataclasses.dataclass(frozen=True)
class SmoothResult:
    """What `smooth` returns.

    - `mesh`: the smoothed `HexMesh` (same connectivity, data and ids; new coordinates).
    - `history`: per iteration (sweep, learning attempt or solver step; entry 0 = input) ``objective`` and
      ``max_condition`` lists, plus method-specific series (CI: ``best``, ``worst`` behaviour; ``moved``).
    - `iterations`, `wall_time` (seconds, including compilation), `method`, `params` (all hyperparameters).
    - `before`, `after`: `QualityReport` of input and output; `boundary`: node counts per class.
    - `node_class`: class of every node (`jaxci.geometry.boundary.INTERIOR` ... `CORNER`), shape ``(n_nodes,)``.
    - `notes`: what a user should know (invariant fallbacks, untangling, an iteration cap that stopped it, ...).
    - `plan`: where it ran (`jaxci.interface.engine.Plan`: engine, device, dtype, kernel, threads, and why).
    - `phases`: where the time went (`jaxci.runtime.phases.PhaseClock.as_dict`: seconds, compile seconds and
      compilations per phase: ``validate``, ``report`` (quality before), ``untangle``, ``setup`` (boundary
      classification, constraints, colouring), ``smooth`` (the method), ``checks`` (float64 invariants and the
      quality after)).
    """

    mesh: HexMesh
    history: dict
    iterations: int
    wall_time: float
    method: str
    params: dict
    before: QualityReport
    after: QualityReport
    boundary: dict
    node_class: np.ndarray | None = None
    notes: tuple[str, ...] = ()
    phases: dict | None = None
    plan: Plan | None = None

    def summary(self) -> dict:
        """JSON-ready summary: before/after quality keys, iterations, wall time, method, params and the engine
        that ran (``engine``: `jaxci.interface.engine.Plan.to_dict`)."""
        return {
            "method": self.method,
            "engine": None if self.plan is None else self.plan.to_dict(),
            "params": self.params,
            "iterations": self.iterations,
            "wall_time": self.wall_time,
            "before": self.before.to_dict(),
            "after": self.after.to_dict(),
            "boundary": self.boundary,
            "notes": list(self.notes),
            "phases": self.phases,
        }


def unchanged_result(mesh: HexMesh, method: str, before: QualityReport, f_before, notes: list, info=None,
                     points=None, after: QualityReport | None = None):
    """``(points, result)`` where no method runs, noted in `notes`: the mesh is already optimal (`info` None), or
    every node is fixed (`info`: its `BoundaryInfo`, whose notes come first). `points`: the coordinates returned
    (default a copy of the mesh's), `after` their report (default `before`)."""
    if info is None:
        notes.append(f"the mesh is already optimal (F = {f_before:.3g}, every corner an ideal cube corner): "
                     f"nothing to do")
    else:
        notes.extend(info.notes)
        notes.append(f"no node can move (all {mesh.n_nodes} nodes are fixed: boundary corners, fixed sets or "
                     f"--fix-boundary): the mesh is returned as it is")
    return np.array(mesh.points) if points is None else points, SmoothResult(
        mesh=mesh, history={"objective": [f_before], "max_condition": [before.max_condition]}, iterations=0,
        wall_time=0.0, method=method, params={}, before=before, after=before if after is None else after,
        boundary={} if info is None else info.counts, node_class=None if info is None else np.asarray(info.node_class))
