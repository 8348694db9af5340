"""The untangling stage's compiled part: the energy with its closed-form gradient, and every eps round in one loop.

`untangle_rounds` runs the whole eps schedule of `jaxci.optim.untangle` (every round's L-BFGS minimisation and
the eps update between rounds) as ONE `jax.lax.while_loop` whose body is one evaluation of the energy and its
gradient: eps, the round's start energy, the L-BFGS memory and the per-round history are loop-carried, the
rounds, steps and tolerances are traced, and the history has a fixed size, so a run compiles once per mesh shape
whatever the number of rounds and reports nothing to Python between rounds. Its L-BFGS takes jaxci's rules
(`jaxci.optim.lbfgs`: the Armijo search, the curvature test of a pair, the Cauchy stop; no trial cap), written
into this loop so that it holds a single evaluation site for every round (a loop per round, as optimistix's,
traced the objective three times and compiled 1.1 CPU s of machinery around it); the eps schedule is `next_eps`,
the host's too (`jaxci.optim.host.untangle_rounds_np`).

The hexahedra's energy and its gradient with respect to the node coordinates come from one closed-form kernel
(`hex_energy`, a `jax.custom_jvp`, as `jaxci.optim.gradient` does for F) over a flat table of corners; the other
cell types (rare) are differentiated by JAX.
"""

from __future__ import annotations

import functools

import numpy as np

from ..cells import CORNER_NEIGHBOURS
from ..metrics import elements as E
from ..runtime._lazy import filter_jit, jax, jnp
from ..runtime.transfer import program
from ._params import MAX_REJECTED_UNCAPPED, UNTANGLE_HISTORY
from .lbfgs import DECREASE, armijo, calm_steps, converged, curvature_ok

#: Corners one interior node moves (8 elements x 4 corners): the energy is a per-node sum (as F in
#: `jaxci.optim.gradient`).
CORNERS_PER_NODE = 32.0

#: Size of the per-round history arrays: `jaxci.optim.untangle.MAX_ROUNDS` (fixed, so that the number of rounds
#: asked for is a traced value and changing it compiles nothing).
HISTORY = 10_000

#: A strict run stops after a round whose result has a boundary node further than this fraction of its flat
#: region's radius from the region's origin, and goes on with the projection (as `jaxci.optim.gradient`'s).
FLAT_REACH = 0.9

#: eps after a round that left every corner above mu (the paper's value).
EPS_FLOOR = 1e-10


def chi(eps, d, xp=jnp):
    """The regularised determinant ``(d + sqrt(eps^2 + d^2)) / 2``, written without cancellation for d < 0
    (``eps^2 / (2 (sqrt(eps^2 + d^2) - d))``): the same value, finite down to eps = 1e-10 at any d. `xp`: the
    array module."""
    s = xp.sqrt(eps * eps + d * d)
    return xp.where(d >= 0, 0.5 * (d + s), 0.5 * eps * eps / xp.where(d >= 0, 1.0, s - d))


def next_eps(eps, e_start, e, dmin, xp=jnp):
    """eps of the next round after a round at `eps` that took the energy from `e_start` to `e` and left the
    smallest det J at `dmin`: ``sigma = max(1 - e / e_start, 0.1)``, ``mu = (1 - sigma) chi(eps, dmin)``, then
    ``2 sqrt(mu (mu - dmin))`` if ``dmin < mu`` else `EPS_FLOOR` (the schedule of `jaxci.optim.untangle`, both
    engines). `xp`: the array module."""
    sigma = xp.where(e_start > 0, xp.maximum(1.0 - e / xp.where(e_start > 0, e_start, 1.0), 0.1), 0.1)
    mu = (1.0 - sigma) * chi(eps, dmin, xp)
    return xp.where(dmin < mu, 2.0 * xp.sqrt(xp.maximum(mu * (mu - dmin), 0.0)), EPS_FLOOR)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def corner_table(hexes) -> np.ndarray:
    """The corners of `hexes` ``(N, 8)`` as one flat table, shape ``(4, 8 N)`` (int32 where the node count
    allows): row 0 the corner's node, rows 1-3 the far ends of its columns a, b, c (`CORNER_NEIGHBOURS`); corner i
    of element e is entry ``i N + e``."""
    h = np.asarray(hexes)
    tab = np.stack([h.T.ravel()] + [h[:, CORNER_NEIGHBOURS[:, j]].T.ravel() for j in range(3)])
    return tab.astype(np.int32) if tab.size == 0 or tab.max() < 2**31 - 1 else tab


def hex_kernel(x, table, inv_len, eps, theta, grad: bool, xp=jnp):
    """Energy (sum over corners / 32), min det J and, if `grad`, d energy / d x ``(n, 3)`` (else None).

    `table` is `corner_table` ``(4, C)``, `inv_len` ``(C,)`` one over the reference length of each corner's
    element. Per corner with J's columns a, b, c (``A / L_e``), u = b x c, v = c x a, w = a x b,
    d = det J = a . u, f = |J|_F^2, s = sqrt(eps^2 + d^2) and chi = chi(eps, d) (d chi / d d = chi / s):
    ``E = (1 - theta) (f / 3) chi^(-2/3) + theta (d^2 + 1) / chi``,
    ``dE/df = (1 - theta) chi^(-2/3) / 3``,
    ``dE/dd = (-(2/3) (1 - theta) (f / 3) chi^(-2/3) - theta (d^2 + 1) / chi) / s + 2 theta d / chi``,
    ``dE/da = 2 dE/df a + dE/dd u`` (b: v, c: w), times 1 / L_e for A's columns; column a goes from the corner's
    node to the node of row 1, so its gradient goes to that node with + and to the corner's node with -.

    Written over the flat corner table (12 gathers, one elementwise loop, one scatter-add per component), not
    the ``(8, N)`` rows of `jaxci.metrics.hexahedron` (whose row permutations and 24 scatters made XLA compile the value
    and gradient in 1.7-1.8 CPU s against 0.46 s here, with the same run time: 35 against 38 ms at 30^3, 294 against
    297 ms at 60^3, float64). `xp`: the array module, `jax.numpy` (default) or `numpy`
    (`jaxci.optim.host.untangle_rounds_np`).
    """
    xt = x.T
    p0, p1, p2, p3 = ([xt[d][table[k]] for d in range(3)] for k in range(4))
    a = tuple((p1[d] - p0[d]) * inv_len for d in range(3))
    b = tuple((p2[d] - p0[d]) * inv_len for d in range(3))
    c = tuple((p3[d] - p0[d]) * inv_len for d in range(3))
    u = _cross(b, c)
    det = a[0] * u[0] + a[1] * u[1] + a[2] * u[2]
    fro2 = sum(t * t for t in (*a, *b, *c))
    s = xp.sqrt(eps * eps + det * det)
    ich = 1.0 / xp.where(det >= 0, 0.5 * (det + s), 0.5 * eps * eps / (s - det))  # 1 / chi
    c23 = ich ** (2.0 / 3.0)
    shape = (1.0 - theta) * (fro2 / 3.0) * c23
    volume = theta * (det * det + 1.0) * ich
    barrier = jax.lax.optimization_barrier if xp is not np else (lambda t: t)
    energy = xp.sum(barrier(shape + volume)) / CORNERS_PER_NODE
    dmin = xp.min(barrier(det), initial=xp.inf)
    if not grad:
        return energy, dmin, None
    unit = inv_len / CORNERS_PER_NODE  # d J / d A and the 1/32
    p = (2.0 / 3.0) * (1.0 - theta) * c23 * unit  # 2 dE/df
    q = ((-(2.0 / 3.0) * shape - volume) / s + 2.0 * theta * det * ich) * unit  # dE/dd
    v, w = _cross(c, a), _cross(a, b)
    nodes = table.ravel()
    grads = []
    for k in range(3):
        ga, gb, gc = p * a[k] + q * u[k], p * b[k] + q * v[k], p * c[k] + q * w[k]
        vals = xp.concatenate([-(ga + gb + gc), ga, gb, gc])
        if xp is np:
            grads.append(np.bincount(nodes, weights=vals, minlength=x.shape[0]))
        else:
            grads.append(jnp.zeros(x.shape[0], x.dtype).at[nodes].add(vals))
    return energy, dmin, xp.stack(grads, axis=1)


def hex_energy(x, table, inv_len, eps, theta):
    """The hexahedra's energy (sum of the corner energies / 32) and min det J, at coordinates `x` ``(n, 3)``;
    `table` the `corner_table` ``(4, C)``, `inv_len` ``(C,)`` one over each corner's element reference length.
    Differentiable in `x` only (closed form: one kernel for the value and the gradient: a `jax.custom_jvp`)."""
    return _hex_energy()(x, table, inv_len, eps, theta)


@functools.cache
def _hex_energy():
    """`hex_energy` as a `jax.custom_jvp`, built on first use (importing this module imports no JAX)."""

    @jax.custom_jvp
    def energy(x, table, inv_len, eps, theta):
        return hex_kernel(x, table, inv_len, eps, theta, False)[:2]

    @energy.defjvp
    def _jvp(primals, tangents):
        x, table, inv_len, eps, theta = primals
        e, dmin, g = hex_kernel(x, table, inv_len, eps, theta, True)
        return (e, dmin), (jnp.sum(g * tangents[0]), jnp.zeros_like(dmin))

    return energy


def _extra_energy(x, extra, inv_lens, eps, theta):
    """Energy and min det J of the wedges, pyramids and tetrahedra (``J = A W^-1 / L_e``) with the volume term of
    their barrier sub-tetrahedra (``J = A / L_e``; `jaxci.cells.CellKernel.barrier`: the pyramids'),
    differentiated by JAX."""
    energy, dmin = 0.0, jnp.inf
    for t, conn, il in zip(extra.types, extra.conns, inv_lens, strict=True):
        cols = [col * il for col in E.normalised_corner_columns_t(x, conn, t)]
        ax, ay, az, bx, by, bz, cx, cy, cz = cols
        d = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        ce = chi(eps, d)
        f2 = sum(col * col for col in cols)
        energy = energy + jnp.sum((1.0 - theta) * (f2 / 3.0) / ce ** (2.0 / 3.0) + theta * (d * d + 1.0) / ce)
        dmin = jnp.minimum(dmin, jnp.min(d))
        sub = E.barrier_dets_t(x, conn, t)
        if sub is not None:
            sub = sub * il**3
            energy = energy + jnp.sum(theta * (sub * sub + 1.0) / chi(eps, sub))
            dmin = jnp.minimum(dmin, jnp.min(sub))
    return energy / CORNERS_PER_NODE, dmin


def energy_fn(v, args):
    """The objective of the inner L-BFGS and min det J, ``(energy, min det J)``, at scaled free coordinates `v`;
    ``args = (par, table, inv_len, eps, theta, extra, inv_lens)`` (`hex_energy`, `_extra_energy`)."""
    par, table, inv_len, eps, theta, extra, inv_lens = args
    x = par.points(v)
    energy, dmin = hex_energy(x, table, inv_len, eps, theta)
    if extra.types:
        e2, d2 = _extra_energy(x, extra, inv_lens, eps, theta)
        energy, dmin = energy + e2, jnp.minimum(dmin, d2)
    return energy, dmin


def _direction(g, S, Y, rho, head, n_mem):
    """``-H g`` for the L-BFGS inverse Hessian of the pairs in the ring buffers `S`, `Y` ``(m, n)`` (inverse inner
    products `rho`, 0 for an empty slot; the newest at ``head - 1``), with the initial scaling
    ``gamma = s.y / y.y`` of the newest pair (1 with none): optimistix's `LBFGS` (Byrd, Nocedal, Schnabel 1994,
    Algorithm 4.1)."""
    m = S.shape[0]
    order = (jnp.arange(m) + head) % m  # oldest first

    def backward(q, i):
        alpha = rho[i] * jnp.dot(S[i], q)
        return q - alpha * Y[i], alpha

    q, alphas = jax.lax.scan(backward, g, order, reverse=True)
    last = (head - 1) % m
    yy = jnp.dot(Y[last], Y[last])
    gamma = jnp.where((n_mem > 0) & (yy > 0), jnp.dot(S[last], Y[last]) / jnp.where(yy > 0, yy, 1.0), 1.0)

    def forward(r, ia):
        i, alpha = ia
        beta = rho[i] * jnp.dot(Y[i], r)
        return r + (alpha - beta) * S[i], None

    r, _ = jax.lax.scan(forward, gamma * q, (order, alphas))
    return -r


@program
@filter_jit
def untangle_rounds(v0, mesh_args, theta, margin, max_rounds, inner_steps, rtol, atol, state=None,
                    flat_reach=FLAT_REACH):
    """Every round of the untangling stage in one compiled loop of single energy-and-gradient evaluations.

    **Arguments:**

    - `v0`: scaled free coordinates to start from ``(n_free,)``.
    - `mesh_args`: ``(par, table, inv_len, extra, inv_lens)`` (see `energy_fn`).
    - `theta`, `margin`, `rtol`, `atol`: float scalars; `max_rounds` (at most `HISTORY`), `inner_steps`: int
      scalars. All traced: other values compile nothing.
    - `state`: None (start at `v0`), or the state a strict run returned (see below): the loop goes on from there.
    - `flat_reach`: a float scalar (traced), `FLAT_REACH` by default (see below).

    One loop iteration is one evaluation of the energy and its gradient (one L-BFGS "step" as optimistix counts
    them: a line-search trial or an accepted point). The first evaluates `v0` for its min det J (eps of the
    first round: ``sqrt(1e-12 + 0.04 min(d_min, 0)^2)``) and is not counted. Each round is an L-BFGS with
    jaxci's rules (`jaxci.optim.lbfgs`): a fresh memory of `UNTANGLE_HISTORY` pairs; its first step evaluates
    the round's start and is accepted; then a backtracking Armijo search (`armijo`, halving from step 1) along
    ``-H g``; pairs that pass `curvature_ok` enter the memory; the round stops on the Cauchy test (`converged`),
    once every corner has det J >= margin, after `MAX_REJECTED_UNCAPPED` steps in a row that leave its iterate
    unchanged, at a non-finite iterate or after `inner_steps` steps. Its result is the iterate of lowest finite
    energy. Then eps follows `next_eps`; rounds go on while ``d_min < margin`` and fewer than `max_rounds` have
    run.

    With a strict parametrisation (`Parametrisation.strict`: no projection compiled) a trial with a boundary node
    outside its flat region has a NaN energy and is rejected like any trial that fails the Armijo test; a round
    whose result has a node beyond `flat_reach` of its region's radius (the flat regions may be holding it back)
    ends the loop with ``state["left"]`` True, so that the caller can go on with the projection (`state`: the
    next round runs projected; `jaxci.optim.gradient.minimise`'s rule for its strict runs).

    **Returns:** the loop state, a dict: ``y_best`` (the last round's result), ``rounds`` and ``steps`` (run in
    all), ``dmin0`` (min det J of `v0`), ``h_eps``, ``h_dmin``, ``h_e`` (eps, min det J and energy after each
    round: arrays of length `HISTORY`, the first ``rounds`` entries filled), ``left`` (see above), and the
    L-BFGS state.
    """
    par, table, inv_len, extra, inv_lens = mesh_args
    dtype = v0.dtype
    n = v0.shape[0]
    history = UNTANGLE_HISTORY
    max_rounds = jnp.minimum(jnp.asarray(max_rounds, jnp.int32), HISTORY)
    inner_steps = jnp.asarray(inner_steps, jnp.int32)
    zero, i0, false = jnp.zeros((), dtype), jnp.int32(0), jnp.array(False)
    nan = jnp.full((HISTORY,), jnp.nan, dtype)

    carry = {
        "probe": jnp.array(True), "done": false, "left": false, "first": false, "y_eval": v0,
        "v": v0, "f": zero, "g": jnp.zeros_like(v0), "d_acc": zero, "d": jnp.zeros_like(v0), "alpha": zero + 1,
        "S": jnp.zeros((history, n), dtype), "Y": jnp.zeros((history, n), dtype), "rho": jnp.zeros((history,), dtype),
        "head": i0, "n_mem": i0,
        "k": i0, "steps": i0, "rejected": i0, "calm": i0, "f_last": zero,
        "y_best": v0, "f_best": zero, "d_best": zero,
        "eps": zero + 1, "e_start": zero, "rounds": i0, "dmin0": zero, "h_eps": nan, "h_dmin": nan, "h_e": nan,
    } if state is None else {**state, "done": false, "left": false}

    def probed(c, f_e, d_e, g_e):
        del f_e, g_e
        eps0 = jnp.sqrt(1e-12 + 0.04 * jnp.minimum(d_e, 0.0) ** 2).astype(dtype)
        return {**c, "probe": false, "first": jnp.array(True), "dmin0": d_e, "eps": eps0,
                "done": (d_e >= margin) | (max_rounds <= 0)}

    def stepped(c, f_e, d_e, g_e):
        first = c["first"]
        s = c["y_eval"] - c["v"]
        slope = jnp.dot(c["g"], s)  # of the whole trial move
        accept = first | ((slope <= 0) & armijo(f_e, c["f"], 1.0, slope))

        def accepted(c):
            yv = g_e - c["g"]
            inner = jnp.dot(s, yv)
            upd = ~first & curvature_ok(inner, jnp.dot(s, s), jnp.dot(yv, yv), jnp)
            slot = c["head"] % history
            S = c["S"].at[slot].set(jnp.where(upd, s, c["S"][slot]))
            Y = c["Y"].at[slot].set(jnp.where(upd, yv, c["Y"][slot]))
            rho = c["rho"].at[slot].set(jnp.where(upd, 1.0 / jnp.where(upd, inner, 1.0), c["rho"][slot]))
            head, n_mem = c["head"] + upd, jnp.minimum(c["n_mem"] + upd, history)
            calm = jnp.where(first, 0, calm_steps(c["calm"], f_e, c["f"], rtol, jnp)).astype(c["calm"].dtype)
            stop = converged(jnp.max(jnp.abs(s), initial=0.0), jnp.max(jnp.abs(c["y_eval"]), initial=0.0), f_e,
                             c["f"], rtol, atol, c["alpha"], calm)
            return {**c, "v": c["y_eval"], "f": f_e, "g": g_e, "d_acc": d_e, "alpha": jnp.ones((), dtype), "calm": calm,
                    "d": _direction(g_e, S, Y, rho, head, n_mem), "S": S, "Y": Y, "rho": rho, "head": head,
                    "n_mem": n_mem}, ~first & stop

        def rejected(c):
            return {**c, "alpha": DECREASE * c["alpha"]}, false

        c, cauchy = jax.lax.cond(accept, accepted, rejected, c)
        # the bookkeeping of jaxci.optim._solve: steps, unchanged steps, best iterate, stop
        f, v = c["f"], c["v"]
        k = c["k"] + 1
        unchanged = jnp.where(first | (f == c["f_last"]), c["rejected"] + 1, 0)
        finite_v = jnp.all(jnp.isfinite(v))
        finite = finite_v & jnp.isfinite(f)
        better = first | (finite & (f <= c["f_best"]))
        c = {**c, "k": k, "rejected": unchanged, "f_last": f,
             "e_start": jnp.where(first, f_e, c["e_start"]), "first": false,
             "y_best": jnp.where(better, v, c["y_best"]), "f_best": jnp.where(better, f, c["f_best"]),
             "d_best": jnp.where(better, c["d_acc"], c["d_best"])}
        end = (cauchy | ~finite_v | ((c["d_acc"] >= margin) & finite) | (unchanged >= MAX_REJECTED_UNCAPPED)
               | (k >= inner_steps))
        return jax.lax.cond(end, end_round, lambda c: {**c, "y_eval": c["v"] + c["alpha"] * c["d"]}, c)

    def end_round(c):
        eps, e, dmin, r = c["eps"], c["f_best"], c["d_best"], c["rounds"]
        new_eps = next_eps(eps, c["e_start"], e, dmin, jnp)
        done = (dmin >= margin) | (r + 1 >= max_rounds)
        left = false
        if par.strict:  # a node near the edge of its flat region: go on with the projection
            x = par.lift(c["y_best"])
            far = jnp.sum((x[par.flat_nodes] - par.flat_origin) ** 2, axis=-1) > (flat_reach * par.flat_radius) ** 2
            left = ~done & jnp.any(far)
            done = done | left
        return {**c, "h_eps": c["h_eps"].at[r].set(eps), "h_dmin": c["h_dmin"].at[r].set(dmin),
                "h_e": c["h_e"].at[r].set(e), "eps": new_eps.astype(dtype), "rounds": r + 1,
                "steps": c["steps"] + c["k"], "done": done, "left": left,
                "first": jnp.array(True), "k": i0, "rejected": i0, "calm": i0, "y_eval": c["y_best"],
                "rho": jnp.zeros_like(c["rho"]), "head": i0, "n_mem": i0}

    def body(c):  # the loop's one evaluation of the energy and its gradient
        args = (par, table, inv_len, jnp.where(c["probe"], jnp.ones((), dtype), c["eps"]), theta, extra, inv_lens)
        (f_e, d_e), g_e = jax.value_and_grad(lambda y: energy_fn(y, args), has_aux=True)(c["y_eval"])
        return jax.lax.cond(c["probe"], probed, stepped, c, f_e, d_e, g_e)

    return jax.lax.while_loop(lambda c: ~c["done"], body, carry)
