"""The worst-element polish of a run whose mesh lives on the device: a window of the worst cells comes down, the
rest of the mesh stays where it is.

The polish (`jaxci.optim.polish`) moves only the nodes of the cells above its level, and its levels fall from the
worst cell down; on the JAX engine the mesh is on the device, and bringing it to the host for the polish would
be O(mesh) host work and traffic for an O(worst elements) job. `window` finds on the device the `window_size`
worst cells (their worst corner kappa/3, float64) and every cell that shares a node with them (the ring), brings
down those cells and the data of their nodes (coordinates, classes, free-coordinate scales and flat regions;
their constraint rows are the host's float64 tables), and gives the polish a compact problem in which:

- the nodes of the worst cells move as in the whole mesh (their class, constraints, scales, flat regions);
- the other nodes of the ring cells are fixed (some of their cells are outside the window);
- the cells outside the window, which no moving node touches, enter the polish's figures as sums (`Rest`).

So the polish decides exactly as on the whole mesh for every level above the window's smallest worst cell;
below it, the worst cell outside the window bounds the worst the polish can reach (`Rest.k_max`), and it stops
there. `put_back` scatters the polished nodes into the device's coordinates. A mesh of at most `WINDOW_MIN` cells
is its own window.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cells import corner_invariants
from ..geometry.boundary import EDGE, INTERIOR, SURFACE
from ..geometry.projection import Constraints
from ..metrics.hexahedron import corner_columns, gather_corners, squared_condition_from_invariants
from ..runtime._lazy import jax, jit, jnp
from ..runtime.transfer import program, to_device, to_host
from ._buckets import bucket
from .parametrisation import Parametrisation
from .polish import Rest, sub_constraints, sub_parametrisation

#: Cells of the window at least (a mesh this small is its own window), and as a fraction of the mesh's cells.
WINDOW_MIN = 8192
WINDOW_FRACTION = 0.01


def window_size(n_cells: int) -> int:
    """How many worst cells the window holds for a mesh of `n_cells` hexahedra."""
    return min(int(n_cells), max(WINDOW_MIN, int(WINDOW_FRACTION * n_cells)))


@dataclasses.dataclass(frozen=True)
class Window:
    """A compact polish problem cut out of a device mesh (`window`): `blocks` ``{"hexahedron": (m, 8)}`` in the
    window's node numbering; `nodes` ``(k,)`` the mesh's index of each window node; `x` ``(k, 3)`` float64 their
    coordinates; `cons`, `par` the numpy float64 `Constraints` and `Parametrisation` of the window (the nodes of
    the worst cells with their own class, the others fixed); `rest` the cells outside it."""

    blocks: dict
    nodes: np.ndarray
    x: np.ndarray
    cons: Constraints
    par: Parametrisation
    rest: Rest


def _cell_terms(x, conn):
    """(kappa/3)^2 of every corner ``(8, N)`` (``inf`` where det <= 0) and each cell's worst kappa/3 ``(N,)``."""
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(x, conn)))
    t = squared_condition_from_invariants(det, fro2, adj2)
    return t, jnp.sqrt(jnp.max(t, axis=0))


@program
@jit(static_argnames=("k",))
def _ring(x, conn, k: int):
    """The `k` worst cells' nodes (``mark``, bool ``(n,)``), the cells that touch them (``ring``, bool ``(N,)``),
    and the ring's size and the sums of the cells outside it (`Rest`'s figures, float64)."""
    t, worst = _cell_terms(x, conn)
    _, top = jax.lax.top_k(worst, k)
    mark = jnp.zeros(x.shape[0], bool).at[conn[:, top]].set(True)
    ring = jnp.any(mark[conn], axis=0)
    out = ~ring
    e = jnp.sum(jnp.where(out, jnp.sum(t - 1.0, axis=0), 0.0))
    figures = jnp.stack([jnp.sum(ring).astype(x.dtype), jnp.sum(out).astype(x.dtype), e,
                         jnp.sum(jnp.where(out, worst, 0.0)), jnp.max(jnp.where(out, worst, 0.0))])
    return mark, ring, figures


@program
@jit(static_argnames=("m",))
def _ring_cells(conn, mark, ring, m: int):
    """The ring's cells ``(8, m)`` (padded with cell 0) and, for each of their nodes, whether it is a
    node of the worst cells."""
    idx = jnp.nonzero(ring, size=m, fill_value=0)[0]
    cells = conn[:, idx]
    return cells, mark[cells]


@program
@jit
def _node_rows(x, cons: Constraints, par: Parametrisation, nodes):
    """Per node of `nodes` ``(k,)``: its coordinates, class, group, row, the index of its first free coordinate
    in `par`'s layout and its flat region's row in `par` (-1: none)."""
    ni, ns = cons.interior_nodes.shape[0], cons.surface_nodes.shape[0]
    cls, row = cons.node_class[nodes], cons.row[nodes]
    inter = jnp.searchsorted(cons.interior_nodes, nodes)
    start = jnp.where(cls == INTERIOR, 3 * inter, jnp.where(cls == SURFACE, 3 * ni + 2 * row,
                                                              jnp.where(cls == EDGE, 3 * ni + 2 * ns + row, -1)))
    flat = jnp.where(cls == SURFACE, row, jnp.where(cls == EDGE, ns + row, -1))
    flat = jnp.where(flat < par.flat_nodes.shape[0], flat, -1)
    return x[nodes], cls, cons.group[nodes], row, start, flat


@program
@jit
def _gather_rows(par: Parametrisation, coords, flat):
    """The scales of the free coordinates `coords` and the flat regions of rows `flat` (zeros where the run has no
    flat region: a boundary held fixed has none, and a gather from no rows is no program)."""
    if not par.flat_origin.shape[0]:
        return par.scale[coords], jnp.zeros((flat.shape[0], 3), par.flat_origin.dtype), jnp.zeros(
            flat.shape, par.flat_radius.dtype)
    return par.scale[coords], par.flat_origin[flat], par.flat_radius[flat]


def window(x, conn, cons: Constraints, par: Parametrisation, tables: Constraints, k: int | None = None) -> Window:
    """The polish's `Window` of a device mesh.

    **Arguments:** `x` ``(n, 3)`` float64 device coordinates (on the boundary); `conn` ``(8, N)`` the device
    hexahedra (transposed); `cons`, `par` the run's device `Constraints` and `Parametrisation` (unpadded);
    `tables` the boundary's tables on the host in float64 (`jaxci.geometry.tables.BoundaryTables`, or numpy
    float64 `Constraints`): the rows of the window's surface and edge nodes (`surface_basis`, `edge_tangent`,
    `surface_cand`, `edge_cand`, indexed as `cons`' rows) and the triangles and segments its projections search;
    `k`: the worst cells to hold (default `window_size`).

    Traffic: O(window) each way, and the four small programs above.
    """
    n_cells = int(conn.shape[1])
    k = window_size(n_cells) if k is None else min(int(k), n_cells)
    mark, ring, figures = _ring(x, conn, k)
    n_ring, n_out, e_out, k_sum, k_max = to_host(figures)
    m = int(n_ring)
    cells, top = to_host(_ring_cells(conn, mark, ring, bucket(m)))
    cells, top = cells[:, :m].T.astype(np.int64), top[:, :m].T
    nodes, local = np.unique(cells, return_inverse=True)
    moving = np.zeros(len(nodes), bool)
    moving[local.reshape(cells.shape)[top]] = True
    kb = bucket(len(nodes))
    padded = np.concatenate([nodes, np.full(kb - len(nodes), nodes[-1])]).astype(np.int32)
    xs, cls, group, row, start, flat = (a[: len(nodes)] for a in to_host(
        _node_rows(x, cons, par, to_device(padded))))
    sub, groups = sub_constraints(xs, cls, moving, group, row, tables)

    def pad(a):  # at least one row, to a bucket (one compiled gather per size class)
        a = np.asarray(a, np.int32)
        return np.concatenate([a, np.zeros(bucket(max(len(a), 1)) - len(a), np.int32)])

    def gather(coords, rows):  # on the device: O(window) down
        scale, origin, radius = to_host(_gather_rows(par, to_device(pad(coords)), to_device(pad(rows))))
        return scale[: len(coords)], origin[: len(rows)], radius[: len(rows)]

    spar = sub_parametrisation(sub, groups, xs, start, flat, gather)
    rest = Rest(n_cells=int(n_out), n_corners=8 * int(n_out), e_sum=float(e_out), k_sum=float(k_sum),
                k_max=float(k_max))
    return Window({"hexahedron": local.reshape(cells.shape)}, nodes, np.asarray(xs, np.float64), sub, spar, rest)


@program
@jit
def _scatter(x, nodes, values):
    return x.at[nodes].set(values)


def put_back(x, win: Window, y: np.ndarray):
    """The device coordinates `x` with the window's nodes at `y` ``(k, 3)`` (the polish's result; the fixed ones
    are where they were): O(window) up."""
    moved = np.flatnonzero((y != win.x).any(axis=1))
    if not len(moved):
        return x
    mb = bucket(len(moved))
    idx = np.concatenate([moved, np.full(mb - len(moved), moved[-1])])
    return _scatter(x, to_device(win.nodes[idx].astype(np.int32)), to_device(y[idx], x.dtype))
