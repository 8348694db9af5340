"""Size classes (`jaxci.optim._buckets`): meshes of similar size share one compiled solver, and the padding
changes no result.

Compilations are counted with `jax.monitoring`'s duration events (one ``backend_compile`` event per XLA
compilation or persistent-cache load, named by the function).
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import monitoring

from jaxci.interface.smooth import build_problem, smooth
from jaxci.mesh.generate import perturb_box
from jaxci.optim import _buckets as B
from jaxci.optim.gradient import GradientParams, make_parametrisation, minimise, pad_parametrisation
from jaxci.optim.solver_objective import solver_objective

_COUNTS: collections.Counter = collections.Counter()
_LISTENING = False


def _on_duration(event, duration, fun_name="?", **_):
    if event == "/jax/core/compile/backend_compile_duration":
        _COUNTS[fun_name] += 1


@contextlib.contextmanager
def compilations():
    """Count XLA compilations by function name inside the block: yields a Counter filled on exit."""
    global _LISTENING
    if not _LISTENING:
        monitoring.register_event_duration_secs_listener(_on_duration)
        _LISTENING = True
    before = collections.Counter(_COUNTS)
    out = collections.Counter()
    yield out
    out.update({k: v - before.get(k, 0) for k, v in _COUNTS.items() if v - before.get(k, 0)})


def test_ladder():
    assert [B.bucket(n) for n in (0, 1, 8, 9, 12, 13, 17, 25, 33, 49, 810, 900, 1000, 1024, 1025, 1331)] == \
        [0, 8, 8, 12, 12, 16, 24, 32, 48, 64, 1024, 1024, 1024, 1024, 1536, 1536]
    for n in range(1, 5000):
        b = B.bucket(n)
        assert n <= b <= max(8, 1.5 * n)


def _problem(nx, ny, nz, dtype=np.float64, seed=3):
    mesh = perturb_box(nx, ny, nz, amplitude=0.3, seed=seed)
    with jax.enable_x64(dtype == np.float64):
        pr = build_problem(mesh, dtype=dtype)
    return mesh, pr


def test_padding_changes_neither_objective_nor_gradient():
    mesh, pr = _problem(4, 3, 5)
    par = make_parametrisation(pr.mesh, pr.info, pr.cons, dtype=np.float64)
    padded, index = pad_parametrisation(par)
    c, w = B.padded_connectivity(mesh.hexes, B.bucket(mesh.n_hexes))
    conn_p, w = jnp.asarray(c), jnp.asarray(w)
    assert padded.n_free > par.n_free and conn_p.shape[1] > mesh.n_hexes and padded.x0.shape[0] > mesh.n_nodes
    rng = np.random.default_rng(0)
    v = 0.05 * rng.standard_normal(par.n_free)
    vp = np.zeros(padded.n_free)
    vp[index] = v
    vp_noise = vp.copy()
    pad_slots = np.setdiff1d(np.arange(padded.n_free), index)
    vp_noise[pad_slots] = rng.standard_normal(len(pad_slots))  # padded coordinates move nothing
    for closed in (True, False):
        def f(v, par=par, conn=pr.conn, weight=None, closed=closed):
            return solver_objective(par.points(v), conn, closed, None, weight)[0]

        f0, g0 = jax.value_and_grad(f)(jnp.asarray(v))
        for vv in (vp, vp_noise):
            fp, gp = jax.value_and_grad(f)(jnp.asarray(vv), par=padded, conn=conn_p, weight=w)
            assert float(fp) == pytest.approx(float(f0), rel=1e-13)
            np.testing.assert_allclose(np.asarray(gp)[index], np.asarray(g0), rtol=1e-11, atol=1e-14)
            assert not np.asarray(gp)[pad_slots].any()  # exactly zero
        kp = solver_objective(padded.points(jnp.asarray(vp)), conn_p, closed, None, w)[1]
        k0 = solver_objective(par.points(jnp.asarray(v)), pr.conn, closed, None, None)[1]
        assert float(kp) == pytest.approx(float(k0), rel=1e-14)
    x = np.asarray(padded.points(jnp.asarray(vp_noise)))
    np.testing.assert_array_equal(x[mesh.n_nodes:], np.asarray(padded.x0)[mesh.n_nodes:])  # padding nodes stay
    np.testing.assert_allclose(x[: mesh.n_nodes], np.asarray(par.points(jnp.asarray(v))), rtol=0, atol=1e-15)


@pytest.mark.parametrize("method", ["lbfgs", "cg"])
def test_padded_solver_gives_the_unpadded_result(method):
    mesh, pr = _problem(4, 3, 5)
    with jax.enable_x64(True):
        par = make_parametrisation(pr.mesh, pr.info, pr.cons, dtype=np.float64)
        out = [minimise(method, par, pr.conn, GradientParams(buckets=b, backend="jax")) for b in (True, False)]
    (xa, ka, ha, _), (xb, kb, hb, _) = out
    assert ha["solver_result"] == hb["solver_result"] == "successful"
    np.testing.assert_allclose(np.asarray(xa), np.asarray(xb), rtol=0, atol=1e-6)
    assert ha["objective"][-1] == pytest.approx(hb["objective"][-1], rel=1e-6, abs=1e-12)
    np.testing.assert_allclose(ha["objective"][: min(ka, kb, 20)], hb["objective"][: min(ka, kb, 20)], rtol=1e-9)


@pytest.mark.parametrize("method,params", [("lbfgs", {"backend": "jax"}), ("lbfgs", {"presmooth": 3, "backend": "jax"}),
                                           ("smart-laplace", {}),
                                           ("laplace", {"max_sweeps": 50})],
                         ids=["lbfgs", "presmooth", "smart-laplace", "laplace"])
def test_two_meshes_of_one_bucket_compile_the_solver_once(method, params):
    """9x9x10 (810 hexahedra, 1100 nodes) and 10x10x9 (900, 1210) are one size class: the second mesh compiles
    no solver loop and no sweep loop."""
    meshes = [perturb_box(9, 9, 10, amplitude=0.3, seed=1), perturb_box(10, 10, 9, amplitude=0.3, seed=2)]
    counts = []
    for mesh in meshes:
        with compilations() as c:
            res = smooth(mesh, method, **params)
        assert res.after.max_condition < 1.01
        counts.append(c)
    assert counts[0]["jit(lbfgs_loop)"] <= 1 and counts[0]["jit(_laplace_run)"] <= 1  # 0: compiled by an earlier test
    assert counts[1]["jit(lbfgs_loop)"] == 0 and counts[1]["jit(_laplace_run)"] == 0, counts[1]


def _cli_smooth(src, out, cache):
    env = dict(os.environ, JAXCI_CACHE_DIR=str(cache))
    p = subprocess.run([sys.executable, "-m", "jaxci", "smooth", str(src), str(out), "--method", "lbfgs", "--json",
                        "--param", "backend=jax"],  # the compiled loop (small meshes run in numpy by default)
                       env=env, capture_output=True, text=True, check=True)
    return json.loads(p.stdout)["phases"]["smooth"]


@pytest.mark.parametrize("buckets", [True, False])
def test_padded_sweeps_give_the_unpadded_result(buckets):
    mesh, pr = _problem(4, 3, 5)
    with jax.enable_x64(True):
        from jaxci.optim.laplace import run_laplace

        out = [run_laplace(pr, "smart-laplace", {"max_sweeps": 30, "buckets": b}) for b in (buckets, False)]
    (xa, sa, ha, _), (xb, sb, hb, _) = out
    assert sa == sb
    np.testing.assert_allclose(np.asarray(xa), np.asarray(xb), rtol=0, atol=1e-12)
    np.testing.assert_allclose(ha["objective"], hb["objective"], rtol=1e-12)
    np.testing.assert_allclose(ha["max_condition"], hb["max_condition"], rtol=1e-12)


@pytest.mark.slow
def test_cli_second_mesh_of_a_size_class_loads_the_solver_from_the_cache(tmp_path):
    """Through the CLI, fresh processes and an empty JAXCI_CACHE_DIR: the second mesh of the size class compiles
    nothing in its smoothing phase but the padding of its own size (the solver comes from the persistent
    cache)."""
    from jaxci.io import write_mesh

    for name, dims, seed in (("a.vtk", (9, 9, 10), 1), ("b.vtk", (10, 10, 9), 2)):
        write_mesh(perturb_box(*dims, amplitude=0.3, seed=seed), str(tmp_path / name))
    cache = tmp_path / "cache"
    first = _cli_smooth(tmp_path / "a.vtk", tmp_path / "a_out.vtk", cache)
    second = _cli_smooth(tmp_path / "b.vtk", tmp_path / "b_out.vtk", cache)
    assert first["compiled"] > first["cache_hits"]
    # one program of the mesh's own size: the parametrisation and the hexahedra padded on the device
    # (`jaxci.optim.parametrisation.pad_problem_device`); the solver comes from the cache
    assert second["compiled"] - second["cache_hits"] <= 1, second


def test_padded_sweeps_keep_their_unpadded_stars_on_the_host(monkeypatch):
    """The padded Laplace run builds its stars and neighbours in the device's layout and dtypes but on the host
    (the device never holds both the unpadded and the padded forms), the same arrays as placed ones, and the
    sweeps give the same mesh as without padding."""
    from jaxci.optim import laplace as L
    from jaxci.optim._moves import coloured_stars

    mesh = perturb_box(5, amplitude=0.3, seed=4)
    problem = build_problem(mesh)
    faces = problem.info.topology.faces
    placed = coloured_stars(mesh.hexes, problem.cons, problem.colour, faces)
    kept = coloured_stars(mesh.hexes, problem.cons, problem.colour, faces, place=False)
    for name in ("nodes", "mask", "star", "smask", "basis", "dims", "plane"):
        a, b = getattr(placed, name), getattr(kept, name)
        assert isinstance(a, jax.Array) and isinstance(b, np.ndarray), name
        assert a.dtype == b.dtype and np.array_equal(np.asarray(a), b), name
    seen = []
    real = L.laplace

    def spy(points, conn, cs, nbr, nmask, *a, **k):
        seen.append(type(cs.star))
        seen.append(type(nbr))
        return real(points, conn, cs, nbr, nmask, *a, **k)

    monkeypatch.setattr(L, "laplace", spy)
    padded = L.run_laplace(problem, "smart-laplace", {"max_sweeps": 2})
    plain = L.run_laplace(problem, "smart-laplace", {"max_sweeps": 2, "buckets": False})
    assert seen[:2] == [np.ndarray, np.ndarray] and all(issubclass(t, jax.Array) for t in seen[2:])
    np.testing.assert_allclose(np.asarray(padded[0]), np.asarray(plain[0]), rtol=0, atol=1e-6)


def test_large_classes_have_no_slot_slack_and_the_same_sweeps(monkeypatch):
    """From `_SLACK_UNTIL` nodes of a class on, the slots of a colour are the most nodes of one colour rounded up to
    the ladder (no slack): fewer padded slots, the same mesh from the sweeps."""
    from jaxci.optim import _moves as M
    from jaxci.optim import laplace as L

    mesh = perturb_box(6, amplitude=0.3, seed=2)
    problem = build_problem(mesh)
    cs = M.coloured_stars(mesh.hexes, problem.cons, problem.colour, problem.info.topology.faces, place=False)
    slack = M.slot_sizes(cs)
    x_slack = np.asarray(L.run_laplace(problem, "smart-laplace", {"max_sweeps": 2})[0])
    monkeypatch.setattr(M, "_SLACK_UNTIL", 1)
    tight = M.slot_sizes(cs)
    sizes = (cs.n_interior, cs.n_surface, cs.n_edge)
    assert all(m <= t <= s for m, t, s in zip(sizes, tight, slack, strict=True)) and sum(tight) < sum(slack)
    assert tight == tuple(B.bucket(max(m, -(-B.bucket(int(np.asarray(cs.mask)[:, lo:lo + m].sum()))
                                            // B.bucket(np.asarray(cs.mask).shape[0])))) if m else 0
                          for m, lo in zip(sizes, np.cumsum((0,) + sizes[:-1]), strict=True))
    x_tight = np.asarray(L.run_laplace(problem, "smart-laplace", {"max_sweeps": 2})[0])
    np.testing.assert_allclose(x_tight, x_slack, rtol=0, atol=1e-6)
