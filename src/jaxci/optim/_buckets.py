"""Size classes: pad a problem's arrays to a small ladder of sizes so that meshes of similar size share one
compiled program.

JAX compiles a jitted function once per argument SHAPE, and its persistent compilation cache (the CLI's
``JAXCI_CACHE_DIR``) is keyed by the lowered program, shapes included: without padding a second mesh of
nearly the same size recompiles the whole solver loop (measured, L-BFGS, 1000-hex boxes, 2-core CPU: 17 s of
XLA compilation for the L-BFGS loop, then optimistix's). Every size below is rounded up to the next size of the
ladder ``8, 12, 16, 24, 32, 48, 64, ...`` (powers of two and 1.5 times powers of two: at most 50% and on
average about 20% padding), so a mesh of 810 and one of 900 hexahedra both run the 1024-element program.

Padding never changes a result (the callers document how): padded elements repeat element 0 with weight 0
(they add nothing to F, its gradient or its max; F is divided by the REAL corner count), padded nodes are
referenced by no real element and never move, padded free coordinates have scale 0 and zero gradient.

`to_device` moves a numpy array to the device without compiling anything: ``jnp.asarray(numpy_array)``
compiles a small ``jit(stage)`` program per shape and dtype in jax 0.10 (measured: 0.05-0.1 s each, 23 of the
41 compilations of a ``jaxci smooth`` run), `jax.device_put` of an array already in the target dtype none.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..runtime._lazy import is_jax_array, jit, jnp

# the ladder itself (stage 0: the device programs of jaxci.geometry size their downloads by it too)
from ..runtime.sizes import bucket

# `to_device`: a numpy array as a device array of a dtype, converted on the host (no compilation), its bytes
# counted; `device_dtype`: that array kept on the host (padded before it goes there, so that the device never
# holds both forms)
from ..runtime.transfer import host_dtype as device_dtype  # noqa: F401
from ..runtime.transfer import program, to_device  # noqa: F401


def _xp(a):
    """``(xp, a)``: `jax.numpy` and `a` for a JAX array (or a tracer inside a jitted function), else numpy and
    ``np.asarray(a)``."""
    return (jnp, a) if is_jax_array(a) else (np, np.asarray(a))


def pad_rows(a, n: int, fill):
    """`a` with rows appended up to `n` rows: `fill` (a scalar or a row) in each new row (numpy, or jax.numpy
    for a JAX array)."""
    xp, a = _xp(a)
    extra = n - a.shape[0]
    if extra <= 0:
        return a
    pad = xp.broadcast_to(xp.asarray(fill, dtype=a.dtype), (extra,) + a.shape[1:])
    return xp.concatenate([a, pad])


def pad_cols(a, n: int):
    """`a` ``(r, c)`` with columns appended up to `n`: copies of its first column (zeros where it has none;
    numpy, or jax.numpy for a JAX array)."""
    xp, a = _xp(a)
    extra = n - a.shape[1]
    if extra <= 0:
        return a
    pad = xp.broadcast_to(a[:, :1], (a.shape[0], extra)) if a.shape[1] else xp.zeros((a.shape[0], extra), a.dtype)
    return xp.concatenate([a, pad], axis=1)


def padded_connectivity(hexes: np.ndarray, n_elements: int) -> tuple[np.ndarray, np.ndarray]:
    """The transposed connectivity ``(8, n_elements)`` (padding elements repeat element 0) and the element
    weights ``(n_elements,)`` (1 real, 0 padding), numpy."""
    return pad_connectivity(np.asarray(hexes).T, n_elements, np.float64)


def pad_connectivity(conn, n_elements: int, dtype):
    """The transposed connectivity `conn` ``(8, N)`` padded to ``(8, n_elements)`` (padding elements repeat
    element 0) and the element weights ``(n_elements,)`` in `dtype` (1 real, 0 padding); numpy, or jax.numpy
    for a JAX array (under `jax.jit`)."""
    xp, conn = _xp(conn)
    n = conn.shape[1]
    c = pad_cols(conn, n_elements)
    if xp is np:
        return np.ascontiguousarray(c), np.concatenate([np.ones(n, dtype), np.zeros(n_elements - n, dtype)])
    # Under jit, weights made from the shapes alone are a constant that XLA folds into the executable (n_elements
    # numbers: at 10^6 hexahedra, about a second of a warm process's loading of the program); compared with a
    # count read from `conn` (its entries are never negative) they stay an iota and a comparison.
    real = n + xp.minimum(conn[0, 0].astype(xp.int32), 0) if n else 0
    return c, (xp.arange(n_elements, dtype=xp.int32) < real).astype(dtype)


def pad_constraints(cons, n_nodes: int):
    """`cons` (`jaxci.geometry.projection.Constraints`) padded for a mesh of `n_nodes` nodes (more than it has: node
    ``n_real`` is the dummy every padded entry points to), every size on the ladder: on the device for device
    constraints (nothing moves), else built in numpy and placed.

    Padded nodes are CORNER nodes at the origin: `jaxci.geometry.projection.project` puts them back there. Padded
    entries of the interior, surface, edge and corner node lists are the dummy node (zero basis and tangent:
    they never move it); padded candidate rows and columns repeat an entry (the padded triangles and segments
    copy the first one and belong to no patch or curve).
    """
    n = cons.x_orig.shape[0]
    if n_nodes <= n:
        raise ValueError(f"pad_constraints needs at least one padding node: {n_nodes} <= {n}")
    if is_jax_array(cons.x_orig):
        return _pad_constraints_device(cons, int(n_nodes))
    host = type(cons)(**{f.name: np.asarray(getattr(cons, f.name)) for f in dataclasses.fields(cons)})
    return to_device(padded_constraints(host, n_nodes))


@program
@jit(static_argnames=("n_nodes",))
def _pad_constraints_device(cons, n_nodes: int):
    return padded_constraints(cons, n_nodes)


def padded_constraints(c, n_nodes: int):
    """`pad_constraints`' arrays, over the array module of `c`'s (numpy, or jax.numpy under `jax.jit`)."""
    from ..geometry.boundary import CORNER

    n = c.x_orig.shape[0]
    fdt = c.x_orig.dtype
    ns_p, ne_p = bucket(c.surface_nodes.shape[0]), bucket(c.edge_nodes.shape[0])

    def nodes(a):
        return pad_rows(a.astype(np.int32), bucket(a.shape[0]), n)

    def cand(a, rows):
        a = pad_cols(a.astype(np.int32), bucket(a.shape[1], 4))
        return pad_rows(a, max(rows, a.shape[0]), a[0]) if rows else a

    tri = pad_cols(c.triangles.astype(fdt), bucket(c.triangles.shape[1]))
    seg = pad_cols(c.segments.astype(fdt), bucket(c.segments.shape[1]))
    return type(c)(
        x_orig=pad_rows(c.x_orig, n_nodes, 0.0),
        node_class=pad_rows(c.node_class.astype(np.int32), n_nodes, CORNER),
        group=pad_rows(c.group.astype(np.int32), n_nodes, -1),
        row=pad_rows(c.row.astype(np.int32), n_nodes, 0),
        interior_nodes=nodes(c.interior_nodes),
        surface_nodes=nodes(c.surface_nodes),
        edge_nodes=nodes(c.edge_nodes),
        corner_nodes=nodes(c.corner_nodes),
        surface_basis=pad_rows(c.surface_basis.astype(fdt), ns_p, 0.0),
        edge_tangent=pad_rows(c.edge_tangent.astype(fdt), ne_p, 0.0),
        surface_cand=cand(c.surface_cand, ns_p),
        edge_cand=cand(c.edge_cand, ne_p),
        triangles=tri,
        triangle_patch=pad_rows(c.triangle_patch.astype(np.int32), tri.shape[1], -1),
        segments=seg,
        segment_curve=pad_rows(c.segment_curve.astype(np.int32), seg.shape[1], -1),
    )


def free_layout(cons) -> tuple[int, int, int]:
    """Interior, surface and edge node counts of `cons` (the three blocks of the free coordinates)."""
    return (int(cons.interior_nodes.shape[0]), int(cons.surface_nodes.shape[0]), int(cons.edge_nodes.shape[0]))


def free_index(real, padded) -> np.ndarray:
    """Position in the padded free-coordinate vector of every real free coordinate, ``(n_free,)`` int64:
    blocks ``[3 interior | 2 surface | 1 edge]`` of `real` ``(ni, ns, ne)`` laid into those of `padded`."""
    (ni, ns, ne), (pi, ps, _) = real, padded
    return np.concatenate([np.arange(3 * ni), 3 * pi + np.arange(2 * ns), 3 * pi + 2 * ps + np.arange(ne)])
