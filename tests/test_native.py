"""The C kernels of `jaxci.native` against the numpy kernels they replace on the host path (float64)."""

import os

import numpy as np
import pytest

from jaxci import native
from jaxci.cells import CORNER_NEIGHBOURS
from jaxci.mesh.generate import perturb_box
from jaxci.metrics.hexahedron import objective_terms_and_grad_np
from jaxci.optim._untangle_loop import corner_table, hex_kernel

if not native.AVAILABLE:
    if os.environ.get("CI") and os.environ.get("JAXCI_NATIVE", "1") != "0":
        pytest.fail("jaxci._ckernels was not built (a C compiler is on CI's machine: the install must build it)")
    pytest.skip("jaxci._ckernels not built (no C compiler at install time)", allow_module_level=True)


def _mesh(amplitude: float, seed: int = 0):
    return perturb_box(6, amplitude=amplitude, seed=seed)


def test_corner_table_of_the_c_kernel_is_jaxcis():
    src = open(os.path.join(os.path.dirname(native.__file__), "_ckernels.c")).read()
    table = src[src.index("NB[8][3] = ") + len("NB[8][3] = "):src.index(";", src.index("NB[8][3]"))]
    assert eval(table.replace("{", "[").replace("}", "]")) == CORNER_NEIGHBOURS.tolist()


@pytest.mark.parametrize("power", [None, 2.0, 4.0])
def test_objective_and_gradient_match_numpy(power):
    m = _mesh(0.2)
    x = np.asarray(m.points, np.float64)
    f, k, g = objective_terms_and_grad_np(x, np.ascontiguousarray(m.hexes.T), power)
    fc, kc, gc = native.hex_terms_and_grad(x, m.hexes, power)
    assert np.isfinite(f) and fc == pytest.approx(f, rel=1e-12)
    assert kc == pytest.approx(k, rel=1e-12)
    np.testing.assert_allclose(gc, g, rtol=1e-10, atol=1e-13 * np.abs(g).max())


def test_inverted_corner_gives_inf_and_the_gradient_of_the_others():
    m = _mesh(0.2)
    x = np.asarray(m.points, np.float64)
    x[m.hexes[0, 0]] = x[m.hexes[0, 6]] + 0.1  # node 0 of element 0 beyond its opposite corner: inverted
    f, k, g = objective_terms_and_grad_np(x, np.ascontiguousarray(m.hexes.T))
    fc, kc, gc = native.hex_terms_and_grad(x, m.hexes)
    assert f == fc == np.inf and kc == np.inf
    np.testing.assert_allclose(gc, g, rtol=1e-10, atol=1e-13 * np.abs(g).max())


@pytest.mark.parametrize("eps", [1.0, 1e-3, 1e-10])
def test_untangling_energy_matches_numpy(eps):
    m = _mesh(0.0)
    x = np.asarray(m.points, np.float64) + np.random.default_rng(3).uniform(-0.1, 0.1, m.points.shape)  # tangled
    inv_len = np.random.default_rng(0).uniform(0.5, 2.0, m.n_hexes)  # per element; the corner table repeats it
    e, d, g = hex_kernel(x, corner_table(m.hexes), np.tile(inv_len, 8), eps, 0.3, True, np)
    ec, dc, gc = native.untangle_energy(x, m.hexes, inv_len, eps, 0.3, True, 32.0)
    assert d < 0 and dc == d
    assert ec == pytest.approx(float(e), rel=1e-12)
    np.testing.assert_allclose(gc, g, rtol=1e-9, atol=1e-12 * np.abs(g).max())
    assert native.untangle_energy(x, m.hexes, inv_len, eps, 0.3, False, 32.0)[2] is None


def test_bad_arrays_are_refused_not_read_out_of_bounds():
    from jaxci import _ckernels as c

    m = _mesh(0.1)
    x = np.asarray(m.points, np.float64)
    h = np.ascontiguousarray(m.hexes, np.int32)  # the connectivity in int32, as the mesh keeps it
    with pytest.raises(TypeError, match="float64"):
        c.hex_condition(x.astype(np.float32), h, 1.0, None, None, None)
    with pytest.raises(TypeError, match="int32"):
        c.hex_condition(x, h.astype(np.int64), 1.0, None, None, None)
    bad = h.copy()
    bad[2, 3] = len(x)
    with pytest.raises(IndexError, match="out of range"):
        c.hex_condition(x, bad, 1.0, None, None, None)
    with pytest.raises(ValueError, match="shapes disagree"):
        c.hex_condition(x, h, 1.0, np.zeros((len(x) - 1, 3)), None, None)
    with pytest.raises(ValueError, match="not C-contiguous|contiguous"):
        c.hex_condition(np.asfortranarray(x), h, 1.0, None, None, None)
    with pytest.raises(ValueError, match="shapes disagree"):
        c.hex_condition(x, h, 0.0, None, None, None, 1, np.zeros((8, len(h) - 1)))


def test_corner_measures_in_c_are_numpys(monkeypatch):
    """kappa/3 and the scaled Jacobian of every corner (the quality report's and the worst elements'), with an
    inverted corner (kappa/3 inf, scaled Jacobian negative) and a zero-length edge (scaled Jacobian 0)."""
    from jaxci.metrics.elements import hex_corner_measures

    m = _mesh(0.3, seed=3)
    x = np.array(m.points, np.float64)
    h = m.hexes
    x[h[5, 0]] = x[h[5, 6]] + 0.01 * (x[h[5, 6]] - x[h[5, 0]])  # node 0 of hexahedron 5 through its far corner
    x[h[9, 1]] = x[h[9, 0]]  # an edge of length 0
    k_c, sj_c = hex_corner_measures(x, h)
    monkeypatch.setattr(native, "AVAILABLE", False)
    k_np, sj_np = hex_corner_measures(x, h)
    assert k_c.shape == k_np.shape == (len(h), 8) and np.isinf(k_np[5]).any() and (sj_np[5] < 0).any()
    assert (sj_np[9] == 0).any()
    np.testing.assert_array_equal(np.isinf(k_c), np.isinf(k_np))
    fin = np.isfinite(k_np)
    np.testing.assert_allclose(k_c[fin], k_np[fin], rtol=1e-14)
    np.testing.assert_allclose(sj_c, sj_np, rtol=1e-14, atol=1e-15)
    # a hexahedron 1e-160 thick: valid, kappa/3 ~5e159 (its square overflows in the C pass: measured by numpy)
    z = np.array([0.0, 1e-160, 1.0])
    pts = np.array([[x, y, zz] for zz in z for y in (0.0, 1.0) for x in (0.0, 1.0)])[[0, 1, 3, 2, 4, 5, 7, 6,
                                                                                        8, 9, 11, 10]]
    thin = np.array([[0, 1, 2, 3, 4, 5, 6, 7], [4, 5, 6, 7, 8, 9, 10, 11]])
    k_np, _ = hex_corner_measures(pts, thin)
    monkeypatch.setattr(native, "AVAILABLE", True)
    k_c, _ = hex_corner_measures(pts, thin)
    assert np.isfinite(k_np).all() and k_np[0].min() > 1e159
    np.testing.assert_allclose(k_c, k_np, rtol=1e-14)


@pytest.mark.parametrize("shuffled", [False, True])
@pytest.mark.parametrize("threads", [2, 3])
def test_threads_give_the_single_threaded_result(threads, shuffled):
    """Each thread has its own range of elements and its own gradient buffer over the nodes of its elements (a
    slice of the nodes where they are numbered along the elements, nearly all of them where the elements are
    shuffled): the same numbers to rounding, also for the corner table's kernel."""
    from jaxci import _ckernels as c
    from jaxci.cells import CORNERS

    m = perturb_box(24, amplitude=0.2, seed=0)  # 13,824 hexahedra: 3 threads of >= 512 elements
    x = np.ascontiguousarray(m.points, np.float64)
    h = np.ascontiguousarray(m.hexes, np.int32)
    if shuffled:
        h = np.ascontiguousarray(h[np.random.default_rng(1).permutation(len(h))])
    g1, g2 = np.zeros_like(x), np.zeros_like(x)
    s1, t1, bad1 = c.hex_condition(x, h, 1.0, g1, None, None, 1)
    s2, t2, bad2 = c.hex_condition(x, h, 1.0, g2, None, None, threads)
    assert s2 == pytest.approx(s1, rel=1e-13) and t2 == t1 and bad1 == bad2 == 0
    np.testing.assert_allclose(g2, g1, rtol=1e-12, atol=1e-14 * np.abs(g1).max())
    inv_len = np.ones(len(h))
    u1, u2 = np.zeros_like(x), np.zeros_like(x)
    e1, d1 = c.untangle_energy(x, h, inv_len, 0.1, 0.3, u1, 1)
    e2, d2 = c.untangle_energy(x, h, inv_len, 0.1, 0.3, u2, threads)
    assert e2 == pytest.approx(e1, rel=1e-13) and d2 == d1
    np.testing.assert_allclose(u2, u1, rtol=1e-12, atol=1e-14 * np.abs(u1).max())
    table = np.ascontiguousarray(h[:, CORNERS["hexahedron"]].reshape(-1, 4).T, np.int64)  # (4, 8 N): 3 threads
    c1, c2 = np.ones_like(x), np.ones_like(x)  # added into what is there
    r1 = c.corner_condition(x, table, np.eye(3), 1.0, c1, None, 1)
    r2 = c.corner_condition(x, table, np.eye(3), 1.0, c2, None, threads)
    assert r2[0] == pytest.approx(r1[0], rel=1e-13) and r2[1:] == r1[1:]
    np.testing.assert_allclose(c2, c1, rtol=1e-12, atol=1e-14 * np.abs(c1).max())
    np.testing.assert_allclose(c1 - 1.0, g1, rtol=1e-9, atol=1e-12 * np.abs(g1).max())  # the hexahedra's gradient


def _pool_case():
    m = perturb_box(12, amplitude=0.2, seed=3)  # 1,728 hexahedra: up to 3 threads of >= 512 elements
    return np.ascontiguousarray(m.points, np.float64), np.ascontiguousarray(m.hexes, np.int32)


def _gradient(x, h, threads):
    g = np.zeros_like(x)
    s, t, bad = native._c.hex_condition(x, h, 1.0, g, None, None, threads)
    return s, t, bad, g


def test_kept_threads_give_each_calls_result_whatever_the_calls_before():
    """The kernels' threads are kept between calls (`_pool.c`): calls on 3, 2, 1, 3, 2 ... threads in a row, a
    call's workers left out of it and taking part in the next, give each call the result of that thread count
    made afresh (the same ranges: the same numbers, bit for bit), and its buffers hold nothing of the last call."""
    x, h = _pool_case()
    half = np.ascontiguousarray(h[: len(h) // 2])
    want = {(k, n): _gradient(x, a, n) for k, a in (("all", h), ("half", half)) for n in (1, 2, 3)}
    for i in range(60):
        k, a = (("all", h), ("half", half))[i % 2]
        n = (3, 2, 1, 3, 2)[i % 5]
        s, t, bad, g = _gradient(x, a, n)
        assert (s, t, bad) == want[k, n][:3]
        np.testing.assert_array_equal(g, want[k, n][3])
    assert want["all", 3][0] == pytest.approx(want["all", 1][0], rel=1e-13)


def test_kernels_called_from_two_threads_at_once_each_get_their_own_result():
    """One caller at a time has the kept threads; a call made while another holds them (Python threads with
    the GIL released, or XLA's) makes its own: both results right."""
    from concurrent.futures import ThreadPoolExecutor

    x, h = _pool_case()
    want = _gradient(x, h, 2)
    with ThreadPoolExecutor(4) as ex:
        got = list(ex.map(lambda _: _gradient(x, h, 2), range(200)))
    for s, t, bad, g in got:
        assert (s, t, bad) == want[:3]
        np.testing.assert_array_equal(g, want[3])


def _child_gradient(queue):
    x, h = _pool_case()
    queue.put(_gradient(x, h, 2)[0])


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork() on this platform")
def test_a_forked_child_runs_the_kernels_on_threads_of_its_own():
    """After fork() the child has none of the parent's kept threads: its first call on two threads makes its own
    (a child that waited on the parent's would hang; the test would time out)."""
    import multiprocessing

    x, h = _pool_case()
    want = _gradient(x, h, 2)[0]  # the parent's threads exist now
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_child_gradient, args=(queue,))
    child.start()
    child.join(60)
    alive = child.is_alive()
    if alive:
        child.kill()
    assert not alive and child.exitcode == 0
    assert queue.get(timeout=5) == want


def test_mixed_kernel_is_the_gradient_of_the_mixed_objective():
    """Hexahedra, wedges, pyramids and tetrahedra: the C kernel's F is `jaxci.metrics.elements.mixed_objective` and its
    gradient JAX's derivative of it; a pyramid whose sub-tetrahedron inverts makes F infinite."""
    import jax
    import jax.numpy as jnp
    from test_mixed_smoothing import all_types_box

    from jaxci.metrics.elements import _mixed_objective, element_blocks, mixed_objective

    mesh = all_types_box()
    blocks = element_blocks(mesh)
    assert set(blocks) == {"hexahedron", "wedge", "pyramid", "tetra"}
    kernel = native.MixedKernel(blocks)
    x = np.asarray(mesh.points, np.float64)
    f, k, g = kernel(x)
    assert f == pytest.approx(float(mixed_objective(x, mesh)), rel=1e-12)
    with jax.enable_x64(True):
        conns = {t: jnp.asarray(np.ascontiguousarray(c.T)) for t, c in blocks.items()}
        gj = np.asarray(jax.grad(lambda p: _mixed_objective(p, conns))(jnp.asarray(x)))
    np.testing.assert_allclose(g, gj, rtol=1e-9, atol=1e-12 * np.abs(gj).max())
    apex = blocks["pyramid"][0, 4]
    base = blocks["pyramid"][0, :4]
    y = x.copy()
    y[apex] = x[base].mean(axis=0) - 0.5 * (x[apex] - x[base].mean(axis=0))  # the apex through its base
    assert kernel(y)[0] == np.inf


@pytest.mark.shared
def test_near_projector_in_c_is_the_numpy_one():
    """`jaxci.geometry.near.NearProjector` with the C search against its numpy search on a paved mesh with curved
    walls: the same points bit for bit and the same triangles, with and without hints and kept nodes."""
    from helpers import MESQUITE

    from jaxci.geometry.boundary import classify_boundary
    from jaxci.geometry.near import NearProjector
    from jaxci.geometry.projection import build_constraints
    from jaxci.io import read_mesh

    mesh = read_mesh(str(MESQUITE / "pave3.e.vtk"))
    cons = build_constraints(mesh, classify_boundary(mesh), dtype=np.float64, device=False)
    fast, ref = NearProjector(cons), NearProjector(cons)
    assert fast.use_c
    ref.use_c = False
    rng = np.random.default_rng(0)
    h = np.median(np.linalg.norm(mesh.points[mesh.hexes[:, 1]] - mesh.points[mesh.hexes[:, 0]], axis=1))
    for it in range(8):
        x = mesh.points + rng.normal(scale=(0.02 if it > 3 else 0.3) * h, size=mesh.points.shape)
        keep = rng.random(len(x)) < 0.3 if it % 2 else None
        (xf, hf), (xr, hr) = fast(x, keep), ref(x, keep)
        np.testing.assert_array_equal(xf, xr)
        for a, b in zip(hf, hr, strict=True):
            np.testing.assert_array_equal(a, b)
        # the numpy search's gathered candidate rows (~10 kB a boundary node) are built only where it runs
        assert "rows" not in vars(fast) and "rows" in vars(ref)
        fast.commit(hf)  # (the anchors move alike: `jaxci.geometry.anchors`)
        ref.commit(hr)
        for a, b in zip(fast._cand, ref._cand, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("curved", [False, pytest.param(True, marks=pytest.mark.shared)])
def test_near_projection_is_the_same_on_any_thread_count(curved, monkeypatch):
    """The C search's threads each take their own active nodes: 1 and 3 threads give the same points and
    triangles bit for bit (a perturbed 24^3 box: 3,000 surface nodes, three threads; pave3's curved walls)."""
    from jaxci.geometry.boundary import classify_boundary
    from jaxci.geometry.near import NearProjector
    from jaxci.geometry.projection import build_constraints

    if curved:
        from helpers import MESQUITE

        from jaxci.io import read_mesh

        mesh = read_mesh(str(MESQUITE / "pave3.e.vtk"))
    else:
        mesh = perturb_box(24, amplitude=0.2, seed=1)
    cons = build_constraints(mesh, classify_boundary(mesh), dtype=np.float64, device=False)
    rng = np.random.default_rng(2)
    h = np.median(np.linalg.norm(mesh.points[mesh.hexes[:, 1]] - mesh.points[mesh.hexes[:, 0]], axis=1))
    x = mesh.points + rng.normal(scale=0.3 * h, size=mesh.points.shape)
    keep = rng.random(len(x)) < 0.2
    got = []
    for threads in (1, 3):
        monkeypatch.setattr(native, "THREADS", threads)
        proj = NearProjector(cons)
        first = proj(x)
        proj.commit(first[1])
        got.append((first, proj(x + 0.05 * h, keep)))
    for (x1, h1), (x3, h3) in zip(*got, strict=True):
        np.testing.assert_array_equal(x1, x3)
        for a, b in zip(h1, h3, strict=True):
            np.testing.assert_array_equal(a, b)

def _pave3_constraints():
    from helpers import MESQUITE

    from jaxci.geometry.boundary import classify_boundary
    from jaxci.geometry.projection import build_constraints
    from jaxci.io import read_mesh

    mesh = read_mesh(str(MESQUITE / "pave3.e.vtk"))
    return mesh, build_constraints(mesh, classify_boundary(mesh), dtype=np.float64, device=False)


@pytest.mark.shared
def test_lift_its_transpose_and_the_pullback_in_c_are_numpys():
    """The steps of `jaxci.optim.host.HostObjective` around the kernel, in C (`native.lift`, `lift_t`,
    `flat_keep`, `pullback`) against the numpy code they replace, on a paved mesh with curved walls (interior,
    surface and edge nodes): bit for bit, so that the host L-BFGS takes the same steps as before."""
    from jaxci.geometry.near import NearProjector
    from jaxci.optim.parametrisation import lift_points, lift_transpose_np

    mesh, cons = _pave3_constraints()
    assert len(cons.surface_nodes) and len(cons.edge_nodes) and len(cons.interior_nodes)
    lay = native.layout(cons)
    rng = np.random.default_rng(3)
    m = 3 * len(cons.interior_nodes) + 2 * len(cons.surface_nodes) + len(cons.edge_nodes)
    x0 = np.asarray(mesh.points, np.float64)
    scale, v = rng.random(m), rng.normal(size=m) * 0.1
    x = native.lift(x0, scale, v, lay)
    np.testing.assert_array_equal(x, lift_points(np, x0, scale, cons, v))
    g = rng.normal(size=x.shape)
    np.testing.assert_array_equal(native.lift_t(g, scale, lay), lift_transpose_np(scale, cons, g))

    nodes = np.ascontiguousarray(np.concatenate([cons.surface_nodes, cons.edge_nodes]), np.int64)
    origin, r2 = x0[nodes], rng.random(len(nodes)) * 0.01
    keep = np.zeros(len(x), bool)
    d2 = np.sum((x[nodes] - origin) ** 2, axis=1)
    assert native.flat_keep(x, nodes, origin, r2, keep) == int(np.sum(d2 >= r2))
    np.testing.assert_array_equal(keep[nodes], d2 < r2)

    fast, ref = NearProjector(cons), NearProjector(cons)
    ref.use_c = False
    xp, hint = fast(x)
    for k in (None, keep):
        np.testing.assert_array_equal(fast.pullback(g, hint, k), ref.pullback(g, hint, k))
    # a trial point d * alpha + v lifted without being made: numpy's numbers, and how many entries moved
    d = rng.normal(size=m)
    d[::5] = 0.0
    for alpha in (1.0, 0.37, 1e-300, 0.0):
        t = d * alpha
        t += v
        xs, moved = native.lift_step(x0, scale, v, d, alpha, lay)
        np.testing.assert_array_equal(xs, native.lift(x0, scale, t, lay))
        assert moved == int(np.sum(t != v))
    assert moved == 0
    with pytest.raises(ValueError, match="shapes disagree"):
        native.lift_step(x0, scale, v, d[:-1], 1.0, lay)
    # the same points read node by node (`lift_nodes`) and where F's kernel reads them (`hex_condition_lifted`)
    slots = native.lift_slots(lay, len(x0))
    hexes = np.ascontiguousarray(mesh.hexes, np.int64)
    some = np.ascontiguousarray(rng.choice(len(x0), 50), np.int64)
    for step in (None, (d, 0.37)):
        dd, alpha = step or (None, 1.0)
        xs, moved = native.lift_step(x0, scale, v, dd, alpha, lay) if step else (native.lift(x0, scale, v, lay), 0)
        np.testing.assert_array_equal(native.lift_nodes(x0, scale, v, dd, alpha, slots, lay, some)[0], xs[some])
        assert native.lift_nodes(x0, scale, v, dd, alpha, slots, lay, some)[1] == moved
        for a, b in zip(native.hex_terms_and_grad_lifted(x0, scale, v, dd, alpha, slots, lay, hexes),
                        native.hex_terms_and_grad(xs, hexes), strict=True):
            np.testing.assert_array_equal(a, b)
    bad = slots.copy()
    bad[lay[0][0]] += 1  # not an interior node's first coordinate
    with pytest.raises(IndexError, match="out of range"):
        native.hex_terms_and_grad_lifted(x0, scale, v, d, 1.0, bad, lay, hexes)
    # the transpose over the gradient's own buffer: the same numbers
    gi = g.copy()
    out = native.lift_t(gi, scale, lay, inplace=True)
    assert np.shares_memory(out, gi)
    np.testing.assert_array_equal(out, native.lift_t(g, scale, lay))
    with pytest.raises(ValueError, match="shapes disagree"):
        native.lift(x0, scale[:-1], v[:-1], lay)
    with pytest.raises(IndexError, match="out of range"):
        native.lift_t(g[:3], scale, lay)


@pytest.mark.shared
def test_face_spheres_change_nothing_in_the_search():
    """The C search passes over a boundary face whose sphere (holding its four triangles') cannot come nearer:
    the same points and triangles as the search over every triangle's sphere, for the projection of whole meshes
    and of trial rows."""
    from jaxci.geometry.near import NearProjector

    mesh, cons = _pave3_constraints()
    fast, plain = NearProjector(cons), NearProjector(cons)
    nodes, cand, table, spheres = plain._c_arrays(0)
    assert table.shape[1] == 19 and len(spheres) == len(table) * 5 // 4  # (the C search's tables are cell-major)
    plain._c[0] = (nodes, cand, table, spheres[: len(table)])
    rng = np.random.default_rng(1)
    h = np.median(np.linalg.norm(mesh.points[mesh.hexes[:, 1]] - mesh.points[mesh.hexes[:, 0]], axis=1))
    for it in range(6):
        x = mesh.points + rng.normal(scale=(0.02 if it > 2 else 0.3) * h, size=mesh.points.shape)
        (xf, hf), (xp, hp) = fast(x), plain(x)
        np.testing.assert_array_equal(xf, xp)
        for a, b in zip(hf, hp, strict=True):
            np.testing.assert_array_equal(a, b)
        fast.commit(hf)
        plain.commit(hp)


@pytest.mark.parametrize("f16", [False, True])
@pytest.mark.parametrize("history", [1, 3, 10])
def test_lbfgs_direction_in_c_is_the_two_loop_recursion(history, f16, monkeypatch):
    """The L-BFGS memory of `jaxci.optim.host` (ring buffers, oldest slot reused): the C two-loop recursion and
    the numpy one agree, before and after the ring wraps, with float64 pairs and with the float16 pairs of a
    large problem (`HISTORY_F16_FROM`: each vector times a power of two, rho then from the stored pair); an empty
    memory gives -g; a pair of non-positive curvature is not stored."""
    from jaxci.optim import host

    rng = np.random.default_rng(history)
    n = 500
    monkeypatch.setattr(host, "HISTORY_F16_FROM", n if f16 else 10 * n)
    mem = host._Memory(n, history)
    assert mem.S.dtype == (np.float16 if f16 else np.float64)
    g = rng.normal(size=n)
    np.testing.assert_array_equal(mem.direction(g), -g)
    s = rng.normal(size=n)
    mem.push(mem.stored(s.copy()), mem.stored(-s))
    assert mem.order == []
    for _ in range(history + 3):
        s = rng.normal(size=n) * 10.0 ** rng.uniform(-9, 3)  # any magnitude: the row's power of two follows it
        y = s + 0.1 * rng.normal(size=n) * np.abs(s).max()
        mem.push(mem.stored(s.copy()), mem.stored(y.copy()))
        k = mem.order[-1]
        s_, y_ = mem.S[k] * mem.inv_scale[0, k], mem.Y[k] * mem.inv_scale[1, k]  # the pair as stored, float64
        if f16:
            assert 2.0 ** 14 <= np.abs(mem.S[k]).max() <= 2.0 ** 15
            np.testing.assert_allclose(s_, s, rtol=2.0 ** -11, atol=2.0 ** -25 * np.abs(s).max())
        else:
            np.testing.assert_array_equal(s_, s)
        assert mem.rho[k] == pytest.approx(1.0 / float(s_ @ y_), rel=1e-13)
        fast = mem.direction(g)
        monkeypatch.setattr(native, "AVAILABLE", False)
        ref = mem.direction(g)
        monkeypatch.setattr(native, "AVAILABLE", True)
        np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-14 * np.abs(ref).max())
    assert len(mem.order) == history and sorted(mem.order) == list(range(history))


@pytest.mark.shared
def test_untangling_without_the_extension_takes_the_same_path(monkeypatch):
    """The untangling stage on the host without the C extension (numpy's `hex_kernel` over the corner table)
    untangles what it untangles with it, in the same number of rounds."""
    from helpers import MESQUITE

    from jaxci.interface.smooth import smooth
    from jaxci.io import read_mesh

    mesh = read_mesh(str(MESQUITE / "hex_5_tangled.vtk"))
    with_c = smooth(mesh)
    monkeypatch.setattr(native, "AVAILABLE", False)
    without = smooth(mesh)
    for res in (with_c, without):
        assert res.after.inverted_elements == 0 and res.after.max_condition < 1.001
    rounds = [next(n for n in r.notes if n.startswith("untangling:")).split(" rounds")[0].split()[-1]
              for r in (with_c, without)]
    assert rounds[0] == rounds[1], rounds


def test_corner_determinants_in_c_are_numpys_bit_for_bit(monkeypatch):
    """`jaxci.cells.corner_determinants` runs in C where built: the numpy loop's numbers exactly (also for int32
    connectivity and an inverted corner), and a node index out of range is an IndexError, not a crash."""
    from jaxci import cells

    mesh = perturb_box(7, 5, 6, amplitude=0.9, seed=3, redraw_inverted=False)  # some corners inverted
    points, hexes = mesh.points, mesh.hexes
    fast = cells.corner_determinants(points, hexes.astype(np.int32))
    monkeypatch.setattr(cells, "load_c_kernels", lambda: None)
    slow = cells.corner_determinants(points, hexes)
    monkeypatch.undo()
    assert (slow <= 0).any() and np.array_equal(fast, slow)
    with pytest.raises(IndexError, match="out of range"):
        cells.corner_determinants(points, np.array([[0, 1, 2, 3, 4, 5, 6, len(points)]]))


# ------------------------------------------------------------ the C kernel inside compiled JAX programs (XLA FFI)
def _ffi_case(dtype):
    import jax.numpy as jnp

    m = perturb_box(5, 4, 3, amplitude=0.3, seed=2)
    x = jnp.asarray(m.points, dtype)
    conn = jnp.asarray(np.ascontiguousarray(m.hexes.T), jnp.int32)
    weight = jnp.ones(conn.shape[1], dtype).at[-4:].set(0.0)  # the last four elements: padding
    return m, x, conn, weight


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-12), ("float32", 2e-5)])
@pytest.mark.parametrize("n_corners", [None, 1.0])
def test_ffi_kernel_matches_the_xla_kernel(dtype, rtol, n_corners):
    """`jaxci.metrics.native_grad.terms_and_grad` (the C kernel as an XLA custom call, under jit) gives the XLA
    kernel's F, max and gradient: padding elements (weight 0) left out, F and the gradient divided by the real
    corners or by `n_corners` (one device's sums)."""
    import jax

    from jaxci.metrics import native_grad
    from jaxci.metrics.hexahedron import objective_terms_and_grad

    assert native_grad.available("cpu") and not native_grad.available("gpu")
    _, x, conn, weight = _ffi_case(dtype)
    f, k, g = jax.jit(lambda x, c, w: native_grad.terms_and_grad(x, c, w, n_corners, threads=2))(x, conn, weight)
    f1, k1, g1 = objective_terms_and_grad(x, conn, weight, None, 0, n_corners)
    assert f.dtype == g.dtype == x.dtype and g.shape == x.shape
    assert float(f) == pytest.approx(float(f1), rel=rtol) and float(k) == pytest.approx(float(k1), rel=rtol)
    g, g1 = np.asarray(g, np.float64), np.asarray(g1, np.float64)
    np.testing.assert_allclose(g, g1, rtol=rtol * 10, atol=rtol * np.abs(g1).max())
    # the padding elements add nothing: the same as the real elements alone
    f2, _, g2 = native_grad.terms_and_grad(x, conn[:, :-4], None, n_corners)
    assert float(f2) == pytest.approx(float(f), rel=rtol)
    np.testing.assert_allclose(np.asarray(g2, np.float64), g, rtol=rtol * 10, atol=rtol * np.abs(g).max())


def test_ffi_kernel_inverted_corner_gives_inf_and_the_gradient_of_the_others():
    from jaxci.metrics import native_grad
    from jaxci.metrics.hexahedron import objective_terms_and_grad

    m, x, conn, weight = _ffi_case("float64")
    x = x.at[m.hexes[0, 0]].set(x[m.hexes[0, 6]] + 0.1)  # element 0 inverted
    f, k, g = native_grad.terms_and_grad(x, conn, weight)
    _, _, g1 = objective_terms_and_grad(x, conn, weight, None, 0)
    assert float(f) == float(k) == np.inf
    np.testing.assert_allclose(np.asarray(g), np.asarray(g1), rtol=1e-10, atol=1e-13 * float(np.abs(g1).max()))


def test_compiled_lbfgs_with_the_ffi_kernel_gives_the_xla_kernels_mesh(monkeypatch):
    """The compiled L-BFGS (``backend="jax"``) on CPU uses the C kernel; with the XLA kernel instead (as on a
    GPU) it takes the same steps to the same mesh (float64)."""
    import jax

    from jaxci import smooth
    from jaxci.metrics import native_grad

    m = perturb_box(4, amplitude=0.3, seed=1)
    traced, ffi = [], native_grad.terms_and_grad
    monkeypatch.setattr(native_grad, "terms_and_grad", lambda *a, **k: traced.append(1) or ffi(*a, **k))
    runs = []
    for use_c in (True, False):
        monkeypatch.setattr(native_grad, "available", lambda platform, use_c=use_c: use_c and platform == "cpu")
        jax.clear_caches()
        runs.append(smooth(m, "lbfgs", backend="jax", dtype="float64", max_steps=40))
        assert bool(traced) == use_c  # the C kernel was (only) compiled into the first run
        traced.clear()
    jax.clear_caches()
    (a, b) = runs
    assert a.iterations == b.iterations
    np.testing.assert_allclose(a.mesh.points, b.mesh.points, rtol=0, atol=1e-9)
    assert a.after.max_condition == pytest.approx(b.after.max_condition, rel=1e-9)


def test_a_c_extension_built_from_other_sources_is_not_used(monkeypatch):
    """A stale build (its interface version other than this jaxci's: after sources changed and before a rebuild)
    is refused with a warning that says how to rebuild, and numpy runs instead; the build of these sources is
    taken."""
    import sys
    import types

    from jaxci import cells

    stale = types.ModuleType("jaxci._ckernels")
    stale.__file__ = "stale.so"
    monkeypatch.setitem(sys.modules, "jaxci._ckernels", stale)
    monkeypatch.setattr(sys.modules["jaxci"], "_ckernels", stale, raising=False)
    with pytest.warns(RuntimeWarning, match="built from other sources.*Rebuild it"):
        assert cells.load_c_kernels.__wrapped__() is None
    stale.ABI = cells.KERNELS_ABI
    assert cells.load_c_kernels.__wrapped__() is stale
