"""The parameters of the gradient baselines (`GradientParams`) and their method names: importable without JAX
(`jaxci.interface.methods` checks a configuration with them before anything is compiled). The methods themselves are
`jaxci.optim.gradient`'s.
"""

from __future__ import annotations

import dataclasses

from ..errors import ConfigError
from . import _params as _p

#: Method names of this module.
METHODS = ("bfgs", "lbfgs", "cg", "lm", "gauss-newton")
#: The least-squares methods (dense Jacobian, small meshes only).
LEAST_SQUARES = ("lm", "gauss-newton")

#: What the solvers minimise (`GradientParams.objective`), and the largest p-mean power.
OBJECTIVES = ("mean", "pmean")
MAX_POWER = 64.0

#: Initial inverse Hessians of the host L-BFGS, preconditioners of truncated Newton (`GradientParams.precondition`).
PRECONDITIONERS = ("auto", "none", "coarse")

#: Solvers of ``"lbfgs"`` (`GradientParams.solver`).
SOLVERS = ("lbfgs", "newton", "auto")
#: Most CG products per Newton iteration (`GradientParams.cg_max`).
MAX_CG = 10_000

#: The worst-element polish's work bound, kernel passes over the mesh's cells (`GradientParams.polish_work`; 0:
#: none; chosen by measurement, `jaxci.optim.polish`), and its upper bound.
POLISH_WORK, MAX_POLISH_WORK = 1000.0, 1e6
#: The polish's mean phase: L-BFGS steps on the mean element's measure before its rounds
#: (`GradientParams.polish_mean_steps`; 0: none; chosen by measurement, `jaxci.optim.polish`).
POLISH_MEAN_STEPS = 100
#: Most escape rounds (`GradientParams.escape`).
MAX_ESCAPE = 100

#: Nonlinear CG beta formulas (`optx.NonlinearCG(method=...)`).
CG_METHODS = ("polak_ribiere", "fletcher_reeves", "hestenes_stiefel", "dai_yuan")

#: Upper bounds of `GradientParams` (a typo must not hang a run or exhaust memory): solver steps (the history
#: arrays have max_steps + 1 entries), L-BFGS memory and restarts, free coordinates of the dense least-squares
#: Jacobian (8 N residuals x max_free, 8 bytes each: 10,000 free coordinates of a mesh of ~3,300 hexahedra is
#: already 2 GB), smart-Laplace presmoothing sweeps.
MAX_STEPS, MAX_HISTORY, MAX_FREE, MAX_PRESMOOTH = 1_000_000, 1000, 10_000, 100_000
#: The L-BFGS memory where `GradientParams.history_length` is not given (`history_pairs`).
DEFAULT_HISTORY = 10


@dataclasses.dataclass(frozen=True)
class GradientParams:
    """Hyperparameters of the gradient baselines. Validated on construction (`ConfigError`).

    - `max_steps`: most solver steps (objective evaluations), default 2000 (1 to 10^6).
    - `rtol`, `atol`: optimistix's Cauchy termination (change of the scaled unknowns AND of the scaled objective
      between accepted steps), default 1e-6 each (see the module docstring for the evidence); jaxci's L-BFGS
      also stops where the objective's change is within them after a step the line search had to cut 8 times
      (`jaxci.optim.lbfgs.converged`: a kink of the objective along the direction).
    - `ftol`: also stop as soon as F <= ftol (default 0: only at a perfect mesh).
    - `ktol`: also stop as soon as max kappa/3 <= 1 + ktol (default 1e-6): every corner is then within ktol of an
      ideal one, the global minimum of F and of the max (kappa/3 >= 1), and further steps change no printed
      figure (0: only at a numerically perfect mesh). On a perturbed 60^3 box after untangling, float32 L-BFGS
      reached max kappa/3 1.000001 at step 38 and then took 67 more steps down to 1.0000002 (F at its float32
      floor, 1.4e-8); float64 L-BFGS took 363 steps in all, F down to 2e-12.
    - `history_length`: L-BFGS memory, in pairs (default None: 10, and on the host engine 5 from
      `jaxci.optim.host.HISTORY_F16_FROM` unknowns, `history_pairs`).
    - `cg_method`: beta formula of nonlinear CG, one of `CG_METHODS` (default ``"polak_ribiere"``).
    - `scaled`: unknowns in units of the local edge length (default True; False: raw coordinate displacements).
    - `restarts`: most restarts of the solver from its last iterate with a fresh state (default 3; see the module
      docstring): a run ending with F above ``restart_tol`` times the input's F (default 1e-6) is restarted, the
      second and later restarts only while the previous run lowered F by more than that. `max_steps` bounds the
      steps of all runs together.
    - `max_free`: least squares only: refuse more free coordinates than this (default 1000; at most 10,000).
    - `gradient`: ``"closed"`` (`objective_and_grad`, default) or ``"autodiff"`` (`jax.grad`).
    - `max_move`: BFGS, L-BFGS, CG: the largest trial move of one free coordinate per step, in local edge lengths
      (default 0.5; 0: no cap): the search direction is shortened to it before the line search.
    - `gn_search`: Gauss-Newton only: ``"armijo"`` (default: backtracking Armijo line search on the Gauss-Newton
      direction) or ``"none"`` (`optx.GaussNewton` as shipped, full steps: it inverts elements at once on the
      perturbed cubes and stops there).
    - `residual`: least squares only: ``"excess"`` (default, ``sqrt((kappa/3)^2 - 1)`` per corner, zero at the
      optimum) or ``"kappa"`` (``kappa/3``); see the module docstring.
    - `presmooth`: sweeps of the smart Laplacian (`jaxci.optim.laplace`) before the solver (default 0: none). The
      smart Laplacian lowers F node by node, so a few sweeps take out the near-degenerate corners of a badly
      shaped input locally, where a solver with one global line search has to shorten every step for them
      (measured on perturbed boxes, amplitude 0.3, float32: at 10^6 elements L-BFGS alone needed 1152 steps to
      max kappa/3 <= 1.0001, half its trials rejected; after 3 sweeps (max kappa/3 149,452 -> 1.0047) it needs 10).
    - `buckets`: BFGS, L-BFGS, CG on a hexahedral mesh: run the problem padded to its size class
      (`jaxci.optim._buckets`; default True), so that meshes of similar size share one compiled solver loop and
      the persistent compilation cache; the padding changes no result beyond rounding (False: exact shapes).
    - `backend`: L-BFGS on a hexahedral mesh: ``"auto"`` (default: numpy in float64, no compilation, up to
      `jaxci.optim.host.HOST_MAX` elements; the compiled loop above), ``"numpy"`` (`jaxci.optim.host`, any size)
      or ``"jax"`` (the compiled loop). Other methods and mixed meshes always run compiled.
    - `objective`: BFGS, L-BFGS, CG: ``"mean"`` (default: F, Eq. 3.1, the mean of the corner
      excesses ``e = (kappa/3)^2 - 1``) or ``"pmean"`` (``M_p = (mean e^p)^(1/p)``,
      `jaxci.metrics.hexahedron.pmean_objective`: the worst corners weigh more, the worst element is pulled harder); `p`
      its power (default 2, 1 to 64; ``p = 1`` is F). The history's ``objective`` is then M_p. Measured (float64 L-BFGS,
      to convergence): a perturbed 6^3 box with its boundary fixed, max kappa/3 3.63 (mean) -> 3.10 / 3.06 (p = 2 / 4;
      mean kappa/3 1.084 -> 1.102 / 1.140; 49 -> 191 / 2000 steps: p = 4 ran to the step cap); a wavy annulus (curved
      walls) 1.401 -> 1.319 / 1.287 (mean 1.2226 -> 1.2232 / 1.2240). p = 2 takes most of the gain at a fraction of the
      steps and of the cost in mean quality.
    - `precondition`: the initial inverse Hessian of L-BFGS on the host (numpy) path: ``"auto"`` (default:
      ``gamma I``, and ``gamma M`` from step `jaxci.optim.coarse.AUTO_AFTER` on, M the two-level Laplacian
      preconditioner of `jaxci.optim.coarse`: a run that is still going there is one whose boundary nodes creep
      along curved walls), ``"coarse"`` (``gamma M`` from the start; refused elsewhere than on the host
      L-BFGS and truncated Newton) or ``"none"`` (``gamma I`` throughout); for ``solver="newton"``, CG's
      preconditioner (M from the first step with ``"auto"`` or ``"coarse"``). See `jaxci.optim.coarse` for the
      figures.
    - `solver`: ``method="lbfgs"``: ``"lbfgs"`` (default, `jaxci.optim.host.lbfgs`, `jaxci.optim.lbfgs.lbfgs_loop`)
      or ``"newton"`` (truncated Newton: CG on Hessian-vector products by differences of the gradient, with the
      same line search and stops, its preconditioner the two-level M of `precondition`, from the first step with
      ``"auto"``; on the host `jaxci.optim.newton.newton_cg`, on the JAX engine `jaxci.optim.newton.newton_loop`,
      one compiled program, without M in a run whose mesh is on the device; refused sharded over devices), or
      ``"auto"`` (the default pipeline's on the JAX engine): ``"newton"`` where its M is built (the JAX engine on
      one device with the mesh on the host, a hexahedral mesh, `precondition` not ``"none"``, at most
      `jaxci.optim.coarse.AUTO_MAX_CELLS` cells or ``"coarse"``), else ``"lbfgs"`` (the host engine: its Newton
      left the 25k cylinder O-grid in a worse minimum). The result's ``params["solver"]`` is the one that ran.
      Measured on the real-mesh corpus: docs/results/bench_solvers.md.
    - `newton_after`: ``solver="newton"``: L-BFGS (as ``solver="lbfgs"``) for this many steps, then Newton from its
      iterate (default 0: Newton from the start; its start is in the history's ``restarts``); a run that L-BFGS
      ends sooner is L-BFGS's (its ``params["solver"]`` ``"lbfgs"``). The default pipeline on the host engine
      asks for ``solver="newton"`` with `jaxci.interface.methods.AUTO_NEWTON_AFTER` (200).
    - `cg_max`: ``solver="newton"``: the most CG products (gradient evaluations) per Newton iteration (default 20).
    - `escape`: L-BFGS on the host engine, hexahedral meshes: after the solve, up to this many rounds of local CI
      sweeps and the solver again where one sweep lowers F by 1% or more: the solver's minimum was one for small
      moves only (`jaxci.optim.escape`; default 0: none, as in the default pipeline, `jaxci.interface.methods.
      AUTO_ESCAPE`).
    - `polish`: with ``objective="mean"``: after the solve, the worst-element polish of
      `jaxci.optim.polish` (the worst element lowered level by level, moving only the nodes of the elements
      above the level, F kept as low as the level allows; on the host whatever the engine). Default False:
      ``method="lbfgs"`` is plain L-BFGS; the default pipeline (``method="auto"``) turns it on.
    - `polish_budget`: the most the polish may raise the mean element quality (the mean over the cells of each
      cell's worst corner kappa/3), as a fraction of it (default 0.01; 0 to 1).
    - `polish_work`: the polish's work bound, in kernel passes over the mesh's cells (a gradient evaluation of
      the solve is one pass over every cell; a step of a polish sub-problem two over its cells): default 1000
      (`POLISH_WORK`), the same whatever the solver; 0: no bound. Measured: docs/results/bench_solvers.md.
    - `polish_cell_power`: what the polish's rounds keep low besides the penalty above their level: 1 (default)
      F's sum over the corners; a power of two P from 2 to 256: each cell's smooth max of its corner terms of
      power P (`jaxci.optim.weighted.cell_measure`), the measure the mean element quality takes (each cell's worst
      corner). Measured (docs/results/bench_solvers.md): P = 32 lowers the worst element on 12 of the 16 real meshes
      the polish works on (up to 1.8%) and raises it on 4 (up to 0.6%).
    - `polish_mean_steps`: the polish's mean phase, before its rounds: this many L-BFGS steps over every free node
      on the sum of each cell's smooth max of its corner terms (P = 32), the measure the mean element quality
      takes, kept where the mean element falls and the worst does not rise; the rounds' budget stays the start's,
      so what the phase takes off the mean is room for the worst element (`jaxci.optim.polish`). Default 100
      (`POLISH_MEAN_STEPS`); 0: none. Its passes over the cells are not in `polish_work`'s bound.
    """

    max_steps: int = 2000
    rtol: float = 1e-6
    atol: float = 1e-6
    ftol: float = 0.0
    ktol: float = 1e-6
    history_length: int | None = None
    cg_method: str = "polak_ribiere"
    scaled: bool = True
    max_free: int = 1000
    restarts: int = 3
    restart_tol: float = 1e-6
    gradient: str = "closed"
    max_move: float = 0.5
    gn_search: str = "armijo"
    residual: str = "excess"
    presmooth: int = 0
    buckets: bool = True
    backend: str = "auto"
    objective: str = "mean"
    p: float = 2.0
    precondition: str = "auto"
    solver: str = "lbfgs"
    cg_max: int = 20
    newton_after: int = 0
    escape: int = 0
    polish: bool = False
    polish_budget: float = 0.01
    polish_work: float = POLISH_WORK
    polish_cell_power: int = 1
    polish_mean_steps: int = POLISH_MEAN_STEPS

    def __post_init__(self):
        L = "gradient-method"
        _p.normalise(
            self,
            max_steps=_p.integer(L, "max_steps", self.max_steps, 1, MAX_STEPS),
            rtol=_p.real(L, "rtol", self.rtol, 0),
            atol=_p.real(L, "atol", self.atol, 0),
            ftol=_p.real(L, "ftol", self.ftol, 0),
            ktol=_p.real(L, "ktol", self.ktol, 0),
            history_length=(None if self.history_length is None
                            else _p.integer(L, "history_length", self.history_length, 1, MAX_HISTORY)),
            cg_method=_p.choice(L, "cg_method", self.cg_method, CG_METHODS),
            scaled=_p.boolean(L, "scaled", self.scaled),
            max_free=_p.integer(L, "max_free", self.max_free, 1, MAX_FREE),
            restarts=_p.integer(L, "restarts", self.restarts, 0, MAX_HISTORY),
            restart_tol=_p.real(L, "restart_tol", self.restart_tol, 0),
            gradient=_p.choice(L, "gradient", self.gradient, ("closed", "autodiff")),
            max_move=_p.real(L, "max_move", self.max_move, 0),
            gn_search=_p.choice(L, "gn_search", self.gn_search, ("armijo", "none")),
            residual=_p.choice(L, "residual", self.residual, ("excess", "kappa")),
            presmooth=_p.integer(L, "presmooth", self.presmooth, 0, MAX_PRESMOOTH),
            buckets=_p.boolean(L, "buckets", self.buckets),
            backend=_p.choice(L, "backend", self.backend, _p.BACKENDS),
            objective=_p.choice(L, "objective", self.objective, OBJECTIVES),
            p=_p.real(L, "p", self.p, 1.0, MAX_POWER),
            precondition=_p.choice(L, "precondition", self.precondition, PRECONDITIONERS),
            solver=_p.choice(L, "solver", self.solver, SOLVERS),
            cg_max=_p.integer(L, "cg_max", self.cg_max, 1, MAX_CG),
            newton_after=_p.integer(L, "newton_after", self.newton_after, 0, MAX_STEPS),
            escape=_p.integer(L, "escape", self.escape, 0, MAX_ESCAPE),
            polish=_p.boolean(L, "polish", self.polish),
            polish_budget=_p.real(L, "polish_budget", self.polish_budget, 0.0, 1.0),
            polish_work=_p.real(L, "polish_work", self.polish_work, 0.0, MAX_POLISH_WORK),
            polish_cell_power=_p.integer(L, "polish_cell_power", self.polish_cell_power, 1, 256),
            polish_mean_steps=_p.integer(L, "polish_mean_steps", self.polish_mean_steps, 0, MAX_STEPS),
        )
        if self.polish_cell_power & (self.polish_cell_power - 1):
            raise ConfigError(f"gradient-method parameter polish_cell_power={self.polish_cell_power} must be a power "
                              "of two (1, 2, 4, ... 256): its cell measure is made by squarings")
        if self.polish and self.objective != "mean":
            raise ConfigError("gradient-method parameter polish=True is for objective='mean' (the p-mean already "
                              "weighs the worst corners); drop one of them")
        if self.escape and self.objective != "mean":
            raise ConfigError(f"gradient-method parameter escape={self.escape} is for objective='mean' (its sweeps "
                              "lower F); drop one of them")
        if self.objective == "pmean" and self.gradient != "closed":
            raise ConfigError("gradient-method parameter objective='pmean' needs gradient='closed' (the p-mean has "
                              "only the closed-form gradient)")
        if self.rtol + self.atol <= 0:
            raise ConfigError(f"gradient-method parameters rtol and atol must not both be 0, got rtol={self.rtol!r}, "
                              f"atol={self.atol!r}")


def history_pairs(p: GradientParams, n_free: int | None = None) -> int:
    """The L-BFGS memory of `p` (`GradientParams.history_length`) for a problem of `n_free` unknowns on the
    host engine (None: on the JAX engine): as given, else 10, or `jaxci.optim.host.LARGE_HISTORY` pairs from
    `jaxci.optim.host.HISTORY_F16_FROM` unknowns."""
    if p.history_length is not None:
        return int(p.history_length)
    from .host import HISTORY_F16_FROM, LARGE_HISTORY

    return LARGE_HISTORY if n_free is not None and n_free >= HISTORY_F16_FROM else DEFAULT_HISTORY
