"""L-BFGS in numpy for small hexahedral meshes: the gradient solver without compilation.

On a mesh of a few thousand hexahedra, XLA's compilation of the solver loop costs far more than the solve
(`jaxci smooth` on a 2360-hex mesh, empty compile cache: 2.9 s compiling `solve_loop`, 0.6 s iterating; with a warm
cache still 0.8 s tracing, lowering and loading it). The same algorithm run by numpy in float64 costs about
1 ms per objective-and-gradient evaluation at that size (the closed-form kernel of
`jaxci.metrics.hexahedron.objective_terms_and_grad_np`, with glibc's huge-page tunable of `jaxci.runtime.process`), so
the whole solve takes less than the compilation alone. `jaxci.optim.gradient.minimise` uses it for ``"lbfgs"`` on
hexahedral meshes of at most `HOST_MAX` elements (``GradientParams(backend="auto")``; ``"jax"`` or ``"numpy"``
force one).

The iteration is jaxci's L-BFGS, the JAX engine's too (`jaxci.optim.lbfgs`, whose rules it calls: the capped
trial, the Armijo search, the curvature test of a pair and the Cauchy stop), with the same stops (``F <= ftol``,
`max_rejected` consecutive rejections, the step limit). Every objective evaluation is a step, as there. One
difference: from step 200 (counted over the solver's restarts) of a solve that has not stopped by then, the initial
inverse Hessian becomes the two-level preconditioner of `jaxci.optim.coarse` (``GradientParams.precondition``,
default ``"auto"``; ``"none"`` keeps the compiled loop's ``gamma I``). An inverted corner makes F infinite, so a
trial that inverts an element is rejected like any trial that does not decrease F enough: validity is kept by
construction.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable

import numpy as np

from .. import native
from ..geometry.near import NearProjector, host_constraints
from ..metrics.hexahedron import objective_terms_and_grad_np
from ..runtime.memory import release_free_memory
from ..runtime.phases import stepper
from ._params import MAX_REJECTED_UNCAPPED, UNTANGLE_HISTORY
from .lbfgs import DECREASE, armijo, calm_steps, cap_factor, converged, curvature_ok
from .parametrisation import Parametrisation, lift_points, lift_transpose_np

#: Largest hexahedral mesh `jaxci.optim.gradient.minimise` solves in numpy with ``backend="auto"``: 100,000
#: with the C kernels of `jaxci.native`, 30,000 without. Measured through ``jaxci smooth`` on perturbed boxes
#: (amplitude 0.3, this 2-core CPU; numpy, then compiled with an empty / a warm compile cache). numpy kernels
#: (2026-11-24, 66d2f51): 4913 hexes 1.7 s against 3.0 / 1.8 s; 9261: 2.4 s against 3.3 / 1.8 s, where float32 L-BFGS
#: stalled at max kappa/3 5.5e5 (float64: 1.0000); 17,576: 3.7 s against 3.4 / 2.2 s; cube30_pert (27,000,
#: tangled; machine loaded): 5.2 s against 9.2 / 4.0 s. C kernels (smooth phase): 64,000 hexes
#: 4.4 s against 9.1 / 4.5 s; 125,000: 9.2 s against 12.0 / 7.9 s; cube60_pert (216,000) 23-31 s against 18 s
#: cold. With the smart-Laplace presmoothing on the host too and the stop at max kappa/3 <= 1 + ktol (2eac279)
#: (`jaxci.optim.gradient_params.GradientParams.ktol`): cube60_pert, whole ``jaxci smooth``, 20.1 s (smooth phase
#: 6.9 s, peak 735 MB) against 27.8 s cold (smooth 15.1 s, 7.3 s of it compiling; 1.25 GB) and 20.2 s with a warm
#: compilation cache (smooth 8.2 s). At 10^6 (a 100^3 box, the same pipeline, in process): 41 s, peak 1.6 GB
#: (0.98 GB from 55d02f9 on), no JAX import, against 52 s and 2.74 GB compiled; at 10^7 (215^3) 794 s, peak
#: 14.4 GB (from 55d02f9 on: 755 s, 8.7 GB; docs/results/boxes.md), where the compiled
#: path ran out of this machine's 24 GB: the host path is faster and leaner at every size measured. Above it
#: (or with ``backend="jax"``, e.g. to use an accelerator) the compiled loop after smart-Laplace sweeps.
HOST_MAX = 20_000_000 if native.AVAILABLE else 30_000

#: Largest hexahedral mesh the untangling stage untangles in numpy with ``backend="auto"``: `HOST_MAX` with the
#: C kernels (the L-BFGS host path's limit), 60,000 without. The compiled loop runs in float64 too,
#: so numpy saves its compilation (1-2 s).
#: numpy kernels: cube30_pert (27,000 hexes) 0.7 s against 2.3 s cold, 0.6 s against 0.65 s warm; cube60_pert
#: (216,000, 50 steps) 16.4 s against 12.4 s cold, 9.9 s warm (numpy ~330 ms a step, XLA ~200-250 ms). C
#: kernels (machine loaded; 2026-11-24, 66d2f51): cube60_pert 8.4 s against 12.3 s cold.
UNTANGLE_HOST_MAX = HOST_MAX if native.AVAILABLE else 60_000

#: From this many free coordinates (about 80,000 hexahedra) the host L-BFGS memory holds its pairs in float16, each
#: vector times a power of two that puts its largest entry in [2^14, 2^15) (relative rounding 2^-11; entries down to
#: 2^-29 of the largest still normal); the C two-loop recursion reads them through a table of every float16's value
#: and folds the powers of two into its scalars, the sums in float64, and each pair's curvature is that of the
#: stored pair. 120 MB instead of 240 (float32) or 480 MB (float64) at 10^6 hexahedra (10 pairs of 3 M unknowns), the
#: largest part of the run's peak; a step's memory work 24 ms instead of 35 ms (float64) at 680,000 unknowns.
#: Below it every result is as before, bit for bit. Measured against float32 pairs (2026-11-29, 2-core VM, the
#: default pipeline, `jaxci smooth`): a curved annulus of 98,304 hexahedra (its nodes moved along its walls: 294,000
#: unknowns) max kappa/3 1.26052 against 1.26031, the mean element +0.007%, 473 steps against 865, 33 s against 47 s;
#: a perturbed 48^3 box the same 35 steps to max kappa/3 1.0. With the bound lowered so that 7 meshes of the
#: real-mesh corpus (14,000 to 75,000 unknowns) reach it, the worst element moved by -0.30% to +0.56% in two runs
#: (the last bits of the curvature sums, summed in another order, moved it by as much: L-BFGS's path on these
#: meshes is that sensitive; float32 against float64 pairs moved it by -0.85% to +0.16%), the mean element within
#: 0.07%.
HISTORY_F16_FROM = 250_000
#: From this many unknowns a trial whose moving boundary nodes all stay inside their flat regions is evaluated
#: from its free coordinates, each point lifted where a corner reads it (`HostObjective.step`): no array of the
#: points beside the gradient's while F's kernel runs (each node is lifted once per corner that reads it, and the
#: candidate triangles go until a search needs them). Measured 2026-11-30 (AMD EPYC VM, outputs byte-identical):
#: cube60_pert 171.5 -> 166.5-167.5 MB and the 10^6 box 572 -> 545 MB (`jaxci smooth` cold, two runs each); a
#: trial's evaluation on a perturbed 40^3 box 4.8-5.0 ms either way (four runs each, in process, commit 9ef7fd1
#: and the lift's helpers shared with the kernel's). Below it the memory is small, and the path stays the plain one.
LIFTED_FROM = HISTORY_F16_FROM
#: The L-BFGS memory from `HISTORY_F16_FROM` unknowns where none is given (`jaxci.optim.gradient_params.
#: history_pairs`): 5 pairs instead of 10, 13 MB less at 216,000 hexahedra (cube60_pert) and 55 MB at 10^6.
#: Measured 2026-11-30 (AMD EPYC VM, `jaxci smooth` cold, one run each, 10 against 5 pairs): the default pipeline
#: on a tet-to-hex bracket of 93,792 hexahedra max kappa/3 1.9262 / 1.9253, mean 1.34708 / 1.34551, 22.3 / 23.0 s;
#: a tet-to-hex sphere of 105,164 1.9304 / 1.9359, 1.33896 / 1.33966, 17.9 / 17.0 s; the 10^6 box 33 / 35 steps to
#: max kappa/3 1.0000009 / 1.0000008, 23.4 / 21.7 s; `--method lbfgs` on the bracket F 0.80896 / 0.808958 in
#: 796 / 747 steps, on the sphere F 0.786886 both, 743 / 784 steps. (Below it, on meshes of 7,000 to 25,000
#: hexahedra, 6 pairs cost 18-26% more steps.)
LARGE_HISTORY = 5
#: From this many unknowns `lbfgs` gives the C heap's free pages back before its memory fills
#: (`jaxci.runtime.memory.release_free_memory`: 85 MB at 10^6 hexahedra); below it there is little to give back,
#: and the worst-element polish starts a solve every round (0.2 ms each on a part of 2,000 hexahedra).
TRIM_FROM = 100_000


def runs_on_host(backend: str, n_hex: int, limit: int, mixed: bool = False) -> bool:
    """Whether a solver with `backend` (``"auto"``, ``"numpy"``, ``"jax"``) runs in numpy: never on a mesh with
    other cell types or with ``"jax"``, always with ``"numpy"``, with ``"auto"`` up to `limit` hexahedra."""
    if mixed or backend == "jax":
        return False
    return backend == "numpy" or n_hex <= limit


@dataclasses.dataclass
class HostObjective:
    """``value, grad, F, max kappa/3 = self(v)`` in numpy float64 for the scaled free coordinates `v`.

    ``value = s F`` (the scaled objective the compiled path minimises), `grad` its gradient with respect to `v`
    (through the lift's linear map ``B`` and, where a node was projected, the projection onto its triangle's
    plane or its segment's line: the derivative `jax.grad` takes through `jaxci.geometry.projection.project`);
    ``value = inf`` (`grad` None) if a corner is inverted. Node coordinates are ``project(x0 + B (scale v))``
    with the candidate projection of the compiled path (`jaxci.geometry.near.NearProjector`), skipped while every
    moving boundary node is inside its flat region.
    """

    par: Parametrisation
    #: the transposed hexahedra ``(8, N)`` of the default kernel (None with a `kernel` of one's own)
    conn: np.ndarray | None
    s: float
    #: ``(f, k, grad) = kernel(points)`` (default: F, max kappa/3 and dF/dx of the hexahedra `conn`,
    #: `jaxci.metrics.hexahedron.objective_terms_and_grad_np`); the untangling stage passes its energy
    kernel: Callable | None = None
    #: the boundary projection (default a new `NearProjector`; successive objectives may share one)
    projector: NearProjector | None = None
    #: the default kernel's p-mean power (None: F)
    power: float | None = None
    #: keep each evaluation's node gradient before the projection's pullback (`hvp` needs it at the accepted
    #: iterate; `jaxci.optim.newton` sets it): a vector more, kept only where asked for
    keep_raw: bool = False
    #: the default projector's `NearProjector.follow`: whether the boundary nodes' anchors move
    follow_anchors: bool = True

    def __post_init__(self):
        par = self.par
        if self.kernel is None:
            self.kernel = hex_objective_kernel(self.conn, self.power)
        self._cons = host_constraints(par.cons)
        self._x0 = np.ascontiguousarray(par.x0, np.float64)
        self._scale = np.ascontiguousarray(par.scale, np.float64)
        self._flat = np.ascontiguousarray(par.flat_nodes)
        self._origin = np.ascontiguousarray(par.flat_origin, np.float64)
        self._r2 = (0.999 * np.ascontiguousarray(par.flat_radius, np.float64)) ** 2
        corners = np.asarray(self._cons.corner_nodes)
        #: the base holds every CORNER node at its original position: a lifted point's corners need no projection
        self._corners_placed = bool(np.array_equal(self._x0[corners],
                                                   np.asarray(self._cons.x_orig, np.float64)[corners]))
        #: the C form of the lift and its transpose (`jaxci.native.layout`), or None (numpy)
        self._layout = native.layout(self._cons) if native.AVAILABLE else None
        #: the lifted points' source (`jaxci.native.lift_slots`) where the kernel reads them as it goes (F's C
        #: kernel, `hex_objective_kernel`) and a trial with every node inside its flat region needs no array of
        #: them (`step`); else None
        self._slots = None
        #: whether the lift's transpose may write over the node gradient (`jaxci.native.lift_t` in place)
        self._t_inplace = False
        if self._layout is not None:
            self._flat = np.ascontiguousarray(self._flat, np.int64)
            self._t_inplace = not self.keep_raw and bool(np.all(np.diff(self._layout[0]) > 0))
            if (hasattr(self.kernel, "lifted") and self.par.shortcut and not self.keep_raw
                    and len(self._scale) >= LIFTED_FROM):
                self._slots = native.lift_slots(self._layout, len(self._x0))
                self._flat_rows = np.arange(len(self._flat), dtype=np.int64)
                # nor does it search for a node: the candidate triangles go until a search needs them again
                # (`jaxci.geometry.projection.HostConstraints.drop_candidates`: made again, the same numbers)
                if self.projector is None and hasattr(self._cons, "drop_candidates"):
                    self._cons.drop_candidates()
        #: ``(v, points, output, hint, raw gradient)`` of the accepted iterate (`accept`): the projector remembers
        #: each node's last triangle, so the same `v` may land a node on a neighbouring triangle after other
        #: trials; a restart from the accepted iterate and the returned points (`points_of`) are this evaluation's
        self.best = self._last = None

    @functools.cached_property
    def _project(self) -> NearProjector:
        """The boundary projection (`projector`, else a new `NearProjector`), made on first use: a solve whose
        moving boundary nodes all stay inside their flat regions never projects (a box: its tables are 6 MB at
        216,000 hexahedra), nor does most of the worst-element polish's rounds on a part of planar faces."""
        return self.projector or NearProjector(self.par.cons, follow=self.follow_anchors)

    def points(self, v: np.ndarray) -> np.ndarray:
        """Node coordinates ``(n, 3)`` of `v` (float64)."""
        return self._points(v)[0]

    def points_of(self, entry: tuple) -> np.ndarray:
        """The node coordinates ``(n, 3)`` of an evaluation (`best`, or the last one) as it was made: kept where
        it projected a node, else its lift made again (the same numbers: nothing else touched them)."""
        return entry[1] if entry[1] is not None else self._lift(self._x0, entry[0])

    def _points(self, v):
        """``(x, (hint, keep))``: the coordinates of `v`, the projector's triangles and the nodes it left alone
        (None: nothing projected), `_placed`."""
        return self._placed(self._lift(self._x0, v))

    def _placed(self, x):
        """``(x, (hint, keep))`` of lifted coordinates `x` (projected in place). A moving boundary node inside
        its flat region is its own projection: only the others are projected (on a bracket with 79% of its
        boundary nodes on planes, 4/5 of the work)."""
        if self._layout is not None:
            keep = np.zeros(x.shape[0], bool)
            if native.flat_keep(x, self._flat, self._origin, self._r2, keep) == 0 and self.par.shortcut:
                return x, None
        else:
            d = x[self._flat] - self._origin
            inside = np.sum(d * d, axis=-1) < self._r2
            if self.par.shortcut and inside.all():
                return x, None
            keep = np.zeros(x.shape[0], bool)
            keep[self._flat[inside]] = True
        # `x` is the lift's new array, its corners the base's (no free coordinate moves them)
        x, hint = self._project(x, keep, inplace=True, corners_placed=self._corners_placed)
        return x, (hint, keep)

    def accept(self) -> None:
        """The last evaluation is the solver's new iterate (`best`); its nodes' triangles are the projector's
        starting point from now on."""
        self.best = self._last
        if self._last[3] is not None:
            self._project.commit(self._last[3][0])

    def __call__(self, v: np.ndarray):
        best = self.best
        if best is not None and np.array_equal(best[0], v) and (best[4] is not None or not self.keep_raw):
            # a restart from the accepted iterate: the same answer
            self._last = best
            return best[2]
        # a rejected trial's arrays (v, points, gradient: 16 MB at 216,000 hexahedra) go before this one's are made;
        # `accept` only ever takes the evaluation just made
        self._last = None
        # `v` itself, not a copy (one vector less at every evaluation: 5 MB at 216,000 hexahedra): `lbfgs` and
        # `jaxci.optim.newton` never write into an array they have passed here, and a caller of its own must not
        # either
        return self._evaluate(v, *self._points(v))

    def step(self, y: np.ndarray, d: np.ndarray, alpha: float):
        """`__call__` at the trial point ``d * alpha + y`` (its numbers, as numpy makes them) without making it:
        one vector fewer while the kernel runs (5 MB at 216,000 hexahedra; `lbfgs`' trials). The evaluation
        holds no point until `settle` gives it the one its caller made (`accept` needs it)."""
        if self._layout is None:
            t = d * alpha
            t += y
            return self(t)
        self._last = None
        x = inside = None
        if self._slots is not None:  # the flat regions' nodes first: where all stay inside, no array of the points
            xs, moved = native.lift_nodes(self._x0, self._scale, y, d, alpha, self._slots, self._layout, self._flat)
            inside = native.flat_keep(xs, self._flat_rows, self._origin, self._r2,
                                      np.zeros(len(xs), bool)) == 0
        else:
            x, moved = native.lift_step(self._x0, self._scale, y, d, alpha, self._layout)
        best = self.best
        if not moved and best is not None and np.array_equal(best[0], y) and (best[4] is not None
                                                                               or not self.keep_raw):
            self._last = best  # the trial point is the accepted iterate: `__call__`'s restart
            return best[2]
        if inside:
            return self._evaluate(None, None, None, lambda: self.kernel.lifted(self._x0, self._scale, y, d, alpha,
                                                                                self._slots, self._layout))
        if x is None:  # a node left its flat region: the points made, placed on the boundary
            x, _ = native.lift_step(self._x0, self._scale, y, d, alpha, self._layout)
        return self._evaluate(None, *self._placed(x))

    def settle(self, v: np.ndarray) -> None:
        """The last evaluation (made by `step`) is at `v`, made by the caller with the same numbers."""
        if self._last[0] is None:
            self._last = (v,) + self._last[1:]

    def _evaluate(self, v, x, hint, run=None):
        """The objective at the lifted (and placed) `x` of `v` (`_placed`): ``(value, gradient, F, max kappa/3)``,
        remembered as the last evaluation; `run` (default: the kernel at `x`): the call that makes the kernel's
        ``(f, k, grad)`` there (`step`'s lifted kernel, with no `x`)."""
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            f, kmax, gx = self.kernel(x) if run is None else run()
        if not np.isfinite(f):
            return np.inf, None, f, kmax
        gx_raw = gx
        if hint is not None:
            gx = self._project.pullback(gx, *hint)
        hold_points = hint is not None or self.keep_raw
        if not hold_points:  # gone before the lift's transpose makes its vector (5 MB at 216,000 hexahedra)
            x = None
        gv = self._lift_t(gx, inplace=self._t_inplace and gx.dtype == np.float64 and gx.flags.c_contiguous)
        del gx  # (where not in place: its new vector made, the projected node gradient goes; `hvp` keeps the raw)
        gv *= self.s  # in place: the same product as ``self.s * gv``, without a second vector
        out = self.s * f, gv, f, kmax
        # the points only where projected (or for `hvp`), else `points_of` lifts `v` again: the accepted
        # iterate's points are another vector during every line search, and only its end reads them
        self._last = (v, x if hold_points else None, out, hint, gx_raw if self.keep_raw else None)
        return out

    def hvp(self, p: np.ndarray, step: float) -> np.ndarray | None:
        """``H p`` at the accepted iterate (`best`) by a forward difference of the kernel's gradient, one
        evaluation: ``J^T (g_x(x + h J p) - g_x(x)) / h`` with ``J = P B S`` the lift followed by the linearised
        projection of the iterate (each projected node on its triangle's plane or its segment's line), ``h`` =
        `step` over ``max |p|``. The Hessian of the objective with every boundary node held to its current
        triangle or segment: F's curvature without the kinks of the piecewise-flat boundary, which a difference
        of `__call__`'s gradient would pick up wherever a node sits on a triangle's edge (an original boundary node
        sits on a vertex). None where the step inverts an element."""
        _, _, _, hint, gx = self.best
        x = self.points_of(self.best)
        size = amax(p)
        if size == 0:
            return np.zeros_like(p)
        h = step / size
        dx = self._lift(np.zeros_like(self._x0), p)
        if hint is not None:
            dx = self._project.pullback(dx, *hint)
        dx *= h
        dx += x
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            f, _, gh = self.kernel(dx)
        if not np.isfinite(f):
            return None
        gh = gh - gx
        gh *= self.s / h
        if hint is not None:
            gh = self._project.pullback(gh, *hint)
        return self._lift_t(gh)

    def _lift(self, x0: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``x0 + B (scale v)``: the nodes ``(n, 3)`` of the free coordinates `v` (the C loop where built)."""
        if self._layout is not None:
            return native.lift(x0, self._scale, v, self._layout)
        return lift_points(np, x0, self._scale, self._cons, v)

    def _lift_t(self, gx: np.ndarray, inplace: bool = False) -> np.ndarray:
        """The transpose of `_lift`'s linear part: a node gradient ``(n, 3)`` as one of the free coordinates
        (`inplace`: over `gx`'s own buffer, `jaxci.native.lift_t`, with the C layout)."""
        if self._layout is not None:
            return native.lift_t(gx, self._scale, self._layout, inplace)
        return lift_transpose_np(self._scale, self._cons, gx)


def hex_objective_kernel(conn: np.ndarray, power: float | None = None) -> Callable:
    """``kernel(points) -> (F, max kappa/3, dF/dx)`` of the hexahedra `conn` (transposed, ``(8, N)``): the C
    loop of `jaxci.native` where it is built, else `jaxci.metrics.hexahedron.objective_terms_and_grad_np`; `power` p:
    the p-mean objective instead of F."""
    if native.AVAILABLE:
        hexes = native.as_conn(np.asarray(conn).T)

        def kernel(x):
            return native.hex_terms_and_grad(x, hexes, power)

        if power is None:  # F's kernel also reads points lifted as it goes (`HostObjective.step`)
            kernel.lifted = lambda x0, scale, v, d, alpha, slots, lay: native.hex_terms_and_grad_lifted(
                x0, scale, v, d, alpha, slots, lay, hexes)
        return kernel
    return lambda x: objective_terms_and_grad_np(x, conn, power)


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """``a . b`` of two vectors without BLAS, summed in float64 (also for float32 vectors): OpenBLAS's
    multi-threaded ``ddot`` took 8 ms for 80,000 entries on this 2-core machine under load (its threads spin
    against the other processes) against 0.04 ms here."""
    if a.dtype == b.dtype == np.float64:
        return float(np.einsum("i,i->", a, b))
    return float(np.einsum("i,i->", a, b, dtype=np.float64))


def amax(a: np.ndarray) -> float:
    """``max |a|`` (0 for an empty `a`) without a temporary array."""
    return max(float(a.max(initial=0.0)), -float(a.min(initial=0.0)))


class _Memory:
    """The L-BFGS memory: up to `history` pairs ``(s, y, 1 / s.y)`` in ring buffers ``(history, n)``, float64, or
    float16 from `HISTORY_F16_FROM` unknowns (with the C kernels; `inv_scale` ``(2, history)``: the inverse of each
    row's power of two, S's then Y's). The initial inverse Hessian is ``s.y / y.y`` I of the newest pair, or after
    `use` ``gamma M`` with ``gamma = s.y / y.M y``."""

    def __init__(self, n: int, history: int):
        self.history = history
        self.precond = None  # M (`use`): a fixed symmetric positive definite `jaxci.optim.coarse.CoarseSpace`
        self.gamma = 1.0
        dtype = np.float16 if n >= HISTORY_F16_FROM and native.AVAILABLE else np.float64
        self.inv_scale = np.ones((2, history))
        # all `history` rows at once, never grown: a large np.empty is mapped, not touched, so a row costs memory
        # only once a pair is written to it (growing by concatenation held the old and the new buffers at once:
        # 480 MB more at 10^6 hexahedra, the peak of the run)
        self.S, self.Y = np.empty((history, n), dtype), np.empty((history, n), dtype)
        self.rho = np.zeros(history)
        self.order: list[int] = []  # slots, oldest first

    def stored(self, v: np.ndarray) -> tuple[np.ndarray, float]:
        """A vector of a pair as the memory stores it, ``(row, inverse scale)``: `v` itself (float64 memory), or
        float16 of `v` times the power of two that puts ``max |v|`` in [2^14, 2^15) (`v`, a temporary of the
        caller's, is scaled in place; it may go as soon as this returns)."""
        if self.S.dtype == np.float64:
            return v, 1.0
        top = amax(v)
        k = math.ldexp(1.0, min(15 - math.frexp(top)[1], 1000)) if top > 0 else 1.0  # (finite for any top)
        v *= k
        return v.astype(np.float16), 1.0 / k

    def push(self, s: tuple[np.ndarray, float], y: tuple[np.ndarray, float]) -> None:
        """Store the pair ``(s, y)`` (each from `stored`) if its curvature ``s.y`` (of the pair as stored) is
        clearly positive, in place of the oldest once full."""
        (s, i_s), (y, i_y) = s, y
        # the curvature of the stored pair: rho then matches what the loop reads
        sy, ss, yy = native.half_dots(s, y) if s.dtype == np.float16 else (dot(s, y), dot(s, s), dot(y, y))
        sy, ss, yy = sy * (i_s * i_y), ss * (i_s * i_s), yy * (i_y * i_y)
        if not curvature_ok(sy, ss, yy):
            return
        slot = self.order.pop(0) if len(self.order) == self.history else len(self.order)
        self.S[slot], self.Y[slot], self.rho[slot] = s, y, 1.0 / sy
        self.inv_scale[:, slot] = i_s, i_y
        self.order.append(slot)
        if self.precond is not None:
            self._scale_newest()

    def use(self, precond) -> None:
        """From now on the initial inverse Hessian is ``gamma M`` with `precond` ``M`` (the pairs are kept)."""
        self.precond = precond
        if self.order:
            self._scale_newest()

    def _scale_newest(self) -> None:
        """``gamma = s.y / y.M y`` of the newest pair (as stored)."""
        k = self.order[-1]
        y = self.Y[k].astype(np.float64) * self.inv_scale[1, k]
        self.gamma = 1.0 / (self.rho[k] * dot(y, self.precond(y)))

    def clear(self) -> None:
        self.order.clear()
        self.gamma = 1.0

    def direction(self, g: np.ndarray) -> np.ndarray:
        """``-H g`` by the two-loop recursion (initial inverse Hessian ``s.y / y.y`` I of the newest pair, or
        ``gamma M`` with a preconditioner): the C loop of `jaxci.native` where it is built."""
        pc = self.precond
        if native.AVAILABLE and len(self.order) <= 64:
            out = np.empty_like(g)
            native.lbfgs_direction(g, self.S, self.Y, self.rho, np.asarray(self.order, np.int64), out, self.gamma, pc,
                                   None if self.S.dtype == np.float64 else self.inv_scale)
            return out
        S, Y = self.S, self.Y
        if S.dtype != np.float64:  # float16 pairs (more than 64 of them): in float64, their scales undone
            S, Y = ({k: A[k] * self.inv_scale[i, k] for k in self.order} for i, A in enumerate((S, Y)))
        q = g.copy()
        alphas = []
        for k in reversed(self.order):
            a = self.rho[k] * dot(S[k], q)
            alphas.append(a)
            q -= a * Y[k]
        if pc is not None:
            q = self.gamma * pc(q)
        elif self.order:
            s, y = S[self.order[-1]], Y[self.order[-1]]
            q *= dot(s, y) / dot(y, y)
        for k, a in zip(self.order, reversed(alphas), strict=True):
            b = self.rho[k] * dot(Y[k], q)
            q += (a - b) * S[k]
        return -q


def lbfgs(fun: Callable, y0: np.ndarray | None, *, limit: int, max_rejected: int, rtol: float, atol: float,
          history: int, cap: float, ftol: float, done: Callable | None = None, deadline: float | None = None,
          precond: Callable | None = None, precond_after: int = 0, stage: str | None = "L-BFGS"):
    """Minimise `fun` (a `HostObjective`: ``value, grad, F, max kappa/3 = fun(y)``; its ``accept()``, if any,
    is called once an evaluation becomes the iterate) from `y0` (float64, ``(n_free,)``; None: zeros of
    ``fun.par.n_free``, made here so that nothing holds them once the iterate moves on: 5 MB at 216,000 hexahedra).

    **Arguments:** `limit` the most objective evaluations (steps); `max_rejected` consecutive rejected trials
    that stop the run; `rtol`, `atol` the Cauchy termination; `history` the L-BFGS memory; `cap` the largest
    trial move of one unknown at step size 1 (0: none); `ftol` stop once F <= ftol; `done` (optional): also
    stop once ``done(F, k)`` holds at an accepted iterate (k the second number `fun` reports); `deadline`
    (optional, `time.perf_counter` seconds): stop after the first step past it (result ``"time budget"``);
    `precond` (optional): a function that returns the initial inverse Hessian's ``M``
    (`jaxci.optim.coarse.CoarseSpace`; default I), called once, at the first accepted iterate after
    `precond_after` steps: M is used from then on. `stage`: the name its steps are reported under to the
    running phase's listener (`jaxci.runtime.phases.stepper`: step, F, max kappa/3); None reports nothing.

    **Returns:** ``(y_best, steps, result, hist_f, hist_k)`` as `jaxci.optim.lbfgs.lbfgs_loop`: the accepted
    iterate of lowest finite F, the number of steps, the result's name (``"successful"``,
    ``"nonlinear_max_steps_reached"``, ``"nonfinite"``), and F and max kappa/3 of the accepted iterate after
    each step (entry 0: `y0`), numpy arrays of length ``steps + 1``.
    """
    def finished(f, k):
        return f <= ftol or (done is not None and bool(done(f, k)))

    # never written into (each step makes a new iterate): no copy
    y = np.zeros(fun.par.n_free) if y0 is None else np.asarray(y0, dtype=np.float64)
    if len(y) >= TRIM_FROM:  # the set-up's freed temporaries (presmoothing, parametrisation) before the memory fills
        release_free_memory()
    del y0
    value, g, f, k = fun(y)
    accept = getattr(fun, "accept", lambda: None)
    # a `HostObjective` evaluates a trial without its point made (`HostObjective.step`); any other `fun` at it
    step = getattr(fun, "step", None)
    hf, hk = [f], [k]
    if g is None:
        return y, 0, "nonfinite", np.asarray(hf), np.asarray(hk)
    accept()
    mem = _Memory(len(y), history)

    def capped(d):  # the trial move at step size 1: `d` scaled in place so that no unknown moves more than `cap`
        k = float(cap_factor(amax(d), cap or 0.0))
        if k != 1.0:
            d *= k
        return d

    trial = d = capped(-g)
    slope = dot(g, trial)
    alpha, rejected, steps, result, calm = 1.0, 0, 0, "nonlinear_max_steps_reached", 0
    stop = finished(f, k)
    tick = None if stage is None else stepper(stage)
    while not stop and steps < limit:
        if deadline is not None and time.perf_counter() > deadline:
            result = "time budget"
            break
        if step is not None:
            v_try, g_try, f_try, k_try = step(y, trial, alpha)
        else:
            y_try = trial * alpha
            y_try += y
            v_try, g_try, f_try, k_try = fun(y_try)
        steps += 1
        if g_try is not None and armijo(v_try, value, alpha, slope):
            if step is not None:
                # the trial point made now, in the direction's own vector, and the pair in the old gradient's:
                # four vectors at once here, and while the kernel ran (5 MB each at 216,000 hexahedra)
                trial *= alpha
                trial += y
                y_try = trial
                fun.settle(y_try)
                y_pair = mem.stored(np.subtract(g_try, g, out=g))
                s = np.subtract(y_try, y, out=None if y_pair[0] is g else g)
            else:
                y_pair, s = None, y_try - y
            trial = d = None  # dead once a trial is accepted: its memory goes before the pair's temporaries come
            calm = int(calm_steps(calm, v_try, value, rtol))
            done_here = bool(converged(amax(s), amax(y_try), v_try, value, rtol, atol, alpha, calm))
            s = mem.stored(s)  # a float16 memory's pair: its float64 temporaries one at a time
            mem.push(s, mem.stored(g_try - g) if y_pair is None else y_pair)
            del s, y_pair
            y, value, g, f, k = y_try, v_try, g_try, f_try, k_try
            accept()
            alpha, rejected = 1.0, 0
            if precond is not None and mem.precond is None and steps >= precond_after:
                mem.use(precond())
            d = mem.direction(g)
            if not dot(g, d) < 0:  # not a descent direction: forget the curvature pairs
                mem.clear()
                d = -g
            trial = capped(d)
            slope = dot(g, trial)
            if done_here:
                result, stop = "successful", True
            stop = stop or finished(f, k)
        else:
            g_try = None  # a rejected trial's gradient goes before the next trial's is made (5 MB at 216,000 hexahedra)
            alpha *= DECREASE
            rejected += 1
            stop = rejected >= max_rejected
        hf.append(f)
        hk.append(k)
        if tick is not None:
            tick(steps, f, k)
    if stop and result == "nonlinear_max_steps_reached":
        result = "successful"
    return y, steps, result, np.asarray(hf, np.float64), np.asarray(hk, np.float64)


def untangle_rounds_np(par: Parametrisation, hexes: np.ndarray, inv_len: np.ndarray, *, theta: float,
                       margin: float, max_rounds: int, inner_steps: int, rtol: float, atol: float,
                       deadline: float | None = None, progress: Callable | None = None):
    """The untangling stage's eps rounds (`jaxci.optim._untangle_loop.untangle_rounds`) in numpy float64.

    Each round minimises the regularised Winslow energy at its eps with `lbfgs` (no cap, the round's Armijo
    search and Cauchy test) from the previous round's result, stopping as soon as every corner has
    ``det J >= margin``; between rounds eps follows the schedule of `jaxci.optim.untangle`. The energy and its
    gradient are the compiled path's closed-form kernel (`hex_kernel` with numpy, or its C form
    `jaxci.native.untangle_energy`). Hexahedral meshes only: `hexes` ``(N, 8)``, `inv_len` ``(N,)`` one over each
    element's reference length.
    `deadline` (`time.perf_counter` seconds, optional): no step after it; `progress` (optional): called after
    each round with ``(round, min det J, eps, energy)``.

    **Returns:** ``(v, points, report)``: the scaled free coordinates and the node coordinates ``(n, 3)`` of the
    result (as evaluated: on the boundary), and a dict ``rounds``, ``steps``, ``dmin0``, ``h_eps``, ``h_dmin``,
    ``h_e`` (numpy arrays, one entry per round).
    """
    from ._untangle_loop import CORNERS_PER_NODE, corner_table, hex_kernel, next_eps

    projector = NearProjector(par.cons)
    if native.AVAILABLE:
        hexes, inv_len = native.as_conn(hexes), np.ascontiguousarray(inv_len, np.float64)
    else:
        table, inv_corner = corner_table(hexes), np.tile(inv_len, 8)

    def objective(eps):
        def kernel(x):
            if native.AVAILABLE:
                return native.untangle_energy(x, hexes, inv_len, eps, theta, True, CORNERS_PER_NODE)
            return hex_kernel(x, table, inv_corner, eps, theta, True, np)

        return HostObjective(par, None, 1.0, kernel, projector)

    v = np.zeros(par.n_free)
    fun = objective(1.0)
    _, _, _, dmin0 = fun(v)  # the energy is finite (chi > 0): the evaluation is kept as `_last`
    points = fun.points_of(fun._last)
    eps = float(np.sqrt(1e-12 + 0.04 * min(dmin0, 0.0) ** 2))
    rounds = steps = 0
    h_eps, h_dmin, h_e = [], [], []
    dmin = dmin0
    out_of_time = False
    while dmin < margin and rounds < max_rounds and not out_of_time:
        fun = objective(eps)
        v, k, result, hf, hk = lbfgs(fun, v, limit=inner_steps, max_rejected=MAX_REJECTED_UNCAPPED, rtol=rtol,
                                     atol=atol, history=UNTANGLE_HISTORY, cap=0.0, ftol=-np.inf,
                                     done=lambda f, d: d >= margin, deadline=deadline, stage=None)
        out_of_time = result == "time budget"
        steps += k + 1  # as the compiled loop counts: the round's first evaluation is a step
        rounds += 1
        e_start, e, dmin = float(hf[0]), float(hf[-1]), float(hk[-1])
        points = fun.points_of(fun.best) if fun.best is not None else fun.points(v)
        h_eps.append(eps)
        h_dmin.append(dmin)
        h_e.append(e)
        if progress is not None:
            progress(rounds, dmin, eps, e)
        eps = float(next_eps(eps, e_start, e, dmin, np))
    return v, points, {"rounds": rounds, "steps": steps, "dmin0": float(dmin0), "h_eps": np.asarray(h_eps),
                       "h_dmin": np.asarray(h_dmin), "h_e": np.asarray(h_e), "out_of_time": out_of_time}
