"""The presmoothing's data and the parametrisation built on the device (`jaxci.geometry.device_colouring`,
`jaxci.optim.device_stars`, `jaxci.optim.device_parametrisation`), against the host's builds, under
``jax.transfer_guard("disallow")``: only the explicit `jaxci.runtime.transfer` moves cross."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import box_or_mesquite

from jaxci.geometry.device_colouring import colour_nodes_device, incidences
from jaxci.interface.methods import build_problem
from jaxci.optim import _moves as M
from jaxci.optim import laplace as L
from jaxci.optim._buckets import free_layout
from jaxci.optim._local import node_stars, relabel
from jaxci.optim.device_parametrisation import make_parametrisation_device, node_lengths_traced
from jaxci.optim.device_stars import sweep_data
from jaxci.optim.parametrisation import (
    flat_intervals,
    make_parametrisation,
    node_lengths,
    pad_parametrisation,
    pad_problem_device,
    unpad_free,
)
from jaxci.runtime.transfer import to_device


def _mesh(name):
    """A box (``box<k>``: perturb_box(k), seed 4) or a Mesquite mesh (`helpers.box_or_mesquite`)."""
    return box_or_mesquite(name, seed=4)


MESHES = ["box5", "box9", "1000hex-block-internal-bias.vtk", "large_box_hex_1000.vtk", "pave3.e.vtk"]


def _problem(name, dtype=np.float64):
    mesh = _mesh(name)
    with jax.enable_x64(dtype == np.float64):
        return mesh, build_problem(mesh, dtype=dtype)


@pytest.mark.parametrize("name", MESHES)
def test_incidences_and_colouring(name):
    """The incidence table is `node_stars`' (bit for bit); the colouring gives no two nodes of one hexahedron
    one colour, and the same colours every time."""
    mesh, pr = _problem(name)
    hexes = np.asarray(mesh.hexes)
    with jax.transfer_guard("disallow"):
        conn = to_device(hexes.T, np.int32)
        inc = incidences(conn, mesh.n_nodes)
        colour, count = colour_nodes_device(conn, inc)
        again, _ = colour_nodes_device(conn, inc)
    ref = node_stars(hexes, mesh.n_nodes, incidences=True)
    table, valence = np.asarray(inc.table), np.asarray(inc.valence)
    assert np.array_equal(valence, ref.valence) and table.shape == ref.star.shape
    assert np.array_equal(table[ref.mask], ref.star[ref.mask])
    colour = np.asarray(colour)
    assert valid_colouring(hexes, colour) and count == colour.max() + 1
    assert np.array_equal(colour, np.asarray(again))
    assert not valid_colouring(hexes, np.zeros_like(colour))  # the check can fail


def valid_colouring(hexes: np.ndarray, colour: np.ndarray) -> bool:
    """Whether no hexahedron of `hexes` ``(N, 8)`` holds two nodes of one colour."""
    c = np.sort(np.asarray(colour)[np.asarray(hexes)], axis=1)
    return not bool((c[:, 1:] == c[:, :-1]).any())


def test_colouring_takes_more_words_for_more_than_32_colours():
    """40 nodes that share hexahedra pairwise (one hexahedron per pair, 6 nodes of its own each) need 40
    colours: past the first 32-colour word, the colouring runs again with two."""
    k = 40
    i, j = np.triu_indices(k, 1)
    filler = k + np.arange(6 * len(i)).reshape(-1, 6)
    hexes = np.concatenate([i[:, None], j[:, None], filler], axis=1)
    with jax.transfer_guard("disallow"):
        conn = to_device(hexes.T, np.int32)
        colour, count = colour_nodes_device(conn, incidences(conn, int(hexes.max()) + 1))
    colour = np.asarray(colour)
    assert valid_colouring(hexes, colour) and count == colour.max() + 1 and count >= k


def _host_sweep_args(mesh, pr):
    cs = M.coloured_stars(mesh.hexes, pr.cons, pr.colour, pr.info.topology.faces, place=False)
    nbr, nmask = L.coloured_neighbours(cs, mesh.hexes, mesh.n_nodes, place=False)
    return L._padded(pr.x0, pr.conn, cs, nbr, nmask, pr.cons)


#: float64 on every mesh, float32 (the same build, another dtype: the shapes do not depend on it) on one box and
#: one real mesh: each case compiles its own sweeps.
DTYPE_CASES = [("box5", np.float32), ("pave3.e.vtk", np.float32)]


@pytest.mark.parametrize("name, dtype", [(n, np.float64) for n in ["box5", "1000hex-block-internal-bias.vtk",
                                                                   "large_box_hex_1000.vtk"]] + DTYPE_CASES[:1])
def test_sweep_data_is_the_host_build(name, dtype):
    """With the host's colouring, the device's slots, stars (incidences relabelled), bases, planes and
    neighbours are those of `coloured_stars` + `pad_stars` + `coloured_neighbours`, and 3 smart-Laplace sweeps
    give the same mesh bit for bit (stars gathered in the sweep or relabelled once)."""
    mesh, pr = _problem(name, dtype)
    with jax.enable_x64(dtype == np.float64):
        x, c, cs, nbr, nmask, cons, w, n_col = _host_sweep_args(mesh, pr)
        colour = pr.colour
        faces = pr.info.topology.faces
        with jax.transfer_guard("disallow"):
            dev = to_device(colour, np.int32)
            d = sweep_data(pr.x0, pr.conn, pr.cons, faces, colour=(dev, int(colour.max()) + 1), split=False)
            lists = sweep_data(pr.x0, pr.conn, pr.cons, faces, colour=(dev, int(colour.max()) + 1), lists=True,
                               split=False)
        real = np.asarray(cs.mask)
        for field in ("nodes", "mask", "smask", "basis", "dims", "plane"):
            a, b = np.asarray(getattr(cs, field)), np.asarray(getattr(d.cs, field))
            assert a.shape == b.shape and a.dtype == b.dtype, field
            # the host's empty slots of a colour hold some node's basis (masked): compared where real
            assert np.array_equal(a[real], b[real]) and (field == "basis" or np.array_equal(a, b)), field
        smask = np.asarray(cs.smask)
        assert np.array_equal(np.asarray(cs.star)[smask], np.asarray(relabel(d.conn, d.cs.star))[smask])
        assert np.array_equal(np.asarray(lists.cs.star)[smask], np.asarray(cs.star)[smask])
        nreal = np.asarray(nmask)
        assert np.array_equal(nreal, np.asarray(d.nmask)) and np.array_equal(np.asarray(nbr)[nreal],
                                                                             np.asarray(d.nbr)[nreal])
        for field in cons.__dataclass_fields__:
            assert np.array_equal(np.asarray(getattr(cons, field)), np.asarray(getattr(d.cons, field))), field
        p = L.LaplaceParams(max_sweeps=3)
        host = L._laplace_run(x, c, cs, nbr, nmask, cons, True, p, L.no_extra(), w, n_col)
        with jax.transfer_guard("disallow"):
            for data in (d, lists):
                xd, sweeps, hist, _ = L.laplace_device(data, p, smart=True)
                assert np.array_equal(np.asarray(host[0])[: mesh.n_nodes], np.asarray(xd))
                assert sweeps == int(host[1]) and np.array_equal(hist["objective"], np.asarray(host[2])[: sweeps + 1])


@pytest.mark.parametrize("name", ["box9", "1000hex-block-internal-bias.vtk", "large_box_hex_1000.vtk"])
def test_device_colouring_sweeps_as_well_as_the_host_colouring(name):
    """3 smart-Laplace sweeps with the device's colouring lower F about as far as with the host's first-fit
    colouring, from the same start (measured on perturbed 9^3 to 25^3 boxes, 4 seeds each: F after them 0.92 to
    1.17 times the host colouring's, 1.01 on average; the Mesquite meshes 0.92 to 0.98)."""
    mesh, pr = _problem(name, np.float32)
    p = L.LaplaceParams(max_sweeps=3)
    faces = pr.info.topology.faces
    colour = pr.colour
    with jax.transfer_guard("disallow"):
        host = L.laplace_device(sweep_data(pr.x0, pr.conn, pr.cons, faces,
                                           colour=(to_device(colour, np.int32), int(colour.max()) + 1)), p, smart=True)
        dev_data = sweep_data(pr.x0, pr.conn, pr.cons, faces)
        dev = L.laplace_device(dev_data, p, smart=True)
    f0, f_host, f_dev = host[2]["objective"][0], host[2]["objective"][-1], dev[2]["objective"][-1]
    assert f_dev < f0 / 10 and f_dev <= 1.3 * f_host
    assert dev_data.colours <= 32


def test_split_rows_hold_parts_of_colours(monkeypatch):
    """Where one row a colour pads many slots (colours of unequal sizes: the host's 8 colours of a box, the last
    cut into 10 small ones; no slot slack), a colour spans several rows: every movable node in one slot, no two
    nodes of a row in one hexahedron, and the sweeps lower F as one row a colour does."""
    monkeypatch.setattr(M, "_SLACK_UNTIL", 1)
    mesh, pr = _problem("box9", np.float32)
    faces = pr.info.topology.faces
    colour = np.asarray(pr.colour).copy()
    last = colour == colour.max()
    colour[last] += np.arange(last.sum()) % 10
    given = (to_device(colour, np.int32), int(colour.max()) + 1)
    p = L.LaplaceParams(max_sweeps=3)
    with jax.transfer_guard("disallow"):
        split = sweep_data(pr.x0, pr.conn, pr.cons, faces, colour=given)
        whole = sweep_data(pr.x0, pr.conn, pr.cons, faces, colour=given, split=False, inc=split.inc)
        f_split = L.laplace_device(split, p, smart=True)[2]["objective"]
        f_whole = L.laplace_device(whole, p, smart=True)[2]["objective"]
    rows = int(np.asarray(split.n_colours))
    assert rows > split.colours == whole.colours == int(np.asarray(whole.n_colours)) == 17
    assert rows * sum(split.cs.nodes.shape[1:]) <= 0.9 * 17 * whole.cs.nodes.shape[1]
    nodes, mask = np.asarray(split.cs.nodes), np.asarray(split.cs.mask)
    movable = np.flatnonzero(np.asarray(pr.cons.node_class) != 3)
    assert np.array_equal(np.sort(nodes[mask]), movable)
    hexes = np.asarray(mesh.hexes)
    for r in range(rows):
        row = np.zeros(mesh.n_nodes, bool)
        row[nodes[r][mask[r]]] = True
        assert (row[hexes].sum(axis=1) <= 1).all()
    assert f_split[-1] < f_split[0] / 10 and f_split[-1] <= 1.3 * f_whole[-1]


@pytest.mark.parametrize("name", MESHES)
def test_node_lengths_on_the_device(name):
    mesh, pr = _problem(name)
    with jax.transfer_guard("disallow"):
        conn = to_device(np.asarray(mesh.hexes).T, np.int32)
        pts = to_device(np.asarray(mesh.points, np.float64))
        h = jax.jit(node_lengths_traced)(conn, pts, incidences(conn, mesh.n_nodes))
    np.testing.assert_allclose(np.asarray(h), node_lengths(mesh.hexes, mesh.points), rtol=1e-13, atol=0)


@pytest.mark.parametrize("name, dtype", [(n, np.float64) for n in MESHES] + DTYPE_CASES)
def test_parametrisation_on_the_device(name, dtype):
    """`make_parametrisation_device` gives `make_parametrisation`'s fields (the scale to rounding), also from a
    base off the original points (a smoothed start: boundary nodes moved along their planes)."""
    mesh, pr = _problem(name, dtype)
    info = pr.info
    with jax.enable_x64(True):
        starts = [None, np.asarray(L.run_laplace(pr, "smart-laplace", {"max_sweeps": 2})[0], np.float64)]
        for x0 in starts:
            ref = make_parametrisation(mesh, info, pr.cons, x0, dtype=dtype)
            with jax.transfer_guard("disallow"):
                pts = to_device(np.asarray(mesh.points, np.float64))
                base = None if x0 is None else to_device(x0)
                par = make_parametrisation_device(pts, pr.conn, info.topology.faces, info.feature_edges, pr.cons,
                                                  base, dtype=dtype)
            assert par.shortcut == ref.shortcut
            tol = 1e-6 if dtype == np.float32 else 1e-13
            for field in ("x0", "scale", "flat_nodes", "flat_origin", "flat_radius"):
                a, b = np.asarray(getattr(ref, field)), np.asarray(getattr(par, field))
                assert a.dtype == b.dtype and a.shape == b.shape, field
                np.testing.assert_allclose(b, a, rtol=tol, atol=0, err_msg=field)


@pytest.mark.parametrize("name", ["box5", "pave3.e.vtk"])
def test_padding_on_the_device(name):
    """`pad_parametrisation` of a device parametrisation pads on the device, as the numpy build does."""
    mesh, pr = _problem(name)
    with jax.enable_x64(True):
        par = make_parametrisation(mesh, pr.info, pr.cons, dtype=np.float64)
        host = jax.tree_util.tree_map(np.asarray, par)
        ref, ref_index = pad_parametrisation(host)
        with jax.transfer_guard("disallow"):
            out, index = pad_parametrisation(par)
            out2, index2, conn, weight = pad_problem_device(par, pr.conn, 2 * mesh.n_hexes)
    assert np.array_equal(index, ref_index) and np.array_equal(index2, ref_index)
    for a, b, c in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(out2),
                       strict=True):
        assert a.shape == b.shape == c.shape and a.dtype == b.dtype and np.array_equal(a, b) and np.array_equal(a, c)
    v = np.arange(out.n_free, dtype=np.float64)
    with jax.transfer_guard("disallow"):
        real = unpad_free(to_device(v), free_layout(par.cons), free_layout(out.cons))
    assert np.array_equal(np.asarray(real), v[index])
    hexes = np.asarray(mesh.hexes)
    assert np.array_equal(np.asarray(conn), np.concatenate([hexes, np.repeat(hexes[:1], mesh.n_hexes, axis=0)]).T)
    assert np.array_equal(np.asarray(weight), np.repeat([1.0, 0.0], mesh.n_hexes))


def _flat_edge_loop(points, fe, edge_nodes):
    """The straight intervals one edge node at a time (the loop `flat_intervals` replaced)."""
    out = np.zeros(len(edge_nodes))
    for j, v in enumerate(edge_nodes):
        rows = fe[(fe[:, 0] == v) | (fe[:, 1] == v)]
        if len(rows) != 2:
            continue
        rel = points[np.where(rows[:, 0] == v, rows[:, 1], rows[:, 0])] - points[v]
        chord = rel[1] - rel[0]
        t = chord / max(float(np.linalg.norm(chord)), 1e-300)
        along = rel @ t
        perp = np.linalg.norm(rel - along[:, None] * t, axis=1)
        r = float(np.min(np.abs(along)))
        if along.min() < 0 < along.max() and perp.max() <= 1e-12 * max(r, 1e-300):
            out[j] = r
    return out


@pytest.mark.parametrize("name", MESHES)
def test_flat_intervals_vectorised(name):
    mesh, pr = _problem(name)
    fe = np.asarray(pr.info.feature_edges)
    edge = np.asarray(pr.cons.edge_nodes)
    pts = np.asarray(mesh.points, np.float64)
    if len(edge):  # a bent curve: its intervals end
        pts = pts.copy()
        pts[edge[::3]] += 1e-3
    np.testing.assert_array_equal(flat_intervals(pts, fe, edge), _flat_edge_loop(pts, fe, edge))


@pytest.mark.parametrize("step", [0.01, 2.0])
def test_reach_and_final_points_of_a_device_parametrisation(step):
    """A device parametrisation's `reach` and `final_points` of a device vector run on the device (one scalar
    comes down) and agree with the host's; a step out of the flat regions (2 local lengths) takes the exact
    projection on the host, as before."""
    mesh, pr = _problem("box5")
    with jax.enable_x64(True):
        par = make_parametrisation(mesh, pr.info, pr.cons, dtype=np.float64)
        v = step * np.random.default_rng(0).uniform(-1, 1, par.n_free)
        ref_reach, ref_points = par.reach(v), np.asarray(par.final_points(v))
        guard = "disallow" if step < 1 else "allow"  # the exact projection is still the host's
        with jax.transfer_guard(guard):
            dev = to_device(v)
            reach, points = par.reach(dev), par.final_points(dev)
    assert (ref_reach < 1) == (step < 1)
    assert reach == pytest.approx(ref_reach, rel=1e-12)
    np.testing.assert_allclose(np.asarray(points), ref_points, rtol=0, atol=1e-13)


def test_parametrisation_takes_the_sweep_datas_incidences_and_planes():
    """The presmoothing's incidences, boundary view and planes (found on the float64 points) serve the
    parametrisation: the same one as built alone, with fewer programs and transfers."""
    from jaxci.runtime import transfer

    mesh, pr = _problem("1000hex-block-internal-bias.vtk", np.float32)
    info = pr.info
    with jax.enable_x64(True), jax.transfer_guard("disallow"):
        pts = to_device(np.asarray(mesh.points, np.float64))
        data = sweep_data(pr.x0, pr.conn, pr.cons, info.topology.faces, plane_points=pts)
        alone = make_parametrisation_device(pts, pr.conn, info.topology.faces, info.feature_edges, pr.cons)
        before = transfer.totals()
        shared = make_parametrisation_device(pts, pr.conn, info.topology.faces, info.feature_edges, pr.cons,
                                             inc=data.inc, view=data.view, planes=data.planes)
        after = transfer.totals()
    assert after["d2h_bytes"] - before["d2h_bytes"] < 16  # the shortcut's boolean alone
    assert alone.shortcut == shared.shortcut
    for a, b in zip(jax.tree_util.tree_leaves(alone), jax.tree_util.tree_leaves(shared), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(b))
