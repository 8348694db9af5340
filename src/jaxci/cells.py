"""The cell types jaxci knows and the algebra of their corners: one home below every stage (numpy only).

Everything that more than one stage needs about a cell type lives here, so that no stage has to re-spell it or
import upwards for it: the mesh model (`jaxci.mesh`: orientation check, midside edges), the geometry (volume cells
of the boundary topology), the metrics (`jaxci.metrics`: corner kernels, objective, report), the C kernels
(`jaxci.native`) and the optimizers.

- Tables: `ELEMENT_TYPES`, `NODES`, `CORNER_NEIGHBOURS` (the hexahedron's corners), `ROTATE_TO_SLOT` (its
  relabellings that bring a node to local node 0), `CORNERS` and `TARGETS` (every
  type's corners and ideal corner matrix, formulas in `jaxci.metrics.elements`), `PYRAMID_TETS`, `EDGES`,
  `EXTRA_TYPES`, `QUADRATIC_TYPES`.
- The table of kernels: `KERNELS`, one `CellKernel` per type (corner rows, W^-1, barrier sub-tetrahedra): what
  every non-hexahedral function iterates over instead of branching on type names.
- Corner algebra, for numpy and jax.numpy arrays alike: `corner_invariants` (det A, |A|_F^2, |adj A|_F^2),
  `edge_lengths2` and `scaled_ratio` (the scaled Jacobian), `corner_determinants` (numpy float64, the
  hexahedra's det A_i alone), `pmean_weights` (the p-mean of corner excesses and its weights).
- The volume cells of a mesh: `element_blocks` (measured linear types), `volume_cells` (quadratic blocks by their
  corners), `fixed_nodes` (nodes of quadratic non-hexahedral cells, which never move).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import warnings
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .mesh import HexMesh

#: For corner i of a hexahedron, the nodes whose differences with node i are the three columns of the corner
#: matrix A_i (Verdict / VTK / Mesquite convention, see ``shared/reference/metrics.md``). Shape ``(8, 3)``.
CORNER_NEIGHBOURS = np.array(
    [
        [1, 3, 4],
        [2, 0, 5],
        [3, 1, 6],
        [0, 2, 7],
        [7, 5, 0],
        [4, 6, 1],
        [5, 7, 2],
        [6, 4, 3],
    ],
    dtype=np.int64,
)

#: ROTATE_TO_SLOT[a] relabels a VTK hexahedron (new local i = old local ROTATE_TO_SLOT[a][i]) by a proper
#: rotation of the reference cube that brings old local node a to slot 0.
ROTATE_TO_SLOT = np.array(
    [
        [0, 1, 2, 3, 4, 5, 6, 7],
        [1, 0, 4, 5, 2, 3, 7, 6],
        [2, 3, 0, 1, 6, 7, 4, 5],
        [3, 2, 6, 7, 0, 1, 5, 4],
        [4, 5, 1, 0, 7, 6, 2, 3],
        [5, 4, 7, 6, 1, 0, 3, 2],
        [6, 7, 3, 2, 5, 4, 0, 1],
        [7, 6, 5, 4, 3, 2, 1, 0],
    ],
    dtype=np.int64,
)

#: The linear volume cell types jaxci measures, in report order.
ELEMENT_TYPES = ("hexahedron", "wedge", "pyramid", "tetra")

#: Nodes per cell of each type.
NODES = {"hexahedron": 8, "wedge": 6, "pyramid": 5, "tetra": 4}

#: Corner table of each type, shape ``(n_corners, 4)``: row ``[i, p, q, r]`` = the corner node i and the nodes
#: whose differences with it are the columns of A_i, in that order.
CORNERS = {
    "hexahedron": np.concatenate([np.arange(8)[:, None], CORNER_NEIGHBOURS], axis=1),
    "wedge": np.array([[0, 1, 2, 3], [1, 2, 0, 4], [2, 0, 1, 5], [3, 5, 4, 0], [4, 3, 5, 1], [5, 4, 3, 2]]),
    "pyramid": np.array([[0, 1, 3, 4], [1, 2, 0, 4], [2, 3, 1, 4], [3, 0, 2, 4]]),
    "tetra": np.array([[0, 1, 2, 3], [1, 2, 0, 3], [2, 0, 1, 3], [3, 0, 2, 1]]),
}

_S3 = math.sqrt(3.0) / 2.0
#: Corner matrix W of the ideal cell of each type (columns as in `CORNERS`), shape ``(3, 3)``.
TARGETS = {
    "hexahedron": np.eye(3),
    "wedge": np.array([[1.0, 0.5, 0.0], [0.0, _S3, 0.0], [0.0, 0.0, 1.0]]),
    "pyramid": np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, math.sqrt(0.5)]]),
    "tetra": np.array([[1.0, 0.5, 0.5], [0.0, _S3, _S3 / 3.0], [0.0, 0.0, math.sqrt(2.0 / 3.0)]]),
}

#: The four tetrahedra of Verdict's pyramid Jacobian and scaled Jacobian (``make_pyramid_tets``).
PYRAMID_TETS = np.array([[0, 1, 2, 4], [0, 2, 3, 4], [0, 1, 3, 4], [1, 2, 3, 4]])


@dataclasses.dataclass(frozen=True, eq=False)
class CellKernel:
    """What the generic corner kernels need of one cell type (`KERNELS`): every function of the non-hexahedral
    cells (objective, barrier, local rows, C kernel, untangling energy) reads these three fields instead of
    branching on the type's name.

    - `corners` ``(n_corners, 4)``: the objective corners, rows ``[i, p, q, r]`` (`CORNERS`);
    - `winv` ``(3, 3)``: W^-1 of the type's ideal corner (`TARGETS`), so that ``T = A W^-1``;
    - `barrier` ``(n_tets, 4)``: sub-tetrahedra ``[a, b, c, d]`` whose det(b - a, c - a, d - a) must stay > 0
      (the raw A, W = I) but carry no objective term: a validity barrier (the pyramid's four Verdict
      tetrahedra, `PYRAMID_TETS`); ``(0, 4)`` for a type without.
    """

    corners: np.ndarray
    winv: np.ndarray
    barrier: np.ndarray

    @property
    def n_corners(self) -> int:
        """Objective corners per cell."""
        return int(self.corners.shape[0])


#: Barrier sub-tetrahedra of each type that has some (`CellKernel.barrier`).
BARRIER_TETS = {"pyramid": PYRAMID_TETS}

#: Every measured type's `CellKernel`, in `ELEMENT_TYPES` order: defined once, here, from `CORNERS`, `TARGETS` and
#: `BARRIER_TETS`. The hexahedra also have their own fast path (`jaxci.metrics.hexahedron`, `jaxci.native`); the
#: other types (`EXTRA_TYPES`) run through this table alone.
KERNELS = {
    t: CellKernel(CORNERS[t], np.linalg.inv(TARGETS[t]), BARRIER_TETS.get(t, np.zeros((0, 4), np.int64)))
    for t in ELEMENT_TYPES
}


#: Edges (pairs of local corner nodes) of the linear volume cells, in the order of the midside nodes of VTK's
#: quadratic cells (``hexahedron20``, ``wedge15``, ``pyramid13``, ``tetra10``) and of ANSYS's SOLID186/187.
EDGES = {
    "hexahedron": np.array(
        [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]
    ),
    "wedge": np.array([[0, 1], [1, 2], [2, 0], [3, 4], [4, 5], [5, 3], [0, 3], [1, 4], [2, 5]]),
    "pyramid": np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 4], [1, 4], [2, 4], [3, 4]]),
    "tetra": np.array([[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]]),
}

#: The non-hexahedral linear cell types that are measured and smoothed.
EXTRA_TYPES = ("wedge", "pyramid", "tetra")

#: meshio's quadratic volume cell types kept as their own blocks -> their linear type (the first k nodes are the
#: corners, in VTK order). Their nodes are never moved.
QUADRATIC_TYPES = {"hexahedron20": "hexahedron", "hexahedron27": "hexahedron", "wedge15": "wedge",
                   "pyramid13": "pyramid", "tetra10": "tetra"}


# ---------------------------------------------------------------------------------------------- corner algebra
def corner_invariants(ax, ay, az, bx, by, bz, cx, cy, cz):
    """det A, |A|_F^2 and |adj A|_F^2 of corner matrices given column by column (any common shape)."""
    # b x c, c x a, a x b
    ux, uy, uz = by * cz - bz * cy, bz * cx - bx * cz, bx * cy - by * cx
    vx, vy, vz = cy * az - cz * ay, cz * ax - cx * az, cx * ay - cy * ax
    wx, wy, wz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    det = ax * ux + ay * uy + az * uz
    fro2 = ax * ax + ay * ay + az * az + bx * bx + by * by + bz * bz + cx * cx + cy * cy + cz * cz
    adj2 = ux * ux + uy * uy + uz * uz + vx * vx + vy * vy + vz * vz + wx * wx + wy * wy + wz * wz
    return det, fro2, adj2


def edge_lengths2(ax, ay, az, bx, by, bz, cx, cy, cz):
    """|a|^2 |b|^2 |c|^2 of corner matrices given column by column (the scaled Jacobian's denominator, squared)."""
    return (ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz) * (cx * cx + cy * cy + cz * cz)


def scaled_ratio(xp, det, l2):
    """det / sqrt(l2), the scaled Jacobian from det A and `edge_lengths2`; 0 where l2 == 0 (an edge of length 0)."""
    return xp.where(l2 > 0, det / xp.sqrt(xp.where(l2 > 0, l2, 1.0)), 0.0)


#: The C extension's interface version (its ``ABI``), raised whenever an argument of a kernel changes.
KERNELS_ABI = 6


@functools.cache
def load_c_kernels():
    """The C extension `jaxci._ckernels`, or None (not built, or ``JAXCI_NATIVE=0``): loaded here, the lowest
    stage, for `corner_determinants` and `jaxci.native` alike."""
    if os.environ.get("JAXCI_NATIVE", "1") == "0":
        return None
    try:
        from . import _ckernels
    except ImportError:  # pragma: no cover - no compiler at install time
        return None
    if getattr(_ckernels, "ABI", None) != KERNELS_ABI:  # built from other sources: its arguments may differ
        warnings.warn(f"jaxci's C extension ({_ckernels.__file__}) was built from other sources than this jaxci "
                      f"(interface {getattr(_ckernels, 'ABI', 1)}, this jaxci's {KERNELS_ABI}); it is not used "
                      f"(numpy runs instead). Rebuild it: python3 -m pip install -e . (or python3 setup.py "
                      f"build_ext --inplace)", RuntimeWarning, stacklevel=2)
        return None
    return _ckernels


def corner_determinants(points: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """det A_i of every corner of every hexahedron, float64 (the determinants alone: the mesh model's
    orientation check and the validity checks; `jaxci.metrics.hexahedron` has the fast kernels). In C where the
    extension is built (one pass; 10x numpy's at 216,000 hexahedra), with numpy's arithmetic: the same numbers.

    **Arguments:** `points` of shape ``(n, 3)``; `hexes` of shape ``(N, 8)``.

    **Returns:** an array of shape ``(N, 8)``.
    """
    p = np.asarray(points, dtype=np.float64)
    h = np.asarray(hexes)
    c = load_c_kernels()
    if c is not None and h.ndim == 2 and h.shape[1] == 8 and p.ndim == 2 and p.shape[1] == 3:
        out = np.empty((h.shape[0], 8))
        c.hex_determinants(np.ascontiguousarray(p), np.ascontiguousarray(h, dtype=np.int32), out)
        return out
    X, Y, Z = (np.ascontiguousarray(p[:, d][h.T]) for d in range(3))  # (8, N) each: one row per local node
    out = np.empty((h.shape[0], 8))
    for i, (j, k, m) in enumerate(CORNER_NEIGHBOURS):  # columns a, b, c from node i; det = a . (b x c)
        ax, ay, az = X[j] - X[i], Y[j] - Y[i], Z[j] - Z[i]
        bx, by, bz = X[k] - X[i], Y[k] - Y[i], Z[k] - Z[i]
        cx, cy, cz = X[m] - X[i], Y[m] - Y[i], Z[m] - Z[i]
        out[:, i] = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    return out


def pmean_weights(xp, e, real, power: float):
    """``(M_p, c)`` for the excesses `e` ``(8, N)`` (``inf`` where inverted) of the corners where `real`
    (None: all): the p-mean and per corner ``c_i = (e_i / M_p)^(p - 1)``, so that
    ``d M_p = mean_i c_i d e_i``. Scaled by the largest excess, so that e^p neither overflows nor underflows."""
    e = xp.maximum(e, 0.0)
    if real is not None:
        e = xp.where(real, e, 0.0)
    n = e.size if real is None else 8.0 * xp.sum(real.astype(e.dtype))
    top = xp.max(e)
    safe = xp.where((top > 0) & (top < xp.inf), top, 1.0)
    m = top * (xp.sum((e / safe) ** power) / n) ** (1.0 / power)
    m = xp.where(top < xp.inf, m, xp.inf)
    c = xp.where(m > 0, (e / xp.where(m > 0, m, 1.0)) ** (power - 1.0), 0.0)
    return m, c


# ---------------------------------------------------------------------------------------------- volume cells
def element_blocks(mesh: HexMesh) -> dict[str, np.ndarray]:
    """The volume cells of `mesh` by type, blocks of a type concatenated in file order.

    **Returns:** type -> connectivity of shape ``(N_type, k)``, in `ELEMENT_TYPES` order, only types present; a
    type held in one block is a read-only view of it (no copy: 64 MB at 10^6 hexahedra, and a run asks ~20 times).
    """
    out = {}
    for t in ELEMENT_TYPES:
        blocks = [b.data for b in mesh.cells if b.type == t and len(b.data)]
        if len(blocks) == 1:
            out[t] = blocks[0].view()
            out[t].flags.writeable = False
        elif blocks:
            out[t] = np.concatenate(blocks)
    return out


def volume_cells(mesh: HexMesh) -> dict[str, np.ndarray]:
    """Corner connectivity of every volume cell, by linear type (what bounds the volume, for the topology).

    **Returns:** type (``"hexahedron"``, ``"wedge"``, ``"pyramid"``, ``"tetra"``) -> int64 array ``(N, k)``, only
    types present; quadratic meshio blocks (`QUADRATIC_TYPES`) contribute their corner nodes.
    """
    out: dict[str, list] = {}
    for b in mesh.cells:
        t = QUADRATIC_TYPES.get(b.type, b.type)
        if t in NODES and len(b.data):
            out.setdefault(t, []).append(np.asarray(b.data, np.int64)[:, : NODES[t]])
    return {t: np.concatenate(out[t]) for t in ELEMENT_TYPES if t in out}


def fixed_nodes(mesh: HexMesh) -> np.ndarray:
    """Nodes that stay fixed because a quadratic non-hexahedral cell (or a meshio quadratic block) uses them.

    **Returns:** sorted unique int64 node indices.
    """
    parts = [np.asarray(b.data).ravel() for b in mesh.cells if len(b.data) and (
        b.type in QUADRATIC_TYPES or (b.type in EXTRA_TYPES and b.midside is not None))]
    return np.unique(np.concatenate(parts)).astype(np.int64) if parts else np.zeros(0, np.int64)
