"""Inverted cells that no allowed move can fix, found before any iteration.

A corner's determinant depends on four nodes only: the corner node and its three neighbours along the cell's
edges (`jaxci.cells.CORNERS`). An inverted corner (det <= 0) whose four nodes are all fixed (corners of the
boundary, nodes of `fix_boundary`, `fixed_nodes` or `fixed_sets`, coincident nodes) keeps its determinant
whatever the smoother does, so its cell can never become valid: the untangling stage would only run to its cap.
`stuck_cells` finds those cells in one vectorised pass, so `jaxci.smooth` can say at once which they are and why.

The way out where the boundary's own corners and edges hold an inversion (``untangle_boundary``):
`release_features` lets those nodes slide on a surface during the untangling stage, `put_back` returns the ones
the untangled mesh does not need moved, `released_note` says what stayed moved.
"""

from __future__ import annotations

import numpy as np

from ..cells import CORNERS, element_blocks
from ..geometry.boundary import CORNER, BoundaryInfo, releasable_feature_nodes, slide_on_surface
from ..geometry.topology import csr_gather, incidence
from ..mesh import HexMesh
from ..metrics import elements as E
from .untangle import element_lengths


def stuck_cells(mesh: HexMesh, info: BoundaryInfo) -> dict[str, np.ndarray]:
    """Per cell type, the cells of `mesh` with an inverted corner whose four nodes are all fixed.

    **Arguments:** `mesh`; `info` its `BoundaryInfo` (fixed nodes are class `CORNER`).

    **Returns:** type -> int64 array of cell indices within the type's blocks (`jaxci.cells.element_blocks`
    order), only types with some.
    """
    fixed = np.asarray(info.node_class) == CORNER
    out = {}
    for t, cells in element_blocks(mesh).items():
        inverted = E.corner_determinant(mesh.points, cells, t) <= 0  # (N, n_corners)
        some = np.flatnonzero(inverted.any(axis=1))  # only their corner nodes are gathered (55 MB at 216,000)
        frozen = fixed[cells[some][:, E.CORNERS[t]]].all(axis=2)  # (n_some, n_corners)
        bad = some[(inverted[some] & frozen).any(axis=1)]
        if len(bad):
            out[t] = bad
    return out


def release_features(mesh: HexMesh, info: BoundaryInfo, fixed_nodes, fixed_sets) -> tuple[BoundaryInfo, np.ndarray]:
    """``untangle_boundary``: `info` with the corner and edge nodes of the inverted corners (det <= 0: a corner
    node and its three edge neighbours) that only the boundary's geometry holds made surface nodes
    (`jaxci.geometry.boundary.slide_on_surface`), and those nodes."""
    keep = [np.asarray(fixed_nodes, dtype=np.int64)]
    keep += [np.asarray(mesh.point_sets[name], dtype=np.int64).ravel() for name in fixed_sets]
    bad = [cells[:, CORNERS[t]][E.corner_determinant(mesh.points, cells, t) <= 0].ravel()
           for t, cells in element_blocks(mesh).items()]
    nodes = releasable_feature_nodes(mesh, info, np.concatenate(bad), np.concatenate(keep))
    return slide_on_surface(info, nodes), nodes


def put_back(mesh: HexMesh, nodes: np.ndarray, x: np.ndarray) -> np.ndarray:
    """`x` with each of `nodes` (released feature nodes the untangling moved) back at its input position, one
    after the other, wherever that leaves every cell around it valid: the feature nodes an untangled mesh does
    not need moved stay put. Returns the nodes still moved."""
    around = [(t, cells, incidence(cells, mesh.n_nodes)) for t, cells in element_blocks(mesh).items()]
    still = []
    for i in nodes:
        old = x[i].copy()
        x[i] = mesh.points[i]
        if any(E.inverted(x, cells[csr_gather(*inc, np.array([i]))[1]], t).any() for t, cells, inc in around):
            x[i] = old
            still.append(i)
    return np.asarray(still, dtype=np.int64)


def released_note(mesh: HexMesh, moved: np.ndarray, untangled: np.ndarray) -> str:
    """The note of `jaxci.smooth` saying how many released feature nodes stayed moved, and how far."""
    h = float(np.median(element_lengths(mesh.points, mesh.hexes))) if mesh.n_hexes else 1.0
    d = float(np.linalg.norm(untangled[moved] - mesh.points[moved], axis=1).max())
    return (f"untangle_boundary: {len(moved)} corner and edge nodes of inverted elements slid on the boundary "
            f"surface during untangling (up to {d / h:.3g} median edge lengths); shape improvement keeps them where "
            f"they are, and the boundary faces next to them follow them")
