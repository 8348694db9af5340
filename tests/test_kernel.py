"""The closed-form F + gradient kernel in each of its forms (`jaxci.metrics.incidence`): the gradient summed into
the nodes by scatter-adds, by a gather over the node incidences or by a sorted segment sum gives F and dF/dx of
`jax.grad` (float64), leaves padding elements out of every node, and repeats its bits from run to run."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import box_or_mesquite

from jaxci.mesh.generate import perturb_box
from jaxci.metrics import incidence as I
from jaxci.metrics.hexahedron import objective_t, objective_terms_and_grad, transposed
from jaxci.metrics.incidence import FORMS, default_form, node_incidence, valence_class

_KERNEL = jax.jit(objective_terms_and_grad, static_argnames=("power", "block"))


def _mesh(name: str):
    """A perturbed box (seed 3), or a Mesquite mesh (`helpers.box_or_mesquite`)."""
    return box_or_mesquite(name, seed=3)


def _close(g, ref):
    np.testing.assert_allclose(np.asarray(g), np.asarray(ref), rtol=1e-10, atol=1e-12 * float(jnp.abs(ref).max()))


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("name", ["box4", "1000hex-block-internal-bias.vtk", "pave3.e.vtk"])
def test_every_form_gives_the_autodiff_gradient(form, name):
    """F and dF/dx in each form against `jax.value_and_grad` of the forward objective (float64); on pave3 (an
    unstructured mesh, nodes of valence up to 12, inverted corners) F is inf and the gradient of every form is
    the scatter form's, which leaves the inverted corners out."""
    mesh = _mesh(name)
    x = jnp.asarray(mesh.points, jnp.float64)
    conn = transposed(mesh.hexes)
    inc = node_incidence(conn, x.shape[0], form=form)
    f, k, g = _KERNEL(x, conn, incidence=inc)
    f_s, k_s, g_s = _KERNEL(x, conn)
    _close(g, g_s)
    assert float(k) == float(k_s)
    if not np.isfinite(float(f_s)):
        assert np.isinf(float(f)) and bool(jnp.all(jnp.isfinite(g)))
        return
    f_ad, g_ad = jax.value_and_grad(objective_t)(x, conn)
    assert float(f) == pytest.approx(float(f_ad), rel=1e-12)
    _close(g, g_ad)


@pytest.mark.parametrize("form", ["gather", "segment"])
def test_padding_elements_reach_no_node(form):
    """A connectivity padded as `jaxci.optim._buckets` pads it (padding elements repeat element 0, weight 0,
    spare nodes after the real ones): the incidences list no padding slot, and F, its max and the gradient
    (whole and in blocks) are those of the unpadded mesh; p-mean included."""
    mesh = perturb_box(4, amplitude=0.3, seed=5)
    n_el, n_pts = mesh.n_hexes, len(mesh.points)
    x = jnp.asarray(np.r_[mesh.points, np.zeros((3, 3))], jnp.float64)
    hexes = np.r_[mesh.hexes, np.repeat(mesh.hexes[:1], 9, axis=0)]
    conn, weight = transposed(hexes), jnp.asarray(np.r_[np.ones(n_el), np.zeros(9)])
    inc = node_incidence(conn, x.shape[0], weight, form=form)
    slots = np.asarray(inc.table).ravel() if form == "gather" else np.asarray(inc.order)[np.asarray(inc.keys) < len(x)]
    listed = slots[slots < conn.size] % conn.shape[1]
    assert listed.max() < n_el and len(listed) == 8 * n_el
    # values at every slot, padding slots included: only the real slots reach their nodes
    vals = np.random.default_rng(0).standard_normal((2, *conn.shape))
    got = np.asarray(I.accumulate(tuple(jnp.asarray(v) for v in vals), conn, x.shape[0], inc))
    real = np.asarray(conn)[:, :n_el].ravel()
    want = np.stack([np.bincount(real, v[:, :n_el].ravel(), minlength=x.shape[0]) for v in vals], axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    ref_conn = transposed(mesh.hexes)
    for power, block in [(None, 0), (None, 16), (4.0, 0)]:
        f, k, g = _KERNEL(x, conn, weight, power=power, block=block, incidence=inc)
        f0, k0, g0 = _KERNEL(x[:n_pts], ref_conn, power=power, block=0)
        assert float(f) == pytest.approx(float(f0), rel=1e-12) and float(k) == pytest.approx(float(k0), rel=1e-12)
        _close(g[:n_pts], g0)
        assert not np.any(np.asarray(g[n_pts:]))


@pytest.mark.parametrize("block", [7, 64])
@pytest.mark.parametrize("form", FORMS)
def test_blocks_give_the_whole_mesh_gradient(form, block):
    """In blocks (7 and 64 do not divide the 125 elements; the last block overlaps the one before) the per-element
    gradients are written block by block and summed into the nodes after the loop: the whole mesh's values."""
    mesh = perturb_box(5, amplitude=0.3, seed=2)
    x = jnp.asarray(mesh.points, jnp.float64)
    conn = transposed(mesh.hexes)
    inc = node_incidence(conn, x.shape[0], form=form)
    f0, k0, g0 = _KERNEL(x, conn, block=0)
    f1, k1, g1 = _KERNEL(x, conn, block=block, incidence=inc)
    # max kappa/3 to the last bits: an element's arithmetic is the compiler's in either program (XLA:CPU's older
    # code generation, the suite's, puts one ulp between them where its default one does not)
    assert float(f1) == pytest.approx(float(f0), rel=1e-12) and float(k1) == pytest.approx(float(k0), rel=4e-16)
    _close(g1, g0)


@pytest.mark.parametrize("form", ["gather", "segment"])
def test_the_gradient_repeats_its_bits(form):
    """Two calls of the float32 kernel on one device, in a fresh compilation each: identical bits (the gather
    sums each node's slots in a fixed order; the sorted segment sum is sequential on a CPU)."""
    mesh = perturb_box(6, amplitude=0.3, seed=1)
    x = jnp.asarray(mesh.points, jnp.float32)
    conn = transposed(mesh.hexes)
    inc = node_incidence(conn, x.shape[0], form=form)
    runs = []
    for _ in range(2):
        jax.clear_caches()
        f, _, g = _KERNEL(x, conn, incidence=inc)
        runs.append((np.asarray(f).tobytes(), np.asarray(g).tobytes()))
    assert runs[0] == runs[1]


def test_the_gather_table_lists_each_nodes_slots_once():
    """The gather table against numpy: column v holds exactly the slots ``m N + e`` with ``conn[m, e] == v``, in
    increasing order, then the fill ``8N``; its height is the valence class of the largest valence."""
    mesh = _mesh("pave3.e.vtk")
    conn = transposed(mesh.hexes)
    n = len(mesh.points)
    table = np.asarray(node_incidence(conn, n, form="gather").table)
    flat = np.asarray(conn).ravel()
    valence = np.bincount(flat, minlength=n)
    assert table.shape == (valence_class(valence.max()), n) and valence.max() > 8
    for v in range(n):
        want = np.flatnonzero(flat == v)
        assert list(table[: len(want), v]) == list(want) and np.all(table[len(want):, v] == flat.size)


def test_unknown_form_and_default():
    with pytest.raises(ValueError, match="unknown kernel form"):
        node_incidence(transposed(perturb_box(2).hexes), 27, form="atomic")
    assert default_form("cpu") in FORMS and default_form("gpu") == "gather"
    assert node_incidence(transposed(perturb_box(2).hexes), 27, form="scatter") is None


@pytest.mark.parametrize("objective", ["mean", "pmean"])
def test_the_solver_builds_the_incidences_once_and_follows_the_scatter_form(monkeypatch, objective):
    """L-BFGS on the JAX engine without the C kernel, its problem padded to a size class: the gather form's
    incidences are built once for the whole run (restarts included) from the padded connectivity, and the run
    takes the scatter form's steps to the same points (float64)."""
    from jaxci.interface.smooth import build_problem
    from jaxci.metrics import native_grad
    from jaxci.optim import gradient as G
    from jaxci.optim import solver_objective as O

    monkeypatch.setattr(native_grad, "available", lambda platform: False)
    built = []

    def spy(conn, n_nodes, weight=None, form=None):
        built.append((conn.shape, weight is not None))
        return I.node_incidence(conn, n_nodes, weight, form)

    monkeypatch.setattr(O, "node_incidence", spy)
    mesh = perturb_box(3, amplitude=0.3, seed=4, which="interior")
    pr = build_problem(mesh, dtype=np.float64, fix_boundary=True)
    par = G.make_parametrisation(pr.mesh, pr.info, pr.cons, pr.x0)
    params = {"backend": "jax", "objective": objective} | ({"p": 4.0} if objective == "pmean" else {})
    out = {}
    for form in ("scatter", "gather"):
        monkeypatch.setattr(I, "default_form", lambda platform=None, form=form: form)
        built.clear()
        x, steps, hist, _ = G.minimise("lbfgs", par, pr.conn, G.GradientParams(**params))
        assert len(built) == 1 and built[0][1] and built[0][0][1] > mesh.n_hexes  # once, padded, weighted
        out[form] = (np.asarray(x), steps)
    assert out["gather"][1] == out["scatter"][1]
    np.testing.assert_allclose(out["gather"][0], out["scatter"][0], atol=1e-9)
