"""The local (coloured, node by node) methods in numpy and C for hexahedral meshes, without compilation: local CI
(`local_ci_np`, the sweep of `jaxci.optim.ci.local_ci`) and the (smart) Laplacian (`laplace_np`, that of
`jaxci.optim.laplace.laplace`).

The compiled sweep is one XLA program per mesh size class; on a 2-core CPU it takes 10-12 s to compile (a
command's whole budget on a small mesh, and most of the main job), then about 0.1 s a sweep at 10^3 hexahedra.
Here the same algorithm runs colour by colour, a colour's visit in C (`jaxci.native.ci_visit`: every node's
cohort, its trials projected by the C search of `jaxci.geometry.near.NearProjector`, their local
objective from four corners of every element around the node), the sweep's bookkeeping and the pattern move in
numpy: nothing to compile (cube729: 1000 nodes, about 20 ms a sweep on 2 cores).

The iteration is the compiled one (`jaxci.optim.ci._local_ci_colour`, `_local_ci_run`): per colour, for every
node, a cohort of C candidates improves for T learning attempts (each follows a candidate by roulette on
1/(g + delta) for the first ``stage_switch`` share of the attempts, then the best; samples t trials in its
interval, shrunk by ``reduction`` per attempt, in the node's free directions; projects them onto its surface or
edge; keeps the best if it is better); the node takes the cohort's best if it lowers its local objective (so F
never increases: a colour's nodes share no element). Widths adapt per node (4 x the move after an accepted
move, halved otherwise, within ``[min_width, init_width] h``); after each sweep the pattern move (`PATTERN_FACTORS`)
and Anderson acceleration over the last ``anderson`` sweeps (`jaxci.optim._anderson`), and the same stops
(``F <= ftol``, a decrease below ``tol F + atol``, no node moved, max kappa/3 <= 1 + ktol, ``max_sweeps``).
Random numbers: each visit draws a seed from numpy's PCG64 (seeded by the run's seed), each node its own
xoshiro256** stream from it: same seed, same result on any number of threads, but not the compiled path's stream;
with ``stream="counter"`` every node draws from `jaxci.optim._draws`' counter stream instead, the compiled path's
numbers with the same stream (`tests/test_ci_parity.py`: the same mesh). The cohort's loop is C, not this module's
numpy over the compiled sweep's functions: a node's cohort is a few numbers, where numpy's per-call overhead would
cost more than the arithmetic. Everything is float64. `laplace_np` sweeps the colours the same way with the
Laplacian's one move per node (the centroid of its edge neighbours, in its free directions, projected; the smart
one tries the steps 1, 1/2, ... at once and takes the longest that lowers the node's local sum).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .. import native
from ..cells import ROTATE_TO_SLOT
from ..geometry.boundary import CORNER, EDGE, INTERIOR, SURFACE
from ..geometry.near import NearProjector
from ..geometry.projection import Constraints
from ..runtime.phases import stepper
from . import _draws
from ._anderson import AndersonMemory
from ._local import edge_neighbours, laplace_trials, longest_step, node_stars
from ._moves import free_dims, node_bases, node_rows, onto_plane, surface_node_rings
from .ci_params import PATTERN_FACTORS, CIParams, excess_within_bound, pattern_choice, sweep_done
from .laplace import LaplaceParams

#: Largest hexahedral mesh on which ``engine="auto"`` runs the local methods on the host (with the C kernels;
#: `jaxci.interface.engine.host_limit`). It was 100,000; a 60^3 box (216,000, amplitude 0.3) measured both ways
#: (2026-11-26, dd22c91): local CI 79.8 s on the host (float64, ends at max kappa/3 1.00013) against 81.9 s compiled
#: (float32, 9 s of it compiling, stopped at 1.0003); smart Laplace 162 s (converged in 336 sweeps, 1.00000002)
#: against 151 s (its 500-sweep cap, 1.0000029).
HOST_LOCAL_MAX = 250_000


@dataclasses.dataclass(frozen=True)
class _Colour:
    """The movable nodes of one colour (numpy): `nodes` ``(M,)``; `inc` ``(M, K)`` their stars as incidences
    (``8 e + s``: `jaxci.optim._local.node_stars`; int32 where they fit), the first ``count[m]`` real; the slots
    ``[0, a)`` are interior nodes, ``[a, b)`` surface nodes, ``[b, M)`` edge nodes (rows `srow`, `erow` of the
    projector's surface and edge lists); `kind` ``(M,)`` 0 / 1 / 2 for an interior / surface / edge slot and `row`
    its row in its list (-1 interior), for `jaxci.native.ci_visit`.

    The move bases `basis` ``(M, 3, 3)``, free directions `free` ``(M, 3)`` (1 for a free one) and planar disks
    `plane` ``(M, 7)`` (`jaxci.optim._moves.planar_rings`) are made on each use from those of the boundary slots
    (`bound_basis` ``(M - a, 3, 3)``, `bound_free` ``(M - a, 3)``, `surface_plane` ``(b - a, 7)``): an interior
    slot's are the identity, all free and none, and stored for every node they were 150 bytes a node (30 MB on
    cube60_pert, its untangling's peak)."""

    nodes: np.ndarray
    inc: np.ndarray
    count: np.ndarray
    bound_basis: np.ndarray
    bound_free: np.ndarray
    surface_plane: np.ndarray
    a: int
    b: int
    srow: np.ndarray
    erow: np.ndarray
    index: int = 0  # the colour's row in the coloured stars (the compiled sweep's colour index)

    @property
    def basis(self) -> np.ndarray:
        out = np.empty((len(self.nodes), 3, 3))
        out[: self.a] = np.eye(3)
        out[self.a :] = self.bound_basis
        return out

    @property
    def free(self) -> np.ndarray:
        out = np.ones((len(self.nodes), 3))
        out[self.a :] = self.bound_free
        return out

    @property
    def plane(self) -> np.ndarray:
        out = np.zeros((len(self.nodes), 7))
        out[self.a : self.b] = self.surface_plane
        return out

    @functools.cached_property
    def kind(self) -> np.ndarray:
        return np.repeat(np.arange(3, dtype=np.int64), [self.a, self.b - self.a, len(self.nodes) - self.b])

    @functools.cached_property
    def row(self) -> np.ndarray:
        return np.concatenate([np.full(self.a, -1, np.int64), self.srow, self.erow])


def sweep_colours(hexes, cons: Constraints, colour, faces, rings: np.ndarray | None = None) -> list[_Colour]:
    """The colours of `jaxci.optim._moves.coloured_stars` (the same nodes in the same order: by class, interior,
    surface, edge, each by number; the same values), made one colour at a time without its padded tables: those
    tables, and the per-node bases and planes they were gathered from, were cube60_pert's untangling peak.
    `rings` (optional): the surface nodes' planar rings of ``cons.x_orig`` in float64 where they are made already
    (`jaxci.optim.parametrisation.flat_surface_rings`), else they are made here."""
    cls = np.asarray(cons.node_class)
    n = len(cls)
    colour = np.asarray(colour)
    movable = cls != CORNER
    colours = np.unique(colour[movable]) if movable.any() else np.zeros(1, np.int64)
    by_class = [(c, np.flatnonzero(cls == c)) for c in (INTERIOR, SURFACE, EDGE)]
    parts = [[ids[colour[ids] == c] for _, ids in by_class] for c in colours]
    # the stars of the colours' nodes, colour after colour (each colour's rows a view of them), first: their sort's
    # temporaries (20 MB on cube60_pert) go before the rest is made; the stars of every node and the colours' copies
    # of their rows were 14 MB at once there
    stars = node_stars(hexes, n, incidences=True, rows=np.concatenate([np.concatenate(p) for p in parts]))
    rows = node_rows(cons)
    dims = free_dims(cons)
    # the planar rings of the surface nodes alone, in the working dtype's rounding, as the compiled sweep's tables
    if rings is None:
        rings = surface_node_rings(np.asarray(cons.x_orig, np.float64), faces, cons)
    rings = np.asarray(np.asarray(rings).astype(cons.x_orig.dtype), np.float64)
    inc_type = np.int32 if 8 * len(hexes) < 2**31 else np.int64  # the incidences: half the bytes while they fit
    star = stars.star.astype(inc_type, copy=False)
    out, lo = [], 0
    for i, part in enumerate(parts):
        nodes = np.concatenate(part).astype(np.int64)
        if not len(nodes):
            continue
        sl = slice(lo, lo + len(nodes))
        lo += len(nodes)
        a, b = len(part[0]), len(part[0]) + len(part[1])
        srow, erow = rows[0][nodes[a:b]], rows[1][nodes[b:]]
        bound = nodes[a:]
        out.append(_Colour(
            nodes=nodes, inc=star[sl], count=stars.mask[sl].sum(axis=1).astype(np.int64),
            bound_basis=np.asarray(node_bases(cons, bound, rows), np.float64),
            bound_free=(np.arange(3)[None] < dims[bound][:, None]).astype(np.float64), surface_plane=rings[srow],
            a=a, b=b, srow=srow, erow=erow, index=i))
    return out


#: Nodes per block of `_local_length` (its gathered edge ends and their coordinates, about 0.6 kB a node: a colour
#: at once would be 80 MB at 10^6 hexahedra, a block of 4096 nodes is 2.5 MB).
LENGTH_CHUNK = 4096
#: The local nodes of slot s's three edge neighbours in its hexahedron (slots 1, 3 and 4 of `star_nodes`' lists).
_EDGE_ENDS = ROTATE_TO_SLOT[:, [1, 3, 4]].astype(np.intp)


def _local_length(x: np.ndarray, hexes: np.ndarray, col: _Colour) -> np.ndarray:
    """`jaxci.optim._local.local_length` of the nodes of `col` at `x`, ``(M,)``: the same sums in the same order,
    from the three edge neighbours of each node in each of its hexahedra alone (not the whole relabelled star: a
    third of the gathers). Only the real slots of the stars are measured (a tet-to-hex mesh's stars hold 6 real
    hexahedra on average in 48 slots), then laid into zeros for the padding: the rows summed are the same."""
    real = np.arange(col.inc.shape[1])[None] < col.count[:, None]
    flat = np.asarray(hexes).ravel()
    out = np.empty(len(col.inc))
    for lo in range(0, len(out), LENGTH_CHUNK):
        sl = slice(lo, lo + LENGTH_CHUNK)
        rows, slots = np.nonzero(real[sl])
        inc = col.inc[sl][rows, slots].astype(np.intp)
        ends = np.take(flat, (inc & ~7)[:, None] + _EDGE_ENDS[inc & 7])  # (r, 3): the real slots' edge ends
        x0 = x[col.nodes[sl]][rows]
        tot = 0.0
        for j in range(3):
            d = x[ends[:, j]] - x0
            tot = tot + np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)
        full = np.zeros(real[sl].shape)
        full[rows, slots] = tot
        cnt = np.maximum(np.sum(real[sl], axis=-1), 1)
        out[sl] = np.sum(full, axis=-1) / (3.0 * cnt)
    return out


class _Sweeper:
    """One local run's state: coordinates, the colours, the projector (and its remembered cells); for CI the
    widths and the RNG."""

    def __init__(self, points, hexes, cons: Constraints, colour, faces, p, seed: int = 0, stream: str = "native",
                 colours: list[_Colour] | None = None):
        self.x = np.array(points, dtype=np.float64)
        self.hexes = native.as_conn(hexes)
        self.p = p
        self.rng = np.random.default_rng(seed)
        self.stream, self.words = stream, _draws.seed_words(seed)
        self.colours = sweep_colours(hexes, cons, colour, faces) if colours is None else colours
        self.projector = NearProjector(cons)
        # every boundary node's cell at the start, but for the surface nodes that are their own projection onto the
        # plane of their planar ring, inside its disk: those are on the boundary, and their cell is found by their
        # first search (none on a box: its triangle table is never made)
        self.projector.commit(self.projector(self.x, self._on_their_planes())[1])
        self.width = np.zeros(len(self.x))
        if isinstance(p, CIParams):
            for col in self.colours:
                self.width[col.nodes] = p.init_width * _local_length(self.x, self.hexes, col)

    def _on_their_planes(self) -> np.ndarray:
        """Per node ``(n,)``: a surface node at `x` inside 0.999 of the disk its planar ring covers and exactly its
        own orthogonal projection onto its plane (`jaxci.optim._moves.onto_plane`), where the nearest point of
        its patch is itself."""
        out = np.zeros(len(self.x), bool)
        for col in self.colours:
            if col.b > col.a:
                nodes = col.nodes[col.a : col.b]
                foot, inside = onto_plane(np, self.x[nodes], col.surface_plane)
                out[nodes] = inside & (foot == self.x[nodes]).all(axis=1)
        return out

    def objective(self, x: np.ndarray) -> tuple[float, float]:
        """``(F, max kappa/3)`` at `x` (F infinite if a corner is inverted)."""
        return native.hex_objective(x, self.hexes)

    def _project(self, col: _Colour, trials: np.ndarray, hint: np.ndarray) -> np.ndarray:
        """`trials` ``(M, S, 3)`` projected onto each node's surface or edge (interior slots unchanged; a surface
        trial inside its planar disk by the orthogonal projection, exact there); `hint` ``(M, S)`` the cell
        columns of the boundary trials, updated."""
        a, b = col.a, col.b
        if a == len(col.nodes):
            return trials
        out = trials.copy()
        if b > a:
            t = out[a:b]
            flat, inside = onto_plane(np, t, col.surface_plane[:, None])
            t[inside] = flat[inside]
            m, s = np.nonzero(~inside)
            if len(m):
                pts = np.ascontiguousarray(t[m, s])
                h = np.ascontiguousarray(hint[a + m, s])
                self.projector.project_rows(0, col.srow[m], pts, h)
                t[m, s], hint[a + m, s] = pts, h
        if len(col.nodes) > b:
            S = out.shape[1]
            pts = np.ascontiguousarray(out[b:].reshape(-1, 3))
            h = np.ascontiguousarray(hint[b:].reshape(-1))
            self.projector.project_rows(1, np.repeat(col.erow, S), pts, h)
            out[b:], hint[b:] = pts.reshape(-1, S, 3), h.reshape(-1, S)
        return out

    def visit(self, col: _Colour, sweep: int) -> int:
        """One cohort run for every node of `col` in sweep `sweep` (`jaxci.native.ci_visit`); returns the number of
        nodes moved. Its random numbers: a seed drawn from the run's PCG64, or (``stream="counter"``) the visit's
        word of `jaxci.optim._draws` at ``(sweep, colour)``, as the compiled sweep's."""
        pr = self.projector
        counter = self.stream == "counter"
        seed = int(_draws.visit_word(self.words, sweep, col.index, np)) if counter else int(self.rng.integers(2**63))
        return native.ci_visit(self.x, self.width, col.nodes, self.hexes, col.inc, col.count, col.basis, col.free,
                               col.plane, col.row, col.kind, pr.hint, pr.native_tables, self.p, seed,
                               *pr.tolerances, counter=counter)

    def laplace_visit(self, col: _Colour, nbr: np.ndarray, nmask: np.ndarray, h: np.ndarray, smart: bool) -> float:
        """Every node of `col` towards the centroid of its edge neighbours `nbr` ``(M, K)`` (real where `nmask`);
        returns the largest move over the nodes' lengths `h` ``(M,)``."""
        x = self.x
        x0 = x[col.nodes]
        n_steps = self.p.backtrack if smart else 1
        hints = self._hints(col)
        th = np.repeat(hints[:, None], n_steps, axis=1)
        trials = self._project(col, laplace_trials(x, x0, nbr, nmask, col.basis, n_steps, np), th)
        rows = np.arange(len(x0))
        if smart:
            f0 = native.local_sums(x, self.hexes, col.inc, col.count, x0[:, None])[:, 0]
            j, accept = longest_step(f0, native.local_sums(x, self.hexes, col.inc, col.count, trials), np)
        else:
            j = np.zeros(len(x0), np.int64)
            accept = np.ones(len(x0), bool)
        new = np.where(accept[:, None], trials[rows, j], x0)
        x[col.nodes] = new
        self._remember(col, np.where(accept, th[rows, j], hints))
        return float((np.linalg.norm(new - x0, axis=-1) / h).max(initial=0.0))

    def _hints(self, col: _Colour) -> np.ndarray:
        """The projector's remembered cell column of every slot of `col` (-1 for interior slots)."""
        out = np.full(len(col.nodes), -1, np.int64)
        out[col.a : col.b] = self.projector.hint[0][col.srow]
        out[col.b :] = self.projector.hint[1][col.erow]
        return out

    def _remember(self, col: _Colour, hints: np.ndarray) -> None:
        self.projector.hint[0][col.srow] = hints[col.a : col.b]
        self.projector.hint[1][col.erow] = hints[col.b :]

    def pattern(self, D: np.ndarray, f: float, kmax: float) -> tuple[float, float]:
        """The pattern move along the sweep's displacement `D` (`jaxci.optim.ci._pattern_move`): the mesh becomes
        the projected ``x + a D`` that `pattern_choice` picks (`f`, `kmax`: F and max kappa/3 at the current `x`),
        the factors `PATTERN_FACTORS` tried in order up to the first rise of F; returns ``(F, max kappa/3)`` after
        it. Only the trial picked so far is kept (the pick over a prefix of the trials changes only to its
        newest)."""
        fys, kys, best = [], [], (f, kmax, None, None)
        for a in PATTERN_FACTORS:
            y, hint = self.projector(self.x + a * D)
            fy, ky = self.objective(y)
            fys.append(fy)
            kys.append(ky)
            if int(pattern_choice(f, kmax, fys, kys, np)) == len(fys) - 1:
                best = (fy, ky, y, hint)
            if not fy < (fys[-2] if len(fys) > 1 else f):  # the first rise: the trials after it are not considered
                break
        return self._take(best)

    def best_of(self, trials, f: float, kmax: float) -> tuple[float, float]:
        """The mesh becomes the best of `trials` (an iterable of ``(n, 3)`` points, each projected onto the
        boundary) where it lowers `f` (F at the current `x`) and its max kappa/3 - 1 is at most `EXCESS_GROWTH`
        times ``kmax - 1`` (`kmax` the current max kappa/3; `jaxci.optim.ci._better`); returns
        ``(F, max kappa/3)`` after it."""
        best = (f, kmax, None, None)
        for t in trials:
            y, hint = self.projector(t)
            fy, ky = self.objective(y)
            if fy < best[0] and excess_within_bound(kmax, ky):
                best = (fy, ky, y, hint)
        return self._take(best)

    def _take(self, best) -> tuple[float, float]:
        """``best`` = ``(F, max kappa/3, points, projector hint)``: the mesh becomes `points` unless None."""
        if best[2] is not None:
            self.x = best[2]
            self.projector.commit(best[3])
        return best[0], best[1]


def local_ci_np(points, hexes, cons: Constraints, colour, faces, p: CIParams, seed: int = 0,
                stream: str = "native", colours: list | None = None):
    """Local CI on the host from `points` ``(n, 3)`` of the hexahedra `hexes` ``(N, 8)``, `cons` the numpy
    float64 constraints, `colour` the node colouring, `faces` the boundary faces (for the planar shortcut);
    `stream` the random numbers' (``"native"``, or ``"counter"``: `jaxci.optim.ci.local_ci`'s with the same);
    `colours` (optional): `sweep_colours` of these, made once for several runs on one mesh (they do not depend on
    the points).

    **Returns:** ``(points, sweeps, history)`` as `jaxci.optim.ci.local_ci` (float64 points).
    """
    sw = _Sweeper(points, hexes, cons, colour, faces, p, seed, stream, colours)
    f, kmax = sw.objective(sw.x)
    hist_f, hist_k, hist_m = [f], [kmax], [0]
    done = f <= p.ftol or kmax <= 1.0 + p.ktol
    memory = AndersonMemory(p.anderson, sw.x.size) if p.anderson else None  # the last sweeps
    tick = stepper("local CI", "sweep")
    while not done and len(hist_f) <= p.max_sweeps:
        start = sw.x.copy()
        moved = sum(sw.visit(col, len(hist_f) - 1) for col in sw.colours)
        f_new, k_new = sw.objective(sw.x)
        D = sw.x - start  # the sweep's displacement
        if memory is not None:
            memory.push(start.ravel(), D.ravel())
        if p.pattern:
            f_new, k_new = sw.pattern(D, f_new, k_new)
        point = memory.point() if memory is not None else None
        if point is not None:
            f_new, k_new = sw.best_of([point.reshape(-1, 3)], f_new, k_new)
        hist_f.append(f_new)
        hist_k.append(k_new)
        hist_m.append(moved)
        if tick is not None:
            tick(len(hist_f) - 1, f_new, k_new)
        done = sweep_done(f, f_new, k_new, moved, p.ftol, p.tol, p.atol, p.ktol)
        f = f_new
    n = len(hist_f) - 1
    return sw.x, n, {"objective": np.asarray(hist_f), "max_condition": np.asarray(hist_k),
                     "moved": np.asarray(hist_m, np.int32)}


def laplace_np(points, hexes, cons: Constraints, colour, faces, p: LaplaceParams, *,
               smart: bool = False, until_valid: bool = False):
    """The (smart) Laplacian on the host from `points` ``(n, 3)``; arguments as `local_ci_np`; `until_valid`:
    also stop after the first sweep that leaves no inverted corner (F finite: the untangling's first try,
    `jaxci.optim.untangle`).

    **Returns:** ``(points, sweeps, history, params)`` as `jaxci.optim.laplace.laplace` (float64 points; F and
    max kappa/3 are ``inf`` once the plain Laplacian has inverted a corner).
    """
    # the neighbours first: their sort's temporaries (~380 B a hexahedron) are gone before the stars are built;
    # in int32 while the node numbers fit (half the bytes, and so the colours' rows taken from them)
    it = np.int32 if len(points) < 2**31 else np.int64
    nbr, nmask = edge_neighbours(hexes, len(points), dtype=it)
    sw = _Sweeper(points, hexes, cons, colour, faces, p)
    per_colour = []
    for col in sw.colours:
        h = _local_length(sw.x, sw.hexes, col)
        per_colour.append((nbr[col.nodes], nmask[col.nodes], np.where(h > 0, h, 1.0)))
    del nbr, nmask  # every movable node's rows are in `per_colour` now
    f, kmax = sw.objective(sw.x)
    hist_f, hist_k, hist_m = [f], [kmax if np.isfinite(f) else np.inf], [0.0]
    tick = stepper("smart Laplace" if smart else "Laplace", "sweep")
    while len(hist_f) <= p.max_sweeps:
        move = max((sw.laplace_visit(col, *extra, smart) for col, extra in zip(sw.colours, per_colour, strict=True)),
                   default=0.0)
        f, kmax = sw.objective(sw.x)
        hist_f.append(f)
        hist_k.append(kmax if np.isfinite(f) else np.inf)
        hist_m.append(move)
        if tick is not None:
            tick(len(hist_f) - 1, f, hist_k[-1])
        if move <= p.tol or (until_valid and np.isfinite(f)):
            break
    n = len(hist_f) - 1
    hist = {"objective": np.asarray(hist_f), "max_condition": np.asarray(hist_k), "max_move": np.asarray(hist_m)}
    return sw.x, n, hist, {"method": "smart-laplace" if smart else "laplace", **dataclasses.asdict(p)}
