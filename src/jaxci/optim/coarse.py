"""A two-level preconditioner for the host L-BFGS: the mesh's Laplacian on a coarse space of node aggregates,
plus its diagonal.

On a mesh whose boundary nodes slide on curved walls, L-BFGS spends most of its steps on long-wavelength moves of
many nodes together (a wall's nodes creeping along it, the interior following), which F barely resists and which
its memory of 10 pairs resolves slowly: a 2070-hex annulus needs ~960 steps with its skin sliding and 46 with it
fixed. L-BFGS's initial inverse Hessian ``gamma I`` becomes ``gamma M`` with

    M = Z P_c^-1 Z^T + D^-1,

where ``P`` is the graph Laplacian of the hexahedra's edges (weights 1 / length^2) in the free coordinates
(``P = S B^T (L x I_3) B S``, `jaxci.optim.parametrisation`'s lift ``B`` and scales ``S``), ``D`` its
diagonal, ``Z`` the free coordinates of moving one aggregate of nearby nodes rigidly along x, y or z (each
moving node's share: its lift's transpose), and ``P_c = Z^T P Z + delta`` the coarse matrix (3 per aggregate,
a few hundred in all: inverted densely once). ``M`` is symmetric positive definite (a sum of a positive diagonal
and a positive semi-definite term), fixed for a run, so L-BFGS keeps its guarantees. Aggregates are the cells of a
uniform grid over the bounding box holding about `NODES_PER_AGGREGATE` nodes each, at most `MAX_AGGREGATES`.

Measured (cb5d522, 2026-11-26; in process, 2-core CPU; plain L-BFGS -> ``precondition="coarse"``, the fastest of two
runs): annulus (2070 hexes) 1021 -> 467 steps, 1.69 -> 0.73 s, worst kappa/3 1.24387 -> 1.24347; plate with holes
(2644) 759 -> 234 steps, 1.11 -> 0.50 s; sphere (1944, tet-to-hex) 511 -> 326 steps, 0.70 -> 0.44 s; its 8784-hex
version 1227 -> 345 steps, 5.0 -> 1.8 s; F as low or lower on every one. But not everywhere: bracket (2360) 377
-> 364 steps, 0.42 -> 0.52 s; cylinder O-grid (1610) 258 -> 371 steps, 0.27 -> 0.38 s; pave3 after untangling
269 -> 224 steps and a lower F, but its worst element 2.800 -> 2.903 (another local minimum). With ``delta =
1e-3`` a plate ended in a worse minimum (F 0.06476 against 0.06472).

Hence the default, ``precondition="auto"``: plain L-BFGS for `AUTO_AFTER` steps, M from then on (built then, and
only then). Runs that end sooner (perturbed boxes, most meshes with flat walls) are those of ``"none"`` to the last
bit; the long ones are those creeping along curved walls. The switch point, measured on eleven curved meshes (the
six above and 8,300-9,000-hex annulus, plate, bracket, cylinder, sphere; one process, in turn; total seconds, and
what changed against plain L-BFGS): never 15.0 s; from step 50 10.5 s (pave3's worst element 2.80 -> 2.91, the small
sphere's 2.987 -> 2.992); 100: 11.8 s; 150: 12.4 s (the 9,000-hex annulus's 1.392 -> 1.401); 200: 11.5 s, no worst
element more than 3e-4 above plain L-BFGS's (pave3's 2.800 -> 2.790, bracket's 2.916 -> 2.909), F within 1e-6 of it
or lower on all; annulus 1021 -> 539 steps, plate 759 -> 372, 8784-hex sphere 1227 -> 358. So 200. ``"coarse"`` uses
M from the first step, ``"none"`` never.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .. import native
from ..cells import EDGES
from .parametrisation import Parametrisation

#: ``precondition="auto"``: plain L-BFGS for this many steps, then with M (see the module docstring), on meshes
#: of at most `AUTO_MAX_CELLS` cells: building M holds about 0.9 kB per hexahedron for a moment (200 MB at
#: cube60_pert's 216,000, 1.2 s) and keeps about 130 B per node, which the 10^6-hexahedron memory budget
#: (docs/results/boxes.md) has no room for; ``"coarse"`` builds it at any size.
AUTO_AFTER = 200
AUTO_MAX_CELLS = 250_000

#: Nodes per aggregate aimed at, and the most aggregates (the coarse matrix is ``3 MAX_AGGREGATES`` square).
NODES_PER_AGGREGATE = 27
MAX_AGGREGATES = 128
#: The coarse matrix's regularisation, relative to its mean diagonal: a mesh with no fixed node has rigid
#: motions its Laplacian does not resist.
DELTA = 0.1


@dataclasses.dataclass(frozen=True)
class CoarseSpace:
    """The operator ``M`` of the module docstring over ``n`` free coordinates and ``m = 3 * aggregates`` coarse
    ones (float64, int64, contiguous: the C two-loop recursion reads them).

    - `block` ``(n,)``: each free coordinate's aggregate;
    - `z` ``(n, 3)``: its coefficient in the aggregate's x, y, z moves (the column of ``Z``);
    - `coarse_inv` ``(m, m)``: ``P_c^-1``;
    - `inv_diag` ``(n,)``: ``1 / diag(P)``.
    """

    block: np.ndarray
    z: np.ndarray
    coarse_inv: np.ndarray
    inv_diag: np.ndarray

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """``M q`` for a vector `q` ``(n,)`` (a new float64 array; in C where `jaxci.native` is built)."""
        if native.AVAILABLE:
            return native.coarse_apply(q, self)
        return coarse_apply(self.arrays(), np.asarray(q, np.float64))

    def arrays(self) -> tuple:
        """``(block, z, coarse_inv, inv_diag)``, for `coarse_apply`."""
        return self.block, self.z, self.coarse_inv, self.inv_diag

    def padded(self, index: np.ndarray | None, n: int) -> CoarseSpace:
        """``M`` over a padded vector of `n` free coordinates whose real ones are at `index`
        (`jaxci.optim.parametrisation.pad_parametrisation`; None: as is): a padding coordinate has no coarse move and a
        unit diagonal, so ``M`` leaves it as it is."""
        if index is None:
            return self
        block, z, inv_diag = np.zeros(n, np.int64), np.zeros((n, 3)), np.ones(n)
        block[index], z[index], inv_diag[index] = self.block, self.z, self.inv_diag
        return CoarseSpace(block=block, z=z, coarse_inv=self.coarse_inv, inv_diag=inv_diag)


def coarse_apply(arrays: tuple, q, xp=np):
    """``M q`` of the `CoarseSpace` arrays ``(block, z, coarse_inv, inv_diag)`` (`CoarseSpace.arrays`) for a vector
    `q` ``(n,)``, over the array module `xp` (numpy: the host without the C kernels; jax.numpy: the JAX engine's
    truncated Newton, `jaxci.optim.newton.newton_loop`)."""
    block, z, coarse_inv, inv_diag = arrays
    m = coarse_inv.shape[0]
    index = 3 * block[:, None] + xp.arange(3)
    w = (z * q[:, None]).ravel()
    coarse = np.bincount(index.ravel(), w, m) if xp is np else xp.bincount(index.ravel(), w, length=m)
    c = coarse_inv @ coarse
    return inv_diag * q + xp.einsum("kd,kd->k", z, c[index])


def free_directions(par: Parametrisation) -> tuple[np.ndarray, np.ndarray]:
    """``(node, direction)``: for each free coordinate of `par`, its node ``(n_free,)`` and the unit direction
    ``(n_free, 3)`` its unscaled value moves that node along (the column of the lift ``B``)."""
    c = par.cons
    inter, surf, edge = (np.asarray(a, np.int64) for a in (c.interior_nodes, c.surface_nodes, c.edge_nodes))
    node = np.concatenate([np.repeat(inter, 3), np.repeat(surf, 2), edge])
    direction = np.concatenate([np.tile(np.eye(3), (len(inter), 1)),
                                np.asarray(c.surface_basis, np.float64).reshape(-1, 3),
                                np.asarray(c.edge_tangent, np.float64).reshape(-1, 3)])
    return node, direction


def aggregates(points: np.ndarray, nodes_per_aggregate: int = NODES_PER_AGGREGATE,
               max_aggregates: int = MAX_AGGREGATES) -> np.ndarray:
    """Each node's aggregate ``(n,)`` (0 .. k-1): the occupied cells of a uniform grid over the bounding box of
    `points` ``(n, 3)``, sized for about `nodes_per_aggregate` nodes a cell and at most `max_aggregates` cells
    in the box (flat or thin boxes: no cells across a zero extent)."""
    x = np.asarray(points, np.float64)
    lo, hi = x.min(axis=0), x.max(axis=0)
    ext = hi - lo
    live = ext > 1e-12 * max(float(ext.max()), 1e-300)
    target = int(np.clip(len(x) // max(nodes_per_aggregate, 1), 1, max_aggregates))
    cell = (np.prod(ext[live]) / target) ** (1.0 / max(int(live.sum()), 1)) if live.any() else 1.0
    counts = np.where(live, np.maximum(1, np.floor(ext / cell)), 1).astype(np.int64)
    while np.prod(counts) > max_aggregates and counts.max() > 1:  # rounding up may overshoot the budget
        counts[np.argmax(counts)] -= 1
    grid = np.minimum(((x - lo) / np.where(live, ext, 1.0) * counts).astype(np.int64), counts - 1)
    key = (grid[:, 0] * counts[1] + grid[:, 1]) * counts[2] + grid[:, 2]
    return np.unique(key, return_inverse=True)[1].reshape(-1)


def build_coarse(par: Parametrisation, cells: dict, *, delta: float = DELTA) -> CoarseSpace:
    """The `CoarseSpace` of the free coordinates of `par` (numpy) on the mesh's cells: `cells` maps a linear
    cell type of `jaxci.cells.EDGES` to its connectivity ``(N, k)``."""
    x = np.asarray(par.x0, np.float64)
    scale = np.asarray(par.scale, np.float64)
    node, direction = free_directions(par)
    pairs = np.sort(np.concatenate([np.asarray(c, np.int64)[:, EDGES[t]].reshape(-1, 2)
                                    for t, c in cells.items() if len(c)]), axis=1)
    key = np.unique(pairs[:, 0] * len(x) + pairs[:, 1])  # each edge once
    a, b = key // len(x), key % len(x)
    d2 = np.sum((x[a] - x[b]) ** 2, axis=1)
    w = 1.0 / np.maximum(d2, 1e-12 * max(float(np.median(d2)), 1e-300))  # coincident nodes: a finite weight
    degree = np.bincount(a, w, len(x)) + np.bincount(b, w, len(x))
    degree = np.where(degree > 0, degree, degree.max(initial=1.0))  # a node of no cell: not a free one anyway
    inv_diag = 1.0 / (scale * scale * degree[node])

    agg = aggregates(x)
    m = 3 * (int(agg.max()) + 1)
    # each node's projector onto its free directions (I inside, the tangent plane or line on the boundary, 0 fixed)
    from ._moves import node_bases

    c = par.cons
    basis = np.asarray(node_bases(c), np.float64)
    proj = np.einsum("nik,njk->nij", basis, basis)
    # P_c = Z^T P Z = E^T Pi (L x I) Pi E: per edge (a, b, w), w (Pi_a e_agg(a) - Pi_b e_agg(b)) (...)^T, which
    # is zero for an edge inside one aggregate between two interior nodes (Pi = I at both): those, most edges of
    # a large mesh, are left out (cube60_pert, 226,981 nodes: the whole build 3.2 -> 1.1 s)
    inside = np.zeros(len(x), bool)
    inside[np.asarray(c.interior_nodes)] = True
    keep = (agg[a] != agg[b]) | ~inside[a] | ~inside[b]
    a, b, w = a[keep], b[keep], w[keep]
    coarse = np.zeros(m * m)
    pa, pb = proj[a], proj[b]
    cross = w[:, None, None] * np.einsum("kij,kjl->kil", pa, pb)
    rows, cols = 3 * agg[a][:, None] + np.arange(3), 3 * agg[b][:, None] + np.arange(3)
    for r, c, blk in ((rows, rows, w[:, None, None] * pa), (cols, cols, w[:, None, None] * pb),
                      (rows, cols, -cross), (cols, rows, -cross.transpose(0, 2, 1))):
        coarse += np.bincount((r[:, :, None] * m + c[:, None, :]).ravel(), blk.ravel(), m * m)
    coarse = coarse.reshape(m, m)
    diag = np.diag(coarse).copy()
    used = diag > 0
    coarse[np.diag_indices(m)] += np.where(used, delta * (diag[used].mean() if used.any() else 1.0), 1.0)
    coarse_inv = np.linalg.inv(coarse)
    coarse_inv = 0.5 * (coarse_inv + coarse_inv.T)  # symmetric to the last bit: M must be
    return CoarseSpace(block=np.ascontiguousarray(agg[node], np.int64),
                       z=np.ascontiguousarray(direction / scale[:, None], np.float64),
                       coarse_inv=np.ascontiguousarray(coarse_inv), inv_diag=np.ascontiguousarray(inv_diag))
