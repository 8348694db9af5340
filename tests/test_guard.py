"""The worst-element guard (`jaxci.metrics.guard`, `smooth(keep_worst=True)`): the returned mesh's worst cell
is no worse than the input's, whatever the method did, and only the nodes near the offending cells are put back."""

from __future__ import annotations

import numpy as np
import pytest

import jaxci
from jaxci.mesh.generate import perturb_box
from jaxci.metrics import guard


@pytest.fixture(scope="module")
def case():
    """A perturbed 4^3 box, its L-BFGS result, and that result with one interior node pushed so that a cell ends
    worse than the input's worst cell (while F stays lower than the input's)."""
    mesh = perturb_box(4, 4, 4, amplitude=0.25, seed=4)
    res = jaxci.smooth(mesh, "lbfgs", dtype="float64")
    good = np.array(res.mesh.points)
    inner = np.flatnonzero(res.node_class == 0)
    node = int(inner[0])
    bad = good.copy()
    w0 = guard.worst(mesh, mesh.points)
    direction = np.array([1.0, 0.7, 0.4]) / np.linalg.norm([1.0, 0.7, 0.4])
    for step in np.linspace(0.01, 0.24, 47):  # the smallest push that makes the worst cell worse than the input's
        bad[node] = good[node] + step * direction
        if guard.worst(mesh, bad) > w0:
            break
    assert guard.worst(mesh, bad) > w0
    return mesh, good, bad, node


def test_keep_worst_puts_back_only_what_it_must(case):
    mesh, good, bad, node = case
    x, n_back, w0, w1 = guard.keep_worst(mesh, mesh.points, bad)
    assert w1 > w0 and n_back >= 1
    assert guard.worst(mesh, x) <= w0 * (1 + 1e-12)
    np.testing.assert_array_equal(x[node], np.asarray(mesh.points)[node])
    moved_back = np.flatnonzero((x != bad).any(axis=1))
    assert len(moved_back) == n_back < mesh.n_nodes // 4  # local: most of the smoothing is kept


def test_keep_worst_leaves_a_better_result_alone(case):
    mesh, good, _, _ = case
    x, n_back, w0, w1 = guard.keep_worst(mesh, mesh.points, good)
    assert n_back == 0 and w1 <= w0
    np.testing.assert_array_equal(x, good)


def test_smooth_applies_the_guard_to_any_method(case, monkeypatch):
    """Whatever a method returns, smooth's float64 checks keep the worst cell (and say what it cost)."""
    from jaxci.interface import methods as S  # MethodRun.run looks run_method up there
    from jaxci.mesh import to_unit, unit_frame

    mesh, _, bad, _ = case
    real = S.run_method
    bad_unit = to_unit(bad, unit_frame(mesh.points))  # smooth works in the unit frame

    def worsening(problem, method, key, params):
        x, it, hist, resolved = real(problem, method, key, params)
        return bad_unit, it, hist, resolved

    monkeypatch.setattr(S, "run_method", worsening)
    guarded = jaxci.smooth(mesh, "lbfgs", dtype="float64")
    raw = jaxci.smooth(mesh, "lbfgs", dtype="float64", keep_worst=False)
    assert raw.after.max_condition > raw.before.max_condition
    assert guarded.after.max_condition <= guarded.before.max_condition * (1 + 1e-12)
    assert any(n.startswith("worst cell kept no worse") for n in guarded.notes)
    assert guarded.after.objective <= guarded.before.objective
