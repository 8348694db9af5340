"""The problem every smoothing method works on (`Problem`, `build_problem`), the dispatch to a method on the
engine its plan names (`run_method`, `method_params`; the plan: `jaxci.interface.engine`), and the default pipeline
(`auto_pipeline`). `jaxci.smooth` is the one interface over them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from collections.abc import Sequence

import numpy as np

from .. import native
from ..cells import volume_cells
from ..errors import ConfigError
from ..geometry.boundary import BoundaryInfo, classify_boundary
from ..geometry.projection import Constraints, build_constraints
from ..geometry.topology import colour_nodes, node_adjacency
from ..mesh import HexMesh
from ..metrics import objective as mixed
from ..metrics.hexahedron import transposed
from ..runtime._lazy import enable_x64, jax, jnp
from ..runtime.transfer import to_device

#: Method names accepted by `smooth` (and ``jaxci smooth --method``); ``"auto"`` is the default pipeline
#: (`auto_pipeline`).
METHODS = ("auto", "ci", "ci-global", "bfgs", "lbfgs", "cg", "lm", "gauss-newton", "laplace", "smart-laplace")

#: Hexahedra from which the default pipeline runs smart-Laplace sweeps before L-BFGS on the host engine
#: (`auto_pipeline`; on the JAX engine at any size: float32 L-BFGS alone stalls on
#: near-flat corners (a perturbed 21^3 box with a corner of kappa/3 7.7e5: 5.5e5 after 40 steps; float64 reached
#: 1.0000 in 188 steps). On large meshes the sweeps also save most of the steps in float64: cube60_pert after
#: untangling (216,000 hexes, max kappa/3 25.8) reached max kappa/3 1.0001 in about 100 host L-BFGS steps alone,
#: in 3 sweeps and about 20 steps after them.
AUTO_PRESMOOTH_FROM = 100_001
#: L-BFGS steps after which the default pipeline's host solve goes on with truncated Newton (`jaxci.optim.newton`;
#: ``solver="newton"``, ``newton_after``): a run L-BFGS ends sooner is L-BFGS's (a structured or presmoothed mesh,
#: and the 25k cylinder O-grid, where Newton from the start reaches a worse minimum), the long ones on curved
#: and unstructured meshes end in Newton's fewer evaluations. Measured on the real-mesh corpus, the default
#: pipeline (polish included) against L-BFGS alone on 19 meshes (2026-11-30, docs/results/bench_solvers.md): 22.7
#: against 29.5 s in all (the 27k tet-to-hex sphere 6.4 against 11.2 s), the worst element lower on 7 meshes, the
#: same on 8 and at most 0.27% higher on 4; 100 steps left pave3's worst element 0.75% higher.
AUTO_NEWTON_AFTER = 200
#: Escape rounds of the default pipeline on the host engine (hexahedral meshes: `jaxci.optim.escape`): none. The
#: one mesh they helped, Mesquite's graded cub_fru (four rounds, F 34.96 -> 5.70), was held by the boundary nodes'
#: candidate rings; with candidates that follow their nodes (`jaxci.geometry.anchors`) the solver itself ends at
#: F 4.3, and on every mesh of `scripts/bench_realmesh.py`'s corpus, the paved three and cub_fru the escape's first
#: sweep gains under 1% (2026-11-30): it ran none, at the cost of that sweep (0.2-0.5 s at 25,000 hexahedra).
#: ``escape=N`` (`jaxci.optim.gradient_params.GradientParams`) asks for them.
AUTO_ESCAPE = 0

#: F at or below which a mesh is already optimal: `smooth` returns it after this one evaluation.
OPTIMAL_F = 1e-14

#: The iteration cap of each method: the parameter that stops it, for the note when it does.
_CAPS = {"ci": "max_sweeps", "laplace": "max_sweeps", "smart-laplace": "max_sweeps", "bfgs": "max_steps",
         "lbfgs": "max_steps", "cg": "max_steps", "lm": "max_steps", "gauss-newton": "max_steps"}

@dataclasses.dataclass(frozen=True)
class Problem:
    """Everything a method needs, built once: constraints, transposed connectivity, dtype; for a mixed mesh the
    non-hexahedral cells (`extra`: `jaxci.metrics.objective.ExtraCells`; `table`:
    `jaxci.metrics.objective.CornerTable`), None for a hexahedral one; the colouring (`colour`) on first use;
    `devices`: None (one device) or the `jax.sharding.Mesh` the compiled methods shard the elements over;
    `plan`: the `jaxci.interface.engine.Plan` the methods run on (its engine: numpy arrays on the host engine, JAX
    arrays on the JAX engine); `tables`: where the mesh lives on the device (`jaxci.interface.device_run`), the
    boundary's float64 tables on the host (`jaxci.geometry.tables.BoundaryTables`: the exact projection of the
    boundary nodes and the worst-element polish's window read them) and `points64` its coordinates in float64 on
    the device (the geometry the presmoothing's planes and the parametrisation are measured on), else None."""

    mesh: HexMesh
    info: BoundaryInfo
    cons: Constraints
    conn: jnp.ndarray
    x0: jnp.ndarray
    dtype: type
    extra: mixed.ExtraCells | None = None
    table: mixed.CornerTable | None = None
    devices: object = None
    plan: object = None
    tables: object = None
    points64: object = None

    @property
    def host(self) -> bool:
        """Whether the methods run on the host engine (numpy and C)."""
        return self.plan is not None and self.plan.engine == "host"

    @functools.cached_property
    def host_cons(self) -> Constraints:
        """The constraints as numpy float64 arrays on the host (`cons` itself on the host engine in float64), for
        the host-side stages of any engine (the worst-element polish, the final exact projection). Built on first
        use, once per run."""
        if self.host and np.asarray(self.x0).dtype == np.float64:
            return self.cons
        return build_constraints(self.mesh, self.info, dtype=np.float64, device=False)

    @functools.cached_property
    def boundary_planes(self) -> tuple:
        """Where the mesh lives on the device: ``(view, planes)``, the boundary view of `points64` and the planar
        rings of its surface nodes (`jaxci.optim.device_stars.boundary_view`, `surface_planes` measured on the
        device: O(boundary) each way), for the presmoothing, the parametrisation and `project_device`. Built on
        first use, once per run."""
        from ..optim.device_stars import boundary_view, surface_planes

        view = boundary_view(self.points64, self.info.topology.faces, self.cons)
        return view, surface_planes(view, device=True)

    @functools.cached_property
    def _flats(self) -> tuple:
        view, planes = self.boundary_planes
        ns = len(view.surf)
        return (self.points64, *to_device((np.asarray(planes[:ns, 3:6], np.float64),
                                           np.asarray(planes[:ns, 6], np.float64))))

    def project_device(self, x):
        """Where the mesh lives on the device: the device coordinates `x` ``(n, 3)`` (any float dtype) with their
        boundary nodes projected exactly onto the original boundary, float64
        (`jaxci.geometry.device_constraints.project_boundary`: the nodes inside the flat regions of
        `boundary_planes` onto their planes on the device, the others searched on the host)."""
        from ..geometry.device_constraints import project_boundary

        with enable_x64():
            return project_boundary(self.cons, self.tables, x, self._flats)

    @functools.cached_property
    def colour(self) -> np.ndarray:
        """The colour of every node, int32 ``(n_nodes,)``: no two nodes of one colour share a cell of any type
        (`jaxci.geometry.topology.colour_nodes`; the methods that move nodes colour by colour, CI and the Laplacians).
        Computed on first use: L-BFGS needs none."""
        mesh = self.mesh
        adjacency = node_adjacency(list(volume_cells(mesh).values()), mesh.n_nodes) if self.extra is not None \
            else None
        return np.asarray(colour_nodes(mesh.hexes, mesh.n_nodes, adjacency).colour)


def build_problem(mesh: HexMesh, *, dtype=np.float32, feature_angle: float = 40.0, fix_boundary: bool = False,
                  fixed_nodes: Sequence[int] | None = None, fixed_sets: Sequence[str] = (),
                  info: BoundaryInfo | None = None, devices=None, plan=None) -> Problem:
    """Classify the boundary and build the constraints of `mesh` (call inside the dtype context).

    `plan`: the `jaxci.interface.engine.Plan` (`Problem.plan`): on the host engine the arrays stay in numpy (JAX is not
    imported), else (or without a plan) they go to JAX's default device. `info`: the `BoundaryInfo` of `mesh`
    with these arguments if it is at hand (the untangling stage's), else classified. `devices`:
    `Problem.devices`."""
    device = plan is None or plan.engine != "host"
    if info is None:
        info = classify_boundary(mesh, feature_angle=feature_angle, fix_boundary=fix_boundary,
                                 fixed_nodes=fixed_nodes, fixed_sets=tuple(fixed_sets))
    cons = build_constraints(mesh, info, dtype=dtype, device=device)
    extra = table = None
    if mixed.has_extra(mesh):
        extra, table = mixed.extra_cells(mesh, device=device), mixed.corner_table(mesh)
    put = jax.device_put if device else (lambda a: a)
    # on the host a view: the C kernels read the hexahedra (N, 8) themselves (a copy was 64 MB at 10^6, and the
    # objective's kernel made another of it)
    conn = transposed(mesh.hexes) if device else np.asarray(mesh.hexes).T
    return Problem(mesh, info, cons, conn, put(np.asarray(mesh.points, dtype)), dtype, extra, table, devices, plan)


def auto_pipeline(mesh: HexMesh, params: dict, plan) -> tuple[str, dict, str]:
    """The default pipeline (``method="auto"``) on `mesh` where `plan` (a `jaxci.interface.engine.Plan`) runs it:
    ``(method, params, description)``.

    Chosen by measurement on real and generated meshes (docs/results): L-BFGS on F after the untangling stage
    (when the input has inverted elements), on the host engine going on with truncated Newton after
    `AUTO_NEWTON_AFTER` steps, on the JAX engine (one device, hexahedra) truncated Newton with the
    two-level preconditioner where that is built (``solver="auto"``: docs/results/bench_solvers.md); on the JAX
    engine, and on the host engine from `AUTO_PRESMOOTH_FROM`
    hexahedra on (hexahedral meshes: the host's sweeps are for hexahedra), 3 smart-Laplace sweeps first (they fix
    the worst corners node by node; at 10^6 elements L-BFGS alone needed 1152 steps, 13 after them; the host's
    sweeps are the C kernels: without them none on the host). Then the
    worst-element polish (`jaxci.optim.polish`; ``polish=False`` leaves it out): F alone leaves a few elements
    bad (the real-mesh corpus: worst kappa/3 2.99 on a tet-to-hex sphere, where the p-mean reaches 2.19), and
    the polish lowers the worst element below the p-mean's at a cost of at most ``polish_budget`` (1%) of the
    mean element quality (docs/results/realmesh.md). Local CI ran to its sweep cap on unstructured meshes.
    `params` (the user's) win; with ``objective="pmean"`` there is no polish (the p-mean weighs the worst
    corners itself).
    """
    params = dict(params)
    host = plan.engine == "host"
    if "presmooth" not in params and (not host or (mesh.n_hexes >= AUTO_PRESMOOTH_FROM and native.AVAILABLE
                                                   and not mixed.has_extra(mesh))):
        params["presmooth"] = 3
    if "polish" not in params and params.get("objective", "mean") == "mean":
        params["polish"] = True
    pick_solver = "solver" not in params and params.get("objective", "mean") == "mean"
    newton = not host and plan.devices <= 1 and pick_solver and not mixed.has_extra(mesh)
    if newton:  # truncated Newton where its preconditioner is built (`GradientParams.solver`)
        params["solver"] = "auto"
    elif host and pick_solver:  # L-BFGS, then truncated Newton on a long run
        params["solver"] = "newton"
        params.setdefault("newton_after", AUTO_NEWTON_AFTER)
    if host and params.get("objective", "mean") == "mean" and native.AVAILABLE and not mixed.has_extra(mesh):
        params.setdefault("escape", AUTO_ESCAPE)
    pre = int(params.get("presmooth", 0))
    after = int(params.get("newton_after", 0)) if params.get("solver") == "newton" else None
    if newton:
        desc = "truncated Newton (L-BFGS where its preconditioner is not built: the mesh on the device) on F"
    elif after == 0:
        desc = "truncated Newton on F"
    else:
        desc = "L-BFGS on F" + (f" (truncated Newton from its step {after})" if after else "")
    desc += f" after {pre} smart-Laplace sweeps" if pre else ""
    if params.get("polish"):
        desc += (", then the worst-element polish" + ("" if host else " (on the host: numpy and C; its sub-problems "
                 "are too small and too many to compile)"))
    return "lbfgs", params, desc


def run_method(problem: Problem, method: str, seed: int, params: dict):
    """Dispatch to a method; returns (points, iterations, history, resolved params). `seed` makes the PRNG key
    of the randomised methods (only there: building it compiles a program)."""
    if problem.host and method in ("ci", "ci-global", "laplace", "smart-laplace"):
        from ..optim.host_global import global_ci_np
        from ..optim.host_local import laplace_np, local_ci_np
        from ..optim.parametrisation import free_lengths

        p = method_params(method, params)
        mesh = problem.mesh
        if method == "ci-global":
            x, it, hist = global_ci_np(problem.x0, mesh.hexes, problem.cons, free_lengths(mesh, problem.cons), p,
                                       seed, problem.info.topology.faces)
            return x, it, hist, dataclasses.asdict(p)
        args = (problem.x0, mesh.hexes, problem.cons, problem.colour, problem.info.topology.faces, p)
        if method != "ci":
            return laplace_np(*args, smart=method == "smart-laplace")
        x, it, hist = local_ci_np(*args, seed)
        return x, it, hist, dataclasses.asdict(p)
    if method in ("ci", "ci-global"):
        key = jax.random.key(seed, impl="rbg")
        from ..optim._moves import coloured_stars
        from ..optim.ci import global_ci, local_ci

        p = method_params(method, params)
        if method == "ci":
            cs = coloured_stars(problem.mesh.hexes, problem.cons, problem.colour, problem.info.topology.faces,
                                problem.table)
            x, it, hist = local_ci(key, problem.x0, problem.conn, cs, problem.cons, p, problem.extra,
                                   devices=problem.devices)
        else:
            x, it, hist = global_ci(key, global_parametrisation(problem), problem.conn, free_scale(problem), p,
                                    problem.extra, devices=problem.devices)
        return x, it, hist, dataclasses.asdict(p)
    if method in ("bfgs", "lbfgs", "cg", "lm", "gauss-newton"):
        from ..optim.gradient import run_gradient

        return run_gradient(problem, method, params)
    if method in ("laplace", "smart-laplace"):
        from ..optim.laplace import run_laplace

        return run_laplace(problem, method, params)
    raise ConfigError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")


def global_parametrisation(problem: Problem):
    """The unscaled `jaxci.optim.parametrisation.Parametrisation` of `problem` from its start ``x0``: global CI's
    unknowns (coordinates along each node's free directions)."""
    from ..optim.parametrisation import make_parametrisation

    return make_parametrisation(problem.mesh, problem.info, problem.cons, np.asarray(problem.x0), scaled=False,
                                dtype=problem.dtype)


def free_scale(problem: Problem) -> jnp.ndarray:
    """Local edge length per free coordinate (the `jaxci.geometry.projection` layout), shape ``(n_free,)``
    (`jaxci.optim.parametrisation.free_lengths`)."""
    from ..optim.parametrisation import free_lengths

    return jax.device_put(np.asarray(free_lengths(problem.mesh, problem.cons), problem.dtype))


def method_params(method: str, params: dict):
    """The checked parameter dataclass of `method` built from `params` (`ConfigError` naming the method and the
    parameter for an unknown name or a bad value). A parameter not given takes its METHOD's default: CI's come
    from `jaxci.optim.ci.CIParams.for_method` (``"ci"`` local CI's, ``"ci-global"`` the paper's global CI's),
    the one source for `smooth`, ``jaxci smooth`` and YAML configs (`jaxci.experiments.config`)."""
    from ..optim._params import make_params

    if params.get("objective", "mean") != "mean" and method not in ("bfgs", "lbfgs", "cg"):
        raise ConfigError(f"objective {params['objective']!r} is for the gradient methods bfgs, lbfgs and cg (and "
                          f"the default pipeline), not {method!r}")
    if method in ("ci", "ci-global"):
        from ..optim.ci_params import ci_params

        return ci_params(method, params)
    cls = method_param_class(method)
    if cls is None:  # no parameter class of its own: the gradient methods'
        from ..optim.gradient_params import GradientParams as cls
    return make_params(cls, params, method)


def method_param_class(method: str):
    """The parameter dataclass of `method`, whose fields are the method's ``params`` (`method_params` builds
    it): `jaxci.optim.ci_params.CIParams` for ``"ci"`` and ``"ci-global"``, `jaxci.optim.gradient.GradientParams`
    for the gradient methods, `jaxci.optim.laplace.LaplaceParams` for the Laplacians; None for ``"auto"`` or an
    unknown name (its parameters are checked when it runs). The one method -> class table (YAML configs,
    `jaxci.experiments.config`, read it too); the class is imported on use."""
    if method in ("ci", "ci-global"):
        from ..optim.ci_params import CIParams

        return CIParams
    if method in ("bfgs", "lbfgs", "cg", "lm", "gauss-newton"):
        from ..optim.gradient_params import GradientParams

        return GradientParams
    if method in ("laplace", "smart-laplace"):
        from ..optim.laplace import LaplaceParams

        return LaplaceParams
    return None


@dataclasses.dataclass(frozen=True)
class MethodRun:
    """What `smooth_steps` asks its driver to run: `method` with `seed` and `params` on `problem` (a `Problem`,
    whose `plan` says where), timed in `clock`'s ``smooth`` phase. The driver sends back ``(points, iterations,
    history, resolved params)`` (`jaxci.interface.methods.run_method`)."""

    problem: Problem
    method: str
    seed: int
    params: dict
    clock: object

    def context(self):
        """The contexts the method runs in: the plan's dtype and device on the JAX engine."""
        plan = self.problem.plan
        stack = contextlib.ExitStack()
        if plan.engine != "host":
            stack.enter_context(jax.enable_x64(plan.dtype == "float64"))
        stack.enter_context(plan.context())
        return stack

    def run(self):
        """The method alone, in its plan's contexts, timed in its clock: `run_method`'s output."""
        with self.context(), self.clock.phase("smooth"):
            return run_method(self.problem, self.method, self.seed, self.params)


def cap_note(method: str, resolved: dict, iterations, history: dict) -> str | None:
    """The note of a method that stopped at its iteration cap (`_CAPS`), or None."""
    cap = _CAPS.get(method)
    if cap is not None and cap in resolved:
        run = int(iterations) - int(np.asarray(history.get("presmooth", 0)))
        if run >= int(resolved[cap]):
            return (f"{method} stopped at its cap of {resolved[cap]} iterations ({cap}) before it converged; "
                    f"--param {cap}=N lets it go further")
    return None


def standard_history(h: dict) -> dict:
    """Every method's history with `objective` and `max_condition` lists (entry 0 = input)."""
    out = {k: np.asarray(v).tolist() for k, v in h.items()}
    if "objective" not in out and "best" in out:
        out["objective"] = out["best"]
    return out
