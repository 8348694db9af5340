"""Size classes: pad a problem's arrays to a small ladder of sizes so that meshes of similar size share one
compiled program.

JAX compiles a jitted function once per argument SHAPE, and its persistent compilation cache (the CLI's
``JAXCI_CACHE_DIR``) is keyed by the lowered program, shapes included: without padding a second mesh of
nearly the same size recompiles the whole solver loop (measured, L-BFGS, 1000-hex boxes, 2-core CPU: 17 s of
XLA compilation for `jaxci.optim._solve.solve_loop`). Every size below is rounded up to the next size of the
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

import numpy as np

# the ladder itself (stage 0: the device programs of jaxci.geometry size their downloads by it too)
from ..sizes import MIN_BUCKET, bucket  # noqa: F401

# `to_device`: a numpy array as a device array of a dtype, converted on the host (no compilation), its bytes
# counted; `device_dtype`: that array kept on the host (padded before it goes there, so that the device never
# holds both forms)
from ..transfer import host_dtype as device_dtype  # noqa: F401
from ..transfer import to_device  # noqa: F401


def pad_rows(a: np.ndarray, n: int, fill) -> np.ndarray:
    """`a` with rows appended up to `n` rows: `fill` (a scalar or a row) in each new row."""
    a = np.asarray(a)
    extra = n - a.shape[0]
    if extra <= 0:
        return a
    pad = np.empty((extra,) + a.shape[1:], a.dtype)
    pad[...] = fill
    return np.concatenate([a, pad])


def pad_cols(a: np.ndarray, n: int, *, repeat_first: bool = True, fill=0) -> np.ndarray:
    """`a` ``(r, c)`` with columns appended up to `n`: copies of its first column, or `fill`."""
    a = np.asarray(a)
    extra = n - a.shape[1]
    if extra <= 0:
        return a
    if repeat_first and a.shape[1]:
        pad = np.repeat(a[:, :1], extra, axis=1)
    else:
        pad = np.full((a.shape[0], extra), fill, a.dtype)
    return np.concatenate([a, pad], axis=1)


def padded_connectivity(hexes: np.ndarray, n_elements: int) -> tuple[np.ndarray, np.ndarray]:
    """The transposed connectivity ``(8, n_elements)`` (padding elements repeat element 0) and the element
    weights ``(n_elements,)`` (1 real, 0 padding), numpy."""
    hexes = np.asarray(hexes)
    n = len(hexes)
    conn = np.concatenate([hexes, np.repeat(hexes[:1], n_elements - n, axis=0)]).T
    weight = np.concatenate([np.ones(n), np.zeros(n_elements - n)])
    return np.ascontiguousarray(conn), weight


def pad_constraints(cons, n_nodes: int):
    """`cons` (`jaxci.geometry.projection.Constraints`) padded for a mesh of `n_nodes` nodes (more than it has: node
    ``n_real`` is the dummy every padded entry points to), numpy-built, every size on the ladder.

    Padded nodes are CORNER nodes at the origin: `jaxci.geometry.projection.project` puts them back there. Padded
    entries of the interior, surface, edge and corner node lists are the dummy node (zero basis and tangent:
    they never move it); padded candidate rows and columns repeat an entry (the padded triangles and segments
    copy the first one and belong to no patch or curve).
    """
    from ..geometry.boundary import CORNER
    from ..geometry.projection import Constraints

    n = cons.x_orig.shape[0]
    if n_nodes <= n:
        raise ValueError(f"pad_constraints needs at least one padding node: {n_nodes} <= {n}")
    fdt = cons.x_orig.dtype
    g = {k: np.asarray(getattr(cons, k)) for k in ("x_orig", "node_class", "group", "row", "interior_nodes",
                                                    "surface_nodes", "edge_nodes", "corner_nodes", "surface_basis",
                                                    "edge_tangent", "surface_cand", "edge_cand", "triangles",
                                                    "triangle_patch", "segments", "segment_curve")}
    ns, ne = len(g["surface_nodes"]), len(g["edge_nodes"])
    ns_p, ne_p = bucket(ns), bucket(ne)

    def nodes(a):
        return pad_rows(a, bucket(len(a)), n)

    def cand(a, rows):
        a = pad_cols(a, bucket(a.shape[1], 4))
        return pad_rows(a, max(rows, a.shape[0]), a[0]) if rows else a

    tri = pad_cols(g["triangles"], bucket(g["triangles"].shape[1]))
    seg = pad_cols(g["segments"], bucket(g["segments"].shape[1]))
    out = Constraints(
        x_orig=to_device(pad_rows(g["x_orig"], n_nodes, 0.0), fdt),
        node_class=to_device(pad_rows(g["node_class"], n_nodes, CORNER), np.int32),
        group=to_device(pad_rows(g["group"], n_nodes, -1), np.int32),
        row=to_device(pad_rows(g["row"], n_nodes, 0), np.int32),
        interior_nodes=to_device(nodes(g["interior_nodes"]), np.int32),
        surface_nodes=to_device(nodes(g["surface_nodes"]), np.int32),
        edge_nodes=to_device(nodes(g["edge_nodes"]), np.int32),
        corner_nodes=to_device(nodes(g["corner_nodes"]), np.int32),
        surface_basis=to_device(pad_rows(g["surface_basis"], ns_p, 0.0), fdt),
        edge_tangent=to_device(pad_rows(g["edge_tangent"], ne_p, 0.0), fdt),
        surface_cand=to_device(cand(g["surface_cand"], ns_p), np.int32),
        edge_cand=to_device(cand(g["edge_cand"], ne_p), np.int32),
        triangles=to_device(tri, fdt),
        triangle_patch=to_device(pad_rows(g["triangle_patch"], tri.shape[1], -1), np.int32),
        segments=to_device(seg, fdt),
        segment_curve=to_device(pad_rows(g["segment_curve"], seg.shape[1], -1), np.int32),
    )
    return out


def free_layout(cons) -> tuple[int, int, int]:
    """Interior, surface and edge node counts of `cons` (the three blocks of the free coordinates)."""
    return (int(cons.interior_nodes.shape[0]), int(cons.surface_nodes.shape[0]), int(cons.edge_nodes.shape[0]))


def free_index(real, padded) -> np.ndarray:
    """Position in the padded free-coordinate vector of every real free coordinate, ``(n_free,)`` int64:
    blocks ``[3 interior | 2 surface | 1 edge]`` of `real` ``(ni, ns, ne)`` laid into those of `padded`."""
    (ni, ns, ne), (pi, ps, _) = real, padded
    return np.concatenate([np.arange(3 * ni), 3 * pi + np.arange(2 * ns), 3 * pi + 2 * ps + np.arange(ne)])
