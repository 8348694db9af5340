"""The objectives the JAX engine's solvers see (`jaxci.optim.gradient`): F of the free coordinates (or the p-mean),
scaled to a per-node sum, with its max kappa/3 and the solvers' own stop, for optimistix's minimisers
(`solver_args`), jaxci's compiled L-BFGS (`value_and_grad_closed`) and the least-squares solvers (one residual per
corner); over hexahedra, or every corner of a mixed mesh.

**Closed-form gradient.** `jaxci.metrics.hexahedron.objective_terms_and_grad` is F, its max and d F / d x in
closed form (per corner d kappa^2 / d columns, accumulated per element node and scattered into the nodes; on a
CPU with the C extension, its kernel `jaxci.metrics.native_grad`). It agrees with `jax.grad` to rounding and is
what the solvers use by default (``GradientParams(gradient="closed")``, through a `jax.custom_jvp`,
`solver_objective`); ``"autodiff"`` is `jax.grad` through the forward kernel (same values to rounding; 1.3-1.5x
slower from 27k elements up, see `jaxci.metrics.hexahedron.objective_and_grad`).
"""

from __future__ import annotations

import functools

import numpy as np

from ..cells import corner_invariants, pmean_weights
from ..metrics import native_grad
from ..metrics.hexahedron import (
    corner_columns,
    gather_corners,
    objective_terms_and_grad,
    squared_condition_from_invariants,
)
from ..metrics.incidence import node_incidence
from ..metrics.objective import extra_barrier, extra_terms, no_extra, objective_and_max
from ..runtime._lazy import compute_platform, jax, jnp
from ._buckets import to_device
from .gradient_params import LEAST_SQUARES, GradientParams
from .parametrisation import Parametrisation

#: Corners one interior node moves (8 elements x 4 corners): the objective seen by the solvers is F * 8N / 32.
_CORNERS_PER_NODE = 32.0


def closed_incidence(conn, n_nodes: int, weight=None, power=None):
    """The node incidences (`jaxci.metrics.incidence.node_incidence`, the platform's `default_form`) with which
    `_objective_closed` sums the XLA kernel's gradient of `conn` ``(8, N)`` over `n_nodes` nodes: built once per
    problem, on the device. None where the C kernel computes the gradient instead (F on a CPU with the
    extension) or the form is the scatter."""
    if power is None and native_grad.available(compute_platform()):
        return None
    return node_incidence(conn, n_nodes, weight)


def _terms_and_grad(points, conn, weight, incidence, power, block, mesh):
    """``(F, max kappa/3, dF/dx)`` for `_objective_closed`: each device's share summed and exchanged once where
    the elements are sharded over `mesh` (F, not the p-mean; the gradient scattered: no `incidence`), else
    `objective_terms_and_grad`."""
    if mesh is not None and power is None and weight is not None:
        from .sharding import sharded_terms_and_grad

        return sharded_terms_and_grad(points, conn, weight, mesh)
    if power is None and native_grad.available(compute_platform()):
        return native_grad.terms_and_grad(points, conn, weight)
    return objective_terms_and_grad(points, conn, weight, power, block, incidence=incidence)


@functools.cache
def _objective_closed():
    """``objective(points, conn, weight, incidence, power, block, mesh) -> (F, max kappa/3)`` from one closed-form
    kernel; F differentiable (the max has a zero tangent). `weight`: None, or ``(N,)`` element weights (0: a
    padding element, `objective_terms_and_grad`); `power` (static): None for F, p for the p-mean
    (`jaxci.metrics.hexahedron.pmean_objective`). A `jax.custom_jvp` built on first use (importing this module
    imports no JAX). `block` (static): elements per block (`jaxci.metrics.hexahedron.objective_terms_and_grad`;
    None: its default; 0: the whole mesh at once). `mesh` (static): None, or the `jax.sharding.Mesh` that `conn`
    and `weight` are sharded over: F (not the p-mean) then by `jaxci.optim.sharding.sharded_terms_and_grad`.
    `incidence`: the node incidences of `conn` (`closed_incidence`; None: the gradient is scattered into the
    nodes)."""

    @functools.partial(jax.custom_jvp, nondiff_argnums=(4, 5, 6))
    def objective(points, conn, weight, incidence, power=None, block=None, mesh=None):
        return _terms_and_grad(points, conn, weight, incidence, power, block, mesh)[:2]

    @objective.defjvp
    def _jvp(power, block, mesh, primals, tangents):
        points, conn, weight, incidence = primals
        f, k, g = _terms_and_grad(points, conn, weight, incidence, power, block, mesh)
        return (f, k), (jnp.sum(g * tangents[0]), jnp.zeros_like(k))

    return objective


def solver_objective(x, conn, closed: bool, extra=None, weight=None, power=None, block=None, mesh=None, incidence=None):
    """F and max kappa/3 of coordinates `x` (``inf`` for an inverted mesh); over every corner of the hexahedra and
    of `extra` (`jaxci.metrics.objective.ExtraCells`, static types) when it has cells. `weight` (hexahedral meshes
    only): None, or ``(N,)`` element weights, 0 for the padding elements of a size class (`jaxci.optim._buckets`): they
    add nothing and F is the mean over the real corners. With `power` and `extra` cells: the p-mean over every
    corner (`mixed_pmean`). `incidence`: the closed form's node incidences (`closed_incidence`)."""
    if power is not None and extra is not None and extra.types:
        return mixed_pmean(x, conn, extra, power)
    if closed:  # one kernel for F, its gradient and the max
        f, kmax = _objective_closed()(x, conn, weight, incidence, power, block, mesh)
    else:  # the hexahedra's F and max from one pass over their corners
        f, kmax = objective_and_max(x, conn, no_extra(), weight)
    if extra is not None and extra.types:
        f, kmax = _mixed_objective(x, 8 * conn.shape[1], f, kmax, extra)
    return f, kmax


def _done(f, kmax, stops):
    """The solvers' own stop (`solve_loop`'s `stop`): F <= ftol, or every corner within ktol of an ideal one
    (max kappa/3 <= 1 + ktol: the global minimum of F and of the max). `stops` = ``(ftol, 1 + ktol)`` (traced:
    one compilation for any tolerances)."""
    return (f <= stops[0]) | (kmax <= stops[1])


def _min_fn(v, args):
    par, conn, s, stops, extra, weight = args
    f, kmax = solver_objective(par.points(v), conn, False, extra, weight)
    return s * f, (f, kmax, _done(f, kmax, stops))


def min_fn_closed(v, args):
    par, conn, s, stops, extra, weight, incidence, power, block, mesh = args
    f, kmax = solver_objective(par.points(v), conn, True, extra, weight, power, block, mesh, incidence)
    return s * f, (f, kmax, _done(f, kmax, stops))


def value_and_grad_closed(v, args, conn, weight, n_dev: int, platform: str, power=None, closed: bool = True):
    """The objective of `jaxci.optim.lbfgs.lbfgs_loop` on one device: ``(s F, its gradient in v, F, max kappa/3)``
    at the free coordinates `v` ``(n,)``. `args`: ``(par, s, extra, incidence)``, the `Parametrisation`, the
    objective's scale (`_scale`), the other cell types (`jaxci.metrics.objective.ExtraCells`) and the closed
    form's node incidences (`closed_incidence`, or None); `power` (static): the p-mean's (None: F); `closed`
    (static): the closed-form kernel's gradient (False: JAX's autodiff of F). `n_dev`, `platform`: unused (one
    device)."""
    del n_dev, platform
    par, s, extra, incidence = args

    def value(v):
        f, k = solver_objective(par.points(v), conn, closed, extra, weight, power, None, None, incidence)
        return s * f, (f, k)

    (val, (f, k)), gv = jax.value_and_grad(value, has_aux=True)(v)
    return val, gv, f, k


def hessian_closed(v, args, conn, weight, power=None, closed: bool = True, step: float = 1e-6):
    """The Hessian of `value_and_grad_closed`'s value at `v` ``(n,)``, as a function ``p -> H p`` ``(n,)``, for
    `jaxci.optim.newton.newton_loop`: `jaxci.optim.newton.newton_cg`'s product, ``J^T (g_x(x + h J p) - g_x(x)) /
    h`` with ``J`` the lift and the boundary's projection linearised at `v` (each node held to its triangle or
    segment), ``g_x`` the node gradient of ``s F``, ``h`` = `step` over ``max |p|``. Costs one node gradient here
    and one a product (the closed form's kernel is not differentiable twice: a C call on CPUs). `args`, `power`,
    `closed`: as `value_and_grad_closed`'s."""
    par, s, extra, incidence = args

    def node_grad(x):
        return jax.grad(lambda x: s * solver_objective(x, conn, closed, extra, weight, power, None, None,
                                                       incidence)[0])(x)

    x, lift = jax.linearize(par.points, v)
    pull = jax.linear_transpose(lift, v)  # J^T: the lift's transpose, without evaluating the points again
    gx = node_grad(x)

    def product(p):
        size = jnp.max(jnp.abs(p), initial=0.0)
        h = step / jnp.where(size > 0, size, 1.0)
        (hp,) = pull((node_grad(x + h * lift(p)) - gx) / h)
        return jnp.where(size > 0, hp, 0.0)

    return product


def _lsq_fn(v, args):
    """Residuals kappa/3 per corner, times sqrt(2 s / n_corners): 0.5 |r|^2 = s (F + 1)."""
    par, conn, s, stops, extra, _ = args
    x = par.points(v)
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(x, conn)))
    valid = det > 0
    k3 = jnp.where(valid, jnp.sqrt(fro2 * adj2) / (3.0 * jnp.where(valid, det, 1.0)), jnp.inf)
    if extra is not None and extra.types:
        return _mixed_residuals(x, k3 * k3, extra, s, stops, excess=False)
    w = jnp.sqrt(2.0 * s / k3.size).astype(k3.dtype)
    k3b = jax.lax.optimization_barrier(k3)
    f = jnp.mean(k3b * k3b) - 1.0
    kmax = jnp.max(k3b)
    return (w * k3).reshape(-1), (f, kmax, _done(f, kmax, stops))


def _lsq_fn_excess(v, args):
    """Residuals sqrt((kappa/3)^2 - 1) per corner, times sqrt(2 s / n_corners): 0.5 |r|^2 = s F (zero at the
    optimum)."""
    par, conn, s, stops, extra, _ = args
    x = par.points(v)
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(x, conn)))
    if extra is not None and extra.types:
        return _mixed_residuals(x, squared_condition_from_invariants(det, fro2, adj2), extra, s, stops, excess=True)
    valid = det > 0
    sdet = jnp.where(valid, det, 1.0)
    # (kappa/3)^2 - 1 = (|A|^2 |adj A|^2 - 9 det^2) / (9 det^2) >= 0; clipped at a tiny floor so that the square
    # root stays differentiable at a perfect corner
    tiny = jnp.finfo(det.dtype).tiny ** 0.5
    ex = jnp.where(valid, jnp.maximum(fro2 * adj2 / (9.0 * sdet * sdet) - 1.0, tiny), jnp.inf)
    w = jnp.sqrt(2.0 * s / ex.size).astype(ex.dtype)
    exb = jax.lax.optimization_barrier(ex)
    f = jnp.mean(exb)
    kmax = jnp.sqrt(1.0 + jnp.max(exb))
    return (w * jnp.sqrt(ex)).reshape(-1), (f, kmax, _done(f, kmax, stops))


def solver_args(method: str, par: Parametrisation, conn, p: GradientParams, extra=None, weight=None,
                n_hex: int | None = None, block: int | None = None, mesh=None, incidence=None):
    """The objective function and its `args` for `solve_loop` (``fn(v, args) -> (value, (F, max kappa/3, stop))``,
    stop: `_done`, F <= ``p.ftol`` or max kappa/3 <= 1 + ``p.ktol``).

    `extra`: the non-hexahedral cells (`jaxci.metrics.objective.ExtraCells`; default none): F is then the mean over
    every corner (`jaxci.metrics.elements.mixed_objective`) and ``s = n_corners / 32``. `weight` ``(N,)`` and `n_hex`:
    the element weights of a padded connectivity (0: padding) and the number of real hexahedra (default: every
    element of `conn` is real). `block`: the closed-form gradient's elements per block (None: its default,
    `jaxci.metrics.hexahedron.GRAD_BLOCK`; 0: the whole mesh at once, as on sharded elements: each device holds
    its own block already). `mesh`: None, or the `jax.sharding.Mesh` `conn` and `weight` are sharded over
    (the closed-form objective then sums each device's share explicitly: `_objective_closed`). `incidence`: the
    node incidences of `conn` for the closed-form gradient (`closed_incidence`, built once per problem; None: the
    gradient is scattered into the nodes).
    """
    extra = no_extra() if extra is None else extra
    n_hex = conn.shape[1] if n_hex is None else n_hex
    dtype = par.x0.dtype
    s = to_device(np.asarray(objective_scale(n_hex, extra)), dtype)
    if method in LEAST_SQUARES:
        fn = _lsq_fn_excess if p.residual == "excess" else _lsq_fn
    else:
        fn = min_fn_closed if p.gradient == "closed" else _min_fn
    args = (par, conn, s, to_device(np.asarray([p.ftol, 1.0 + p.ktol]), dtype), extra, weight)
    if fn is min_fn_closed:  # static (filter_jit): the p-mean's power (one compilation per power), the block, the mesh
        args = (*args, incidence, float(p.p) if p.objective == "pmean" else None, block, mesh)
    return fn, args


def objective_scale(n_hex: int, extra) -> float:
    """s of `solver_args`: the objective the solvers minimise is ``s F`` (a per-node sum, as in the paper)."""
    return (8.0 * n_hex + extra.n_corners) / _CORNERS_PER_NODE


# ---------------------------------------------------------------------------------------------- mixed meshes
def _mixed_objective(x, n_hex: int, f_hex, k_hex, extra):
    """F and max kappa/3 over the `n_hex` hexahedral corners (their F `f_hex`, max `k_hex`) and every corner of
    `extra`; ``inf`` if a corner or a pyramid sub-tetrahedron is inverted."""
    terms = extra_terms(x, extra)
    n = n_hex + sum(t.size for t in terms)
    barrier = extra_barrier(x, extra)
    f = ((f_hex + 1.0) * n_hex + sum(jnp.sum(t) for t in terms)) / n - 1.0 + barrier
    k = k_hex
    for t in terms:
        k = jnp.maximum(k, jnp.sqrt(jnp.max(jax.lax.optimization_barrier(t))))
    return f, k + barrier


def mixed_pmean(x, conn, extra, power: float):
    """The p-mean ``M_p`` of the corner excesses over every corner of the hexahedra `conn` and of `extra`
    (`jaxci.cells.pmean_weights`; differentiated by JAX), and max kappa/3; ``inf`` if a corner or a pyramid
    sub-tetrahedron is inverted."""
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(x, conn)))
    terms = [squared_condition_from_invariants(det, fro2, adj2).reshape(-1)]
    terms += [t.reshape(-1) for t in extra_terms(x, extra)]
    t = jnp.concatenate(terms)
    barrier = extra_barrier(x, extra)
    f, _ = pmean_weights(jnp, t - 1.0, None, power)
    kmax = jnp.sqrt(jnp.max(jax.lax.optimization_barrier(t)))
    return f + barrier, kmax + barrier


def _mixed_residuals(x, hex_terms, extra, s, stops, *, excess: bool):
    """Least-squares residuals over every corner of a mixed mesh from the hexahedra's (kappa/3)^2 `hex_terms`
    ``(8, N)``: kappa/3 (or ``sqrt((kappa/3)^2 - 1)`` when `excess`) times ``sqrt(2 s / n_corners)``, plus one
    residual 0 (``inf`` when a pyramid sub-tetrahedron is inverted). Returns ``(residuals, (F, max kappa/3,
    stop))`` (`_done` with `stops`)."""
    terms = [hex_terms.reshape(-1)] + [t.reshape(-1) for t in extra_terms(x, extra)]
    sq = jnp.concatenate(terms)
    barrier = extra_barrier(x, extra)
    w = jnp.sqrt(2.0 * s / sq.size).astype(sq.dtype)
    sqb = jax.lax.optimization_barrier(sq)
    if excess:
        tiny = jnp.finfo(sq.dtype).tiny ** 0.5
        r = jnp.sqrt(jnp.where(jnp.isfinite(sq), jnp.maximum(sq - 1.0, tiny), jnp.inf))
    else:
        r = jnp.sqrt(sq)
    f = jnp.mean(sqb) - 1.0 + barrier
    kmax = jnp.sqrt(jnp.max(sqb)) + barrier
    return jnp.concatenate([w * r, barrier[None]]), (f, kmax, _done(f, kmax, stops))
