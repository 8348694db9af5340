"""`jaxci.optim.lbfgs`: the L-BFGS loop of sharded runs, its memory split by free coordinate.

The recursion on Gram matrices is checked against the host path's two-loop recursion on vectors; the loop itself
on 4 forced CPU devices (one subprocess, `tests/test_sharded_smooth.py`'s helper): the same steps as on one
device and as the host path, each device holding its share of the memory, and the exchanges it is meant to make.
"""

from __future__ import annotations

import textwrap

import numpy as np
import pytest
from test_sharded_smooth import _run_on_4_devices

from jaxci.optim import host
from jaxci.optim.lbfgs import RESULTS, _two_loop_coefficients, result_name


def _pairs(rng, k: int, n: int):
    """`k` pairs ``(s, y)`` of positive curvature (y = A s + noise with A symmetric positive definite)."""
    a = rng.normal(size=(n, n))
    a = a @ a.T / n + np.eye(n)
    s = rng.normal(size=(k, n))
    return s, s @ a + 0.01 * rng.normal(size=(k, n))


@pytest.mark.parametrize("pushes, m, stale", [(3, 5, False), (5, 5, False), (8, 5, False), (13, 4, False),
                                               (0, 3, False), (2, 5, True), (0, 4, True)])
def test_the_recursion_on_gram_matrices_is_the_two_loop_recursion(pushes, m, stale):
    """``H g`` from the m x m recursion (slots of a ring buffer, filled in push order and overwritten oldest
    first; empty slots) equals the host path's two-loop recursion over the same newest m pairs, float64
    (conftest.py). `stale`: the memory was cleared before these pushes (a non-descent direction): the empty
    slots still hold old pairs, and their Gram entries are garbage (inf among them), which must not count."""
    import jax.numpy as jnp

    rng = np.random.default_rng(pushes + 10 * m)
    n = 40
    s, y = _pairs(rng, pushes, n)
    g = rng.normal(size=n)
    slots_s, slots_y = (rng.normal(size=(m, n)), rng.normal(size=(m, n))) if stale else (np.zeros((m, n)),) * 2
    slots_s, slots_y = slots_s.copy(), slots_y.copy()
    age = np.full(m, -1, np.int32)
    mem = host._Memory(n, m)
    for p in range(pushes):  # the loop's ring buffer: push p in slot p % m
        slots_s[p % m], slots_y[p % m], age[p % m] = s[p], y[p], p
        mem.push(mem.stored(s[p]), mem.stored(y[p]))  # float64 pairs: stored as they are
    newest = int(np.argmax(age))
    gamma = float(slots_s[newest] @ slots_y[newest] / (slots_y[newest] @ slots_y[newest])) if pushes else 1.0
    sy, yy, a, b = slots_s @ slots_y.T, slots_y @ slots_y.T, slots_s @ g, slots_y @ g
    if stale:  # entries of an empty slot as the loop may leave them
        empty = age < 0
        sy[empty, :], yy[:, empty], a[empty] = np.inf, -np.inf, np.nan
    c, e, got_gamma = _two_loop_coefficients(*map(jnp.asarray, (sy, yy, a, b, age)))
    assert abs(float(got_gamma) - gamma) <= 1e-14 * gamma, (float(got_gamma), gamma)  # the newest pair's
    hg = gamma * g + np.asarray(c) @ slots_s + np.asarray(e) @ slots_y
    want = -mem.direction(g)
    assert np.allclose(hg, want, rtol=1e-11, atol=1e-12), np.abs(hg - want).max()
    if pushes:  # the pairs matter: not the steepest descent
        assert not np.allclose(hg, gamma * g)
    assert np.all(np.asarray(c)[age < 0] == 0) and np.all(np.asarray(e)[age < 0] == 0)


def _rosenbrock(v, xp):
    return xp.sum(100.0 * (v[1:] - v[:-1] ** 2) ** 2 + (1.0 - v[:-1]) ** 2)


def _wiggly(v, xp):
    return xp.sum(xp.cos(3.0 * v) + 0.1 * v ** 2) + xp.sum((v[1:] - v[:-1]) ** 4)


def _synthetic(v, args, conn, weight, n_dev, platform):
    """A non-convex test objective for `lbfgs_loop`: ``(f, grad, f, 1 + f / scale)`` (so that the k stop fires
    once f <= ktol * scale). `args`: ``(kind, scale)``, kind 0 Rosenbrock, 1 a sum of cosines with quartic
    couplings."""
    import jax
    import jax.numpy as jnp

    kind, scale = args
    f, g = jax.value_and_grad(lambda u: jnp.where(kind == 0, _rosenbrock(u, jnp), _wiggly(u, jnp)))(v)
    return f, g, f, 1.0 + f / scale


def _compare_with_host(kind, n, seed, history, max_rejected, ktol, steps, n_dev=1):
    """Run `lbfgs_loop` (on the first `n_dev` devices) and `jaxci.optim.host.lbfgs` on `_synthetic` from the same
    start; assert the same steps, F at every step, result and iterate. Returns the host's ``(whether each pair
    was skipped, F at every step, result)``."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxci.optim.lbfgs import lbfgs_loop
    from jaxci.optim.sharding import AXIS, device_mesh

    skipped = []
    push = host._Memory.push

    def counting_push(self, s, y):
        before = list(self.order)
        push(self, s, y)
        skipped.append(before == self.order)

    y0 = np.random.default_rng(seed).normal(size=n) * 1.5
    fn = _rosenbrock if kind == 0 else _wiggly
    scale = 1.0
    grad = jax.jit(jax.grad(lambda u: fn(u, jnp)))

    def fun(v):
        f = float(fn(v, np))
        return f, np.asarray(grad(jnp.asarray(v))), f, 1.0 + f / scale

    cap, rtol, atol = 0.5, 1e-10, 1e-12
    host._Memory.push = counting_push
    try:
        yh, kh, rh, hfh, _ = host.lbfgs(fun, y0, limit=steps, max_rejected=max_rejected, rtol=rtol, atol=atol,
                                        history=history, cap=cap, ftol=-np.inf, done=lambda f, k: k <= 1.0 + ktol)
    finally:
        host._Memory.push = push
    mesh = device_mesh(jax.devices()[:n_dev])
    conn = jax.device_put(jnp.zeros((8, n_dev), jnp.int32), NamedSharding(mesh, P(None, AXIS)))
    weight = jax.device_put(jnp.ones(n_dev), NamedSharding(mesh, P(AXIS)))
    y, k, code, hf, _ = lbfgs_loop(_synthetic, (jnp.int32(kind), jnp.float64(scale)), conn, weight, jnp.asarray(y0),
                                   jnp.asarray([-np.inf, 1.0 + ktol, rtol, atol, cap]), jnp.int32(steps), mesh=mesh,
                                   max_steps=steps, history=history, max_rejected=max_rejected)
    # step for step: roundoff (the recursion on Gram matrices, numpy against XLA) grows along a Rosenbrock
    # valley to 1e-9 of F in 60 steps; a different step would differ at once by far more
    assert int(k) == kh and result_name(code) == rh, (int(k), kh, result_name(code), rh)
    assert np.allclose(np.asarray(hf)[: kh + 1], hfh, rtol=1e-7, atol=1e-12)
    assert np.allclose(np.asarray(y), yh, rtol=1e-6, atol=1e-9)
    return skipped, hfh, rh


@pytest.mark.parametrize("case", ["skipped pairs", "memory wrapped, step limit", "k stop", "Cauchy stop"])
def test_the_loop_takes_the_host_paths_steps_on_non_convex_functions(case):
    """`lbfgs_loop` on one device against `jaxci.optim.host.lbfgs`, float64, from the same start: the same steps,
    F at every step, result and iterate, in runs that exercise each part of the algorithm (checked here on
    the host's run: pairs of non-positive curvature skipped; a memory of 5 overwritten 10 times over; the k
    stop; the Cauchy test)."""
    if case == "skipped pairs":  # Rosenbrock in 20 unknowns, memory 3, ended by 2 rejected trials in a row
        skipped, hf, result = _compare_with_host(0, 20, 0, 3, 2, 0.0, 60)
        assert sum(skipped) >= 1 and result == "successful" and hf[-1] == hf[-2] == hf[-3], (sum(skipped), hf[-3:])
    elif case == "memory wrapped, step limit":
        skipped, hf, result = _compare_with_host(0, 37, 0, 5, 30, 0.0, 60)
        assert len(skipped) - sum(skipped) >= 50 and result == "nonlinear_max_steps_reached"
    elif case == "k stop":  # k = 1 + F: stops at the first accepted F <= 0.5, long before the Cauchy test
        skipped, hf, result = _compare_with_host(0, 7, 1, 4, 30, 0.5, 80)
        _, longer, _ = _compare_with_host(0, 7, 1, 4, 30, 0.0, 80)
        assert result == "successful" and hf[-1] <= 0.5 < hf[-2] and len(longer) > len(hf) + 10
    else:  # cosines with quartic couplings: a local minimum in 10 steps
        skipped, hf, result = _compare_with_host(1, 37, 2, 5, 30, 0.0, 60)
        assert result == "successful" and len(hf) < 20


def test_result_names():
    assert [result_name(np.int32(i)) for i in range(3)] == list(RESULTS)
    assert RESULTS[0] == "successful"


SCRIPT = textwrap.dedent(
    """
    import re
    import sys
    jax.config.update("jax_enable_x64", True)
    from jaxci.mesh.generate import perturb_box
    from jaxci.optim import lbfgs
    from jaxci.interface.smooth import smooth

    sys.path.insert(0, TESTS)
    from helpers import wavy_annulus as _wavy

    hlo = []
    loop = lbfgs.lbfgs_loop

    def spy(*args, **kw):  # the compiled program of the first call on each device count, then the call
        n = kw["mesh"].devices.size
        if all(d != n for d, _ in hlo):  # (compiling every call's again cost ~10 s of the test)
            hlo.append((n, loop.lower(*args, **kw).compile().as_text()))
        return loop(*args, **kw)

    lbfgs.lbfgs_loop = spy

    # boxes, sliding boundary on flat walls: the host path's steps exactly, on one device and on four (the 8^3
    # box ends on the k stop, max kappa/3 <= 1 + ktol)
    for box, stop in ((perturb_box(6, 5, 4, amplitude=0.3, seed=1), "cauchy"),
                      (perturb_box(8, 8, 8, amplitude=0.3, seed=1), "k")):
        ref = smooth(box, "lbfgs", dtype="float64", presmooth=0, backend="numpy", precondition="none")
        assert (ref.after.max_condition <= 1 + 1e-6) == (stop == "k"), ref.after.max_condition
        for dev in (1, 4):
            r = smooth(box, "lbfgs", dtype="float64", presmooth=0, devices=dev)
            assert r.iterations == ref.iterations, (dev, r.iterations, ref.iterations)
            assert r.history["solver_result"] == ref.history["solver_result"] == "successful"
            assert np.allclose(r.history["objective"], ref.history["objective"], rtol=1e-9, atol=1e-15)
            assert np.abs(r.mesh.points - ref.mesh.points).max() < 1e-9
            assert r.after.inverted_corners == 0 and r.after.max_condition < r.before.max_condition
    # 37 unknowns on 4 devices: shares of 10, the last padded
    from test_lbfgs import _compare_with_host
    _compare_with_host(0, 37, 0, 5, 30, 0.0, 60, n_dev=4)
    _compare_with_host(0, 20, 0, 3, 2, 0.0, 60, n_dev=4)
    # four devices: each holds its quarter of the memory (10 pairs of s and y: a (20, n / 4) block), and the
    # program exchanges once per trial and once more per accepted step (plus the start's evaluation), and
    # gathers the direction once
    one, four = ({int(k) for k in re.findall(r"f64\\[20,(\\d+)\\]", h) if int(k) > 3}
                 for h in (next(h for d, h in hlo if d == 1), next(h for d, h in hlo if d == 4)))
    assert len(one) == len(four) == 1 and 4 * min(four) == min(one), (one, four)
    prog = next(h for d, h in hlo if d == 4)
    assert prog.count("all-reduce(") == 3 and prog.count("all-gather(") == 1, (prog.count("all-reduce("),
                                                                               prog.count("all-gather("))

    # curved walls (nodes projected onto the cylinders; a strict first run, then a projected one): one device
    # and four take the same steps
    wavy = _wavy()
    runs = [smooth(wavy, "lbfgs", dtype="float64", presmooth=0, devices=dev) for dev in (1, 4)]
    (r1, r4) = runs
    assert r1.iterations == r4.iterations > 50, (r1.iterations, r4.iterations)
    assert list(r1.history["restarts"]) == list(r4.history["restarts"])
    assert np.allclose(r1.history["objective"], r4.history["objective"], rtol=1e-9, atol=0)
    assert np.abs(r1.mesh.points - r4.mesh.points).max() < 1e-9
    host = smooth(wavy, "lbfgs", dtype="float64", presmooth=0, backend="numpy", precondition="none")
    for r in runs:
        assert r.after.inverted_corners == 0
        assert r.after.objective < 0.4 * r.before.objective
        assert abs(r.after.objective - host.after.objective) < 1e-3 * host.after.objective
    print("SHARDED-LBFGS-OK")
    """
)


def test_the_sharded_loop_takes_the_host_paths_steps_on_one_and_four_devices():
    import os

    tests = os.path.dirname(os.path.abspath(__file__))
    _run_on_4_devices(f"TESTS = {tests!r}\n" + SCRIPT, "SHARDED-LBFGS-OK")


@pytest.mark.parametrize("name, steps", [("box6", 2000), ("1000hex-block-internal-bias.vtk", 30)])
def test_both_engines_take_the_same_lbfgs_steps(name, steps):
    """L-BFGS on the JAX engine (one device, `lbfgs_loop`) and on the host engine (`jaxci.optim.host.lbfgs`),
    float64, no presmoothing, no preconditioner: the same steps, F at every step and result to 1e-9. A box whose
    walls slide runs to its end; on Mesquite's biased block (sliding walls) the summation orders of the two
    kernels differ at 1e-16 and L-BFGS amplifies that about threefold a step, so the first 30 steps are compared."""
    from helpers import box_or_mesquite

    from jaxci.interface.smooth import smooth

    mesh = box_or_mesquite(name, seed=1)
    kw = dict(dtype="float64", presmooth=0, precondition="none", max_steps=steps)
    ref = smooth(mesh, "lbfgs", backend="numpy", **kw)
    got = smooth(mesh, "lbfgs", backend="jax", **kw)
    assert got.iterations == ref.iterations and got.history["solver_result"] == ref.history["solver_result"]
    assert np.allclose(got.history["objective"], ref.history["objective"], rtol=1e-9, atol=0)
    assert np.abs(got.mesh.points - ref.mesh.points).max() < 1e-9
    assert got.after.max_condition < got.before.max_condition


def test_a_step_cut_eight_times_that_changes_nothing_ends_the_run(monkeypatch):
    """`converged`: the objective's change within the tolerance and either the step's within it or a step size
    cut to `STUCK_STEP`. On a curved annulus (boundary nodes sliding over the triangles of its wall: F kinked
    where they cross a triangle's edge) L-BFGS then stops where the old test (the step's change alone) went on
    cutting its steps, at F as low (to 1e-5)."""
    from helpers import wavy_annulus

    from jaxci import smooth
    from jaxci.optim import lbfgs as rules

    assert rules.converged(1.0, 1.0, 1.0, 1.0, 1e-6, 1e-6, rules.STUCK_STEP)
    assert not rules.converged(1.0, 1.0, 1.0, 1.0, 1e-6, 1e-6, 2 * rules.STUCK_STEP)
    assert not rules.converged(1.0, 1.0, 1.0, 2.0, 1e-6, 1e-6, rules.STUCK_STEP)  # F still changing
    assert rules.converged(0.0, 1.0, 1.0, 1.0, 1e-6, 1e-6)  # the Cauchy test as before
    mesh = wavy_annulus(16, 3, 3)
    new = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False)
    monkeypatch.setattr(rules, "STUCK_STEP", 0.0)
    old = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False)
    assert new.iterations < 0.8 * old.iterations, (new.iterations, old.iterations)
    assert new.after.objective <= old.after.objective * (1 + 1e-5) and new.after.inverted_elements == 0


def _creeping(v, args, conn, weight, n_dev, platform):
    """F = 1 + 1e-8 exp(-v0) + v1^2 for `lbfgs_loop`: every capped step along v0 lowers F by under 1e-8 of it, and
    no step ever gets short (a valley of F, as an O-grid cylinder's turn about its axis)."""
    import jax
    import jax.numpy as jnp

    f, g = jax.value_and_grad(lambda u: 1.0 + 1e-8 * jnp.exp(-u[0]) + u[1] ** 2)(v)
    return f, g, f, 1.0 + f


def test_a_run_of_calm_steps_ends_the_run_in_every_loop():
    """`converged` with `calm_steps`: `SETTLED_RUN` accepted steps in a row that change F by less than rtol of it
    end the run whatever their size, in the host loop and in `lbfgs_loop` alike (the same steps); without the
    rule both went on to their step limit. The count is relative only: near F = 0 a change under atol is no calm
    step."""
    import jax.numpy as jnp

    from jaxci.optim import lbfgs as rules

    calm = 0
    for _ in range(rules.SETTLED_RUN):
        calm = int(rules.calm_steps(calm, 1.0, 1.0 + 1e-9, 1e-6))
    assert calm == rules.SETTLED_RUN and rules.converged(1.0, 1.0, 1.0, 1.0 + 1e-9, 1e-6, 1e-6, 1.0, calm)
    assert not rules.converged(1.0, 1.0, 1.0, 1.0 + 1e-9, 1e-6, 1e-6, 1.0, calm - 1)
    assert int(rules.calm_steps(5, 1.0, 1.1, 1e-6)) == 0  # a real decrease starts the count again
    assert int(rules.calm_steps(0, 1e-9, 2e-9, 1e-6)) == 0  # near 0: halving F is no calm step

    def fun(v):
        f = 1.0 + 1e-8 * np.exp(-v[0]) + v[1] ** 2
        return f, np.array([-1e-8 * np.exp(-v[0]), 2.0 * v[1]]), f, 1.0 + f

    y0, limit = np.zeros(2), 100
    _, kh, rh, _, _ = host.lbfgs(fun, y0, limit=limit, max_rejected=20, rtol=1e-6, atol=1e-12, history=5, cap=0.5,
                                 ftol=-np.inf)
    from jaxci.optim.lbfgs import lbfgs_loop

    _, k, code, _, _ = lbfgs_loop(_creeping, (), jnp.zeros((8, 1), jnp.int32), jnp.ones(1), jnp.asarray(y0),
                                  jnp.asarray([-np.inf, 0.0, 1e-6, 1e-12, 0.5]), jnp.int32(limit), max_steps=limit,
                                  history=5, max_rejected=20)
    assert rh == result_name(code) == "successful" and kh == int(k) <= rules.SETTLED_RUN + 2, (kh, int(k))
