"""Candidate cells that follow their node: the anchors of the host projection (`jaxci.geometry.near.NearProjector`).

Each boundary node projects onto the cells of its 2-ring on the original boundary (`jaxci.geometry.tables`): the
faces (segments) around the nodes next to it. That holds a node within about two cells of where it started. On a
strongly graded mesh the best mesh has boundary nodes further away: on Mesquite's cub_fru (10,752 hexahedra)
L-BFGS stopped at F 35.0 with nodes held on the rims of their 2-rings, where the same solver with 5-rings
reaches F 5.71 (2026-11-30). Wider rings cost every projection their width.

So a node's candidates are those of its *anchor*, a boundary node of its own kind and group: at first the node
itself; once the solver accepts a point whose cell is no longer a face (segment) of the anchor's own 1-ring, the
anchor becomes a corner of that cell (`moves`), and the node's candidates the new anchor's 2-ring, which
holds the cell and all the cells around it. A node that stays within its own cells never changes anchor: the
projection is then exactly the 2-ring's.

The corners of the cells are found from the geometry alone (`anchor_tables`: a cell's corner is the node of its
candidates at the same point), so that any `jaxci.geometry.projection.Constraints` has them; a corner not found
(e.g. a node that is not where the table's cell has its corner) never becomes an anchor. The projector makes these
tables only once a node's cell is not one of its own (`at_own_cells`, one cell a node, until then), so that a mesh
whose boundary nodes stay near their starts never pays for them. A node with no remembered cell walks its anchor
towards its point at its first projection (`NearProjector.__call__`): a projector made for points the solver left
starts where they are. The worst-element polish anchors its candidates once, at its start
(`jaxci.geometry.near.anchored`), and its rounds' projectors do not follow (``follow=False``).
"""

from __future__ import annotations

import numpy as np

from ._closest import cell_corners

#: A cell's corner and a node are the same point where their distance is at most this times the cell's size.
MATCH = 1e-6
#: Candidate pairs matched at once: the temporaries, about 20 float64 a pair, stay near 3 MB at any size.
CHUNK = 1 << 14


def anchor_tables(positions: np.ndarray, cand: np.ndarray, table: np.ndarray, kind: int) -> tuple:
    """``(inner, ends)`` of one kind of boundary node: `positions` ``(R, 3)`` the nodes' original coordinates,
    `cand` ``(>= R, K)`` their candidate columns (the 2-rings, `jaxci.geometry.tables`), `table` the packed cells
    (``(rows, nc)``, `jaxci.geometry._closest`), `kind` 0 triangles (4 per face: a face is their unit), 1
    segments.

    - `inner` bool ``(R, K)``: candidate k of node r lies in a unit (face, segment) one of whose corners is node r.
    - `ends` int32 ``(nc, 2)``: the node (row) at corner a and at corner b of each cell, -1 where none of the
      candidates' nodes is there.
    """
    R, K = len(positions), cand.shape[1]
    nc = table.shape[1]
    n_units = (nc + 3) // 4 if kind == 0 else nc
    ends = np.full((nc, 2), -1, np.int32)
    inner = np.zeros((R, K), bool)
    step = max(CHUNK // max(K, 1), 1)
    for lo in range(0, R, step):  # a block of rows at a time: its temporaries a few MB at any size
        hi = min(R, lo + step)
        cells = cand[lo:hi]
        p = positions[lo:hi].T[:, :, None]
        a, b, size2 = cell_corners(table, cells, kind)
        match = np.zeros(cells.shape, bool)
        for j, corner in enumerate((a, b)):
            hit = _same_point(corner, p, size2)
            r, k = np.nonzero(hit)
            ends[cells[r, k], j] = lo + r
            match |= hit
        key = np.arange(hi - lo, dtype=np.int64)[:, None] * n_units + (cells // 4 if kind == 0 else cells)
        # a node at no corner of its candidates (its ring is not around it: a polish's sub-problem, whose nodes
        # are where the solver left them) never moves
        inner[lo:hi] = np.isin(key, np.unique(key[match])) | ~match.any(axis=1, keepdims=True)
    return inner, ends


def at_own_cells(positions: np.ndarray, cells: np.ndarray, table: np.ndarray, kind: int) -> np.ndarray:
    """Whether each node at `positions` ``(R, 3)`` is a corner of the unit (face, segment) of its cell `cells`
    ``(R,)``: True where a node's cell is one of its own, as `anchor_tables`' `inner` says, from the R cells alone
    (no tables: a mesh whose boundary nodes never leave their own cells never builds them)."""
    if kind == 0:
        corners, _, size2 = cell_corners(table, (np.asarray(cells) // 4)[:, None] * 4 + np.arange(4), 0)
        size2 = size2[:, 0]  # (the face's: its four triangles')
    else:
        a, b, size2 = cell_corners(table, cells, 1)
        corners = np.stack([a, b], axis=-1)
    return _same_point(corners, positions.T[:, :, None], size2[:, None]).any(axis=1)


def _same_point(corner: np.ndarray, p: np.ndarray, size2: np.ndarray) -> np.ndarray:
    """Whether the points `corner` and `p` (``(3, ...)``, broadcast) are one, within `MATCH` of the cells' sizes
    (`size2` squared)."""
    return np.sum((corner - p) ** 2, axis=0) <= MATCH * MATCH * size2


def moves(hint: np.ndarray, anchor: np.ndarray, cand: np.ndarray, inner: np.ndarray, ends: np.ndarray,
          kind: int, rows: np.ndarray | None = None) -> tuple:
    """The anchors to move: `hint` ``(R,)`` each node's candidate column (-1 unknown), `anchor` ``(R,)`` its
    anchor row, `cand` the candidate columns it projects with (row i: the 2-ring of ``anchor[i]``), `inner` and
    `ends` of `anchor_tables`; `rows` (optional): the nodes to look at (default all). A node moves where its cell
    is not in its anchor's 1-ring; its new anchor is the cell's corner a, else b, else (a triangle) a corner of
    its face; where none is a node of this kind it stays.

    **Returns:** ``(rows, new, cells)`` int64: the nodes that move, their new anchors and their cells (the new
    hint is the cell's column in the new anchor's row)."""
    rows = np.flatnonzero(hint >= 0) if rows is None else rows[hint[rows] >= 0]
    rows = rows[~inner[anchor[rows], hint[rows]]]
    cell = cand[rows, hint[rows]].astype(np.int64)
    new = np.where(ends[cell, 0] >= 0, ends[cell, 0], ends[cell, 1])
    if kind == 0 and len(rows):  # else any corner of the face that is a node of this kind
        face = ends[(cell // 4)[:, None] * 4 + np.arange(4), 0]
        new = np.where(new >= 0, new, face.max(axis=1))
    ok = new >= 0
    return rows[ok], new[ok], cell[ok]
