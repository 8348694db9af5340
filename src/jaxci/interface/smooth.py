"""`jaxci.smooth`: one interface for every smoothing method, one history record for all of them.

Every method works on the same problem: minimise the paper's F (Eq. 3.1) by moving nodes, corner nodes fixed,
edge nodes on their feature curve, surface nodes on their surface (`jaxci.geometry.boundary`,
`jaxci.geometry.projection`). On a hex-dominant mesh F is the mean over the corners of EVERY cell, hexahedra, wedges,
pyramids and tetrahedra (`jaxci.metrics.elements.mixed_objective`, `jaxci.metrics.objective`), and the nodes of linear
non-hexahedral cells move too. Whatever the method, `smooth` guarantees on return (checked in float64, not assumed,
by `jaxci.interface.invariants.enforce`):

- no cell of any type is inverted that was valid in the input, and F (over every corner) did not increase, or,
  where the method weighs the worst element first (the default pipeline's worst-element polish), F rose only
  while the worst cell fell (`jaxci.metrics.guard.worst_first`); else the input is returned, with a note
  saying why;
- every boundary node lies on the ORIGINAL boundary (a final exact float64 projection; on the host path the
  solver's own float64 projection onto the original boundary's triangles and segments).

A mesh with inverted elements cannot be smoothed by F (its objective is infinite): with ``untangle="auto"`` it
goes through the untangling stage first where one is available, otherwise `InvertedMeshError` is raised.
"""

from __future__ import annotations

import contextlib
import dataclasses
import numbers
import time
from collections.abc import Sequence

import numpy as np

from ..errors import ConfigError, InvertedMeshError, MeshError
from ..geometry.boundary import BoundaryInfo, classify_boundary, fix_nodes
from ..geometry.projection import n_free
from ..mesh import HexMesh, as_hex_mesh, check_volume, from_unit, to_unit, unit_frame
from ..mesh import merge_coincident as merge
from ..mesh.generate import check_seed
from ..metrics import objective as mixed
from ..metrics.elements import objective_on_host
from ..metrics.report import quality_report, worst_elements
from ..runtime._lazy import enable_x64, jax
from ..runtime.memory import check_fits, smooth_bytes
from .engine import DEVICES, Plan, check_choice, engine_request, resolve_plan, stage_params
from .invariants import enforce
from .methods import (  # noqa: F401  (Problem, build_problem, method_params ... are also reached as jaxci.interface.smooth.X)
    AUTO_PRESMOOTH_FROM,
    METHODS,
    OPTIMAL_F,
    MethodRun,
    Problem,
    auto_pipeline,
    build_problem,
    cap_note,
    free_scale,
    method_params,
    run_method,
    standard_history,
)
from .result import SmoothResult, unchanged_result

#: The plan's note where the worst-element polish (`jaxci.optim.polish`) runs on the host beside the JAX engine.
POLISH_ON_HOST = ("the worst-element polish runs on the host engine (numpy and C kernels) after the JAX engine's "
                  "solve, on a window of the worst cells where the mesh lives on the device: its small "
                  "sub-problems, one per level, would each be compiled anew")

_DTYPES = {"float32": np.float32, "float64": np.float64}


def smooth(
    mesh: HexMesh,
    method: str = "auto",
    *,
    seed: int = 0,
    dtype: str = "float32",
    feature_angle: float = 40.0,
    fix_boundary: bool = False,
    fixed_nodes: Sequence[int] | None = None,
    fixed_sets: Sequence[str] = (),
    untangle: str = "auto",
    untangle_boundary: bool = False,
    merge_coincident: bool = False,
    keep_worst: bool = True,
    clock=None,
    devices=None,
    engine: str = "auto",
    device: str = "auto",
    **params,
) -> SmoothResult:
    """Smooth the hexahedra of `mesh` by moving nodes; connectivity never changes.

    **Arguments:**

    - `mesh`: the input `HexMesh` (not modified); a `meshio.Mesh` is converted (as `jaxci.io.read_mesh` converts
      a file); a path or an array raises `jaxci.errors.UsageError` (read it with `jaxci.read_mesh` first).
    - `method`: one of `METHODS`: ``"auto"`` the default pipeline (`auto_pipeline`: untangle if needed, then
      L-BFGS, with smart-Laplace sweeps first on large meshes), ``"ci"`` batched local Cohort Intelligence,
      ``"ci-global"`` the paper's global CI; ``"bfgs"``, ``"lbfgs"``, ``"cg"``, ``"lm"``, ``"gauss-newton"``
      the optimistix baselines (`jaxci.optim.gradient`); ``"laplace"``, ``"smart-laplace"`` (`jaxci.optim.laplace`).
    - `seed`: an integer in [0, 2**32 - 1] (`jaxci.mesh.generate.check_seed`), the seed of the `jax.random` key
      of stochastic methods (same seed, same result; distinct seeds, distinct keys). The key uses the ``"rbg"``
      generator (XLA's RngBitGenerator): its code compiles in a tenth of the time of threefry's.
    - `dtype`: ``"float32"`` (default, fast) or ``"float64"``: the JAX engine's arithmetic (the host engine
      computes in float64 whatever this says; the result's `plan` says which ran).
    - `feature_angle`: degrees; boundary edges sharper than this are feature curves (nodes slide along them).
    - `fix_boundary`: fix every boundary node; `fixed_nodes`: node indices to fix; `fixed_sets`: names of node
      sets of the file to fix.
    - `untangle`: ``"auto"`` (untangle first if the input has inverted elements, `jaxci.optim.untangle`),
      ``"always"`` (run the untangling stage anyway: it also lifts corners below its det margin), ``"never"``
      (refuse inverted input with `InvertedMeshError`). If untangling fails, `InvertedMeshError` is raised,
      except with ``"partial"``: untangle what can be untangled (also around elements no allowed move can fix)
      and, if elements stay inverted, return that mesh without shape improvement (``result.after`` counts them,
      a note names them; the command exits with status 3). ``untangle_time_budget=S`` bounds the stage.
    - `untangle_boundary`: let the corner and edge nodes of inverted cells slide on a boundary surface (one of
      the patches around each) during the untangling stage, where the boundary's geometry alone fixes them or
      ties them to a curve (never nodes fixed by `fix_boundary`, `fixed_nodes`, `fixed_sets` or coincident
      nodes): the way out when inverted cells touch the boundary's corners so that nothing else can untangle
      them. Those that moved stay where the stage left them during shape improvement (the boundary faces next to
      them follow them; a note says how many and how far). Default False.
    - `merge_coincident`: merge coincident nodes first (`jaxci.mesh.merge_coincident`: the result has fewer
      nodes). Default False: each set of coincident nodes (`HexMesh.coincident_nodes`, an unmerged interface)
      moves as one node, sliding on the interface it lies on, and is written back unmerged (exactly coincident;
      `jaxci.geometry.coincident`), and a note says how many; `fixed_nodes` holds them.
    - `keep_worst`: guarantee that the worst cell (max corner kappa/3, float64, every cell type) is no worse than
      the input's (`jaxci.metrics.guard.keep_worst`: the nodes of cells that ended worse are put back, and a note says
      what that cost in mean quality). False returns the method's result as it is.
    - `devices`: None (default: one device; small meshes' L-BFGS on the host in numpy), or a device count,
      ``"all"`` or a list of devices (`jaxci.optim.sharding.resolve_devices`): L-BFGS (with its presmoothing),
      BFGS, CG, the Laplacians and local CI of a hexahedral mesh run compiled with the elements (and the colour
      sweeps' node slots) sharded over them, node data replicated; global CI with the trial meshes of each
      learning attempt split over them; same result as on one device to float tolerance (a note says so; the
      result's ``params["devices"]`` is the count).
    - `engine`: ``"auto"`` (default), ``"host"`` (numpy and the C kernels, float64, on the CPU) or ``"jax"``
      (the compiled JAX programs); `device`: ``"auto"`` (default: an accelerator where JAX sees one and the
      mesh is large enough for it to win, `jaxci.interface.engine.ACCELERATOR_FROM`), ``"cpu"`` or ``"gpu"`` (any
      accelerator JAX sees). One decision (`jaxci.interface.engine.resolve_plan`) made before any work, followed by
      every stage; a request that cannot be honoured is a `ConfigError`. The parameters ``backend`` and
      ``untangle_backend`` (``"numpy"``: host, ``"jax"``) are the same request.
    - `clock`: a `jaxci.runtime.phases.PhaseClock` to record the phases in (default: a new one); the result's
      ``phases`` is its `as_dict`.
    - `**params`: the method's hyperparameters (e.g. `jaxci.optim.ci.CIParams`,
      `jaxci.optim.gradient.GradientParams`, `jaxci.optim.laplace.LaplaceParams` fields; one not given takes the
      method's default: ``"ci-global"`` has its own, the paper's, `jaxci.optim.ci.GLOBAL_DEFAULTS`); keys starting with
      ``untangle_`` go to `jaxci.optim.untangle.UntangleParams` (e.g. ``untangle_margin=1e-2``).

    Every argument is checked before any work (`ConfigError` naming the argument or parameter, the method and
    the value). The mesh is refused (`MeshError`) if its estimated peak memory (`jaxci.runtime.memory.smooth_bytes`)
    exceeds the memory available, or if it has no volume (`jaxci.mesh.check_volume`). All the work is done in
    the unit frame of `jaxci.mesh.unit_frame` (scale-invariant metrics, no overflow at 1e300 or underflow at
    1e-300), and the nodes that moved are mapped back; the others keep their input coordinates bit for bit.

    **Returns:** a `SmoothResult`.
    """
    return _drive(smooth_steps(mesh, method, seed=seed, dtype=dtype, feature_angle=feature_angle,
                                fix_boundary=fix_boundary, fixed_nodes=fixed_nodes, fixed_sets=fixed_sets,
                                untangle=untangle, untangle_boundary=untangle_boundary,
                                merge_coincident=merge_coincident, keep_worst=keep_worst, clock=clock,
                                devices=devices, engine=engine, device=device, **params))


def _drive(steps):
    """Run the generator `steps` (`smooth_steps`) to its result, running each `MethodRun` it yields."""
    try:
        req = next(steps)
        while True:
            req = steps.send(req.run())
    except StopIteration as done:
        return done.value


def smooth_steps(mesh, method="auto", *, seed=0, dtype="float32", feature_angle=40.0, fix_boundary=False,
                 fixed_nodes=None, fixed_sets=(), untangle="auto", untangle_boundary=False, merge_coincident=False,
                 keep_worst=True, clock=None, devices=None, engine="auto", device="auto", seeds=1, **params):
    """`smooth` as a generator: it yields one `MethodRun` (unless no method needs to run), receives its output
    and returns the `SmoothResult`; `_drive` runs one, `jaxci.interface.seeds.smooth_seeds` several at once. `seeds`:
    how many seeds of this mesh run together (the plan's batch rule: `jaxci.interface.engine.resolve_plan`)."""
    from ..runtime.phases import PhaseClock

    clock = PhaseClock() if clock is None else clock
    user_presmooth = "presmooth" in params
    with clock.phase("validate"):
        mesh, method, seed, fixed_sets, untangle_params, params, auto, shard, shard_note, plan, tangled = _validate(
            mesh, method, seed, dtype, feature_angle, fixed_sets, untangle, params,
            {"fix_boundary": fix_boundary, "merge_coincident": merge_coincident, "keep_worst": keep_worst,
             "untangle_boundary": untangle_boundary}, engine, device, devices, seeds)
        on_device = plan.engine == "jax" and not merge_coincident and not untangle_boundary and _device_run().applies(
            mesh, method, plan, shard, len(mesh.coincident_nodes()), tangled, untangle)
        if not on_device:  # else on the device, after its upload
            check_volume(mesh)
    clock.progress("engine", plan.describe())
    t0 = time.perf_counter()
    notes: list[str] = []
    if auto:
        notes.append(_auto_note(auto))
    if shard is not None:
        notes.append(shard_note)
    if on_device:
        notes.extend(plan.notes)
        real, res = yield from _device_run().smooth_unit_device(
            mesh, method, seed, plan, feature_angle, fix_boundary, _fixed_nodes(mesh, fixed_nodes), fixed_sets,
            params, notes, clock, keep_worst)
        out = mesh if real is mesh.points else mesh.with_points(real, trusted=True)
        return _finish(res, out, t0, auto, method, seed, plan, feature_angle, fix_boundary, shard, notes, clock)
    if merge_coincident:
        merged = merge(mesh)
        if merged is not mesh:
            notes.append(merged.notes[-1])
        mesh = merged
    fixed = _fixed_nodes(mesh, fixed_nodes)
    pairs = mesh.coincident_nodes()
    joined = None
    if len(pairs):
        from ..geometry.coincident import join_coincident

        joined = join_coincident(mesh)  # each set one node; None where a cell has two nodes of one set
        if joined is None:
            fixed = np.union1d(fixed, pairs.ravel())
            notes.append(f"{len(pairs)} pairs of coincident nodes ({len(np.unique(pairs))} nodes, first: "
                         f"{mesh.node_label(int(pairs[0, 0]))} and {mesh.node_label(int(pairs[0, 1]))}) fixed, so "
                         f"they stay coincident: a cell has two nodes of one set (--merge-coincident, or "
                         f"merge_coincident=True, merges them)")
        else:
            notes.append(joined.note(mesh))
    frame = unit_frame(mesh.points)
    unit = dataclasses.replace(mesh, points=to_unit(mesh.points, frame), fix_orientation=False, notes=(),
                               check_coincident=False)
    notes.extend(plan.notes)
    solve, base_info = unit, None
    if joined is not None:
        from ..geometry.coincident import joined_info

        solve = dataclasses.replace(joined.mesh, points=to_unit(joined.mesh.points, frame), fix_orientation=False,
                                    notes=(), check_coincident=False)
        base_info = joined_info(joined, classify_boundary(unit, feature_angle=feature_angle, fix_boundary=fix_boundary,
                                                          fixed_nodes=fixed, fixed_sets=tuple(fixed_sets)),
                                unit.points)
        fixed = np.unique(joined.node_of[fixed])
    points, res = yield from _smooth_unit(
        solve, method, seed, plan, feature_angle, fix_boundary, fixed, fixed_sets, untangle, untangle_params, params,
        notes, clock, keep_worst, untangle_boundary, shard,
        auto_note=_auto_note(auto) if auto and not user_presmooth else None, base_info=base_info)
    if joined is not None:
        points, res = joined.unjoin(unit, solve, points, res)
    moved = (points != unit.points).any(axis=1)
    real = np.array(mesh.points)
    real[moved] = from_unit(points[moved], frame, inplace=True)  # (the gathered rows mapped where they are)
    return _finish(res, mesh.with_points(real), t0, auto, method, seed, plan, feature_angle, fix_boundary, shard,
                   notes, clock)


def _finish(res: SmoothResult, mesh: HexMesh, t0: float, auto, method, seed, plan, feature_angle, fix_boundary,
            shard, notes, clock) -> SmoothResult:
    """The `SmoothResult` of a run: `res` with the smoothed `mesh`, the wall time since `t0`, the run's
    parameters, notes, phases and plan."""
    return dataclasses.replace(
        res, mesh=mesh, wall_time=time.perf_counter() - t0,
        method="auto" if auto else method,
        params={**res.params, "seed": seed, "dtype": plan.dtype, "feature_angle": feature_angle,
                "fix_boundary": fix_boundary, **({"pipeline": auto} if auto else {}),
                **({} if shard is None else {"devices": int(shard.devices.size)})},
        notes=tuple(notes), phases=clock.as_dict(), plan=plan,
    )


def _device_run():
    """`jaxci.interface.device_run` (imported on use: it imports JAX)."""
    from . import device_run

    return device_run


def _sharding(method, devices, params: dict, device: str):
    """``(device mesh, params, note)`` of a ``devices=`` request (`jaxci.optim.sharding.sharded_params`);
    ``(None, params, "")`` without one (JAX is then not imported here). `device` ``"cpu"`` takes CPU devices
    (on a machine with an accelerator), else JAX's default platform's."""
    if devices is None:
        return None, params, ""
    from ..optim.sharding import resolve_devices, sharded_params

    shard = resolve_devices(devices, platform="cpu" if device == "cpu" else None)
    params, note = sharded_params(method, params, shard)
    return shard, params, note


def _validate(mesh, method, seed, dtype, feature_angle, fixed_sets, untangle, params, flags: dict, engine, device,
              devices, seeds=1):
    """`smooth`'s argument checks and the engine's plan, before any work: ``(mesh, method, seed, fixed_sets,
    untangle_params, params, auto, shard, shard_note, plan)`` with the `auto_pipeline` resolved (`auto`: its
    description, else ""), the device mesh of a sharded run (`shard`, None) and its note, and the
    `jaxci.interface.engine.Plan` every stage follows (their ``backend`` parameters set from it:
    `jaxci.interface.engine.stage_params`)."""
    mesh = as_hex_mesh(mesh, "smooth")
    if not isinstance(method, str) or method not in METHODS:
        raise ConfigError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    check_choice("smooth: dtype", dtype, tuple(_DTYPES))
    engine, params = engine_request(engine, params)
    check_choice("smooth: device", device, DEVICES)
    shard, params, shard_note = _sharding(method, devices, params, device)
    if shard is not None and mixed.has_extra(mesh):
        raise ConfigError("devices: only hexahedral meshes run sharded (this one has other cell types); leave "
                          "devices out")
    check_choice("smooth: untangle", untangle, ("auto", "always", "never", "partial"))
    seed = check_seed(seed)
    if isinstance(feature_angle, bool) or not isinstance(feature_angle, numbers.Real) or \
            not 0 < feature_angle < 180:
        raise ConfigError(f"smooth: feature_angle must be in degrees strictly between 0 and 180, got "
                          f"{feature_angle!r}")
    if isinstance(fixed_sets, str):
        raise ConfigError(f"smooth: fixed_sets must be a list of node set names, got the string {fixed_sets!r} "
                          f"(write [{fixed_sets!r}])")
    for name, flag in flags.items():
        if not isinstance(flag, bool):
            raise ConfigError(f"smooth: {name} must be True or False, got {flag!r}")
    untangle_params = {k: params.pop(k) for k in list(params) if isinstance(k, str) and k.startswith("untangle_")}
    # the hexahedra were counted when the mesh was made
    tangled = bool(mesh.inverted_hexes) or (mixed.has_extra(mesh) and any(
        b.any() for t, b in mixed.inverted_cells(mesh, mesh.points).items() if t != "hexahedron"))
    untangling = untangle == "always" or (untangle != "never" and tangled)
    plan = resolve_plan(mesh, "lbfgs" if method == "auto" else method, params, engine=engine, device=device,
                        dtype=dtype, devices=shard, untangling=untangling, seeds=seeds)
    auto = ""
    if method == "auto":
        method, params, auto = auto_pipeline(mesh, params, plan)
    if params.get("polish") and plan.engine != "host":  # the one stage that runs on the host whatever the engine
        plan = dataclasses.replace(plan, notes=(*plan.notes, POLISH_ON_HOST))
    params, untangle_params = stage_params(plan, params, untangle_params)
    try:
        p = method_params(method, params)  # checked now, not after the untangling
    except ConfigError as e:
        if not auto:
            raise
        raise ConfigError(f"{e} (the default method, auto, runs {method}; --method picks another)") from None
    if untangle_params:
        from ..optim._params import make_params
        from ..optim.untangle import UntangleParams

        make_params(UntangleParams, untangle_params, "untangling", prefix="untangle_",
                    what="the untangling stage")
    where = f"{mesh.source}: " if mesh.source else ""
    trials = p.cohort * p.variations if method in ("ci", "ci-global") else 16
    n_cells = mesh.n_hexes + sum(len(c) for c in mixed.extra_blocks(mesh).values())
    check_fits(smooth_bytes(n_cells, plan.dtype, trials, host=plan.engine == "host", method=method),
               f"{where}smoothing {mesh.n_hexes} hexahedra in {plan.dtype}")
    return mesh, method, seed, fixed_sets, untangle_params, params, auto, shard, shard_note, plan, tangled


def _auto_note(description: str) -> str:
    """The note that says which pipeline the default method (auto) runs."""
    return f"default method (auto): {description}; choose another with --method / method="


def _smooth_unit(mesh: HexMesh, method, seed, plan: Plan, feature_angle, fix_boundary, fixed_nodes, fixed_sets,
                 untangle, untangle_params, params, notes, clock, keep_worst, untangle_boundary=False,
                 devices=None, auto_note: str | None = None, base_info: BoundaryInfo | None = None
                 ) -> tuple[np.ndarray, SmoothResult]:
    """`smooth` on a mesh in the unit frame, arguments checked, as a generator (it yields the `MethodRun` of the
    method, receives its output): returns ``(points, result)`` (the result's mesh and wall time are filled in by
    `smooth`; `notes` is appended to, `clock` records the phases).
    `auto_note`: the note of the default pipeline where it chose the presmoothing (not the user): a Laplace
    sweep of the untangling stage then stands for it, and the note says so. `base_info`: the classification of
    `mesh` where the caller made it (coincident sets: `jaxci.geometry.coincident.joined_info`), else classified
    here."""
    host = plan.engine == "host"
    x64 = not objective_on_host(mesh)  # the reports and checks: float64, in JAX where numpy does not hold them
    with clock.phase("report"), enable_x64(x64):
        before = quality_report(mesh)
    untangled = None
    smesh = mesh  # the mesh whose boundary the shape improvement keeps (`untangle_boundary` may move it)
    tangled = bool(before.inverted_corners) or bool(before.overall and before.overall["inverted"])
    f_before = before.overall["objective"] if before.overall else before.objective
    if not tangled and untangle != "always" and f_before is not None and f_before <= OPTIMAL_F:
        return unchanged_result(mesh, method, before, f_before, notes)
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
        from ..optim._params import make_params
        from ..optim.feasibility import put_back, release_features, released_note
        from ..optim.untangle import UntangleParams, untangle_stage

        up = make_params(UntangleParams, untangle_params, "untangling", prefix="untangle_",
                         what="the untangling stage")
        partial = untangle == "partial"
        with clock.phase("untangle"):
            info = base_info or classify_boundary(mesh, feature_angle=feature_angle, fix_boundary=fix_boundary,
                                                  fixed_nodes=fixed_nodes, fixed_sets=tuple(fixed_sets))
            info_u, released = info, np.zeros(0, np.int64)
            if untangle_boundary and not fix_boundary:
                info_u, released = release_features(mesh, info, fixed_nodes, fixed_sets)
            if not partial:
                _refuse_stuck(mesh, info_u)
            # InvertedMeshError if it fails (unless partial)
            with plan.context():
                untangled, untangle_notes, swept = untangle_stage(
                    mesh, info_u, up, partial=partial, progress=lambda text: clock.progress("untangle", text))
            if swept and auto_note is not None and int(params.get("presmooth", 0)):
                # the untangling's plain Laplace sweep has just smoothed the mesh: cube60_pert's smooth phase
                # 6.4 -> 3.6 s without the 3 smart-Laplace sweeps, the same result (37 L-BFGS steps against 36)
                sweeps = f" after {int(params['presmooth'])} smart-Laplace sweeps"
                params = {**params, "presmooth": 0}
                notes[notes.index(auto_note)] = auto_note.replace(
                    sweeps, " (the untangling's Laplace sweep stands for the smart-Laplace sweeps)")
            moved = released[(untangled[released] != mesh.points[released]).any(axis=1)]
            if len(moved):
                untangled = np.array(untangled, dtype=np.float64)
                moved = put_back(mesh, moved, untangled)
            if len(moved):  # shape improvement keeps them where they are: a mesh whose boundary follows them
                points = np.array(mesh.points, dtype=np.float64)
                points[moved] = untangled[moved]
                smesh = mesh.with_points(points)
                info = fix_nodes(info, moved)  # the input's classification, with them fixed where they are
                untangle_notes.append(released_note(mesh, moved, untangled))
        notes.extend(untangle_notes)
        if partial:
            with clock.phase("checks"), enable_x64(x64):
                left = quality_report(mesh, untangled)
            if left.inverted_elements or left.inverted_corners:  # no shape improvement on a tangled mesh
                return np.asarray(untangled, dtype=np.float64), SmoothResult(
                    mesh=mesh, history={"objective": [f_before], "max_condition": [before.max_condition]},
                    iterations=0, wall_time=0.0, method=method, params={"untangle": "partial"}, before=before,
                    after=left, boundary=info.counts, node_class=np.asarray(info.node_class))
    np_dtype = _DTYPES[plan.dtype]  # the host engine's is float64: exact start and boundary
    with (contextlib.nullcontext() if host else jax.enable_x64(plan.dtype == "float64")), plan.context():
        with clock.phase("setup"):
            problem = build_problem(smesh, dtype=np_dtype, feature_angle=feature_angle, fix_boundary=fix_boundary,
                                    fixed_nodes=fixed_nodes, fixed_sets=fixed_sets, plan=plan,
                                    info=base_info if untangled is None else info, devices=devices)
            if untangled is not None:
                start = np.asarray(untangled, np_dtype)
                problem = dataclasses.replace(problem, x0=start if host else jax.device_put(start))
        if n_free(problem.cons) == 0:  # every node fixed: no method can change anything
            x = np.asarray(mesh.points if untangled is None else untangled, dtype=np.float64)
            return unchanged_result(mesh, method, before, f_before, notes, problem.info, x,
                                    None if untangled is None else quality_report(mesh, x))
    x, iterations, history, resolved = yield MethodRun(problem, method, seed, params, clock)
    x = np.asarray(x, dtype=np.float64)
    if resolved.get("batched_seeds"):
        notes.append(f"global CI of {resolved['batched_seeds']} seeds ran as one batched program on the JAX engine "
                     "(jaxci.interface.seeds.smooth_seeds); this run's smooth phase is its equal share of the batch's "
                     "time")
    escaped = history.get("escape") or {}
    if escaped.get("rounds"):
        notes.append(f"escape: the solver had stopped at a minimum for small moves only; {escaped['rounds']} rounds of "
                     f"local CI sweeps and the solver again lowered F from {escaped['objective'][0]:.6g} to "
                     f"{escaped['objective'][1]:.6g} (--param escape=0: none)")
    notes.extend(problem.info.notes)
    cap = cap_note(method, resolved, iterations, history)
    if cap:
        notes.append(cap)
    with clock.phase("checks"), enable_x64(x64):
        power = float(resolved["p"]) if resolved.get("objective") == "pmean" else None
        # the input's worst cell from its report (valid input: every corner counted), not recomputed
        w0 = (before.overall or {}).get("max_condition", before.max_condition)
        points, check_notes = enforce(  # `problem` is of `smesh`: `mesh`, or its boundary where untangling moved it
            smesh, problem.host_cons, mesh.points if untangled is None else np.asarray(untangled, np.float64), x,
            untangled=untangled is not None, keep_worst=keep_worst and untangled is None,
            worst_start=w0 if untangled is None else None,
            power=power, projected=host, worst_first=bool(resolved.get("polish")) and power is None)
        notes.extend(check_notes)
        after = quality_report(mesh, points)
        after = dataclasses.replace(after, worst_elements=worst_elements(
            mesh, points, problem.info.node_class, problem.info.feature_edges))
    res = SmoothResult(
        mesh=mesh, history=standard_history(history), iterations=int(iterations), wall_time=0.0, method=method,
        params=resolved, before=before, after=after, boundary=problem.info.counts,
        node_class=np.asarray(problem.info.node_class),
    )
    return points, res


def _refuse_stuck(mesh: HexMesh, info: BoundaryInfo) -> None:
    """`InvertedMeshError` at once, naming them, if some inverted cells cannot be fixed by any allowed move
    (`jaxci.optim.feasibility.stuck_cells`: an inverted corner whose four nodes are all fixed)."""
    from ..optim.feasibility import stuck_cells

    stuck = stuck_cells(mesh, info)
    if not stuck:
        return
    where = f"{mesh.source}: " if mesh.source else ""
    n = sum(len(v) for v in stuck.values())
    labels = [_label(mesh, t, int(k)) for t, ks in stuck.items() for k in ks[:5]][:5]
    raise InvertedMeshError(
        f"{where}{n} inverted {'element cannot' if n == 1 else 'elements cannot'} be untangled: each has an inverted "
        f"corner whose four nodes are all fixed (boundary corners, fixed sets or --fix-boundary), so no allowed "
        f"move changes it ({', '.join(labels)}{', ...' if n > len(labels) else ''}); free those nodes (drop "
        f"--fix-boundary / --fixed-set; --untangle-boundary lets the boundary's own corners and edge nodes slide "
        f"on the surface) or repair the elements in the mesher"
    )


def _fixed_nodes(mesh: HexMesh, fixed_nodes) -> np.ndarray:
    """`fixed_nodes` as sorted unique node indices (`MeshError` for anything but integers in range)."""
    if fixed_nodes is None:
        return np.zeros(0, np.int64)
    where = f"{mesh.source}: " if mesh.source else ""
    try:
        a = np.asarray(fixed_nodes).ravel()
    except (TypeError, ValueError):
        a = np.asarray([object()])
    n = mesh.n_nodes
    if a.size and (a.dtype.kind not in "iu" or a.min() < 0 or a.max() >= n):
        raise MeshError(f"{where}fixed_nodes must be node indices in [0, {n}), got {a.tolist()[:10]}")
    return np.unique(a.astype(np.int64))


def _label(mesh: HexMesh, cell_type: str, k: int) -> str:
    return f"element {mesh.hex_label(k)}" if cell_type == "hexahedron" else mixed.cell_label(mesh, cell_type, k)
