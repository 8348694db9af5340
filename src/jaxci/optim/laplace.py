"""Laplacian and smart Laplacian smoothing: every free node to the centroid of its edge neighbours, by colours.

**Laplacian** (``"laplace"``): a node's target is the mean of the nodes joined to it by a cell edge (each neighbour
once; the edges of hexahedra, and on a mixed mesh of wedges, pyramids and tetrahedra too). The move ``d = centroid
- x`` is restricted to the node's free directions (``B B^T d`` with the move basis of `jaxci.optim._moves`: all of
d inside, its tangent part on a surface, its component along the curve on an edge) and the new position is
projected onto the node's constraint (`project_trials`). Every move is accepted: on a concave region the plain
Laplacian can fold elements, which is what it is compared for.

**Smart Laplacian** (``"smart-laplace"``): the same target, but a node moves only if the sum of (kappa/3)^2 over
the corners it moves (`jaxci.optim._moves.local_sum`: those of every cell type around it) decreases and none of
them inverts; the steps ``1, 1/2, 1/4, ...`` (`LaplaceParams.backtrack` of them) of the move are tried at once and
the longest acceptable one is taken. Nodes of one colour share no element, so F decreases by the sum of the
accepted local decreases: from a valid mesh the smart Laplacian never inverts a corner and never raises F.

Both sweep the colours in turn (Gauss-Seidel by colour, as the local CI does: `ColouredStars`, one batched
evaluation per colour, `jax.lax` loops under one `jax.jit`) until the largest move of a sweep is below
``tol * h`` (h the local edge length of the node that moved) or after `max_sweeps` sweeps. A colour's trials and
the choice among them are written once for both engines (`jaxci.optim._local.laplace_trials`, `longest_step`;
the host engine's sweep: `jaxci.optim.host_local.laplace_np`); the projection and the local objective's kernel are
each engine's own.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ConfigError
from ..geometry.projection import Constraints
from ..metrics.objective import (
    ExtraCells,
    corner_table,
    edge_pairs,
    extra_cells,
    has_extra,
    no_extra,
    objective_and_max,
)
from ..runtime._lazy import jax, jit, jnp
from ..runtime.transfer import program, to_host
from . import _params as _p
from ._buckets import bucket, device_dtype, to_device
from ._local import edge_neighbours, laplace_trials, longest_step, star_coords
from ._moves import (
    ColouredStars,
    colour_slice,
    coloured_stars,
    local_scale,
    local_sum,
    pad_slots,
    padded_sweeps,
    project_trials,
)

#: Method names of this module.
METHODS = ("laplace", "smart-laplace")

#: Most sweeps (the history arrays have max_sweeps + 1 entries): a typo must not hang a run or exhaust memory.
MAX_SWEEPS = 1_000_000


@dataclasses.dataclass(frozen=True)
class LaplaceParams:
    """Hyperparameters of the (smart) Laplacian. Validated on construction (`ConfigError`).

    - `max_sweeps`: most colour sweeps (default 500; 1 to 10^6).
    - `tol`: stop when the largest move of a sweep is below ``tol * h`` (h: local edge length), default 1e-5.
    - `backtrack`: smart Laplacian only: number of step lengths tried, ``1, 1/2, ..., 1/2^(backtrack-1)``
      (default 3; 1: the full step or nothing).
    - `buckets`: on a hexahedral mesh, run the sweeps on the problem padded to its size class
      (`jaxci.optim._buckets`; default True), so that meshes of similar size share one compiled sweep loop and
      the persistent compilation cache; the padding changes no result beyond rounding (False: exact shapes).
    - `backend`: on a hexahedral mesh, ``"auto"`` (default: the sweeps on the host, numpy and C, nothing to
      compile, up to `jaxci.optim.host_local.HOST_LOCAL_MAX` hexahedra where the C kernels are built; compiled
      otherwise), ``"numpy"`` (always on the host) or ``"jax"`` (always compiled).
    """

    max_sweeps: int = 500
    tol: float = 1e-5
    backtrack: int = 3
    buckets: bool = True
    backend: str = "auto"

    def __post_init__(self):
        L = "Laplace"
        _p.normalise(
            self,
            max_sweeps=_p.integer(L, "max_sweeps", self.max_sweeps, 1, MAX_SWEEPS),
            tol=_p.real(L, "tol", self.tol, 0),
            backtrack=_p.integer(L, "backtrack", self.backtrack, 1, 16),
            buckets=_p.boolean(L, "buckets", self.buckets),
            backend=_p.choice(L, "backend", self.backend, _p.BACKENDS),
        )


def _colour_step(x, conn, cs_i, nbr_i, nmask_i, h_i, cons: Constraints, smart: bool, n_steps: int):
    """Move every node of one colour; returns new points and the largest move relative to h (`conn`: the
    hexahedra the stars' incidences refer to, where they are incidences: `jaxci.optim._local.star_coords`)."""
    nodes, mask = cs_i.nodes, cs_i.mask
    safe = jnp.minimum(nodes, x.shape[0] - 1)
    x0 = x[safe]  # (M, 3)
    trials = project_trials(cons, cs_i, laplace_trials(x, x0, nbr_i, nmask_i, cs_i.basis, n_steps, jnp))
    if smart:
        E = star_coords(x, conn, cs_i.star)
        f0 = local_sum(x, cs_i, E, x0[:, None])[:, 0]
        j, accept = longest_step(f0, local_sum(x, cs_i, E, trials), jnp)
        accept = mask & accept
        new = jnp.take_along_axis(trials, j[:, None, None], axis=1)[:, 0]
    else:
        accept = mask
        new = trials[:, 0]
    new = jnp.where(accept[:, None], new, x0)
    move = jnp.linalg.norm(new - x0, axis=-1) / h_i
    x = x.at[nodes].set(new, mode="drop")
    return x, jnp.max(jnp.where(mask, move, 0.0), initial=0.0)  # initial: a mesh with no movable node


@program
@jit(static_argnames=("smart", "p"))
def _laplace_run(x, conn, cs: ColouredStars, nbr, nmask, cons: Constraints, smart: bool, p: LaplaceParams,
                 extra: ExtraCells, weight=None, n_colours=None):
    """The sweeps under one jit. `weight` ``(N,)`` and `n_colours` (traced): for a problem padded to its size
    class, the element weights (0: padding) and the number of real colours (the padded ones are skipped)."""
    n_colours = cs.nodes.shape[0] if n_colours is None else n_colours
    dtype = x.dtype

    def h_colour(i):
        cs_i = colour_slice(cs, i)
        h = local_scale(x, cs_i, star_coords(x, conn, cs_i.star))
        return jnp.where(h > 0, h, 1.0)

    h = jax.lax.map(h_colour, jnp.arange(cs.nodes.shape[0]))  # (n_colours, M)
    f0, k0 = objective_and_max(x, conn, extra, weight)
    hist_f = jnp.full((p.max_sweeps + 1,), jnp.nan, dtype).at[0].set(f0)
    hist_k = jnp.full((p.max_sweeps + 1,), jnp.nan, dtype).at[0].set(k0)
    hist_m = jnp.full((p.max_sweeps + 1,), jnp.nan, dtype).at[0].set(0.0)

    def sweep(carry):
        x, s, _, hf, hk, hm = carry

        def colour(i, c):
            x, mv = c
            x, m = _colour_step(x, conn, colour_slice(cs, i), nbr[i], nmask[i], h[i], cons, smart,
                                p.backtrack if smart else 1)
            return x, jnp.maximum(mv, m)

        x, mv = jax.lax.fori_loop(0, n_colours, colour, (x, jnp.zeros((), dtype)))
        s = s + 1
        f, k = objective_and_max(x, conn, extra, weight)
        hf = hf.at[s].set(f)
        hk = hk.at[s].set(k)
        hm = hm.at[s].set(mv)
        return x, s, mv <= p.tol, hf, hk, hm

    def cond(carry):
        return (carry[1] < p.max_sweeps) & ~carry[2]

    x, s, _, hf, hk, hm = jax.lax.while_loop(cond, sweep, (x, jnp.int32(0), jnp.array(False), hist_f, hist_k, hist_m))
    return x, s, hf, hk, hm


def laplace(points, conn, cs: ColouredStars, nbr, nmask, cons: Constraints, p: LaplaceParams = LaplaceParams(),
            *, smart: bool = False, extra: ExtraCells | None = None, devices=None):
    """Run the (smart) Laplacian from `points` ``(n, 3)``.

    **Arguments:**

    - `points`: start coordinates ``(n, 3)``; `conn`: transposed connectivity ``(8, N)``.
    - `cs`: `ColouredStars` of the mesh (`coloured_stars`); `nbr`, `nmask`: ``(n_colours, M, K)`` edge
      neighbours of the nodes of `cs` and their mask (`coloured_neighbours`).
    - `cons`: the `Constraints`; `p`: `LaplaceParams`; `smart`: the smart variant.
    - `extra`: keyword only; the non-hexahedral cells (`jaxci.metrics.objective.extra_cells`, default none), whose
      corners `cs` must hold too: F in the history is then over every corner.
    - `devices`: keyword only; None (one device) or a `jax.sharding.Mesh` (hexahedral meshes): padded as for
      ``p.buckets``, the elements (F and max kappa/3 of the history) and the node slots of every colour (the
      sweeps' work) sharded over it, the coordinates and constraints replicated
      (`jaxci.optim.sharding.place_problem`).

    **Returns:** ``(points, sweeps, history, params)``: coordinates ``(n, 3)``, the number of sweeps, numpy
    arrays of length ``sweeps + 1`` (entry 0 = input): ``objective`` (F; ``inf`` once an element is inverted),
    ``max_condition`` (max kappa/3, ``inf`` likewise) and ``max_move`` (largest move of the sweep / h); and the
    resolved hyperparameters.
    """
    extra = no_extra() if extra is None else extra
    n = int(points.shape[0])
    if padded(p, devices, extra):  # padded to the size class: one compiled loop
        n_dev = 1 if devices is None else int(devices.devices.size)
        points, conn, cs, nbr, nmask, cons, weight, n_col = _padded(points, conn, cs, nbr, nmask, cons, n_dev)
        if devices is not None:
            from .sharding import place_problem

            conn, weight, (points, cons, n_col), (cs, nbr, nmask) = place_problem(
                conn, weight, (points, cons, n_col), devices, (cs, nbr, nmask))
        x, s, hf, hk, hm = _laplace_run(points, conn, cs, nbr, nmask, cons, bool(smart), p, extra, weight, n_col)
        x = to_device(np.asarray(x)[:n])  # sliced on the host: no compilation
    else:
        x, s, hf, hk, hm = _laplace_run(points, conn, cs, nbr, nmask, cons, bool(smart), p, extra)
    s = int(s)
    hist = {"objective": np.asarray(hf)[: s + 1], "max_condition": np.asarray(hk)[: s + 1],
            "max_move": np.asarray(hm)[: s + 1]}
    return x, s, hist, {"method": "smart-laplace" if smart else "laplace", **dataclasses.asdict(p)}


def laplace_device(data, p: LaplaceParams = LaplaceParams(), *, smart: bool = False):
    """`laplace` on sweep data built on the device (`jaxci.optim.device_stars.sweep_data`: hexahedral meshes,
    one device): the same sweeps, and only the history (O(sweeps)) comes down.

    **Returns:** as `laplace`; the points a device array ``(n, 3)``.
    """
    x, s, hf, hk, hm = _laplace_run(data.x, data.conn, data.cs, data.nbr, data.nmask, data.cons, bool(smart), p,
                                    no_extra(), data.weight, data.n_colours)
    s, hf, hk, hm = to_host((s, hf, hk, hm))
    s = int(s)
    hist = {"objective": hf[: s + 1], "max_condition": hk[: s + 1], "max_move": hm[: s + 1]}
    return head_rows(x, data.n_nodes), s, hist, {"method": "smart-laplace" if smart else "laplace",
                                                  **dataclasses.asdict(p)}


@program
@jit(static_argnames=("n",))
def head_rows(x, n: int):
    """The first `n` rows of `x`, on the device (the real nodes of padded points)."""
    return x[:n]


def padded(p: LaplaceParams, devices=None, extra: ExtraCells | None = None) -> bool:
    """Whether `laplace` runs the sweeps padded to their size class: ``p.buckets`` or several devices, on a
    hexahedral mesh (`extra` without types)."""
    return bool(p.buckets or devices is not None) and not (extra is not None and extra.types)


def _padded(points, conn, cs: ColouredStars, nbr, nmask, cons: Constraints, multiple: int = 1):
    """The arguments of `_laplace_run` padded to their size class (`jaxci.optim._moves.padded_sweeps`, and the
    neighbour lists' slots and width: `pad_slots`). Returns them with the element weights and the
    real colour count; the elements a multiple of `multiple`."""
    x, c, cs_p, cons_p, w, n_col = padded_sweeps(points, conn, cs, cons, multiple)
    k_pad = bucket(np.asarray(nmask).shape[2], 4)
    nbr_p = pad_slots(nbr, cs, 0, k_pad)  # the width padded with copies of entry 0, in one copy
    nmask_p = pad_slots(nmask, cs, False, k_pad, False)
    return x, c, cs_p, to_device(nbr_p, np.int32), to_device(nmask_p), cons_p, w, n_col


def coloured_neighbours(cs: ColouredStars, hexes: np.ndarray, n_nodes: int,
                        edges: np.ndarray | None = None, place: bool = True) -> tuple[jax.Array, jax.Array]:
    """Edge neighbours laid out like `cs.nodes`: ``(n_colours, M, K)`` indices and mask (`edges`: further cell
    edges, as in `edge_neighbours`); device arrays, or with `place` False their numpy form (to be padded first)."""
    nbr, mask = edge_neighbours(hexes, n_nodes, edges)
    nodes = np.asarray(cs.nodes)
    real = np.asarray(cs.mask)
    safe = np.minimum(nodes, n_nodes - 1)
    put = to_device if place else device_dtype
    return put(nbr[safe], np.int32), put(mask[safe] & real[..., None])


def run_laplace(problem, method: str, params: dict):
    """`jaxci.smooth`'s entry: `LaplaceParams` from `params`, stars and neighbours of `problem`, then `laplace`.

    **Returns:** ``(points, sweeps, history, resolved params)``.
    """
    if method not in METHODS:
        raise ConfigError(f"unknown Laplace method {method!r}; choose one of {', '.join(METHODS)}")
    p = _p.make_params(LaplaceParams, params, method)
    mesh = problem.mesh
    mixed = has_extra(mesh)
    # padded (`laplace`, hexahedral meshes): kept on the host until padded, so the device never holds both forms
    place = mixed or not padded(p, problem.devices)
    cs = coloured_stars(mesh.hexes, problem.cons, problem.colour, problem.info.topology.faces,
                        corner_table(mesh) if mixed else None, place=place)
    nbr, nmask = coloured_neighbours(cs, mesh.hexes, mesh.n_nodes, edge_pairs(mesh) if mixed else None, place=place)
    extra = extra_cells(mesh) if mixed else None
    return laplace(problem.x0, problem.conn, cs, nbr, nmask, problem.cons, p, smart=method == "smart-laplace",
                   extra=extra, devices=problem.devices)
