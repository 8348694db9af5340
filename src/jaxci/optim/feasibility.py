"""Inverted cells that no allowed move can fix, found before any iteration.

A corner's determinant depends on four nodes only: the corner node and its three neighbours along the cell's
edges (`jaxci.cells.CORNERS`). An inverted corner (det <= 0) whose four nodes are all fixed (corners of the
boundary, nodes of `fix_boundary`, `fixed_nodes` or `fixed_sets`, coincident nodes) keeps its determinant
whatever the smoother does, so its cell can never become valid: the untangling stage would only run to its cap.
`stuck_cells` finds those cells in one vectorised pass, so `jaxci.smooth` can say at once which they are and why.
"""

from __future__ import annotations

import numpy as np

from ..cells import element_blocks
from ..geometry.boundary import CORNER, BoundaryInfo
from ..mesh import HexMesh
from ..metrics import elements as E


def stuck_cells(mesh: HexMesh, info: BoundaryInfo, points=None) -> dict[str, np.ndarray]:
    """Per cell type, the cells with an inverted corner whose four nodes are all fixed.

    **Arguments:** `mesh`; `info` its `BoundaryInfo` (fixed nodes are class `CORNER`); `points` of shape
    ``(n_nodes, 3)`` (default: the mesh's).

    **Returns:** type -> int64 array of cell indices within the type's blocks (`jaxci.cells.element_blocks`
    order), only types with some.
    """
    points = mesh.points if points is None else points
    fixed = np.asarray(info.node_class) == CORNER
    out = {}
    for t, cells in element_blocks(mesh).items():
        det = E.corner_determinant(points, cells, t)  # (N, n_corners)
        corner_nodes = cells[:, E.CORNERS[t]]  # (N, n_corners, 4)
        frozen = fixed[corner_nodes].all(axis=2)
        bad = np.flatnonzero(((det <= 0) & frozen).any(axis=1))
        if len(bad):
            out[t] = bad
    return out
