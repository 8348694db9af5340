"""Gradient baselines: L-BFGS (jaxci's), optimistix's minimisers and least-squares solvers on F over the free
coordinates.

The unknowns are the free coordinates of `jaxci.geometry.projection` (3 per interior node, 2 per surface node, 1 per
edge node; corner nodes fixed), divided by the local edge length h of their node: ``u = h * v`` and the solvers see
``v``. Node coordinates are ``project(x0 + B u)`` (`jaxci.optim.parametrisation.Parametrisation.points`), so
every iterate lies on the original boundary. On a mixed mesh F is the mean over the corners of every cell
(`jaxci.metrics.objective`).

**Step cap and stalls** (`jaxci.optim.lbfgs`, `jaxci.optim._solve`). BFGS, L-BFGS and CG trials move no free coordinate
more than ``max_move`` (0.5) local edge lengths, and a capped solver stops after 20 consecutive rejected trials.
Measured (L-BFGS, float32, perturbed boxes, amplitude 0.3, seed 0): at 30^3 the uncapped first step was halved 35 times
and 28 rejected trials followed convergence (122 steps; 79 to max kappa/3 <= 1.0001); capped: 83 steps, 55 to 1.0001. At
60^3: 99 steps to 1.0001 instead of 282-411.

**Methods.** ``"lbfgs"`` minimises ``s F`` with jaxci's L-BFGS (`jaxci.optim.lbfgs.lbfgs_loop`, the host engine's
algorithm, `jaxci.optim.host.lbfgs`: the same iterates); ``"bfgs"`` and ``"cg"`` with `optx.BFGS` and
`optx.NonlinearCG`. ``s = 8N / 32`` (N elements, 32 = the corners an interior node moves) makes the objective a
per-node sum, so that the solvers' identity initial (inverse) Hessian has the right order of magnitude.
``"lm"`` (`optx.LevenbergMarquardt`) and ``"gauss-newton"`` (optimistix's Gauss-Newton descent,
`optx.NewtonDescent`, with a backtracking Armijo search: ``gn_search="armijo"``) solve a least-squares problem
with one residual per corner, weighted by ``sqrt(2 s / 8N)``:

- ``residual="excess"`` (default): ``r = sqrt((kappa/3)^2 - 1)``, so ``0.5 |r|^2 = s F``: zero at the optimum;
- ``residual="kappa"``: ``r = kappa/3``, so ``0.5 |r|^2 = s (F + 1)``: the residuals tend to 1, not 0, and the
  Gauss-Newton model ``J^T J`` misses the dominant second-order term.

Measured (float64, 3^3 and 4^3 cubes with a sliding perturbation of 0.3 h, sliding boundary): with ``"kappa"``
LM needs 146 and 202 steps to max kappa/3 = 1 + 2e-10 and Gauss-Newton stalls at 1.83 and 1.69 after 2000
steps; with ``"excess"`` LM needs 51 and 78 steps and Gauss-Newton 19 and 9 (to 1 + 2e-16). optimistix's own
`optx.GaussNewton` takes full steps (``gn_search="none"``): its first step inverts elements on every cube tried,
the next Jacobian is NaN, and the input comes back.

**Why these scalings** (measured, float64, ``rtol = atol = 1e-6``; 1000hex-block-internal-bias.vtk with its
boundary fixed, and the 9^3 cube perturbed by 0.3 h inside): with raw coordinates and raw F, NonlinearCG needs
more than 3000 steps and L-BFGS stops early (ecosystem.md: at 1.79); with ``v`` in units of h and the objective
``s F``, L-BFGS reaches max kappa/3 = 1.000000 in 73 and 56 steps, NonlinearCG in 363 and 122 steps. With
``rtol = atol = 1e-8`` L-BFGS and CG hit `max_steps` on the block (rounding noise in F is larger than the
tolerance), so ``1e-6`` is the default. float32 reaches 1.000002 (block) and 1.000000 (cube) with the same
steps, so the user's dtype is kept (float32 by default in `jaxci.smooth`).

**Iterations and history.** An optimistix solver runs under one `jax.jit` as optimistix's own loop does (`init`, then
`step`/`terminate` in a bounded `lax.while_loop`, the same calls `optx.minimise` makes: same iterates, same step
count; checked in the tests), and records after every step the objective F and the max kappa/3 of the current
accepted iterate (returned by the objective as auxiliary data, so they cost nothing extra). One step is one
evaluation of the objective (a line-search trial or an accepted step, as optimistix counts
``stats["num_steps"]``). The loop also keeps the best valid iterate: if a solver ever returns a state with an
inverted corner or a NaN (Gauss-Newton takes full steps without a line search), the best valid iterate is
returned instead. Minimisers with a backtracking line search never accept an inverted iterate: F is ``inf``
there and fails the Armijo test.

**Restarts.** The solvers terminate on small changes of the unknowns and of the objective between accepted
steps; after a run of backtracked (tiny) steps that test fires far from the optimum. On the paper's 27-element
cube, 30 seeds, BFGS stopped "successful" at max kappa/3 up to 459 (4 seeds above 1.0001 in float32, 1 in float64,
2.25). Restarting the solver once from its last iterate with a fresh state (identity Hessian, empty L-BFGS
memory) took every one of them to 1 + 1e-6 or better, so `minimise` restarts a run that ends with F above
1e-6 of the input's F, and again while a restart still lowers F (`GradientParams.restarts`, `restart_tol`).

**Least squares.** LM and Gauss-Newton form the dense Jacobian (8N x n_free) and factorise it: they are for
small meshes only and refuse more than `GradientParams.max_free` free coordinates (1000 by default). Measured
warm (float32, paper cubes): LM 0.24 s at 81 free coordinates (cube27), 0.67 s at 225 (cube64); the cost grows
like residuals x unknowns^2 per step, so the 2400 unknowns of cube729 would take many minutes (ecosystem.md:
more than 8 minutes at 3000). BFGS keeps a dense n_free x n_free inverse Hessian:
seconds per hundred steps at 2400 unknowns; use L-BFGS or CG for anything but small meshes.

**Objectives.** What the solvers minimise (F or the p-mean over the free coordinates, the least-squares residuals,
the closed-form gradient) is `jaxci.optim.solver_objective`.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .. import native
from ..errors import ConfigError
from ..geometry.projection import project_np
from ..metrics.objective import extra_cells, has_extra, no_extra
from ..runtime._lazy import is_jax_array, jax, jit, jnp
from ..runtime.phases import progress
from ..runtime.transfer import program, to_host
from . import _params as _p
from ._buckets import bucket, free_layout, padded_connectivity, to_device
from ._params import MAX_REJECTED, MAX_REJECTED_UNCAPPED
from .gradient_params import (  # noqa: F401  (re-exported: the parameters and names of these methods)
    CG_METHODS,
    LEAST_SQUARES,
    MAX_FREE,
    MAX_HISTORY,
    MAX_POWER,
    MAX_PRESMOOTH,
    MAX_STEPS,
    METHODS,
    OBJECTIVES,
    GradientParams,
    history_pairs,
)
from .host import HOST_MAX, HostObjective, runs_on_host
from .host import lbfgs as host_lbfgs
from .parametrisation import (  # noqa: F401  (node_lengths re-exported)
    Parametrisation,
    make_parametrisation,
    node_lengths,
    pad_parametrisation,
    pad_problem_device,
    unpad_free,
)
from .solver_objective import (
    closed_incidence,
    hessian_closed,
    objective_scale,
    solver_args,
    solver_objective,
    value_and_grad_closed,
)

#: The parameters a solver call takes when given none.
DEFAULT_PARAMS = GradientParams()

#: A strict run (no projection: `Parametrisation.strict`) whose result has a boundary node further than this
#: fraction of its flat region's radius from the region's origin is continued with the projection.
FLAT_REACH = 0.9


def _max_rejected(method: str, p: GradientParams) -> int:
    return MAX_REJECTED if method in ("bfgs", "lbfgs", "cg") and p.max_move else MAX_REJECTED_UNCAPPED


def _result_message(result) -> str:
    if isinstance(result, str):  # the numpy solver's (`jaxci.optim.host`)
        return result
    from ._solve import result_message

    return result_message(result)


#: The methods whose problem is padded to its size class (`jaxci.optim._buckets`) on a hexahedral mesh.
BUCKETED = ("bfgs", "lbfgs", "cg")


def _host_mixed_kernel(conn, extra, power: float | None = None):
    """The host kernel of F over every cell of a mixed mesh (`jaxci.native.MixedKernel`), or of the p-mean with
    `power` (`jaxci.optim.weighted.pmean_kernel`); None (the hexahedra's kernel) for a hexahedral mesh."""
    if not extra.types:
        return None
    if power is not None:
        from .weighted import pmean_kernel

        return pmean_kernel(_cells_by_type(conn, extra), power)
    return native.MixedKernel(_cells_by_type(conn, extra))


def _cells_by_type(conn, extra) -> dict:
    """Every cell's connectivity ``(N, k)`` (numpy) by type: the hexahedra of `conn` ``(8, N)`` and the cells of
    `extra`."""
    return {"hexahedron": np.asarray(conn).T,
            **{t: np.asarray(c).T for t, c in zip(extra.types, extra.conns, strict=True)}}


def use_host(method: str, p: GradientParams, n_hex: int, extra=None) -> bool:
    """Whether `minimise` runs `method` in numpy (`jaxci.optim.host`): L-BFGS on a hexahedral mesh with
    ``p.backend`` ``"numpy"``, or ``"auto"`` and at most `HOST_MAX` elements."""
    mixed = extra is not None and bool(extra.types)
    n_cells = n_hex + (sum(int(c.shape[1]) for c in extra.conns) if mixed else 0)
    return method == "lbfgs" and runs_on_host(p.backend, n_cells, HOST_MAX, mixed and not native.AVAILABLE)


def _bucketed(method: str, par: Parametrisation, conn, p: GradientParams, extra, n_devices: int = 0):
    """``(par, conn, weight, index)`` to run: `par` and `conn` padded to their size class
    (`pad_parametrisation`, `jaxci.optim._buckets.padded_connectivity`; `index`: the real free coordinates in
    the padded vector) for `BUCKETED` methods on a hexahedral mesh with ``p.buckets`` or sharded over
    `n_devices` (the elements then a multiple of it); else as given (`weight` and `index` None)."""
    if not ((p.buckets or n_devices) and method in BUCKETED and not extra.types):
        return par, conn, None, None
    n_el = bucket(int(conn.shape[1]), multiple=max(n_devices, 1))
    if is_jax_array(conn) and is_jax_array(par.x0):  # on the device: nothing moves
        padded, index, c, w = pad_problem_device(par, conn, n_el)
        return padded, c, w, index
    padded, index = pad_parametrisation(par)
    c, w = padded_connectivity(np.asarray(conn).T, n_el)
    return padded, to_device(c, np.asarray(conn).dtype), to_device(w, par.x0.dtype), index


def minimise(method: str, par: Parametrisation, conn, p: GradientParams = DEFAULT_PARAMS, extra=None,
             devices=None, project=None):
    """Run one gradient baseline from ``par.points(0)``.

    **Arguments:**

    - `method`: one of `METHODS`.
    - `par`: the `Parametrisation` (`make_parametrisation`).
    - `conn`: transposed connectivity ``(8, N)``.
    - `p`: `GradientParams`.
    - `extra`: the wedges, pyramids and tetrahedra (`jaxci.metrics.objective.ExtraCells`, default none): F over every
      corner.
    - `devices`: None (one device), or a `jax.sharding.Mesh` (`jaxci.optim.sharding.resolve_devices`): the
      compiled loop with the elements sharded over it (`jaxci.optim.sharding.place_problem`), never the host path.
      ``"lbfgs"`` runs `jaxci.optim.lbfgs.lbfgs_loop` (the host path's algorithm; sharded: F over hexahedra, its
      memory split over the devices), the other methods (and sharded L-BFGS of the p-mean or on mixed meshes)
      optimistix's loop.
    - `project`: None, or (a compiled run whose mesh lives on the device) a function of device coordinates
      ``(n, 3)`` that projects them exactly onto the original boundary: the result is lifted on the device and
      projected by it where a node left its flat region (else `Parametrisation.final_points`, in numpy).

    **Returns:** ``(points, iterations, history, params)``: coordinates ``(n, 3)`` (the best valid iterate), the
    number of solver steps, a dict of numpy arrays of length ``iterations + 1`` (entry 0 = input):
    ``objective`` (F) and ``max_condition`` (max kappa/3) of the accepted iterate after each step, plus
    ``restarts`` (the steps at which the solver was restarted) and ``solver_result`` (optimistix's result name
    of the last run); and the resolved hyperparameters. Raises `ConfigError` for a
    least-squares method on more than ``p.max_free`` free coordinates.

    Where every moving boundary node has a flat region (``par.shortcut``) the first run is strict (no projection
    compiled; a trial that leaves a region is rejected); if its result has a node beyond `FLAT_REACH` of its
    region's radius, the solver goes on from there with the projection (one more run, in ``restarts``).
    """
    if method not in METHODS:
        raise ConfigError(f"unknown gradient method {method!r}; choose one of {', '.join(METHODS)}")
    nf = par.n_free
    extra = no_extra() if extra is None else extra
    if method in LEAST_SQUARES and nf > p.max_free:
        raise ConfigError(
            f"method {method!r} forms a dense Jacobian ({8 * conn.shape[1] + extra.n_corners} residuals x {nf} "
            f"free coordinates) and "
            f"is only for small meshes: {nf} free coordinates > max_free={p.max_free}; use 'lbfgs' or 'cg', or raise "
            f"max_free"
        )
    if p.objective == "pmean" and method not in BUCKETED:
        raise ConfigError(f"objective 'pmean' is for bfgs, lbfgs and cg, not {method!r}")
    params = {"method": method, **dataclasses.asdict(p)}
    n_hex = int(conn.shape[1])
    on_host = devices is None and use_host(method, p, n_hex, extra)
    # the two-level preconditioner (`jaxci.optim.coarse`) is built on the host from the mesh there: for the host's
    # solvers, and for the JAX engine's truncated Newton where the mesh is on the host (not in a run on the device),
    # if `precondition` asks for it at this size
    from . import coarse  # (numpy; imported on use, as the other solvers' modules)

    n_cells = n_hex + sum(int(c.shape[1]) for c in extra.conns)
    newton_m = method == "lbfgs" and devices is None and project is None
    wants_m = p.precondition == "coarse" or (p.precondition == "auto" and n_cells <= coarse.AUTO_MAX_CELLS)
    if p.solver == "auto":  # truncated Newton where its preconditioner is built, on the JAX engine
        newton = not on_host and newton_m and not extra.types and wants_m
        p = dataclasses.replace(p, solver="newton" if newton else "lbfgs")
        params["solver"] = p.solver
    if nf == 0:
        x = par.points(jnp.zeros((0,), par.x0.dtype))
        f, k = solver_objective(x, conn, False, extra)
        return x, 0, {"objective": np.asarray([f]), "max_condition": np.asarray([k]),
                      "solver_result": "no free coordinates"}, params
    if p.solver == "newton" and not (method == "lbfgs" and devices is None):
        raise ConfigError(f"gradient-method parameter solver='newton' is for method 'lbfgs' on one device or the "
                          f"host, not {method!r}{' sharded over devices' if devices is not None else ''}; use "
                          f"solver='lbfgs'")
    coarse_ok = on_host or (newton_m and p.solver == "newton")
    if p.precondition == "coarse" and not coarse_ok:
        raise ConfigError(f"gradient-method parameter precondition={p.precondition!r} is for L-BFGS on the host "
                          f"(numpy) path and for solver='newton', not {method!r} with backend={p.backend!r}"
                          f"{' sharded over devices' if devices is not None else ''}"
                          f"{' in a run on the device' if project is not None else ''}; use precondition='none'")
    n_dev = 0 if devices is None else int(devices.devices.size)
    # L-BFGS: jaxci's own loop (`jaxci.optim.lbfgs`), on one device or sharded (F over hexahedra); the other
    # methods: optimistix's
    own_loop = method == "lbfgs" and (not n_dev or (p.objective != "pmean" and not extra.types))
    if not on_host and not own_loop:  # optimistix (imported here: 0.35 s the other paths do without)
        from ._solve import make_solver, solve_loop

        solver = make_solver(method, p)
    run_par, run_conn, weight, index = (par, conn, None, None) if on_host else _bucketed(method, par, conn, p, extra,
                                                                                          n_dev)
    if n_dev:
        from .sharding import place_problem, replicate

        run_conn, weight, run_par = place_problem(run_conn, weight, run_par, devices)

    if on_host:
        def real(y):  # the real free coordinates of the iterate (numpy)
            return y if index is None else y[index]
    elif project is None:  # compiled, the mesh on the host: the iterate comes down (programs of the size class only)
        def real(y):
            y = to_host(y)
            return y if index is None else y[index]
    else:  # the mesh on the device: the iterate never comes down (`Parametrisation.reach`, `lift_reach`)
        layouts = None if index is None else (free_layout(par.cons), free_layout(run_par.cons))

        def real(y):
            return y if layouts is None else _unpad(y, *layouts)

    # on the host the solvers make the zero start themselves (None): no reference here keeps it once they move on
    y = None if on_host else _zeros(run_par.n_free, np.dtype(par.x0.dtype))
    incidence = None  # the closed-form gradient's node incidences: once for every run
    if not (on_host or n_dev or method in LEAST_SQUARES or p.gradient != "closed"):
        incidence = closed_incidence(run_conn, run_par.x0.shape[0], weight,
                                     float(p.p) if p.objective == "pmean" else None)
    hist_f, hist_k, starts = [], [], []
    steps = 0
    f0 = None
    # first without the projection fallback (strict: leaving a flat region is a rejected trial), a 40% smaller
    # compiled loop; only if a node ends near the edge of its flat region, on with the projection
    # (not where the start is already outside a flat region, e.g. after presmooth or untangling, and not for a
    # solver that accepts every step: it would accept a NaN point)
    never_rejects = method == "gauss-newton" and p.gn_search == "none"
    strict = par.shortcut and not never_rejects and not on_host and par.reach(
        _zeros(nf, np.dtype(par.x0.dtype)) if project is not None else np.zeros(nf)) < FLAT_REACH
    runs, max_runs = 0, 1 + int(p.restarts)
    host_fn = precond = None
    after = outer = 0
    newton_ran = False  # (``solver="newton"`` with `newton_after`: a run that L-BFGS ends sooner is L-BFGS's)
    while runs < max_runs:
        cur = dataclasses.replace(run_par, strict=True) if strict else run_par
        if on_host:  # one objective for every run: its projector remembers each node's triangle
            power = p.p if p.objective == "pmean" else None
            host_fn = host_fn or HostObjective(run_par, np.asarray(conn), objective_scale(n_hex, extra),
                                               kernel=_host_mixed_kernel(conn, extra, power), power=power)
        if coarse_ok and wants_m and precond is None:
            after = 0 if p.precondition == "coarse" else coarse.AUTO_AFTER
            precond = functools.cache(lambda: coarse.build_coarse(par, _cells_by_type(conn, extra)))
        lbfgs_first = p.solver == "newton" and steps < p.newton_after  # L-BFGS's steps, then Newton
        lbfgs_limit = min(p.max_steps, p.newton_after if lbfgs_first else p.max_steps) - steps
        if on_host and p.solver == "newton" and not lbfgs_first:
            from .newton import newton_cg

            y, k, result, hf, hk, n_outer = newton_cg(
                host_fn, y, limit=p.max_steps - steps, max_rejected=_max_rejected(method, p), rtol=p.rtol,
                atol=p.atol, cap=p.max_move, ftol=p.ftol, done=lambda f, k: k <= 1.0 + p.ktol, precond=precond,
                cg_max=int(p.cg_max))
            outer, newton_ran = outer + n_outer, True
        elif on_host:
            y, k, result, hf, hk = host_lbfgs(host_fn, y, limit=lbfgs_limit, max_rejected=_max_rejected(method, p),
                                              rtol=p.rtol, atol=p.atol, history=history_pairs(p, nf),
                                              cap=p.max_move, ftol=p.ftol,
                                              done=lambda f, k: k <= 1.0 + p.ktol, precond=precond,
                                              precond_after=max(after - steps, 0) if precond else 0)
        elif own_loop:
            from .lbfgs import lbfgs_loop, result_name, value_and_grad

            dtype = par.x0.dtype
            consts = np.asarray([p.ftol, 1.0 + p.ktol, p.rtol, p.atol, p.max_move or 0.0], dtype)
            scale = np.asarray(objective_scale(n_hex, extra), dtype)
            static = (float(p.p) if p.objective == "pmean" else None, p.gradient == "closed")
            loop = functools.partial(lbfgs_loop, max_steps=int(p.max_steps), history=history_pairs(p),
                                     max_rejected=_max_rejected(method, p))
            if p.solver == "newton" and not lbfgs_first:
                from .newton import newton_loop

                m = None if precond is None else tuple(
                    to_device(a, np.int32 if a.dtype.kind == "i" else dtype)
                    for a in precond().padded(index, run_par.n_free).arrays())
                y, k, code, hf, hk, n_outer = newton_loop(
                    value_and_grad_closed, hessian_closed, (cur, to_device(scale), extra, incidence), run_conn,
                    weight, y, to_device(consts), to_device(np.int32(p.max_steps - steps)), m, static=static,
                    max_steps=int(p.max_steps), max_rejected=_max_rejected(method, p), cg_max=int(p.cg_max))
                outer, newton_ran = outer + int(to_host(n_outer)), True
            elif n_dev:  # (numpy arrays placed straight from the host: `replicate`)
                y, k, code, hf, hk = loop(value_and_grad, (cur, replicate(scale, devices)), run_conn, weight,
                                          replicate(y, devices), replicate(consts, devices),
                                          replicate(np.int32(p.max_steps - steps), devices), mesh=devices)
            else:
                y, k, code, hf, hk = loop(
                    value_and_grad_closed, (cur, to_device(scale), extra, incidence), run_conn, weight, y,
                    to_device(consts), to_device(np.int32(lbfgs_limit)), static=static)
            result = result_name(to_host(code))
        else:
            fn, args = solver_args(method, cur, run_conn, p, extra, weight, n_hex, 0 if n_dev else None,
                                   devices if n_dev > 1 else None, incidence)
            y = replicate(y, devices) if n_dev else y  # one input sharding for every run: one compilation
            y, k, result, hf, hk = solve_loop(solver, fn, y, args, int(p.max_steps),
                                          to_device(np.int32(p.max_steps - steps)), _max_rejected(method, p))
        k, hf, hk = to_host((k, hf, hk))  # the step count and the histories (max_steps + 1 floats each)
        k = int(k)
        seg_f, seg_k = hf[: k + 1], hk[: k + 1]  # sliced on the host: no compilation
        if runs == 0:
            f0 = float(seg_f[np.isfinite(seg_f)][0]) if np.isfinite(seg_f).any() else float(seg_f[0])
            hist_f.append(seg_f)
            hist_k.append(seg_k)
        else:
            starts.append(steps)
            hist_f.append(seg_f[1:])
            hist_k.append(seg_k[1:])
        steps += k
        runs += 1
        finite = seg_f[np.isfinite(seg_f)]
        progress(f"{method} run {runs}: {steps} steps, F {finite.min(initial=np.inf):.6g}, max kappa/3 "
                 f"{np.min(seg_k):.6g}")  # to the running phase's listener, if any (`jaxci.runtime.phases`)
        gain = float(seg_f[0] - finite.min()) if len(finite) else 0.0
        if steps >= p.max_steps or finite.min(initial=np.inf) <= p.ftol or np.min(seg_k) <= 1.0 + p.ktol:
            break
        if lbfgs_first and steps >= p.newton_after and result == "nonlinear_max_steps_reached":
            max_runs += 1  # L-BFGS's share ran out: Newton from here, not a restart
            continue
        if finite.min(initial=np.inf) <= p.restart_tol * abs(f0):  # converged relative to the input
            break
        if strict and par.reach(real(y)) > FLAT_REACH:
            strict, max_runs = False, max_runs + 1  # the flat regions may have held it back: once more, projected
            continue
        if runs >= 2 and not gain > p.restart_tol * abs(f0):
            break
    if on_host and host_fn.best is not None and np.array_equal(host_fn.best[0], y):
        x = np.asarray(host_fn.points_of(host_fn.best), par.x0.dtype)  # as evaluated (on the boundary)
    else:  # exactly projected where a node left its flat region (by `project` where the mesh is on the device)
        x = par.final_points(real(y), project)
    hist = {"objective": np.concatenate(hist_f), "max_condition": np.concatenate(hist_k),
            "restarts": np.asarray(starts, dtype=np.int64), "solver_result": _result_message(result)}
    if p.solver == "newton":
        hist["newton_iterations"] = outer
        params["solver"] = "newton" if newton_ran else "lbfgs"  # the solver that ran
    return x, steps, hist, params


@program
@jit(static_argnums=(0, 1))
def _zeros(n: int, dtype):
    """A zero vector ``(n,)`` of `dtype` made on the device."""
    return jnp.zeros((n,), dtype)


@program
@jit(static_argnums=(1, 2))
def _unpad(y, real: tuple, padded: tuple):
    """The real free coordinates of a padded iterate, on the device (`unpad_free`)."""
    return unpad_free(y, real, padded)


def run_gradient(problem, method: str, params: dict):
    """`jaxci.smooth`'s entry: build `GradientParams` from `params` and the parametrisation of `problem`.

    **Arguments:** `problem` a `jaxci.interface.smooth.Problem` (its `x0` is the start); `method` one of `METHODS`;
    `params` keyword hyperparameters (fields of `GradientParams`).

    **Returns:** as `minimise`; with ``presmooth`` sweeps of the smart Laplacian first, the history starts with
    theirs (``history["presmooth"]`` = sweeps run) and the iterations count sweeps and solver steps.
    """
    p = _p.make_params(GradientParams, params, method)
    x0, pre = problem.x0, None
    # the mesh on the device: its boundary nodes projected exactly (onto their planes there, else on the host)
    project = None if problem.tables is None else problem.project_device

    if p.presmooth:
        from .laplace import LaplaceParams, laplace_device, run_laplace

        sweep = {"max_sweeps": int(p.presmooth), "buckets": p.buckets}
        if problem.host:  # the host engine's sweeps, in numpy and C
            from .host_local import laplace_np

            xl, sweeps, pre, _ = laplace_np(problem.x0, problem.mesh.hexes, problem.cons, problem.colour,
                                            problem.info.topology.faces,
                                            _p.make_params(LaplaceParams, sweep, "smart-laplace"), smart=True)
        elif problem.tables is not None:  # the mesh on the device: the sweeps' data built there
            from .device_stars import sweep_data

            view, planes = problem.boundary_planes
            data = sweep_data(problem.x0, problem.conn, problem.cons, problem.info.topology.faces, view=view,
                              planes=planes)
            xl, sweeps, pre, _ = laplace_device(data, _p.make_params(LaplaceParams, sweep, "smart-laplace"),
                                                smart=True)
        else:
            xl, sweeps, pre, _ = run_laplace(problem, "smart-laplace", sweep)
        # exactly on the boundary again (float64, the host's float64 constraints: the original boundary, not its
        # float32 rounding), so that the flat-region shortcut of the parametrisation holds; where the mesh lives on
        # the device, its boundary nodes only (`project_boundary`: O(boundary) down and up)
        x0 = project_np(problem.host_cons, np.asarray(xl, dtype=np.float64)) if project is None else project(xl)
        del xl
    if problem.tables is not None:  # the mesh on the device (the presmoothing's incidences and planes reused)
        from .device_parametrisation import make_parametrisation_device

        view, planes = problem.boundary_planes
        kept = {"view": view, "planes": planes} | ({} if pre is None else {"inc": data.inc})
        par = make_parametrisation_device(problem.points64, problem.conn, problem.info.topology.faces,
                                          problem.info.feature_edges, problem.cons, x0, scaled=p.scaled,
                                          dtype=problem.dtype, **kept)
    else:
        par = make_parametrisation(problem.mesh, problem.info, problem.cons, x0, scaled=p.scaled,
                                   dtype=problem.dtype)
    extra = None
    if has_extra(problem.mesh):
        extra = extra_cells(problem.mesh, device=False)
        if not use_host(method, p, problem.mesh.n_hexes, extra):
            extra = extra_cells(problem.mesh)
    if p.escape and not (problem.host and extra is None and native.AVAILABLE and method == "lbfgs"):
        where = (f"{method!r} on the {'host' if problem.host else 'JAX'} engine"
                 + (" on a mixed mesh" if extra is not None else "") + ("" if native.AVAILABLE else " without them"))
        raise ConfigError(f"gradient-method parameter escape={p.escape} is for method 'lbfgs' on the host engine on a "
                          f"hexahedral mesh with the C kernels (its sweeps are theirs), not {where}; use escape=0")
    x, steps, hist, resolved = minimise(method, par, problem.conn, p, extra, problem.devices, project)
    if p.escape:  # (the host's sweeps, then the solver again: `jaxci.optim.escape`)
        from .escape import after_solve

        x, steps, hist, par = after_solve(problem, method, par, x, steps, hist, p, minimise)
    if p.polish:
        x, steps, hist = _polish(problem, par, x, steps, hist, p)
    if pre is None:
        return x, steps, hist, resolved
    hist = {**hist, "presmooth": int(sweeps)}
    for key in ("objective", "max_condition"):
        hist[key] = np.concatenate([np.asarray(pre[key], dtype=np.float64)[: sweeps + 1],
                                    np.asarray(hist[key], dtype=np.float64)[1:]])
    if "restarts" in hist:
        hist["restarts"] = np.asarray(hist["restarts"]) + int(sweeps)
    return x, int(sweeps) + steps, hist, resolved


def _polish(problem, par: Parametrisation, x, steps: int, hist: dict, p: GradientParams):
    """The worst-element polish (`jaxci.optim.polish`) of the solver's result `x`, on the host whatever the engine
    (numpy float64 constraints and parametrisation are made where the run's are JAX arrays; where the mesh lives
    on the device, of a window of its worst cells, `jaxci.optim.polish_window`): ``(x, steps, hist)``
    with one step and one history entry per polish round, and ``polish`` (the polish's report) in the history.
    Its work is bounded by `GradientParams.polish_work` kernel passes a cell (whatever the solver and its steps);
    F may end above the method's input's where the worst element fell (`jaxci.metrics.guard.worst_first`: the
    run's final check)."""
    from ..cells import element_blocks
    from .polish import PolishParams, polish

    mesh = problem.mesh
    blocks = element_blocks(mesh)
    n_cells = sum(len(c) for c in blocks.values())
    pp = PolishParams(budget=p.polish_budget, work=p.polish_work * n_cells if p.polish_work > 0 else None,
                      cell_k=int(p.polish_cell_power).bit_length() - 1, mean_steps=p.polish_mean_steps)
    if problem.tables is not None:  # the mesh on the device: the polish on a window of its worst cells
        from ..geometry.device_constraints import as_float64
        from .polish_window import put_back, window

        with jax.enable_x64(True):
            x = as_float64(x)
            win = window(x, problem.conn, problem.cons, par, problem.tables)
            y, report = polish(None, win.cons, win.par, win.x, pp, win.blocks, win.rest)
            return put_back(x, win, y), steps + int(report["rounds"]), _polish_history(hist, report)
    x = np.asarray(x, np.float64)
    cons = problem.host_cons  # shared with the run's final check
    if problem.host and np.asarray(par.x0).dtype == np.float64:
        hpar = par
    else:
        hpar = make_parametrisation(mesh, problem.info, cons, x, scaled=p.scaled, dtype=np.float64)
    y, report = polish(mesh, cons, hpar, x, pp, blocks)
    return np.asarray(y, np.asarray(x).dtype), steps + int(report["rounds"]), _polish_history(hist, report)


def _polish_history(hist: dict, report: dict) -> dict:
    """The run's history with the polish's rounds appended (F and max kappa/3 after each) and its report."""
    hist = {**hist, "polish": {k: v for k, v in report.items() if k not in ("objective", "max_condition")}}
    hist["objective"] = np.concatenate([np.asarray(hist["objective"], np.float64), report["objective"]])
    hist["max_condition"] = np.concatenate([np.asarray(hist["max_condition"], np.float64),
                                            report["max_condition"]])
    return hist
