"""Smoothing hex-dominant meshes: the wedges, pyramids and tetrahedra's share of the objective, for every method.

The objective of a mixed mesh is `jaxci.metrics.elements.mixed_objective`: the mean over ALL element corners (8 per
hexahedron, 6 per wedge, 4 base corners per pyramid, 4 per tetrahedron) of ``(kappa_i/3)^2 - 1``, each corner
relative to its type's ideal cell. A pyramid is also invalid when one of Verdict's four sub-tetrahedra
(`jaxci.cells.PYRAMID_TETS`) has det <= 0; those determinants carry no objective term, only a barrier.

Every function here reads one table, `jaxci.cells.KERNELS` (per type: corner rows, W^-1, barrier
sub-tetrahedra), and branches on no type name.

Everything here is built to cost nothing on a pure hexahedral mesh: `ExtraCells` of such a mesh has no types
(``types == ()``, a static field), and every function branches on that in Python, so the hexahedral code path
(`jaxci.metrics.hexahedron.objective_t`) runs unchanged and compiles to the same program.

- `ExtraCells`: the transposed connectivities of the non-hexahedral cells, a pytree for the global objectives
  (gradient methods, global CI, histories): `mixed_objective_t`, `mixed_max_condition`, `extra_terms`.
- `CornerTable`: one row per non-hexahedral corner (its 4 nodes, W^-1 and a weight: 1 for an objective corner,
  0 for a pyramid sub-tetrahedron, which only has to stay positive), for the local (per-node) methods:
  `local_extra_terms` evaluates the rows around a node for trial positions of that node.

Nodes of QUADRATIC non-hexahedral cells (``wedge15``, ``pyramid13``, ``tetra10``: midside nodes given) stay
fixed (`jaxci.cells.fixed_nodes`): moving their corners would need their midside nodes re-placed on curved edges.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cells import EDGES, KERNELS, corner_invariants, element_blocks, volume_cells
from ..geometry.topology import unique_edges
from ..mesh import HexMesh
from ..runtime._lazy import jax, jnp, pytree_dataclass
from . import elements as E
from .hexahedron import (
    condition_from_invariants,
    corner_columns,
    gather_corners,
    objective_t,
    squared_condition_from_invariants,
)


# ---------------------------------------------------------------------------------------------- cell blocks
def extra_blocks(mesh: HexMesh) -> dict[str, np.ndarray]:
    """The measured non-hexahedral cells (`jaxci.cells.element_blocks` without the hexahedra)."""
    return {t: c for t, c in element_blocks(mesh).items() if t != "hexahedron"}


def has_extra(mesh: HexMesh) -> bool:
    """Whether `mesh` has measured wedges, pyramids or tetrahedra."""
    return bool(extra_blocks(mesh))


# ---------------------------------------------------------------------------------------------- global form
@pytree_dataclass(static=("types",))
class ExtraCells:
    """The non-hexahedral cells of a mesh as a pytree: `types` (static) and `conns`, one transposed int32
    connectivity ``(k, N)`` per type. Empty (``types == ()``) for a hexahedral mesh."""

    types: tuple[str, ...]
    conns: tuple

    @property
    def n_corners(self) -> int:
        """Number of objective corners (6, 4, 4 per wedge, pyramid, tetrahedron)."""
        return int(sum(KERNELS[t].n_corners * c.shape[1] for t, c in zip(self.types, self.conns, strict=True)))


def extra_cells(mesh: HexMesh, device: bool = True) -> ExtraCells:
    """`ExtraCells` of `mesh` (empty for a hexahedral mesh); `device`: JAX arrays (default) or numpy arrays (the
    numpy path, `jaxci.native.MixedKernel`)."""
    blocks = extra_blocks(mesh)
    put = jax.device_put if device else (lambda a: a)
    return ExtraCells(tuple(blocks), tuple(put(np.ascontiguousarray(c.T).astype(np.int32)) for c in blocks.values()))


def no_extra() -> ExtraCells:
    """The empty `ExtraCells` (a hexahedral mesh)."""
    return ExtraCells((), ())


def extra_terms(x, extra: ExtraCells) -> list:
    """(kappa/3)^2 of every non-hexahedral corner: one array ``(n_corners, N)`` per type (``inf`` if det <= 0)."""
    return [E.corner_terms_t(x, c, t) for t, c in zip(extra.types, extra.conns, strict=True)]


def extra_barrier(x, extra: ExtraCells):
    """0, or ``inf`` when a barrier sub-tetrahedron (`jaxci.cells.CellKernel.barrier`: the pyramids' Verdict
    tetrahedra) has det <= 0: a scalar."""
    out = jnp.zeros((), x.dtype)
    for t, c in zip(extra.types, extra.conns, strict=True):
        dets = E.barrier_dets_t(x, c, t)
        if dets is not None:
            out = jnp.where(jnp.all(dets > 0), out, jnp.inf)
    return out


def mixed_objective_t(x, conn, extra: ExtraCells):
    """F over every corner (`jaxci.metrics.elements.mixed_objective`) from `x` ``(n, 3)``, the transposed hexahedra
    `conn` ``(8, N)`` and `extra`, plus the pyramid barrier; exactly `jaxci.metrics.hexahedron.objective_t` when
    `extra` is empty."""
    if not extra.types:
        return objective_t(x, conn)
    term = squared_condition_from_invariants(*corner_invariants(*corner_columns(*gather_corners(x, conn))))
    term = jax.lax.optimization_barrier(term)
    terms = extra_terms(x, extra)
    total = jnp.sum(term) + sum(jnp.sum(t) for t in terms)
    return total / (term.size + sum(t.size for t in terms)) + extra_barrier(x, extra) - 1.0


def mixed_max_condition(x, conn, extra: ExtraCells):
    """Max kappa/3 over every corner (``inf`` if any is inverted, or a pyramid sub-tetrahedron)."""
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(x, conn)))
    k = jnp.max(jax.lax.optimization_barrier(condition_from_invariants(det, fro2, adj2)))
    if not extra.types:
        return k
    for t in extra_terms(x, extra):
        k = jnp.maximum(k, jnp.sqrt(jnp.max(t)))
    return k + extra_barrier(x, extra)


def objective_and_max(x, conn, extra: ExtraCells, weight=None):
    """F and max kappa/3 of `x` ``(n, 3)`` over every corner (`mixed_objective_t`, `mixed_max_condition`); with
    `weight` ``(N,)``, the element weights of a padded connectivity `conn` ``(8, N)`` (0: a padding element,
    `jaxci.optim._buckets.padded_connectivity`; hexahedral meshes), over the real hexahedra only. On hexahedra
    both come from one pass over the corners: max kappa/3 is the square root of the largest term (kappa/3)^2."""
    if weight is None and extra.types:
        return mixed_objective_t(x, conn, extra), mixed_max_condition(x, conn, extra)
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(x, conn)))
    term = jax.lax.optimization_barrier(squared_condition_from_invariants(det, fro2, adj2))
    if weight is None:  # as `jaxci.metrics.hexahedron.objective_t`
        return jnp.mean(term - 1.0), jnp.sqrt(jnp.max(term))
    real = weight > 0
    f = jnp.sum(jnp.where(real, term - 1.0, 0.0)) / (8.0 * jnp.sum(real.astype(term.dtype)))
    return f, jnp.sqrt(jnp.max(jnp.where(real, term, 0.0)))


# ---------------------------------------------------------------------------------------------- local form
@dataclasses.dataclass(frozen=True)
class CornerTable:
    """One row per non-hexahedral corner, for per-node evaluation (numpy).

    - `nodes` ``(R, 4)``: corner node, then the three nodes whose differences with it are the columns of A;
    - `winv` ``(R, 9)``: W^-1 of the cell type, row-major (``T = A W^-1``);
    - `weight` ``(R,)``: 1 for an objective corner, 0 for a barrier sub-tetrahedron (`jaxci.cells.CellKernel`: the
      pyramids'; its det must stay > 0).
    """

    nodes: np.ndarray
    winv: np.ndarray
    weight: np.ndarray

    @property
    def n_rows(self) -> int:
        return int(self.nodes.shape[0])


def corner_table(mesh: HexMesh) -> CornerTable:
    """The `CornerTable` of the wedges, pyramids and tetrahedra of `mesh` (0 rows for a hexahedral mesh): per type
    of `jaxci.cells.KERNELS`, its corner rows, then its barrier rows (W = I, weight 0) if it has any."""
    nodes, winv, weight = [np.zeros((0, 4), np.int64)], [np.zeros((0, 9))], [np.zeros(0)]
    for t, cells in extra_blocks(mesh).items():
        k = KERNELS[t]
        for tab, wi, w in ((k.corners, k.winv, 1.0), (k.barrier, np.eye(3), 0.0)):
            if not len(tab):
                continue
            rows = cells[:, tab].reshape(-1, 4)
            nodes.append(rows)
            winv.append(np.broadcast_to(wi.reshape(1, 9), (len(rows), 9)))
            weight.append(np.full(len(rows), w))
    return CornerTable(np.concatenate(nodes), np.concatenate(winv), np.concatenate(weight))


def node_corner_rows(table: CornerTable, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """For each node, the rows of `table` that involve it, padded.

    **Returns:** ``(rows, mask)`` of shape ``(n_nodes, K)`` (K >= 0 the largest count; padding holds row 0 and
    is False in `mask`). K = 0 for an empty table.
    """
    if not table.n_rows:
        return np.zeros((n_nodes, 0), np.int64), np.zeros((n_nodes, 0), bool)
    node = table.nodes.ravel()
    row = np.repeat(np.arange(table.n_rows), 4)
    order = np.argsort(node, kind="stable")
    node, row = node[order], row[order]
    count = np.bincount(node, minlength=n_nodes)
    K = int(count.max())
    k = np.arange(len(node)) - np.repeat(np.cumsum(count) - count, count)
    rows = np.zeros((n_nodes, K), np.int64)
    mask = np.zeros((n_nodes, K), bool)
    rows[node, k] = row
    mask[node, k] = True
    return rows, mask


def local_extra_terms(x, v, nodes, winv, weight, mask, y):
    """Sum over the non-hexahedral corners around each node of ``weight (kappa/3)^2`` with the node at `y`.

    **Arguments:**

    - `x`: current coordinates ``(n, 3)``; `v`: the nodes ``(M,)``;
    - `nodes` ``(M, K, 4)``, `winv` ``(M, K, 9)``, `weight` ``(M, K)``, `mask` ``(M, K)``: their `CornerTable`
      rows (`node_corner_rows`);
    - `y`: trial positions ``(M, S, 3)``.

    **Returns:** shape ``(M, S)``: the local sum, ``inf`` where a corner (or pyramid sub-tetrahedron) of a real
    row has det <= 0.
    """
    is_v = (nodes == v[:, None, None])[:, None]  # (M, 1, K, 4)
    P = [jnp.where(is_v, y[..., d][:, :, None, None], x[:, d][nodes][:, None]) for d in range(3)]  # (M, S, K, 4)
    a = [[P[d][..., j] - P[d][..., 0] for d in range(3)] for j in (1, 2, 3)]
    wi = winv[:, None]  # (M, 1, K, 9)
    cols = []
    for j in range(3):
        for d in range(3):
            cols.append(a[0][d] * wi[..., j] + a[1][d] * wi[..., 3 + j] + a[2][d] * wi[..., 6 + j])
    term = squared_condition_from_invariants(*corner_invariants(*cols))  # (M, S, K)
    term = jnp.where(jnp.isfinite(term), term * weight[:, None], jnp.inf)
    return jnp.sum(jnp.where(mask[:, None], term, 0.0), axis=-1)


def local_extra_length(x, v, nodes, weight, mask):
    """Mean distance from each node `v` ``(M,)`` to the other nodes of its objective corner rows, ``(M,)`` (0 for
    a node without rows): a local length scale where the node has no hexahedron."""
    xv = x[v]  # (M, 3)
    d = jnp.sqrt(sum((x[:, k][nodes] - xv[:, k][:, None, None]) ** 2 for k in range(3)))  # (M, K, 4)
    use = (mask & (weight > 0))[..., None] & (nodes != v[:, None, None])
    cnt = jnp.sum(use, axis=(1, 2))
    return jnp.sum(jnp.where(use, d, 0.0), axis=(1, 2)) / jnp.maximum(cnt, 1)


def node_lengths(mesh: HexMesh, points=None) -> np.ndarray:
    """Mean length of the cell edges at each node over every volume cell (each edge once per cell), float64
    ``(n,)``; 0 for unused nodes."""
    p = np.asarray(mesh.points if points is None else points, dtype=np.float64)
    n = len(p)
    total, count = np.zeros(n), np.zeros(n)
    for t, cells in volume_cells(mesh).items():
        e = cells[:, EDGES[t]].reshape(-1, 2)
        length = np.linalg.norm(p[e[:, 1]] - p[e[:, 0]], axis=1)
        for k in (0, 1):
            total += np.bincount(e[:, k], weights=length, minlength=n)
            count += np.bincount(e[:, k], minlength=n)
    return np.divide(total, count, out=np.zeros(n), where=count > 0)


def edge_pairs(mesh: HexMesh) -> np.ndarray:
    """Every distinct edge of every volume cell, sorted node pairs ``(E, 2)``."""
    parts = [cells[:, EDGES[t]].reshape(-1, 2) for t, cells in volume_cells(mesh).items()]
    return unique_edges(np.concatenate(parts))


# ---------------------------------------------------------------------------------------------- checks (numpy)
def inverted_cells(mesh: HexMesh, points) -> dict[str, np.ndarray]:
    """Per measured type, which cells are inverted at `points` (`jaxci.metrics.elements.inverted`), bool ``(N,)``."""
    return {t: E.inverted(points, c, t) for t, c in element_blocks(mesh).items()}


def newly_inverted(mesh: HexMesh, before, after) -> dict[str, int]:
    """Per type, the number of cells valid at `before` and inverted at `after` (only types with some)."""
    b, a = inverted_cells(mesh, before), inverted_cells(mesh, after)
    return {t: int((a[t] & ~b[t]).sum()) for t in a if (a[t] & ~b[t]).any()}


def cell_label(mesh: HexMesh, cell_type: str, k: int) -> str:
    """A readable label of cell `k` (0-based over the blocks of `cell_type`, `jaxci.cells.element_blocks`'
    order), with its file id if any: ``"wedge element 12 (index 3)"``."""
    k = int(k)
    for b in mesh.cells:
        if b.type != cell_type or not len(b.data):
            continue
        if k < len(b.data):
            return f"{cell_type} element {HexMesh.block_label(b, k)}"
        k -= len(b.data)
    raise IndexError(k)
