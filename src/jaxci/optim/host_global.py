"""The paper's global CI in numpy and C for hexahedral meshes: `jaxci.optim.ci.global_ci` without compilation.

Each candidate is a whole mesh, a point of the free coordinates (the layout of `jaxci.geometry.projection`);
its behaviour is F. The compiled loop takes 9-10 s to compile per mesh size and attempt budget on a 2-core CPU
(the main job compiled it five times), and evaluates the C x t trial meshes of an attempt one after the other
(`jax.lax.map`); here each trial mesh is lifted, projected onto the boundary by the C search of
`jaxci.geometry.near.NearProjector` and evaluated by the C kernel of `jaxci.native` (tens of
microseconds on the paper's cubes). The iteration is the compiled one, its steps the same functions
(`jaxci.optim.cohort`: `follow`, `trials`, `learning_attempt`, `calm_after`, with numpy and a seed axis of size
1): follow by roulette on 1/(F + delta) for the first ``stage_switch`` share of the attempts, then the best; t
trials per candidate in its interval (``init_width h`` per coordinate, shrunk by ``reduction`` per attempt);
greedy replacement; saturation for `patience` attempts or F <= ftol stops it. numpy's PCG64 stream, seeded by the
run's seed (or, with ``stream="counter"``, the JAX engine's numbers for the same seed: `jaxci.optim._draws`);
float64.
"""

from __future__ import annotations

import numpy as np

from .. import native
from ..geometry.near import NearProjector, host_constraints
from ..geometry.projection import Constraints
from ..runtime.phases import stepper
from . import _draws
from ._moves import onto_plane, planar_rings
from .ci_params import CIParams
from .cohort import calm_after, counter_follow, counter_rows, follow, learning_attempt, trials


def global_ci_np(points, hexes, cons: Constraints, scale, p: CIParams, seed: int = 0, faces=None,
                 stream: str = "native"):
    """Global CI on the host from `points` ``(n, 3)`` of the hexahedra `hexes` ``(N, 8)``; `scale` ``(n_free,)``
    the local edge length per free coordinate (`jaxci.optim.parametrisation.free_lengths`); `faces` the
    boundary faces (optional): a surface node whose ring of faces is planar and that stays inside the disk the
    ring covers (`jaxci.optim._moves.planar_rings`) is projected onto that plane, its exact nearest point, with
    no search. `stream`: ``"native"`` (numpy's PCG64 from `seed`) or ``"counter"`` (`jaxci.optim._draws`: the
    numbers of `jaxci.optim.global_ci` with ``stream="counter"`` and the key of `seed`).

    **Returns:** ``(points, attempts, history)`` as `jaxci.optim.ci.global_ci` (float64 points).
    """
    hc = host_constraints(cons)
    x0 = np.array(points, dtype=np.float64)
    hexes = native.as_conn(hexes)
    scale = np.asarray(scale, np.float64)
    projector = NearProjector(cons)
    projector.commit(projector(x0)[1])  # every boundary node's cell at the start: the searches start there
    rng = np.random.default_rng(seed)

    ni, ns = len(hc.interior_nodes), len(hc.surface_nodes)
    plane = planar_rings(x0, np.asarray(faces), hc) if faces is not None else np.zeros((len(x0), 7))
    flat = np.flatnonzero(plane[:, 6] > 0)

    def meshes(U):  # (S, n_free) -> (S, n, 3): project(x0 + B u) for each row u
        X = np.repeat(x0[None], len(U), axis=0)
        X[:, hc.interior_nodes] += U[:, : 3 * ni].reshape(len(U), ni, 3)
        X[:, hc.surface_nodes] += np.einsum("tsk,skd->tsd", U[:, 3 * ni : 3 * ni + 2 * ns].reshape(len(U), ns, 2),
                                            hc.surface_basis)
        X[:, hc.edge_nodes] += U[:, 3 * ni + 2 * ns :, None] * hc.edge_tangent
        keep = np.zeros(X.shape[:2], bool)
        if len(flat):
            foot, inside = onto_plane(np, X[:, flat], plane[flat])
            X[:, flat] = np.where(inside[..., None], foot, X[:, flat])
            keep[:, flat] = inside
        projector.project_many(X, keep)
        return X

    def behaviours(U):  # (S, n_free) -> (F, max kappa/3) (2, S)
        return np.array([native.hex_objective(x, hexes) for x in meshes(U)]).T

    C, t, T, nf = p.cohort, p.variations, p.attempts, len(scale)
    words = _draws.seed_words(seed)

    def draw(a, rows):  # attempt a's uniforms in [0, 1): the roulette's (1, C), or the trials' (1, C t, n_free)
        if stream == "counter":
            return (counter_rows(words, a, np.arange(C * t), nf, np.float64, np) if rows
                    else counter_follow(words, a, C, np.float64, np))[None]
        return rng.random((1, C * t, nf) if rows else (1, C))

    f0, k0 = behaviours(np.zeros((1, nf)))[:, 0]
    cand = np.zeros((1, C, nf))
    fc, kc = np.full((1, C), f0), np.full((1, C), k0)
    hist = [(f0, f0, k0)]
    n_roulette = round(p.stage_switch * T)
    calm = np.zeros(1, np.int64)
    tick = stepper("global CI", "learning attempt")
    while len(hist) <= T and not fc.min() <= p.ftol:
        a = len(hist) - 1
        roulette = a < n_roulette
        chosen = follow(fc, p.delta, roulette, draw(a, False) if roulette else np.zeros((1, C)), np)
        w = (p.init_width * scale * p.reduction ** (a + 1))[None]
        u = draw(a, True)
        best_before = fc.min(axis=-1)
        cand, fc, kc = learning_attempt(
            cand, fc, kc, chosen,
            lambda centre, u=u, w=w: behaviours(trials(centre, np.arange(C * t)[None], u, w, t, np)[0]),
            lambda centre, rows, u=u, w=w: trials(centre, rows, np.take_along_axis(u, rows[..., None], axis=1), w,
                                                  t, np), t, np)
        hist.append((fc.min(), fc.max(), kc[0, np.argmin(fc[0])]))
        if tick is not None:
            tick(a + 1, fc.min(), hist[-1][2])
        with np.errstate(invalid="ignore"):  # inf - inf while a candidate is inverted: not calm, as compiled
            calm = calm_after(fc, best_before, calm, p.tol, p.ftol, np)
        if calm[0] >= p.patience:
            break
    h = np.asarray(hist)
    x = meshes(cand[0, np.argmin(fc[0])][None])[0]
    return x, len(hist) - 1, {"objective": h[:, 0], "best": h[:, 0], "worst": h[:, 1], "max_condition": h[:, 2]}
