"""`jaxci.smooth(..., devices=...)` and ``jaxci smooth --devices``: sharded and single-device runs give the same
mesh, the same guarantees, and the sharded solver loop compiles once.

The multi-device checks run in ONE subprocess with ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (the
flag is read when JAX starts); compilations are counted there with `jax.monitoring`'s duration events, as in
`tests/test_compile_buckets.py`.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
from helpers import cpu_env

import jaxci
from jaxci.errors import ConfigError
from jaxci.interface.smooth import smooth
from jaxci.mesh.generate import perturb_box

#: The start of every 4-device script: compilations counted per function (`COUNTS`), then JAX with 4 devices.
PREAMBLE = textwrap.dedent(
    """
    import collections
    from jax import monitoring
    COUNTS = collections.Counter()

    def on_duration(event, duration, fun_name="?", **_):
        if event == "/jax/core/compile/backend_compile_duration":
            COUNTS[fun_name] += 1

    monitoring.register_event_duration_secs_listener(on_duration)
    import jax
    import numpy as np
    assert len(jax.devices()) == 4, jax.devices()
    """
)


def _run_on_4_devices(script: str, marker: str, cwd=None) -> None:
    """Run `PREAMBLE` + `script` in a fresh process with 4 forced CPU devices (the flag is read when JAX starts)
    and the jaxci under test on its path, whatever the working directory; it must print `marker`."""
    src = os.path.dirname(os.path.dirname(jaxci.__file__))
    env = dict(cpu_env(4), PYTHONPATH=os.pathsep.join([src, *filter(None, [os.environ.get("PYTHONPATH")])]))
    r = subprocess.run([sys.executable, "-c", PREAMBLE + script], env=env, capture_output=True, text=True,
                       timeout=300, cwd=cwd)
    assert r.returncode == 0 and marker in r.stdout, r.stdout[-2000:] + r.stderr[-3000:]


SCRIPT = textwrap.dedent(
    """
    import contextlib, io
    from jaxci.errors import ConfigError
    from jaxci.mesh.generate import perturb_box
    from jaxci.geometry.boundary import INTERIOR
    from jaxci.interface.smooth import smooth

    def loops(counts):
        return {k: v for k, v in counts.items() if "solve_loop" in k or "lbfgs_loop" in k or "laplace_run" in k}

    m = perturb_box(6, 5, 4, amplitude=0.3, seed=1)  # 120 hexes: 128 padded elements, 32 per device
    runs = {}
    for dev in (1, 4):
        COUNTS.clear()
        # boundary fixed: a smaller program to compile (no projection), so that the test takes ~20 s
        r = smooth(m, "lbfgs", devices=dev, dtype="float64", presmooth=2, fix_boundary=True)
        runs[dev] = (r, loops(COUNTS), sum(COUNTS.values()))
    (r1, c1, _), (r4, c4, all4) = runs[1], runs[4]
    # the sharded run compiles the sweeps and the solver loop once each, as the single-device run does, and
    # nothing else (its arrays are placed on the devices from the host: no resharding programs)
    assert c4 == {"jit(_laplace_run)": 1, "jit(lbfgs_loop)": 1} == c1, (c1, c4)
    assert all4 == 2, all4
    assert r4.params["devices"] == 4 and r4.params["backend"] == "jax" and r4.history["presmooth"] == 2
    assert any("sharded over 4 cpu devices" in n and "host path" in n for n in r4.notes), r4.notes
    # same mesh to float tolerance, same validity
    assert np.allclose(r1.mesh.points, r4.mesh.points, rtol=0, atol=1e-9), np.abs(r1.mesh.points - r4.mesh.points).max()
    assert abs(r1.iterations - r4.iterations) <= 2, (r1.iterations, r4.iterations)
    for r in (r1, r4):
        assert r.after.inverted_corners == 0 and r.after.objective < r.before.objective
        assert r.after.max_condition <= r.before.max_condition
    assert abs(r1.after.max_condition - r4.after.max_condition) <= 1e-9
    # the fixed (boundary) nodes stay where they were, bit for bit; the interior ones moved
    fixed = np.asarray(r4.node_class) != INTERIOR
    assert np.array_equal(r4.mesh.points[fixed], m.points[fixed])
    assert (r4.mesh.points[~fixed] != m.points[~fixed]).all()
    # a second sharded run of the same size compiles no loop again
    COUNTS.clear()
    again = smooth(perturb_box(6, 5, 4, amplitude=0.3, seed=2), "lbfgs", devices="all", dtype="float64", presmooth=2,
                   fix_boundary=True)
    assert loops(COUNTS) == {}, COUNTS
    assert again.after.inverted_corners == 0
    # more devices than exist: a clear error that says how many exist; from the command: one line, exit 2
    try:
        smooth(m, "lbfgs", devices=8)
        raise AssertionError("devices=8 ran")
    except ConfigError as e:
        assert "only 4 cpu devices exist" in str(e), e
    from jaxci.cli import main
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(["smooth", "in.vtu", "out.vtu", "--devices", "9"])
    assert rc == 2 and "only 4 cpu devices exist" in err.getvalue() and "Traceback" not in err.getvalue(), \\
        (rc, err.getvalue())
    print("SHARDED-SMOOTH-OK")
    """
)


def test_sharded_smooth_matches_single_device_and_compiles_once(tmp_path):
    from jaxci.io import write_mesh

    write_mesh(perturb_box(3, 3, 3, amplitude=0.2, seed=0), str(tmp_path / "in.vtu"))
    _run_on_4_devices(SCRIPT, "SHARDED-SMOOTH-OK", cwd=tmp_path)


CI_SCRIPT = textwrap.dedent(
    """
    from jaxci.geometry.boundary import INTERIOR
    from jaxci.mesh.generate import perturb_box
    from jaxci.interface.smooth import smooth

    m = perturb_box(5, 4, 4, amplitude=0.3, seed=3)  # 80 hexes; surface and edge nodes slide
    runs = {}
    for dev in (1, 4):
        COUNTS.clear()
        r = smooth(m, "ci", devices=dev, dtype="float64", max_sweeps=6, seed=7)
        runs[dev] = (r, {k: v for k, v in COUNTS.items() if "local_ci_run" in k})
    (r1, c1), (r4, c4) = runs[1], runs[4]
    assert c1 == c4 == {"jit(_local_ci_run)": 1}, (c1, c4)
    assert r4.params["devices"] == 4 and r4.params["backend"] == "jax"
    assert any("sharded over 4 cpu devices" in n for n in r4.notes), r4.notes
    # the cohorts of a colour's nodes split over the devices draw the same numbers: the same mesh
    gap = np.abs(r1.mesh.points - r4.mesh.points).max()
    assert gap <= 1e-12, gap
    assert r1.iterations == r4.iterations == 6
    assert np.allclose(r1.history["objective"], r4.history["objective"], rtol=1e-12, atol=0)
    for r in (r1, r4):
        assert r.after.inverted_corners == 0 and r.after.objective < 0.5 * r.before.objective
        moved = np.linalg.norm(r.mesh.points - m.points, axis=1) > 0
        assert moved[np.asarray(r.node_class) != INTERIOR].any() and moved[np.asarray(r.node_class) == INTERIOR].all()
    # a second mesh of the same size class, sharded: no new compilation; a third seed, a different result
    COUNTS.clear()
    again = smooth(perturb_box(5, 4, 4, amplitude=0.3, seed=4), "ci", devices=4, dtype="float64", max_sweeps=6)
    assert not {k for k in COUNTS if "local_ci_run" in k}, COUNTS
    assert again.after.objective < again.before.objective
    other = smooth(m, "ci", devices=4, dtype="float64", max_sweeps=6, seed=8)
    assert not np.array_equal(other.mesh.points, r4.mesh.points)
    # global CI: the trial meshes of each attempt split over the devices; the unsharded compiled run's mesh
    small = perturb_box(3, 3, 3, amplitude=0.3, seed=1)
    glob = {}
    for dev in (None, 4):
        COUNTS.clear()
        glob[dev] = smooth(small, "ci-global", devices=dev, dtype="float64", attempts=40, backend="jax")
        assert {k: v for k, v in COUNTS.items() if "global_ci_run" in k} == {"jit(_global_ci_run)": 1}, COUNTS
    assert np.array_equal(glob[None].mesh.points, glob[4].mesh.points)
    assert glob[4].iterations == 40 and glob[4].after.objective < glob[4].before.objective
    assert any("trial meshes" in n for n in glob[4].notes), glob[4].notes
    print("SHARDED-CI-OK")
    """
)


def test_sharded_ci_matches_single_device_and_compiles_once():
    """Local CI over 4 forced CPU devices (each colour's node slots split over them): the single-device mesh,
    one compilation, and none for a second mesh of the size class; global CI (its trial meshes split): the
    unsharded mesh, bit for bit."""
    _run_on_4_devices(CI_SCRIPT, "SHARDED-CI-OK")


@pytest.mark.parametrize("devices, message", [
    (0, "at least 1"), ("two", "positive integer, 'all'"), (True, "positive integer"), ([], "empty"),
    (10**6, "but only"), ([0, 0], "twice"), ([10**6], "out of range"),
])
def test_bad_devices_are_refused_before_any_work(devices, message):
    with pytest.raises(ConfigError, match=message):
        smooth(perturb_box(2, 2, 2, amplitude=0.1, seed=0), "lbfgs", devices=devices)


@pytest.mark.parametrize("method, params, message", [
    ("lm", {}, "not 'lm'"), ("lbfgs", {"backend": "numpy"}, "engine 'host' runs on one CPU and cannot be sharded"),
    ("ci", {"backend": "numpy"}, "engine 'host'"), ("ci", {"engine": "host"}, "engine 'host'"),
])
def test_methods_that_cannot_run_sharded_are_refused(method, params, message):
    with pytest.raises(ConfigError, match=message):
        smooth(perturb_box(2, 2, 2, amplitude=0.1, seed=0), method, devices=1, **params)


PROCESS = textwrap.dedent(
    """
    import sys
    import jax
    from jaxci.optim.sharding import init_distributed
    port, pid, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    init_distributed(f"localhost:{port}", 2, pid, initialization_timeout=120)
    assert jax.process_count() == 2 and len(jax.devices()) == 2 and len(jax.local_devices()) == 1
    import numpy as np
    from jaxci.mesh.generate import perturb_box
    from jaxci.interface.smooth import smooth
    m = perturb_box(6, 5, 4, amplitude=0.3, seed=1)
    r = smooth(m, "lbfgs", devices="all", dtype="float64", fix_boundary=True)  # one element half per process
    assert r.params["devices"] == 2 and r.after.inverted_corners == 0
    np.save(f"{out}/sharded{pid}.npy", r.mesh.points)
    if pid == 0:  # the reference: this process's own device alone
        np.save(f"{out}/single.npy", smooth(m, "lbfgs", devices=jax.local_devices(), dtype="float64",
                                            fix_boundary=True).mesh.points)
    print("PROCESS-OK")
    """
)


@pytest.mark.slow
def test_two_processes_on_localhost_give_the_single_device_mesh(tmp_path):
    """The multi-host launch (`jaxci.optim.sharding.init_distributed`, one process per host, a coordinator
    address) with two processes on this host, one CPU device each: every process gets the single-device mesh."""
    import socket

    import numpy as np

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = str(s.getsockname()[1])
    src = os.path.dirname(os.path.dirname(jaxci.__file__))
    env = dict(cpu_env(), PYTHONPATH=os.pathsep.join([src, *filter(None, [os.environ.get("PYTHONPATH")])]))
    procs = [subprocess.Popen([sys.executable, "-c", PROCESS, port, str(i), str(tmp_path)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = []
    try:
        for p in procs:
            outs.append(p.communicate(timeout=300))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, (out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0 and "PROCESS-OK" in out, err[-3000:]
    single = np.load(tmp_path / "single.npy")
    for i in range(2):
        assert np.allclose(np.load(tmp_path / f"sharded{i}.npy"), single, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["auto", "lbfgs", "laplace", "smart-laplace", "ci", "ci-global"])
def test_methods_with_a_host_path_run_compiled_when_sharded(method):
    """Without devices these run small meshes on the host (numpy and C); with devices, never (the note says so)."""
    from jaxci.optim.sharding import resolve_devices, sharded_params

    params, note = sharded_params(method, {"max_sweeps": 3} if "laplace" in method else {}, resolve_devices(1))
    assert params["backend"] == "jax" and "host path" in note and "compiled JAX path" in note


TERMS_SCRIPT = textwrap.dedent(
    """
    import jax.numpy as jnp
    from jaxci.mesh.generate import perturb_box
    from jaxci.metrics.hexahedron import objective_terms_and_grad
    from jaxci.optim.sharding import device_mesh, place_problem, sharded_terms_and_grad

    jax.config.update("jax_enable_x64", True)
    m = perturb_box(5, 4, 3, amplitude=0.3, seed=2)  # 60 hexes: 4 padding elements on 4 devices
    mesh = device_mesh()
    hexes = np.asarray(m.hexes)  # padded to 64 elements: copies of element 0, weight 0
    conn = np.concatenate([hexes, np.repeat(hexes[:1], 4, axis=0)]).T.copy()
    weight = np.concatenate([np.ones(60), np.zeros(4)])
    conn, weight, x = place_problem(jnp.asarray(conn), jnp.asarray(weight), jnp.asarray(m.points), mesh)
    f, k, g = jax.jit(lambda x, c, w: sharded_terms_and_grad(x, c, w, mesh))(x, conn, weight)
    f1, k1, g1 = objective_terms_and_grad(jnp.asarray(m.points), jnp.asarray(np.asarray(m.hexes).T))
    # (on CPU each device's share comes from the C kernel, jaxci.metrics.native_grad: other roundings)
    assert abs(float(f) - float(f1)) <= 1e-13 * abs(float(f1)), (f, f1)
    assert abs(float(k) - float(k1)) <= 1e-13 * abs(float(k1)), (k, k1)
    assert np.allclose(np.asarray(g), np.asarray(g1), rtol=1e-12, atol=1e-15)
    # one exchange: each device's share summed locally, then a single all-reduce
    hlo = jax.jit(lambda x, c, w: sharded_terms_and_grad(x, c, w, mesh)).lower(x, conn, weight).compile().as_text()
    assert hlo.count("all-reduce(") == 1, hlo.count("all-reduce(")
    print("TERMS-OK")
    """
)


def test_sharded_objective_and_gradient_are_the_whole_meshs_in_one_exchange():
    """`jaxci.optim.sharding.sharded_terms_and_grad` (the sharded L-BFGS's objective) on 4 forced devices: F, the
    max and the gradient of the whole mesh (float64, padding elements included), with ONE all-reduce in the
    compiled program (XLA's own partitioning of the gradient's 24 scatters made 25)."""
    _run_on_4_devices(TERMS_SCRIPT, "TERMS-OK")
