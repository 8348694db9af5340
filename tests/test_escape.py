"""The default pipeline's escape from a solver's poor minimum (`jaxci.optim.escape`): local CI sweeps that probe
the solver's minimum, and the solver again from their end where they lower F."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import wavy_annulus

from jaxci import native, smooth
from jaxci.optim import escape as esc

pytestmark = pytest.mark.skipif(not native.AVAILABLE, reason="the escape's sweeps are the host's C kernels")


def test_a_minimum_the_sweeps_cannot_lower_stands():
    """On a curved annulus L-BFGS's minimum is one for the sweeps too: one sweep probes it, gains less than 1%, and
    the result is L-BFGS's, bit for bit, with no round run."""
    mesh = wavy_annulus(16, 3, 3)
    run = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False, escape=8)
    ref = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False)
    report = run.history["escape"]
    assert report["rounds"] == 0 and len(report["sweeps"]) == 1
    before, after = report["sweeps"][0]
    assert after <= before and not after < (1 - esc.GAIN) * before
    np.testing.assert_array_equal(run.mesh.points, ref.mesh.points)
    assert run.iterations == ref.iterations


def test_rounds_lower_f_and_count_their_sweeps_and_steps(monkeypatch):
    """With the gain needed to start a round at 0, rounds run: F ends lower than L-BFGS's, each round's sweeps and
    solver steps are counted and in the history (one entry each), and no element is inverted."""
    mesh = wavy_annulus(16, 3, 3)
    ref = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False)
    monkeypatch.setattr(esc, "GAIN", 0.0)
    run = smooth(mesh, method="lbfgs", dtype="float64", keep_worst=False, escape=2)
    report = run.history["escape"]
    assert report["rounds"] >= 1
    assert run.after.objective < ref.after.objective and run.after.inverted_elements == 0
    assert len(run.history["objective"]) == run.iterations + 1
    assert run.history["objective"][-1] == pytest.approx(run.after.objective, rel=1e-9)
    assert report["objective"][1] == pytest.approx(run.after.objective, rel=1e-9)
    assert report["objective"][1] < report["objective"][0]
    assert any(n.startswith(f"escape: the solver had stopped at a minimum for small moves only; {report['rounds']} "
                            "rounds") for n in run.notes)


def test_the_default_pipeline_escapes_on_the_host_only_where_asked():
    """The default pipeline's parameters carry `AUTO_ESCAPE` rounds on the host engine (none: the candidate cells
    follow their nodes, `jaxci.geometry.anchors`); `escape=0` turns the stage off (no report), and a mesh L-BFGS
    smooths to the ideal has nothing to escape from."""
    from jaxci.interface.methods import AUTO_ESCAPE
    from jaxci.mesh.generate import perturb_box

    mesh = wavy_annulus(16, 3, 3)
    assert smooth(mesh).params["escape"] == AUTO_ESCAPE
    assert "escape" not in smooth(mesh, escape=0).history
    box = smooth(perturb_box(4, amplitude=0.2, seed=1), escape=8)
    assert "escape" not in box.history and box.after.max_condition <= 1.0 + 1e-6


def test_an_escape_that_cannot_run_is_refused():
    """``escape`` asked for where its sweeps cannot run (another method, the JAX engine, a mixed mesh) or with the
    p-mean (its sweeps lower F): one `ConfigError` naming the parameter, not a silent no-op."""
    from jaxci.errors import ConfigError
    from jaxci.mesh.generate import perturb_box

    box = perturb_box(3, amplitude=0.2, seed=1)
    with pytest.raises(ConfigError, match="escape=2 is for method 'lbfgs'.*not 'bfgs'"):
        smooth(box, method="bfgs", escape=2)
    with pytest.raises(ConfigError, match="escape=2 is for method 'lbfgs'.*not 'lbfgs' on the JAX engine"):
        smooth(box, method="lbfgs", engine="jax", escape=2)
    with pytest.raises(ConfigError, match="escape=2 is for objective='mean'"):
        smooth(box, method="lbfgs", objective="pmean", escape=2)
