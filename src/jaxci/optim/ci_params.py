"""The hyperparameters of Cohort Intelligence (`CIParams`) and their defaults per form, without JAX.

`jaxci.optim.ci` (the compiled sweeps) and `jaxci.optim.host_local` (local CI on the host, which must not import
JAX) both read them; `jaxci.optim.ci` re-exports `CIParams`, `GLOBAL_DEFAULTS` and the pattern move's constants.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping

from ..errors import ConfigError
from . import _params as _p

#: Upper bounds of `CIParams` (a typo must not hang a run or exhaust memory): cohort and variations each, their
#: product (trial positions evaluated at once per node and attempt: batch shapes grow with it), loop bounds
#: (attempts, sweeps, patience), interval widths (fractions of the local edge length).
MAX_COHORT, MAX_TRIALS, MAX_LOOP, MAX_WIDTH, MAX_ANDERSON = 256, 4096, 1_000_000, 1e3, 64


@dataclasses.dataclass(frozen=True)
class CIParams:
    """Hyperparameters of Cohort Intelligence (both forms). Validated on construction (`ConfigError`: types,
    finite values, ranges; an integral float counts as an int).

    Each form has its own defaults: the field defaults below are local CI's (``"ci"``); global CI
    (``"ci-global"``) replaces some of them (`GLOBAL_DEFAULTS`). `CIParams.for_method` builds either, and every
    entry point (`jaxci.smooth`, ``jaxci smooth --method ci-global``, YAML configs) goes through it, so a field the
    user does not give takes its method's default.

    The local defaults (C = 3, t = 3, 8 attempts per colour visit with intervals shrunk by r = 0.65 per attempt:
    72 trial positions per node and sweep) were chosen by measurement with Anderson acceleration on
    (2026-11-26, 0d041f1): against the earlier C = t = 4, 10 attempts at r = 0.7 (160 trials) they
    reach the target (max kappa/3 <= 1.0001 on perturbed boxes, F within 1% of L-BFGS's elsewhere) sooner on every
    mesh measured (10^3 and 20^3 boxes 6.0x and 9.6x L-BFGS's time -> 3.5x; pave3 3.1x -> 1.9x; tet-to-hex sphere
    and bracket 1.1-1.4x -> 0.5-0.8x; annulus 3.6x -> 2.4x) with the same final quality, and stay within 1% of
    L-BFGS's F after 30 sweeps on pave3 for 8 seeds out of 8 (0.0-0.4%; C = t = 3 with 6 attempts: 0.6-1.1%).
    (Before that, 10 attempts at r = 0.7 against 4 at r = 0.8 halved the sweeps; on the compiled path C = 6, t = 8
    needed the same number of sweeps as C = t = 4 at 5-8x the cost.)

    Fields (default local / global where they differ):

    - `cohort`: C, candidates per cohort (default 3 / 5; 2 to 256).
    - `variations`: t, variations sampled per candidate and attempt (default 3 / 5; 1 to 256; C t <= 4096).
    - `reduction`: r in (0, 1), interval shrink factor per learning attempt (default 0.65 / 0.998).
    - `delta`: > 0, regulariser of the follow probabilities 1/(g + delta) (default 1e-3).
    - `attempts`: learning attempts per cohort run (local: per colour visit, default 8; global: total, default
      1000; at most 10^6, as `max_sweeps` and `patience`).
    - `stage_switch`: fraction in [0, 1] of the attempts that follow by roulette (stage 1); the rest follow the
      best (stage 2). Default 0.5 / 0.2.
    - `init_width`: initial interval width as a fraction of the local edge length h (default 0.5 / 0.03).
    - `min_width`: local CI: smallest interval width, fraction of h (default 1e-6).
    - `max_sweeps`: local CI: maximum colour sweeps (default 200).
    - `tol`: saturation: relative change of F per sweep (local) or spread of behaviours (global) (default 1e-6).
    - `atol`: local CI: also stop once a sweep lowers F by at most ``tol F + atol`` (F is dimensionless; default
      1e-7). Without it a perturbed 20^3 box, at max kappa/3 1.00007 after 10 sweeps, swept on to the cap of 120
      (114 s) as F fell geometrically towards 0 (`tol` alone is relative).
    - `ftol`: stop when F <= ftol (default 1e-10).
    - `ktol`: local CI: also stop once max kappa/3 <= 1 + ktol (default 1e-6): every corner within ktol of an ideal
      one, the global minimum (as `jaxci.optim.gradient_params.GradientParams.ktol`; 0: only a numerically
      perfect mesh).
    - `patience`: global CI: saturation must hold for this many consecutive attempts (default 20).
    - `pattern`: local CI: after every sweep, a pattern move along the sweep's displacement D (Hooke & Jeeves):
      the mesh ``x + a D`` for each factor a of `PATTERN_FACTORS`, projected onto the boundary, is evaluated
      (one cohort along one line) and the best taken where it lowers F without letting max kappa/3 - 1 grow by
      more than `EXCESS_GROWTH` (default True).
    - `anderson`: local CI: Anderson acceleration over the last `anderson` sweeps (0: none; default 8, at most
      64; `jaxci.optim._anderson`): after the pattern move, the combination of the last sweeps' starts and
      displacements that best cancels their displacements, projected, is evaluated and taken where it lowers F
      on the same condition (`EXCESS_GROWTH`).
      Measured on pave3 after untangling (30 sweeps, 8 seeds, the C = t = 4 cohorts): F 0.6-1.3% above L-BFGS's
      final F without it, 0.1-0.4% below it with 8; perturbed boxes stop after as many sweeps either way.
    - `backend`: CI on a hexahedral mesh: ``"auto"`` (default: the engine `jaxci.interface.engine.resolve_plan`
      picks; for local CI on a CPU the host, numpy and C, nothing to compile, up to
      `jaxci.optim.host_local.HOST_LOCAL_MAX` hexahedra where the C kernels are built; for global CI the host
      too, unless several seeds run as one batched program), ``"numpy"`` (always on the host) or ``"jax"``
      (always compiled). Same algorithm (`tests/test_ci_parity.py`), different random streams.
    """

    cohort: int = 3
    variations: int = 3
    reduction: float = 0.65
    delta: float = 1e-3
    attempts: int = 8
    stage_switch: float = 0.5
    init_width: float = 0.5
    min_width: float = 1e-6
    max_sweeps: int = 200
    tol: float = 1e-6
    atol: float = 1e-7
    ftol: float = 1e-10
    ktol: float = 1e-6
    patience: int = 20
    pattern: bool = True
    anderson: int = 8
    backend: str = "auto"

    def __post_init__(self):
        L = "CI"
        _p.normalise(
            self,
            cohort=_p.integer(L, "cohort", self.cohort, 2, MAX_COHORT),
            variations=_p.integer(L, "variations", self.variations, 1, MAX_COHORT),
            reduction=_p.real(L, "reduction", self.reduction, 0, 1, lo_open=True, hi_open=True),
            delta=_p.real(L, "delta", self.delta, 0, lo_open=True),
            attempts=_p.integer(L, "attempts", self.attempts, 1, MAX_LOOP),
            stage_switch=_p.real(L, "stage_switch", self.stage_switch, 0, 1),
            init_width=_p.real(L, "init_width", self.init_width, 0, MAX_WIDTH, lo_open=True),
            min_width=_p.real(L, "min_width", self.min_width, 0, MAX_WIDTH, lo_open=True),
            max_sweeps=_p.integer(L, "max_sweeps", self.max_sweeps, 1, MAX_LOOP),
            tol=_p.real(L, "tol", self.tol, 0),
            atol=_p.real(L, "atol", self.atol, 0),
            ftol=_p.real(L, "ftol", self.ftol, 0),
            ktol=_p.real(L, "ktol", self.ktol, 0),
            patience=_p.integer(L, "patience", self.patience, 1, MAX_LOOP),
            pattern=_p.boolean(L, "pattern", self.pattern),
            anderson=_p.integer(L, "anderson", self.anderson, 0, MAX_ANDERSON),
            backend=_p.choice(L, "backend", self.backend, _p.BACKENDS),
        )
        if self.min_width > self.init_width:
            raise ConfigError(f"CI parameter min_width must be <= init_width ({self.init_width:g}), "
                              f"got {self.min_width!r}")
        if self.cohort * self.variations > MAX_TRIALS:
            raise ConfigError(f"CI parameters cohort x variations = {self.cohort} x {self.variations} trial "
                              f"positions per node and attempt must be at most {MAX_TRIALS}")

    @classmethod
    def for_method(cls, method: str = "ci", **params) -> CIParams:
        """The parameters of CI form `method`: ``"ci"`` (local, the field defaults) or ``"ci-global"`` (the
        paper's, `GLOBAL_DEFAULTS` over the field defaults), with `params` (field names) over its defaults.

        The one source of CI defaults: `jaxci.interface.smooth.method_params` (hence `jaxci.smooth`, ``jaxci smooth``
        and ``jaxci run``) and `jaxci.experiments.config`'s up-front check build CI parameters here. Raises
        `ConfigError` for another method or a bad value, `TypeError` for an unknown field
        (`jaxci.optim._params.make_params` names it first)."""
        if method not in METHOD_DEFAULTS:
            raise ConfigError(f"CI parameters: unknown CI method {method!r}; choose one of "
                              f"{', '.join(map(repr, METHOD_DEFAULTS))}")
        return cls(**{**METHOD_DEFAULTS[method], **params})


#: Global CI's defaults where they differ from the field defaults of `CIParams` (local CI's): the paper's
#: algorithm (two stages, roulette then follow-the-best; greedy; intervals shrunk by a constant factor) with the
#: budget and schedule measured on its three cubes, 30 seeds each (docs/results/paper_global_ci.md; the paper
#: gives none of them): 5 candidates x 5 variations (25 evaluations of F per attempt) and 1000 learning attempts,
#: initial intervals 0.03 h wide per free coordinate, shrunk by 0.998 per attempt (to 13.5% at attempt 1000;
#: 0.995, the earlier configs' value, shrank them to 0.7% and stalled cube729 near max kappa/3 1.6), roulette
#: for the first 20% of the attempts, then everyone follows the best: the paper's "after few learning attempts,
#: all candidates follow global best" (following the best converges faster than the roulette, whose
#: probabilities 1/F are nearly uniform over a cohort of close behaviours).
GLOBAL_DEFAULTS: Mapping[str, float] = types.MappingProxyType(
    {"cohort": 5, "variations": 5, "reduction": 0.998, "attempts": 1000, "stage_switch": 0.2, "init_width": 0.03})

#: The defaults of each CI form: method name -> the fields that differ from `CIParams`'s own (read-only).
METHOD_DEFAULTS: Mapping[str, Mapping[str, float]] = types.MappingProxyType(
    {"ci": types.MappingProxyType({}), "ci-global": GLOBAL_DEFAULTS})


def ci_params(method: str, params: Mapping) -> CIParams:
    """`CIParams.for_method` from a mapping of the user's parameters (`params`: field names to values), checked
    as `jaxci.optim._params.make_params` checks them: an unknown name is listed with the valid ones, and every
    `ConfigError` names `method` (``"ci"`` or ``"ci-global"``). `jaxci.interface.smooth.method_params` calls it."""
    if method not in METHOD_DEFAULTS:
        CIParams.for_method(method)  # the error naming the CI methods
    if isinstance(params, Mapping):  # else make_params says what is wrong with it
        params = {**METHOD_DEFAULTS[method], **params}
    return _p.make_params(CIParams, params, method)


#: The factors a of local CI's pattern move ``x + a D`` (D the last sweep's displacement): a sweep moves every
#: node towards its local optimum given its neighbours (a nonlinear Gauss-Seidel step), so it removes local error
#: fast and smooth, long-wavelength error slowly, each sweep moving the mesh a little further along nearly the
#: same D; a step of a few to a few tens of D removes that error at once.
PATTERN_FACTORS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)

#: How much local CI's extrapolations (the pattern and Anderson moves) may let the worst corner's excess
#: max kappa/3 - 1 grow: a trial mesh is taken only where it lowers F and its excess is at most this many times the
#: current one's. Without a bound the worst corner jumped from sweep to sweep while F fell (a 60^3 box passed
#: 1.00006 and ended at 1.00013); with 1.5 (perturbed boxes 10^3-60^3, 411249d) 1.0001 comes after 9-12 sweeps
#: instead of 9-15 and the runs end at 1.000001-1.000004, where the curved and paved meshes (excess 0.2-2) take
#: the same steps as without it; 1 (the excess never grows) held annulus back (F within 1% of L-BFGS's after 160
#: sweeps instead of 62).
EXCESS_GROWTH = 1.5


def excess_within_bound(k, ky):
    """Whether a trial's max kappa/3 `ky` keeps the worst corner's excess within `EXCESS_GROWTH` times that of the
    current max `k` (floats or arrays: the host's `_Sweeper.best_of` and the compiled `jaxci.optim.ci._better`)."""
    return ky - 1.0 <= EXCESS_GROWTH * (k - 1.0)


def pattern_choice(f, k, fy, ky, xp):
    """The trial the pattern move takes, both engines: an index into `fy`, `ky` ``(m,)`` (F and max kappa/3 of
    the projected trials ``x + a D``, a in `PATTERN_FACTORS` in order, the first m of them), or -1 for none. Along
    the line F has one minimum, so the trials after the first whose F is not below its predecessor's (or `f`, F at
    the current mesh, for the first) are not considered; of the others the lowest F that is finite, below `f` and
    keeps the worst corner's excess within bound (`excess_within_bound` of the current max `k`), the first of equal
    ones. The host (`jaxci.optim.host_local`) evaluates the trials in order and stops at that first rise (1-4
    evaluations a sweep on the boxes and pave3 instead of 6), the compiled sweep (`jaxci.optim.ci`) evaluates all
    six at once: the same pick. `xp`: the array module."""
    fy, ky = xp.asarray(fy), xp.asarray(ky)
    idx = xp.arange(fy.shape[0])
    rise = ~(fy < xp.concatenate([xp.reshape(xp.asarray(f, fy.dtype), (1,)), fy[:-1]]))
    last = xp.min(xp.where(rise, idx, fy.shape[0] - 1))  # the last trial considered
    ok = (idx <= last) & xp.isfinite(fy) & (fy < f) & excess_within_bound(k, ky)
    best = xp.argmin(xp.where(ok, fy, xp.inf))
    return xp.where(ok[best], best, -1)


def sweep_done(f_prev, f, k, moved, ftol, tol, atol, ktol):
    """Whether local CI stops after a sweep, both engines (floats or arrays): F at most `ftol`, or a decrease
    from `f_prev` of at most ``tol f_prev + atol``, or no node `moved`, or the worst corner `k` (max kappa/3)
    within `ktol` of an ideal one."""
    return (f <= ftol) | (f_prev - f <= tol * f_prev + atol) | (moved == 0) | (k <= 1.0 + ktol)
