"""`jaxci.optim.sharded_lbfgs`: the L-BFGS loop of sharded runs, its memory split by free coordinate.

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
from jaxci.optim.sharded_lbfgs import RESULTS, _two_loop_coefficients, result_name


def _pairs(rng, k: int, n: int):
    """`k` pairs ``(s, y)`` of positive curvature (y = A s + noise with A symmetric positive definite)."""
    a = rng.normal(size=(n, n))
    a = a @ a.T / n + np.eye(n)
    s = rng.normal(size=(k, n))
    return s, s @ a + 0.01 * rng.normal(size=(k, n))


@pytest.mark.parametrize("pushes, m", [(3, 5), (5, 5), (8, 5), (13, 4), (0, 3)])
def test_the_recursion_on_gram_matrices_is_the_two_loop_recursion(pushes, m):
    """``H g`` from the m x m recursion (slots of a ring buffer, filled in push order and overwritten oldest
    first; empty slots) equals the host path's two-loop recursion over the same newest m pairs, float64."""
    import jax.numpy as jnp

    rng = np.random.default_rng(pushes + 10 * m)
    n = 40
    s, y = _pairs(rng, pushes, n)
    g = rng.normal(size=n)
    slots_s, slots_y = np.zeros((m, n)), np.zeros((m, n))
    age = np.full(m, -1, np.int32)
    mem = host._Memory(n, m)
    for p in range(pushes):  # the loop's ring buffer: push p in slot p % m
        slots_s[p % m], slots_y[p % m], age[p % m] = s[p], y[p], p
        mem.push(s[p], y[p])
    newest = int(np.argmax(age))
    gamma = float(slots_s[newest] @ slots_y[newest] / (slots_y[newest] @ slots_y[newest])) if pushes else 1.0
    c, e = _two_loop_coefficients(*map(jnp.asarray, (slots_s @ slots_y.T, slots_y @ slots_y.T, slots_s @ g,
                                                      slots_y @ g, age)), gamma)
    hg = gamma * g + np.asarray(c) @ slots_s + np.asarray(e) @ slots_y
    want = -mem.direction(g)
    assert np.allclose(hg, want, rtol=1e-11, atol=1e-12), np.abs(hg - want).max()
    if pushes:  # the pairs matter: not the steepest descent
        assert not np.allclose(hg, gamma * g)
    assert np.all(np.asarray(c)[age < 0] == 0) and np.all(np.asarray(e)[age < 0] == 0)


def test_result_names():
    assert [result_name(np.int32(i)) for i in range(3)] == list(RESULTS)
    assert RESULTS[0] == "successful"


SCRIPT = textwrap.dedent(
    """
    import re
    import sys
    jax.config.update("jax_enable_x64", True)
    from jaxci.generate import perturb_box
    from jaxci.optim import sharded_lbfgs
    from jaxci.smooth import smooth

    sys.path.insert(0, TESTS)
    from test_coarse import _wavy

    hlo = []
    loop = sharded_lbfgs.lbfgs_loop

    def spy(*args, **kw):  # the compiled program of each call, then the call
        hlo.append(loop.lower(*args, **kw).compile().as_text())
        return loop(*args, **kw)

    sharded_lbfgs.lbfgs_loop = spy

    # a box, sliding boundary on flat walls: the host path's steps exactly, on one device and on four
    box = perturb_box(6, 5, 4, amplitude=0.3, seed=1)
    ref = smooth(box, "lbfgs", dtype="float64", presmooth=0, backend="numpy", precondition="none")
    for dev in (1, 4):
        r = smooth(box, "lbfgs", dtype="float64", presmooth=0, devices=dev)
        assert r.iterations == ref.iterations, (dev, r.iterations, ref.iterations)
        assert r.history["solver_result"] == ref.history["solver_result"] == "successful"
        assert np.allclose(r.history["objective"], ref.history["objective"], rtol=1e-12, atol=0)
        assert np.abs(r.mesh.points - ref.mesh.points).max() < 1e-12
        assert r.after.inverted_corners == 0 and r.after.max_condition < r.before.max_condition
    # four devices: each holds its quarter of the memory (10 pairs of s and y: a (20, n / 4) block), and the
    # program exchanges once per trial and once more per accepted step (plus the start's evaluation), and
    # gathers the direction once
    prog = hlo[-1]
    one, four = ({int(k) for k in re.findall(r"f64\\[20,(\\d+)\\]", h) if int(k) > 3} for h in (hlo[0], hlo[-1]))
    assert len(one) == len(four) == 1 and 4 * four.pop() == one.pop(), (one, four)
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
