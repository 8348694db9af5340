"""The host's boundary projection (numpy float64, the C search of `jaxci.native` where it is built): each
boundary node to the nearest point of its candidate triangles (surface nodes) or segments (edge nodes), as
`jaxci.geometry.projection.project` does under `jax.jit`, starting from the cell each node had at the solver's
last iterate (`NearProjector`). The numpy solvers (`jaxci.optim.host`, `jaxci.optim.host_local`,
`jaxci.optim.host_global`) project through it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools

import numpy as np

from ._closest import (
    SD,
    TC,
    TN,
    candidate_rows,
    closest_on_segments,
    closest_on_triangles,
    inside_tolerance,
    line_point,
    plane_point,
    segment_bump,
    segment_centres,
    triangle_centres,
)
from .anchors import anchor_tables, at_own_cells, moves
from .projection import Constraints, HostConstraints

#: Most anchor moves of a node with no remembered cell at its first projection (`NearProjector.__call__`): a ring
#: or more each, towards its point.
WALK = 64


def project_near_np(constraints: Constraints, points: np.ndarray) -> np.ndarray:
    """`project` in numpy (the candidate triangles and segments of each node, as under `jax.jit`; float64): a
    new `NearProjector`, so every node searches all its candidates, and a node beyond its own ring of boundary
    faces walks its anchor there first (`jaxci.geometry.anchors`; `project` holds it on its ring's rim).
    `project_np` searches whole patches. **Returns** a new float64 array of shape ``(n_nodes, 3)``."""
    return NearProjector(constraints)(points)[0]


def anchored(constraints: Constraints, points: np.ndarray) -> Constraints:
    """`constraints` (numpy float64, `host_constraints`) with each boundary node's candidates those of its anchor
    at `points` ``(n, 3)`` (`jaxci.geometry.anchors`: found by `NearProjector`'s first projection): for a
    problem made from points the solver left, whose nodes may lie beyond their own rings (the worst-element
    polish's sub-problems). `constraints` itself where every node's anchor is the node."""
    pr = NearProjector(constraints)
    pr(points)
    c = pr.c
    if pr._cand[0] is c.surface_cand and pr._cand[1] is c.edge_cand:
        return constraints
    return dataclasses.replace(c, surface_cand=pr._cand[0], edge_cand=pr._cand[1])


class NearProjector:
    """`project_near_np` that starts from each boundary node's triangle (segment) of the solver's iterate.

    A solver's next trial moves a node by a fraction of its cell, so its orthogonal projection nearly always
    falls inside the triangle the node had at the iterate: that is tested first (one triangle per node instead of
    the ~70 of its 2-ring: 6 ms -> ~1 ms per projection at 2360 hexahedra), and only the nodes that left it
    search all their candidates. Where a point near a concave part of the boundary is inside its old triangle's
    prism and yet nearer to another triangle, it keeps the old one: a point on the boundary either way.

    The remembered triangles change only when the solver accepts a trial (`commit`), never during a line search:
    a rejected long trial that carried a node to another triangle must not change what the iterate's
    neighbourhood projects to (measured on pave3: the objective then jumped between trials 1e-6 apart and the
    line search stalled 2% above the optimum). A point inside its old triangle's prism may still be nearer to
    another candidate (near a concave part of the boundary): each candidate whose bounding sphere comes nearer
    than the old triangle's plane is searched too, so the result is always the nearest candidate point, as with
    no memory (keeping the old one made the projection jump where the point left the prism: pave3's line
    search stalled there at F 0.327 against 0.318).

    A node's candidates are the 2-ring of its anchor (`jaxci.geometry.anchors`), which `commit` moves once the
    node's cell leaves the anchor's own faces, and which a node with no remembered cell walks towards its point
    at its first projection: the solvers slide boundary nodes as far as F takes them, not two cells at most.
    """

    def __init__(self, constraints: Constraints, follow: bool = True):
        from .. import native

        self.c = host_constraints(constraints)
        #: whether the searches run in C (`jaxci.native`, where it is built; else numpy)
        self.use_c = native.AVAILABLE
        #: whether the anchors move (`commit`, and the walk of a node with no remembered cell); False: every node
        #: keeps the candidates of the constraints (a polish round's sub-problem, whose are already anchored)
        self.follow = follow
        # candidate column per surface node, per edge node; -1: not known (search all its candidates)
        self.hint = tuple(np.full(int(n.shape[0]), -1, np.int64) for n in (self.c.surface_nodes, self.c.edge_nodes))
        self._tiled = {}  # `project_many`'s index arrays per (kind, number of meshes)
        #: per kind, the candidate columns each node projects with: its anchor's (`commit`); the constraints' own
        #: until an anchor moves
        self._cand = [self.c.surface_cand, self.c.edge_cand]
        #: per kind, ``(anchor rows, inner, ends, the constraints' columns)`` (`jaxci.geometry.anchors`), made at
        #: the first commit
        self._anchors = [None, None]
        self._seen = [None, None]  # per kind, until the tables are made (`_follow`)
        self._data = [None, None]  # per kind, the table's search data (`_search_of`)
        self._c = [None, None]  # per kind, the C search's arrays (`_c_arrays`)

    def _search_of(self, kind: int) -> tuple:
        """The search data of `kind`'s table (0: triangles, 1: segments; `_search_data`, made once for every
        projector of a `shared_tables` block), on the first search of a node of that kind: a projector whose
        surface nodes all stay inside flat parts of the boundary never searches a triangle, and its constraints'
        triangle table is then never made (`jaxci.geometry.projection.HostConstraints`)."""
        if self._data[kind] is None:
            self._data[kind] = _shared(self.c.triangles if kind == 0 else self.c.segments, kind)
        return self._data[kind]

    @property
    def spheres(self) -> tuple:
        """Per kind, the bounding spheres of the cells (centres (nc, 3), radii (nc,)), for the numpy search."""
        return self._search_of(0)[0], self._search_of(1)[0]

    def _c_arrays(self, kind: int) -> tuple:
        """The C search's arrays of `kind` (the same search as numpy's, one pass per node; `jaxci.native`, which
        must be built): ``(nodes int64, candidate columns int32, the table cell-major, its spheres)``, made on
        first use. The candidate columns as the constraints hold them, int32 (no copy: 11 MB at 216,000 hexahedra
        in int64), or the anchors' where one moved; the table the transpose of the constraints' (no copy of a
        table in `CELL_ORDER`)."""
        if self._c[kind] is None:
            nodes = (self.c.surface_nodes, self.c.edge_nodes)[kind]
            self._c[kind] = (np.ascontiguousarray(nodes, np.int64), np.ascontiguousarray(self._cand[kind], np.int32),
                             *self._search_of(kind)[1:])
        return self._c[kind]

    @functools.cached_property
    def rows(self) -> tuple:
        """Per kind, the candidate rows the numpy search reads (`candidate_rows`): every float64 row of every
        candidate of every boundary node, about 10 kB a node (203 MB on cube60_pert, a third of its run's peak),
        so they are built on first use, never where the C search runs."""
        c = self.c
        if self._cand[0] is c.surface_cand and self._cand[1] is c.edge_cand:  # no anchor moved: the constraints'
            return _candidate_table_rows(c)
        return tuple(candidate_rows(table, cand[: len(nodes)]) if len(nodes) else None for nodes, cand, table in
                     zip((c.surface_nodes, c.edge_nodes), self._cand, (c.triangles, c.segments), strict=True))

    def commit(self, hint) -> None:
        """Remember `hint` (from `__call__`) for the next projections, and move the anchor of each node whose cell
        left its anchor's 1-ring (`jaxci.geometry.anchors`): `hint`'s columns of those nodes change, in place,
        to the same cells in their new rows."""
        self.hint = hint
        for kind in range(2 if self.follow else 0):
            self._follow(kind, hint[kind])

    def _follow(self, kind: int, hint: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Move the anchors of the nodes of `kind` (of `rows`, default all) whose cell (`hint`, columns) left their
        anchor's 1-ring (`jaxci.geometry.anchors.moves`); their columns in `hint` become those of the same cells in
        the new rows, in place. **Returns** the rows moved."""
        nodes = (self.c.surface_nodes, self.c.edge_nodes)[kind]
        if not len(nodes) or not (hint >= 0).any():
            return np.zeros(0, np.int64)
        table = self.c.triangles if kind == 0 else self.c.segments  # (read once a node has a cell: made then)
        if self._anchors[kind] is None:  # no anchor moved yet: the tables only once a node leaves its own cells
            look = np.flatnonzero(hint >= 0) if rows is None else rows[hint[rows] >= 0]
            seen = self._seen[kind]  # each node's cell last found to be one of its own (-1: none yet)
            if seen is not None:
                look = look[hint[look] != seen[look]]
            if at_own_cells(self.c.x_orig[nodes[look]], self._cand[kind][look, hint[look]], table, kind).all():
                if seen is None:
                    seen = self._seen[kind] = np.full(len(hint), -1, np.int64)
                seen[look] = hint[look]
                return np.zeros(0, np.int64)
            base = np.asarray(self._cand[kind])
            inner, ends = anchor_tables(self.c.x_orig[nodes], base, table, kind)
            self._anchors[kind] = (np.arange(len(nodes)), inner, ends, base)
        anchor, inner, ends, base = self._anchors[kind]
        rows, new, cells = moves(hint, anchor, self._cand[kind], inner, ends, kind, rows)
        if not len(rows):
            return rows
        if self._cand[kind] is base:  # the constraints' own columns until the first anchor moves
            self._cand[kind] = np.array(base, np.int32)
        self._cand[kind][rows] = base[new]
        anchor[rows] = new
        hint[rows] = np.argmax(base[new] == cells[:, None], axis=1)
        if self._c[kind] is not None:  # the C search's arrays and `project_many`'s tiles follow
            self._c[kind] = (self._c[kind][0], self._cand[kind], *self._c[kind][2:])
            self._tiled.clear()
        self.__dict__.pop("rows", None)  # (the numpy search's gathered rows: made again on use)
        return rows

    @property
    def tolerances(self) -> tuple[float, float]:
        """``(tol, bump)`` of the float64 search (`jaxci.geometry._closest.inside_tolerance`, `segment_bump`), for a
        C kernel that projects points itself."""
        return inside_tolerance(np.float64), segment_bump(np.float64)

    @property
    def native_tables(self) -> tuple:
        """Per kind (surface, edge), the ``(candidates, table, spheres)`` arrays of the C search (int64 / float64,
        contiguous), for a C kernel that projects points itself (`jaxci.native.ci_visit`); None without the C
        kernels."""
        return tuple(self._c_arrays(kind)[1:] for kind in range(2)) if self.use_c else None

    def project_many(self, points: np.ndarray, keep: np.ndarray | None = None) -> None:
        """Project the boundary nodes of S meshes `points` (float64 ``(S, n, 3)``, in place) as `__call__` does,
        each starting from the remembered cells (not changed): one C search over all of them (the trial meshes of
        `jaxci.optim.host_global`); `keep` (optional, boolean ``(S, n)``): nodes left where they are. The C
        search only (`jaxci.native.AVAILABLE`)."""
        from .. import native

        S, n = points.shape[:2]
        flat = points.reshape(-1, 3)
        for kind, nodes in enumerate((self.c.surface_nodes, self.c.edge_nodes)):
            if not len(nodes):
                continue
            nodes, cand, table, spheres = self._c_arrays(kind)
            key = (kind, S)
            if key not in self._tiled:
                self._tiled[key] = ((np.arange(S)[:, None] * n + nodes[None]).ravel(), np.tile(cand, (S, 1)))
            many, cands = self._tiled[key]
            active = np.arange(len(many)) if keep is None else np.flatnonzero(~keep[:, nodes].ravel())
            if len(active):
                native.near_project(flat, many, active, np.tile(self.hint[kind], S), cands, table, spheres, kind,
                                    inside_tolerance(np.float64), segment_bump(np.float64))
        points[:, self.c.corner_nodes] = self.c.x_orig[self.c.corner_nodes]

    def project_rows(self, kind: int, rows: np.ndarray, points: np.ndarray, hint: np.ndarray) -> None:
        """Project `points` (float64 ``(r, 3)``, in place) each onto the candidates of one boundary node: point i
        onto those of row ``rows[i]`` of `kind` (0: the surface nodes, 1: the edge nodes), starting from the
        candidate column ``hint[i]`` (int64, -1: search all; updated in place): the trial positions of the local
        moves of `jaxci.optim.host_local`. The C search only (`jaxci.native.AVAILABLE`)."""
        from .. import native

        nodes, cand, table, spheres = self._c_arrays(kind)
        idx = np.arange(len(rows), dtype=np.int64)
        native.near_project(points, idx, idx, hint, np.ascontiguousarray(cand[rows]), table, spheres, kind,
                            inside_tolerance(np.float64), segment_bump(np.float64))

    def __call__(self, points: np.ndarray, keep: np.ndarray | None = None, *, inplace: bool = False,
                 corners_placed: bool = False):
        """``(x, hint)``: the projected coordinates (a new float64 ``(n, 3)`` array; with `inplace`, `points`
        itself, projected in place: a caller's own float64 C-ordered array) and the candidate column each boundary
        node ended on (for `commit` and `pullback`; -1 where unknown). `keep` (optional, boolean ``(n,)``): nodes
        left where they are, e.g. those inside a flat part of the boundary, where the point is its own projection
        (their hint stays as it was). CORNER nodes go to their original positions, unless the caller says they are
        there already (`corners_placed`: a solver's lift, whose base holds them; a polish round's fixed nodes are
        thousands, and copying them was 5% of a run)."""
        c = self.c
        inplace = inplace and points.dtype == np.float64 and points.flags.c_contiguous and points.flags.writeable
        x = points if inplace else np.array(points, dtype=np.float64)
        out = []
        for kind, nodes in enumerate((c.surface_nodes, c.edge_nodes)):
            hint = self.hint[kind].copy()
            active = np.arange(len(nodes)) if keep is None else np.flatnonzero(~keep[nodes])
            # a node with no remembered cell finds its anchor: from its own ring towards its point, one ring a step
            fresh = active[hint[active] < 0] if self.follow else active[:0]
            start = x[nodes[fresh]] if len(fresh) else None
            self._search(kind, x, active, hint)
            for _ in range(WALK if len(fresh) else 0):
                moved = self._follow(kind, hint, fresh)
                if not len(moved):
                    break
                x[nodes[moved]] = start[np.searchsorted(fresh, moved)]
                self._search(kind, x, moved, hint)
            out.append(hint)
        if not corners_placed:
            x[c.corner_nodes] = c.x_orig[c.corner_nodes]
        return x, tuple(out)

    def _search(self, kind: int, x: np.ndarray, active: np.ndarray, hint: np.ndarray) -> None:
        """The nodes `active` (rows) of `kind` in `x` to their nearest candidate point, in place, each from its
        cell `hint` (columns, -1: search all; updated in place)."""
        if not len(active):
            return
        tol = inside_tolerance(np.float64)
        if self.use_c:
            from .. import native

            nodes, cand, table, spheres = self._c_arrays(kind)
            native.near_project(x, nodes, active, hint, cand, table, spheres, kind, tol, segment_bump(np.float64))
            return
        c, cand = self.c, self._cand[kind]
        nodes, table = (c.surface_nodes, c.triangles) if kind == 0 else (c.edge_nodes, c.segments)
        closest, orthogonal = (closest_on_triangles, plane_point) if kind == 0 else (closest_on_segments, line_point)
        xs = x[nodes[active]]
        todo = hint[active] < 0
        known = np.flatnonzero(~todo)
        if len(known):
            rows = active[known]
            cell = cand[rows, hint[rows]]
            found = orthogonal(tuple(xs[known].T), table[:, cell], tol)
            p, inside = np.stack(found[0], axis=-1), found[2 if kind == 0 else 1]
            # inside, but a candidate whose bounding sphere comes nearer may hold a nearer point: search all
            centre, radius = self.spheres[kind]
            gap = np.linalg.norm(xs[known][:, None] - centre[cand[rows]], axis=-1) - radius[cand[rows]]
            near2 = np.sum((xs[known] - p) ** 2, axis=1)
            other = ((gap <= 0) | (gap * gap < near2[:, None])).sum(axis=1) > 1  # the hint's own passes
            inside &= ~other
            x[nodes[rows[inside]]] = p[inside]
            todo[known[~inside]] = True
        if todo.any():
            rows = active[todo]
            gathered = [r[rows] for r in self.rows[kind]]
            p, score = closest(np, tuple(xs[todo].T[:, :, None]), gathered, tol)
            k = np.argmin(score, axis=-1)
            pick = np.arange(len(k))
            x[nodes[rows]] = np.stack([pj[pick, k] for pj in p], axis=-1)
            hint[rows] = k

    def pullback(self, g: np.ndarray, hint, keep: np.ndarray | None = None) -> np.ndarray:
        """The gradient `g` ``(n, 3)`` at points projected with `hint` (`__call__`, with the same `keep`) taken
        back through the projection: on a surface node minus its component along its triangle's normal, on an
        edge node its component along its segment (the derivative of the projection onto a plane or a line);
        nodes of `keep` unchanged. A new array."""
        c, g = self.c, np.array(g, dtype=np.float64)
        if self.use_c:
            from .. import native

            for kind, nodes in enumerate((c.surface_nodes, c.edge_nodes)):
                if len(nodes) and (hint[kind] >= 0).any():  # (a node with no cell is not pulled back)
                    nodes, cand, table, _ = self._c_arrays(kind)
                    native.pullback(g, nodes, hint[kind], keep, cand, table, kind)
            return g
        for kind, (nodes, table, cand, row) in enumerate(((c.surface_nodes, c.triangles, self._cand[0], TN),
                                                          (c.edge_nodes, c.segments, self._cand[1], SD))):
            rows = np.flatnonzero(hint[kind] >= 0) if keep is None else np.flatnonzero((hint[kind] >= 0)
                                                                                       & ~keep[nodes])
            if not len(rows):
                continue
            cell = cand[rows, hint[kind][rows]]
            d = table[row : row + 3, cell].T
            d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
            sel = nodes[rows]
            along = np.sum(g[sel] * d, axis=1, keepdims=True) * d
            g[sel] = g[sel] - along if kind == 0 else along
        return g


#: The `shared_tables` blocks open, innermost last: each a dict id(table) -> (table, its `_search_data`).
_SHARED: list[dict] = []


@contextlib.contextmanager
def shared_tables():
    """Within the block, the `NearProjector`s made on the same boundary tables (the same array objects) share
    their search data (`_search_data`: the cells' bounding spheres and the C search's cell-major copy of the
    table), made by the first of them: O(boundary) work and a copy of the table per projector otherwise. For the
    worst-element polish, whose rounds are sub-problems of one mesh, each with its own projector on the mesh's
    tables (pave3: 11% of its polish). The data lives as long as the block."""
    _SHARED.append({})
    try:
        yield
    finally:
        _SHARED.pop()


def _shared(table: np.ndarray, kind: int) -> tuple:
    """`_search_data` of `table`, made once for it within a `shared_tables` block."""
    if not _SHARED:
        return _search_data(table, kind)
    cache = _SHARED[-1]
    if id(table) not in cache:  # (the table is held beside its data: its id stays its own while the block lasts)
        cache[id(table)] = (table, _search_data(table, kind))
    return cache[id(table)][1]


def _search_data(table: np.ndarray, kind: int) -> tuple:
    """``((centres, radii), cell-major table, spheres)`` of the triangles (`kind` 0) or segments (1) `table`: the
    cells' bounding spheres (the numpy search's), and the C search's copy of the table and its spheres
    (`_with_faces` for the triangles; both None without the C kernels)."""
    from .. import native

    spheres = _sphere(table, (triangle_centres, segment_centres)[kind])
    if not native.AVAILABLE:
        return spheres, None, None
    rows = _with_faces(table, spheres) if kind == 0 else np.column_stack(spheres)
    return (spheres, np.ascontiguousarray(np.asarray(table, np.float64).T),
            np.ascontiguousarray(rows, np.float64))


def _with_faces(triangles: np.ndarray, spheres) -> np.ndarray:
    """The triangles' spheres ``(nt, 4)`` (centre, radius) followed by one per boundary face (its 4 triangles,
    columns 4 f .. 4 f + 3, share the face's centroid): centred at the centroid, holding the four triangles'
    spheres, so that the C search passes over a face none of whose triangles can come nearer at once. Only the
    triangles' where nt is not a multiple of 4."""
    centre, radius = spheres
    out = np.column_stack([centre, radius])
    nt = len(radius)
    if nt % 4:
        return out
    c = np.asarray(triangles[TC : TC + 3, ::4], np.float64).T
    reach = np.linalg.norm(centre.reshape(-1, 4, 3) - c[:, None], axis=-1) + radius.reshape(-1, 4)
    return np.concatenate([out, np.column_stack([c, reach.max(axis=1) * (1 + 1e-9)])])


def _sphere(table, centre_radius):
    centre, radius = centre_radius(np.asarray(table, dtype=np.float64))
    return centre, radius * (1 + 1e-12)  # rounding must not prune a cell that holds the nearest point


def host_constraints(c: Constraints) -> Constraints:
    """`c` as numpy with float64 geometry, cached on `c` (converted once per solve, not once per objective
    evaluation)."""
    if isinstance(c, HostConstraints):  # numpy float64 already (and its triangle table not read here)
        return c
    cached = getattr(c, "_host_cache", None)
    if cached is None:
        def conv(a):
            a = np.asarray(a)
            return a.astype(np.float64, copy=False) if np.issubdtype(a.dtype, np.floating) else a

        cached = dataclasses.replace(c, **{f.name: conv(getattr(c, f.name)) for f in dataclasses.fields(c)})
        object.__setattr__(c, "_host_cache", cached)  # a frozen dataclass; a cache is not a field
    return cached


def _candidate_table_rows(h: Constraints) -> tuple:
    """``(triangle rows, segment rows)`` of the numpy constraints `h` (`host_constraints`) gathered at the
    candidates (`candidate_rows`), cached on `h` (built once per solve)."""
    cached = getattr(h, "_rows_cache", None)
    if cached is None:
        ns, ne = h.surface_nodes.shape[0], h.edge_nodes.shape[0]
        cached = (candidate_rows(h.triangles, h.surface_cand[:ns]) if ns else None,
                  candidate_rows(h.segments, h.edge_cand[:ne]) if ne else None)
        object.__setattr__(h, "_rows_cache", cached)
    return cached
