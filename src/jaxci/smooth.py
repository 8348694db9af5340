"""`jaxci.smooth`: one interface for every smoothing method, one history record for all of them.

Every method works on the same problem: minimise the paper's F (Eq. 3.1) by moving nodes, corner nodes fixed,
edge nodes on their feature curve, surface nodes on their surface (`jaxci.boundary`, `jaxci.projection`). On a
hex-dominant mesh F is the mean over the corners of EVERY cell, hexahedra, wedges, pyramids and tetrahedra
(`jaxci.elements.mixed_objective`, `jaxci.mixed`), and the nodes of linear non-hexahedral cells move too.
Whatever the method, `smooth` guarantees on return (checked in float64, not assumed):

- no cell of any type is inverted that was valid in the input, and F (over every corner) did not increase (else
  the input is returned, with a note saying why);
- every boundary node lies on the ORIGINAL boundary (a final exact float64 projection).

A mesh with inverted elements cannot be smoothed by F (its objective is infinite): with ``untangle="auto"`` it
goes through the untangling stage first where one is available, otherwise `InvertedMeshError` is raised.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import mixed
from .boundary import BoundaryInfo, classify_boundary
from .elements import mixed_objective
from .errors import ConfigError, InvertedMeshError
from .mesh import HexMesh
from .projection import Constraints, build_constraints, project_np
from .quality import QualityReport, quality_report, transposed
from .topology import colour_nodes, node_adjacency

#: Method names accepted by `smooth` (and ``jaxci smooth --method``).
METHODS = ("ci", "ci-global", "bfgs", "lbfgs", "cg", "lm", "gauss-newton", "laplace", "smart-laplace")

_DTYPES = {"float32": np.float32, "float64": np.float64}


@dataclasses.dataclass(frozen=True)
class SmoothResult:
    """What `smooth` returns.

    - `mesh`: the smoothed `HexMesh` (same connectivity, data and ids; new coordinates).
    - `history`: per iteration (sweep, learning attempt or solver step; entry 0 = input) ``objective`` and
      ``max_condition`` lists, plus method-specific series (CI: ``best``, ``worst`` behaviour; ``moved``).
    - `iterations`, `wall_time` (seconds, including compilation), `method`, `params` (all hyperparameters).
    - `before`, `after`: `QualityReport` of input and output; `boundary`: node counts per class.
    - `node_class`: class of every node (`jaxci.boundary.INTERIOR` ... `CORNER`), shape ``(n_nodes,)``.
    - `notes`: what a user should know (invariant fallbacks, untangling, ...).
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

    def summary(self) -> dict:
        """JSON-ready summary: before/after quality keys, iterations, wall time, method and params."""
        return {
            "method": self.method,
            "params": self.params,
            "iterations": self.iterations,
            "wall_time": self.wall_time,
            "before": self.before.to_dict(),
            "after": self.after.to_dict(),
            "boundary": self.boundary,
            "notes": list(self.notes),
        }


@dataclasses.dataclass(frozen=True)
class Problem:
    """Everything a method needs, built once: constraints, colouring, transposed connectivity, dtype; for a mixed
    mesh the non-hexahedral cells (`extra`: `jaxci.mixed.ExtraCells`; `table`: `jaxci.mixed.CornerTable`), None
    for a hexahedral one."""

    mesh: HexMesh
    info: BoundaryInfo
    cons: Constraints
    colour: np.ndarray
    conn: jnp.ndarray
    x0: jnp.ndarray
    dtype: type
    extra: mixed.ExtraCells | None = None
    table: mixed.CornerTable | None = None


def build_problem(mesh: HexMesh, *, dtype=np.float32, feature_angle: float = 40.0, fix_boundary: bool = False,
                  fixed_nodes: Sequence[int] | None = None, fixed_sets: Sequence[str] = ()) -> Problem:
    """Classify the boundary, build the constraints and the colouring of `mesh` (call inside the dtype context).

    On a mixed mesh no two nodes of one colour share a cell of any type."""
    info = classify_boundary(mesh, feature_angle=feature_angle, fix_boundary=fix_boundary, fixed_nodes=fixed_nodes,
                             fixed_sets=tuple(fixed_sets))
    cons = build_constraints(mesh, info, dtype=dtype)
    extra = table = None
    if mixed.has_extra(mesh):
        cells = list(mixed.volume_cells(mesh).values())
        colour = colour_nodes(mesh.hexes, mesh.n_nodes, node_adjacency(cells, mesh.n_nodes)).colour
        extra, table = mixed.extra_cells(mesh), mixed.corner_table(mesh)
    else:
        colour = colour_nodes(mesh.hexes, mesh.n_nodes).colour
    return Problem(mesh, info, cons, np.asarray(colour), transposed(mesh.hexes), jnp.asarray(mesh.points, dtype),
                   dtype, extra, table)


def _run_method(problem: Problem, method: str, key, params: dict):
    """Dispatch to a method; returns (points, iterations, history, resolved params)."""
    if method in ("ci", "ci-global"):
        from .optim._moves import coloured_stars
        from .optim.ci import CIParams, global_ci, local_ci

        try:
            p = CIParams(**params)
        except TypeError as e:
            raise ConfigError(f"unknown CI parameter: {e}") from None
        if method == "ci":
            cs = coloured_stars(problem.mesh.hexes, problem.cons, problem.colour, problem.info.topology.faces,
                                problem.table)
            x, it, hist = local_ci(key, problem.x0, problem.conn, cs, problem.cons, p, problem.extra)
        else:
            x, it, hist = global_ci(key, problem.x0, problem.conn, problem.cons, free_scale(problem), p,
                                    problem.extra)
        return x, it, hist, dataclasses.asdict(p)
    if method in ("bfgs", "lbfgs", "cg", "lm", "gauss-newton"):
        from .optim.gradient import run_gradient

        return run_gradient(problem, method, params)
    if method in ("laplace", "smart-laplace"):
        from .optim.laplace import run_laplace

        return run_laplace(problem, method, params)
    raise ConfigError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")


def free_scale(problem: Problem) -> jnp.ndarray:
    """Local edge length per free coordinate (the `jaxci.projection` layout), shape ``(n_free,)``
    (`jaxci.optim.parametrisation.free_lengths`)."""
    from .optim.parametrisation import free_lengths

    return jnp.asarray(free_lengths(problem.mesh, problem.cons), problem.dtype)


def smooth(
    mesh: HexMesh,
    method: str = "ci",
    *,
    seed: int = 0,
    dtype: str = "float32",
    feature_angle: float = 40.0,
    fix_boundary: bool = False,
    fixed_nodes: Sequence[int] | None = None,
    fixed_sets: Sequence[str] = (),
    untangle: str = "auto",
    **params,
) -> SmoothResult:
    """Smooth the hexahedra of `mesh` by moving nodes; connectivity never changes.

    **Arguments:**

    - `mesh`: the input `HexMesh` (not modified).
    - `method`: one of `METHODS`: ``"ci"`` batched local Cohort Intelligence (default), ``"ci-global"`` the
      paper's global CI; ``"bfgs"``, ``"lbfgs"``, ``"cg"``, ``"lm"``, ``"gauss-newton"`` the optimistix
      baselines (`jaxci.optim.gradient`); ``"laplace"``, ``"smart-laplace"`` (`jaxci.optim.laplace`).
    - `seed`: seed of the `jax.random` key of stochastic methods (same seed, same result). The key uses the
      ``"rbg"`` generator (XLA's RngBitGenerator): its code compiles in a tenth of the time of threefry's.
    - `dtype`: ``"float32"`` (default, fast) or ``"float64"``.
    - `feature_angle`: degrees; boundary edges sharper than this are feature curves (nodes slide along them).
    - `fix_boundary`: fix every boundary node; `fixed_nodes`: node indices to fix; `fixed_sets`: names of node
      sets of the file to fix.
    - `untangle`: ``"auto"`` (untangle first if the input has inverted elements, `jaxci.optim.untangle`),
      ``"always"`` (run the untangling stage anyway: it also lifts corners below its det margin), ``"never"``
      (refuse inverted input with `InvertedMeshError`). If untangling fails, `InvertedMeshError` is raised.
    - `**params`: the method's hyperparameters (e.g. `jaxci.optim.ci.CIParams`,
      `jaxci.optim.gradient.GradientParams`, `jaxci.optim.laplace.LaplaceParams` fields); keys starting with
      ``untangle_`` go to `jaxci.optim.untangle.UntangleParams` (e.g. ``untangle_margin=1e-2``).

    **Returns:** a `SmoothResult`.
    """
    if method not in METHODS:
        raise ConfigError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if dtype not in _DTYPES:
        raise ConfigError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    if untangle not in ("auto", "always", "never"):
        raise ConfigError(f"untangle must be 'auto', 'always' or 'never', got {untangle!r}")
    t0 = time.perf_counter()
    notes: list[str] = []
    with jax.enable_x64(True):
        before = quality_report(mesh)
    untangle_params = {k[len("untangle_"):]: params.pop(k) for k in list(params) if k.startswith("untangle_")}
    untangled = None
    tangled = bool(before.inverted_corners) or bool(before.overall and before.overall["inverted"])
    if tangled and untangle == "never":
        where = f"{mesh.source}: " if mesh.source else ""
        bad = {t: np.flatnonzero(b) for t, b in mixed.inverted_cells(mesh, mesh.points).items() if b.any()}
        t0 = next(iter(bad))
        raise InvertedMeshError(
            f"{where}the mesh has {sum(len(b) for b in bad.values())} inverted elements ({before.inverted_corners} "
            f"hexahedron corners with det <= 0; first: {_label(mesh, t0, int(bad[t0][0]))}); it must be untangled "
            f"before it can be smoothed, and untangle='never' was given"
        )
    if tangled or untangle == "always":
        from .optim.untangle import UntangleParams, untangle_stage

        try:
            up = UntangleParams(**untangle_params)
        except TypeError as e:
            raise ConfigError(f"unknown untangling parameter (untangle_*): {e}") from None
        info = classify_boundary(mesh, feature_angle=feature_angle, fix_boundary=fix_boundary,
                                 fixed_nodes=fixed_nodes, fixed_sets=tuple(fixed_sets))
        untangled, untangle_notes = untangle_stage(mesh, info, up)  # InvertedMeshError if it fails
        notes.extend(untangle_notes)
    np_dtype = _DTYPES[dtype]
    with jax.enable_x64(dtype == "float64"):
        problem = build_problem(mesh, dtype=np_dtype, feature_angle=feature_angle, fix_boundary=fix_boundary,
                                fixed_nodes=fixed_nodes, fixed_sets=fixed_sets)
        if untangled is not None:
            problem = dataclasses.replace(problem, x0=jnp.asarray(untangled, np_dtype))
        x, iterations, history, resolved = _run_method(problem, method, jax.random.key(seed, impl="rbg"), params)
        x = np.asarray(x, dtype=np.float64)
    notes.extend(problem.info.notes)
    with jax.enable_x64(True):
        if untangled is None:
            points, check_notes = _enforce_invariants(mesh, problem, x)
        else:
            from .optim.untangle import enforce_after_untangling

            points, check_notes = enforce_after_untangling(mesh, problem.info, untangled, x)
        notes.extend(check_notes)
        after = quality_report(mesh, points)
    history = _standard_history(history)
    out = mesh.with_points(points)
    return SmoothResult(
        mesh=out, history=history, iterations=int(iterations), wall_time=time.perf_counter() - t0, method=method,
        params={**resolved, "seed": seed, "dtype": dtype, "feature_angle": feature_angle,
                "fix_boundary": fix_boundary},
        before=before, after=after, boundary=problem.info.counts, node_class=np.asarray(problem.info.node_class),
        notes=tuple(notes),
    )


def _label(mesh: HexMesh, cell_type: str, k: int) -> str:
    return f"element {mesh.hex_label(k)}" if cell_type == "hexahedron" else mixed.cell_label(mesh, cell_type, k)


def _enforce_invariants(mesh: HexMesh, problem: Problem, x: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Exact float64 projection onto the original boundary, then the no-inversion / no-increase checks over every
    cell type (`jaxci.elements.inverted`, `jaxci.elements.mixed_objective`)."""
    cons64 = build_constraints(mesh, problem.info, dtype=np.float64)
    x = project_np(cons64, x)
    new = mixed.newly_inverted(mesh, mesh.points, x)
    f0, f1 = float(mixed_objective(mesh.points, mesh)), float(mixed_objective(x, mesh))
    if new or not np.isfinite(f1):
        what = ", ".join(f"{k} {t}" for t, k in new.items()) or "non-finite objective"
        return np.array(mesh.points), [f"the result had newly inverted elements ({what}); the input is returned"]
    if f1 > f0:
        return np.array(mesh.points), [f"the objective rose from {f0:.6g} to {f1:.6g}; the input is returned"]
    return x, []


def _standard_history(h: dict) -> dict:
    """Every method's history with `objective` and `max_condition` lists (entry 0 = input)."""
    out = {k: np.asarray(v).tolist() for k, v in h.items()}
    if "objective" not in out and "best" in out:
        out["objective"] = out["best"]
    return out
