"""Phase timings (`jaxci.runtime.phases`), the default pipeline (``method="auto"``), the note when an iteration cap
stops a method, and the already-optimal shortcut."""

from __future__ import annotations

import json

import numpy as np

import jaxci
from jaxci.cli import main
from jaxci.io import write_mesh
from jaxci.mesh.generate import box, perturb_box
from jaxci.runtime.phases import PhaseClock, compile_totals

PHASE_KEYS = {"seconds", "compile_seconds", "compiled", "cache_hits", "h2d_bytes", "d2h_bytes", "device_s", "host_s"}


def test_phase_clock_counts_compilations():
    import jax
    import jax.numpy as jnp

    clock = PhaseClock()
    with clock.phase("a"):
        jax.jit(lambda x: jnp.sin(x) * 3.0 + 0.123456)(jnp.arange(7.0)).block_until_ready()
    with clock.phase("a"):
        pass
    d = clock.as_dict()
    assert set(d) == {"a", "total"}
    assert set(d["a"]) == PHASE_KEYS
    assert d["a"]["compiled"] >= 1 and d["a"]["compile_seconds"] > 0
    assert d["total"]["seconds"] >= d["a"]["compile_seconds"]
    assert compile_totals()["compiled"] >= 1


def test_default_is_auto_and_reports_phases():
    mesh = perturb_box(3, 3, 3, amplitude=0.2, seed=1)
    res = jaxci.smooth(mesh)
    assert res.method == "auto" and res.params["pipeline"].startswith("L-BFGS")
    assert any(n.startswith("default method (auto)") for n in res.notes)
    assert {"validate", "report", "setup", "smooth", "checks", "total"} <= set(res.phases)
    assert res.after.max_condition < res.before.max_condition
    assert res.summary()["phases"] == res.phases


def test_auto_presmooths_large_meshes_on_the_host_and_every_mesh_on_jax(monkeypatch):
    import dataclasses

    from jaxci.interface import methods
    from jaxci.interface.engine import host_plan

    mesh = box(4, 4, 4)  # 64 hexahedra
    host = host_plan()
    compiled = dataclasses.replace(host, engine="jax", kernel="XLA")
    newton = {"solver": "newton", "newton_after": methods.AUTO_NEWTON_AFTER}
    escape = {"escape": methods.AUTO_ESCAPE} if methods.native.AVAILABLE else {}  # (the host's C sweeps)
    assert methods.auto_pipeline(mesh, {}, host)[1] == {"polish": True, **newton, **escape}
    # float32 L-BFGS alone stalls
    assert methods.auto_pipeline(mesh, {}, compiled)[1] == {"presmooth": 3, "polish": True, "solver": "auto"}
    monkeypatch.setattr(methods, "AUTO_PRESMOOTH_FROM", 64)  # the host's sweeps are the C kernels: none without
    want = {"presmooth": 3, "polish": True} if methods.native.AVAILABLE else {"polish": True}
    assert methods.auto_pipeline(mesh, {}, host)[1] == want | newton | escape
    monkeypatch.setattr(methods.native, "AVAILABLE", False)
    assert methods.auto_pipeline(mesh, {}, host)[1] == {"polish": True, **newton}
    # the user's values win; the p-mean has no polish and no Newton
    assert methods.auto_pipeline(mesh, {"presmooth": 0, "polish": False}, host)[1] == {"presmooth": 0,
                                                                                      "polish": False, **newton}
    assert methods.auto_pipeline(mesh, {"newton_after": 50}, host)[1]["newton_after"] == 50
    assert methods.auto_pipeline(mesh, {"solver": "lbfgs"}, host)[1] == {"solver": "lbfgs", "polish": True}
    assert methods.auto_pipeline(mesh, {"objective": "pmean"}, host)[1] == {"objective": "pmean"}


def test_optimal_mesh_returns_at_once():
    mesh = box(3, 3, 3)
    res = jaxci.smooth(mesh, "lbfgs")
    assert res.iterations == 0
    assert any("already optimal" in n for n in res.notes)
    np.testing.assert_array_equal(res.mesh.points, mesh.points)
    assert "smooth" not in res.phases  # no method ran, nothing compiled for it


def test_cap_is_a_note():
    mesh = perturb_box(3, 3, 3, amplitude=0.3, seed=2)
    res = jaxci.smooth(mesh, "lbfgs", max_steps=2)
    assert any("stopped at its cap of 2 iterations (max_steps)" in n for n in res.notes)
    done = jaxci.smooth(mesh, "lbfgs")
    assert not any("cap" in n for n in done.notes)


def test_cli_json_and_verbose_phases(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    write_mesh(perturb_box(3, 3, 3, amplitude=0.2, seed=3), "in.vtk")
    assert main(["smooth", "in.vtk", "out.vtk", "--json", "--verbose"]) == 0
    out, err = capsys.readouterr()
    summary = json.loads(out)
    phases = summary["phases"]
    assert {"startup", "read", "validate", "smooth", "checks", "write", "total"} <= set(phases)
    assert all(set(v) == PHASE_KEYS for v in phases.values())
    assert summary["method"] == "auto"
    lines = err.strip().splitlines()
    assert any(line.startswith("jaxci: read") for line in lines)
    assert lines[-1].startswith("jaxci: total")


def test_every_phase_gives_the_heap_free_pages_back(monkeypatch):
    """A phase starts by handing the C heap's free pages back to the OS (`jaxci.runtime.memory.release_free_memory`,
    glibc's malloc_trim: the last phase's temporaries do not stay resident under the next one's arrays); on
    Linux with glibc it runs, elsewhere it is a no-op that says so."""
    import sys

    from jaxci.runtime import memory, phases

    calls = []
    monkeypatch.setattr(phases, "release_free_memory", lambda: calls.append(1))
    clock = PhaseClock()
    with clock.phase("read"):
        pass
    with clock.phase("smooth"):
        pass
    assert len(calls) == 2
    ran = memory.release_free_memory()
    assert ran is (memory._malloc_trim() is not None)
    if sys.platform.startswith("linux") and "glibc" in " ".join(__import__("platform").libc_ver()):
        assert ran


def test_phase_counts_transfers_and_time_in_programs():
    """A phase records the bytes `jaxci.runtime.transfer` moves each way, the seconds inside `program` calls (their
    compilation excluded) and the rest as host seconds."""
    import time

    import jax
    import numpy as np

    from jaxci.runtime.transfer import program, to_device, to_host

    @program
    @jax.jit
    def double(a):
        return a * 2.0

    clock = PhaseClock()
    a = np.arange(1000, dtype=np.float64)
    with clock.phase("p"):
        d = to_device(a)
        double(d)  # compiles: not device time
        out = to_host(double(d))
        time.sleep(0.05)  # host time
    rec = clock.as_dict()["p"]
    assert rec["h2d_bytes"] == a.nbytes and rec["d2h_bytes"] == a.nbytes
    np.testing.assert_array_equal(out, 2 * a)
    assert rec["compiled"] >= 1 and rec["compile_seconds"] > 0
    assert 0 < rec["device_s"] < rec["seconds"] - rec["compile_seconds"]
    assert rec["host_s"] >= 0.05
    assert abs(rec["host_s"] + rec["device_s"] + rec["compile_seconds"] - rec["seconds"]) < 1e-3
