"""Untangling: move nodes until no hexahedron corner is inverted, before shape improvement.

F (Eq. 3.1) is infinite on a tangled mesh, so it cannot drive the nodes out of a fold. This stage minimises the
regularised Winslow-type energy of Garanzha, Kaporin, Kudryavtseva, Protais, Ray, Sokolov (2021), "Foldover-free
maps in 50 lines of code" (ACM ToG 40(4)), the method behind Gmsh's ``UntangleMeshGeometry``. Per hex corner,
with ``J = A / L_e`` (the corner matrix of element e over a reference length L_e: the mean edge length of e in
the input, so an ideal corner has ``J = I``):

    E_c = (1 - theta) (|J|_F^2 / 3) / chi(eps, det J)^(2/3) + theta (det J^2 + 1) / chi(eps, det J),
    chi(eps, d) = (d + sqrt(eps^2 + d^2)) / 2,

summed over all corners (scaled by 1/32 per corner, as `jaxci.optim.gradient` scales F). chi is a smooth,
positive stand-in for det that tends to det for det >> eps and to eps^2 / (4 |det|) for det < 0, so E is finite
and smooth on tangled meshes and the fold is pushed out as eps decreases. The eps schedule is the paper's:
start with ``eps = sqrt(1e-12 + 0.04 min(det_min, 0)^2)``; after each inner minimisation with E_prev, E,
``sigma = max(1 - E / E_prev, 0.1)``, ``mu = (1 - sigma) chi(eps, det_min)``, and
``eps = 2 sqrt(mu (mu - det_min))`` if ``det_min < mu`` else ``1e-10``.

Each inner minimisation is L-BFGS (optimistix's `LBFGS`: memory 10, backtracking Armijo search, Cauchy
termination) over the same constrained parametrisation as the gradient methods
(`jaxci.optim.parametrisation.Parametrisation`: interior nodes free, surface nodes on their patch, edge nodes on
their curve, corners fixed; all on the ORIGINAL boundary), and stops as soon as every corner has
``det J >= margin`` (det A >= margin L_e^3); the stage stops there. The result is projected onto the original
boundary in float64 (`project_np`) and checked: no corner with det <= 0, else `InvertedMeshError`.

**One compilation.** Every round runs inside one compiled loop (`jaxci.optim._untangle_loop.untangle_rounds`):
eps, the round's start energy, the L-BFGS memory and the per-round history are loop-carried, the loop body holds
the one energy-and-gradient evaluation (a closed-form kernel over a flat corner table), and nothing goes back to
Python between rounds; the float64 checks are numpy. Where every moving boundary node has a flat region (a box)
the rounds run strict, without the projection compiled, until one ends with a node near the edge of its region
(`jaxci.optim._untangle_loop.FLAT_REACH`), then with it. Measured cold in ``jaxci smooth --method lbfgs`` (CPU
s of this stage, 2-core machine, interleaved runs): pave3 with --fix-boundary 3.1 -> 1.45, pave3 sliding 6.4 ->
3.0, hex_5_tangled 5.5 -> 1.6, cube30_pert 6.2 -> 2.0, 7 compilations -> 1, with the same steps (27, 23, 7, 7),
min det and final kappa (optimistix's loop, a separate energy function for the round states, JAX's gradient
and small helper programs before); 60^3 (1838 inverted, 50 steps): 19.7 -> 11.5 cold, 13.7 -> 9.8 warm. One
evaluation of the energy and its gradient costs what one of F does (60^3, float64: 266 against 255 ms).

**Mixed meshes.** The corners of wedges, pyramids and tetrahedra count like the hexahedra's, with
``J = A W^-1 / L_e`` (W the type's ideal corner, `jaxci.cells.TARGETS`, so an ideal cell of edge L_e has
``J = I``); each of the four sub-tetrahedra of a pyramid (`jaxci.cells.PYRAMID_TETS`, which must stay
positive too) adds the volume term ``theta (det J^2 + 1) / chi`` only. "Untangled" means no inverted cell of any type
(`jaxci.metrics.elements.inverted`).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from .. import native
from ..cells import EDGES, corner_determinants, element_blocks
from ..errors import InvertedMeshError
from ..geometry.boundary import CORNER, BoundaryInfo
from ..geometry.projection import Constraints, build_constraints, n_free
from ..mesh import HexMesh
from ..metrics import elements as E
from ..metrics.objective import cell_label, extra_blocks, extra_cells, inverted_cells, no_extra
from ..runtime._lazy import enable_x64, is_jax_array, jax
from . import _params as _p
from ._untangle_loop import FLAT_REACH, corner_table, untangle_rounds
from .host import UNTANGLE_HOST_MAX, runs_on_host, untangle_rounds_np
from .parametrisation import Parametrisation, make_parametrisation

#: Upper bounds of `UntangleParams` (a typo must not hang a run): eps rounds, L-BFGS steps per round.
MAX_ROUNDS, MAX_INNER_STEPS = 10_000, 1_000_000
#: From this many hexahedra the untangling stage tries one plain Laplace sweep first
#: (`UntangleParams.laplace_sweeps` None); below it the Winslow rounds are cheaper than the sweep's set-up.
LAPLACE_UNTANGLE_FROM = 100_001


@dataclasses.dataclass(frozen=True)
class UntangleParams:
    """Hyperparameters of the untangling stage. Validated on construction (`ConfigError`).

    - `theta`: weight in [0, 1) of the volume term (det^2 + 1)/chi against the shape term (default 0.1).
    - `margin`: target: every corner with det A >= margin * L_e^3 (default 1e-3; > 0).
    - `max_rounds`: most eps updates (outer iterations, default 60; at most 10,000).
    - `inner_steps`: most L-BFGS steps per round (default 400; at most 10^6).
    - `rtol`, `atol`: L-BFGS termination per round (default 1e-7 each).
    - `backend`: ``"auto"`` (default: numpy on hexahedral meshes of at most
      `jaxci.optim.host.UNTANGLE_HOST_MAX` elements, no compilation; else the compiled loop), ``"numpy"``
      (hexahedral meshes) or ``"jax"``.
    - `time_budget`: seconds after which the stage stops, untangled or not (default 0: none). Checked at every
      step on the numpy path; the compiled loop (larger or mixed meshes) is bounded by `max_rounds` and
      `inner_steps` only.
    - `laplace_sweeps`: on the numpy path (hexahedral meshes), first up to this many sweeps of the plain
      Laplacian (`jaxci.optim.host_local.laplace_np`, boundary nodes on the boundary), stopping at the first with
      no inverted corner; their result is the stage's if every corner then has ``det A >= margin L_e^3``, else the
      rounds start from the input as without them (0: off). Default None: 1 from `LAPLACE_UNTANGLE_FROM`
      hexahedra, else 0. Measured (2026-11-26, e615006): cube60_pert's 1838 inverted elements in one sweep, the
      stage 7.9 -> about 3 s (50 Winslow L-BFGS steps before), the same final mesh quality (max kappa/3 1.0000007); on
      cube30_pert (27,000) the sweep's set-up (colouring, stars) cost more than the Winslow steps it saves (0.74
      against 0.34 s); pave3 needs 5 sweeps, and its shape improvement then ends at max kappa/3 2.863 against
      2.823 from the Winslow start.
    """

    theta: float = 0.1
    margin: float = 1e-3
    max_rounds: int = 60
    inner_steps: int = 400
    rtol: float = 1e-7
    atol: float = 1e-7
    backend: str = "auto"
    time_budget: float = 0.0
    laplace_sweeps: int | None = None

    def __post_init__(self):
        L = "untangling"
        _p.normalise(
            self,
            theta=_p.real(L, "theta", self.theta, 0, 1, hi_open=True),
            margin=_p.real(L, "margin", self.margin, 0, 1, lo_open=True, hi_open=True),
            max_rounds=_p.integer(L, "max_rounds", self.max_rounds, 1, MAX_ROUNDS),
            inner_steps=_p.integer(L, "inner_steps", self.inner_steps, 1, MAX_INNER_STEPS),
            rtol=_p.real(L, "rtol", self.rtol, 0, lo_open=True),
            atol=_p.real(L, "atol", self.atol, 0, lo_open=True),
            backend=_p.choice(L, "backend", self.backend, ("auto", "jax", "numpy")),
            time_budget=_p.real(L, "time_budget", self.time_budget, 0),
            laplace_sweeps=(None if self.laplace_sweeps is None
                            else _p.integer(L, "laplace_sweeps", self.laplace_sweeps, 0, MAX_ROUNDS)),
        )


def element_lengths(points: np.ndarray, hexes: np.ndarray, cell_type: str = "hexahedron") -> np.ndarray:
    """Mean length of the edges of each cell (`jaxci.cells.EDGES` of `cell_type`), shape ``(N,)`` (float64).
    An edge at a time: the temporaries are a few ``(N, 3)`` arrays (all edges at once held 180 MB at 216,000
    hexahedra, the untangling's peak)."""
    p = np.asarray(points, dtype=np.float64)
    cells = np.asarray(hexes)
    edges = EDGES[cell_type]
    total = np.zeros(len(cells))
    for a, b in edges:
        d = p[cells[:, b]]
        d -= p[cells[:, a]]
        total += np.sqrt(np.einsum("ij,ij->i", d, d))
    return total / len(edges)


def _safe_lengths(lens: np.ndarray) -> np.ndarray:
    return np.where(lens > 0, lens, max(float(lens.max(initial=0.0)), 1.0))


#: `_scaled_min_det` measures this many hexahedra at a time.
MIN_DET_CHUNK = 16_384


def _scaled_min_det(mesh: HexMesh, x: np.ndarray, lens: np.ndarray) -> float:
    """min det / L^3 over every corner (non-hexahedral corners: det A_i, not divided by det W)."""
    out = np.inf
    for lo in range(0, mesh.n_hexes, MIN_DET_CHUNK):  # (every corner's at once: 28 MB at 216,000 hexahedra)
        det = corner_determinants(x, mesh.hexes[lo:lo + MIN_DET_CHUNK])
        det /= lens[lo:lo + MIN_DET_CHUNK, None] ** 3
        out = min(out, float(det.min()))
    for t, cells in extra_blocks(mesh).items():
        lt = _safe_lengths(element_lengths(mesh.points, cells, t))
        out = min(out, float((E.corner_determinant(x, cells, t) / lt[:, None] ** 3).min()))
    return out


def untangle(mesh: HexMesh, info: BoundaryInfo, cons: Constraints, p: UntangleParams = UntangleParams(), *,
             flat_reach: float = FLAT_REACH, progress=None):
    """Untangle `mesh` (float64) keeping its boundary nodes on the original boundary.

    **Arguments:**

    - `mesh`: the input `HexMesh` (its coordinates are the start and define the original boundary).
    - `info`, `cons`: its `BoundaryInfo` and float64 `Constraints`.
    - `p`: `UntangleParams`.
    - `flat_reach`: where every moving boundary node has a flat region, the rounds run without the projection
      until one ends with a node further than this fraction of its region's radius from its start, then with it
      (`jaxci.optim._untangle_loop.untangle_rounds`).
    - `progress`: optional ``progress(text)``, called after each round on the numpy path.

    **Returns:** ``(points, report)``: float64 coordinates ``(n, 3)`` projected onto the original boundary
    (`project_np`), and a dict: ``rounds``, ``steps`` (L-BFGS steps in all), ``eps`` (per round),
    ``min_det`` (min det J per round, entry 0 = input), ``energy`` (per round), ``untangled`` (bool: no
    corner with det <= 0 after projection), ``inverted_elements`` (after), ``min_scaled_det`` (after),
    ``runs`` (per run: ``("flat regions" | "projected" | "numpy", rounds, steps)``), ``wall_time``.
    """
    t0 = time.perf_counter()
    hexes = mesh.hexes
    lens = _safe_lengths(element_lengths(mesh.points, hexes))
    blocks = extra_blocks(mesh)
    on_host = bool(n_free(cons)) and runs_on_host(p.backend, len(hexes), UNTANGLE_HOST_MAX, bool(blocks))
    f64 = np.float64
    rounds = steps = 0
    hist = [np.zeros(0)] * 3
    runs = []
    x = par = None
    sweeps = p.laplace_sweeps
    if sweeps is None:
        sweeps = 1 if len(hexes) >= LAPLACE_UNTANGLE_FROM else 0
    if on_host and sweeps and not blocks and native.AVAILABLE:  # the host's sweeps are the C kernels
        x, sweeps = _laplace_untangle(mesh, info, cons, p, lens, sweeps)
    if x is None:
        if not on_host and not is_jax_array(cons.x_orig):  # numpy constraints (device=False) for the compiled loop
            cons = jax.device_put(cons)
        par: Parametrisation = make_parametrisation(mesh, info, cons, scaled=True, dtype=np.float64)
        if not len(par.flat_nodes):  # no boundary node moves: the points are the lift, nothing to project
            par = dataclasses.replace(par, shortcut=True)
    nf = 0 if par is None else par.n_free
    v = np.zeros((nf,), f64)
    if x is not None:  # the plain Laplacian untangled it
        dmin0 = _scaled_min_det(mesh, np.asarray(mesh.points, f64), lens)
        runs.append(("laplace", sweeps, 0))
    elif on_host:
        def report(r, dmin, eps, e):
            if progress is not None:
                progress(f"round {r}: min det J {dmin:.3g} (target {p.margin:g}), eps {eps:.3g}, "
                         f"{time.perf_counter() - t0:.1f} s")

        v, x, st = untangle_rounds_np(par, hexes, 1.0 / lens, theta=p.theta,
                                      margin=p.margin, max_rounds=p.max_rounds, inner_steps=p.inner_steps,
                                      rtol=p.rtol, atol=p.atol,
                                      deadline=t0 + p.time_budget if p.time_budget else None, progress=report)
        rounds, steps, dmin0 = st["rounds"], st["steps"], st["dmin0"]
        hist = [st["h_eps"], st["h_dmin"], st["h_e"]]
        runs.append(("numpy", rounds, steps))
    elif nf:
        extra = extra_cells(mesh) if blocks else no_extra()
        # numpy in, device_put: jnp.asarray of a numpy array compiles a small 'stage' program per shape (jax 0.10)
        table = jax.device_put(corner_table(hexes))
        inv_len = jax.device_put(np.tile(1.0 / lens, 8))
        inv_lens = tuple(jax.device_put((1.0 / _safe_lengths(element_lengths(mesh.points, c, t)))[None, :])
                         for t, c in blocks.items())
        # strict first where every moving boundary node has a flat region: no projection compiled (a trial that
        # leaves a region is rejected); after a round that ends with a node near the edge of its region, the
        # rounds go on with the projection
        params = (f64(p.theta), f64(p.margin), np.int32(p.max_rounds), np.int32(p.inner_steps), f64(p.rtol),
                  f64(p.atol))
        state = None
        for strict in (True, False) if par.shortcut else (False,):
            run = dataclasses.replace(par, strict=strict)
            state = untangle_rounds(jax.device_put(v), (run, table, inv_len, extra, inv_lens), *params, state,
                                    f64(flat_reach))
            r, k = int(state["rounds"]), int(state["steps"])
            runs.append(("flat regions" if strict else "projected", r - rounds, k - steps))
            rounds, steps = r, k
            if not bool(state["left"]):
                break
        v = state["y_best"]
        dmin0 = float(state["dmin0"])
        hist = [np.asarray(state[key])[:rounds] for key in ("h_eps", "h_dmin", "h_e")]
    else:
        dmin0 = _scaled_min_det(mesh, np.asarray(mesh.points, f64), lens)
    hist_eps, hist_dmin, hist_e = hist
    if x is None:
        x = np.asarray(par.final_points(v), dtype=f64)  # exact: project_np where a node left its flat region
    bad = np.concatenate(list(inverted_cells(mesh, x).values()))
    report = {
        "rounds": rounds,
        "steps": steps,
        "eps": [float(a) for a in hist_eps],
        "min_det": [dmin0, *(float(a) for a in hist_dmin)],
        "energy": [float(a) for a in hist_e],
        "untangled": not bool(bad.any()),
        "inverted_elements": int(bad.sum()),
        "min_scaled_det": _scaled_min_det(mesh, x, lens),
        "runs": runs,
        "laplace_sweeps": sweeps,
        "laplace_untangled": bool(runs) and runs[0][0] == "laplace",
        "out_of_time": bool(on_host and rounds and st["out_of_time"]),
        "wall_time": time.perf_counter() - t0,
    }
    return x, report


def _laplace_untangle(mesh: HexMesh, info: BoundaryInfo, cons: Constraints, p: UntangleParams, lens: np.ndarray,
                      max_sweeps: int):
    """Up to `max_sweeps` plain Laplace sweeps from the input (numpy constraints `cons`), stopping at the first
    with no inverted corner: ``(points, sweeps)``, points None unless every corner then has
    ``det A >= margin L_e^3`` (`p.margin`; `lens` the elements' reference lengths)."""
    from ..geometry.topology import colour_nodes
    from .host_local import laplace_np
    from .laplace import LaplaceParams

    colour = colour_nodes(mesh.hexes, mesh.n_nodes).colour
    x, sweeps, hist, _ = laplace_np(mesh.points, mesh.hexes, cons, colour, info.topology.faces,
                                    LaplaceParams(max_sweeps=max_sweeps), until_valid=True)
    ok = np.isfinite(hist["objective"][-1]) and _scaled_min_det(mesh, x, lens) >= p.margin
    return (x if ok else None), int(sweeps)


def untangle_stage(mesh: HexMesh, info: BoundaryInfo, p: UntangleParams = UntangleParams(), *,
                   partial: bool = False, progress=None):
    """`jaxci.smooth`'s untangling stage: untangle or raise `InvertedMeshError` (the input is never modified).

    **Arguments:** `mesh` the input mesh; `info` its `BoundaryInfo` (with the user's fixed nodes); `p`;
    `partial`: where some elements stay inverted, return the result with fewer of them instead of raising (the
    input if the stage left more); `progress`: optional ``progress(text)`` per round (`untangle`).

    **Returns:** ``(points, notes, swept)``: untangled float64 coordinates ``(n, 3)`` with every boundary node on
    the original boundary (with `partial`, possibly some elements still inverted: the notes say how many),
    sentences for `SmoothResult.notes`, and whether plain Laplace sweeps untangled it (`UntangleParams.
    laplace_sweeps`: they also smoothed it, so the default pipeline's presmoothing is not needed).
    """
    where = f"{mesh.source}: " if mesh.source else ""
    # only the count of inverted corners is kept: the determinants (64 B a hexahedron) are not held through the stage
    n_corners0 = int((corner_determinants(mesh.points, mesh.hexes) <= 0).sum()) + sum(
        int((E.corner_determinant(mesh.points, c, t) <= 0).sum()) for t, c in extra_blocks(mesh).items())
    inv0 = np.concatenate(list(inverted_cells(mesh, mesh.points).values()))
    host = on_host(mesh, p)
    with enable_x64(not host):
        cons = build_constraints(mesh, info, dtype=np.float64, device=not host)
        x, rep = untangle(mesh, info, cons, p, progress=progress)
    budget = (f" (its time budget of {p.time_budget:g} s ran out)" if rep.get("out_of_time") else "")
    if not rep["untangled"] and partial:
        left = rep["inverted_elements"]
        if left > int(inv0.sum()):
            x, left = np.array(mesh.points, dtype=np.float64), int(inv0.sum())
        bad = {t: np.flatnonzero(b) for t, b in inverted_cells(mesh, x).items() if b.any()}
        first = ", ".join(cell_label(mesh, t, int(k)) for t, ks in bad.items() for k in ks[:5])
        return x, [f"partial untangling{budget}: {int(inv0.sum())} inverted elements in the input, {left} left "
                   f"inverted ({first}{', ...' if left > 5 else ''}) after {rep['rounds']} rounds; shape "
                   f"improvement skipped: the mesh is returned with them"], False
    if not rep["untangled"]:
        blocks = element_blocks(mesh)
        bad = {t: np.flatnonzero(b) for t, b in inverted_cells(mesh, x).items() if b.any()}
        t0 = next(iter(bad))
        nodes = np.unique(np.concatenate([blocks[t][k].ravel() for t, k in bad.items()]))
        stuck = np.asarray(info.node_class)[nodes] == CORNER
        raise InvertedMeshError(
            f"{where}untangling failed{budget}: {_elements(rep['inverted_elements'])} inverted after {rep['rounds']} "
            f"rounds ({int(inv0.sum())} {'was' if int(inv0.sum()) == 1 else 'were'} in the input; {rep['steps']} "
            f"L-BFGS steps; first: {cell_label(mesh, t0, bad[t0][0])}; {int(stuck.sum())} of their {len(nodes)} nodes "
            f"are fixed corners of the boundary); the input is left unchanged (untangle='partial' / --untangle "
            f"partial returns the mesh with what could be untangled; untangle_boundary=True / --untangle-boundary "
            f"lets the boundary's corner and edge nodes of inverted elements slide on the surface)"
        )
    if not inv0.any() and rep["rounds"] == 0:
        return x, [f"untangling: no inverted element and min det / L^3 = {rep['min_det'][0]:.3g} >= margin "
                   f"{p.margin:g}: nothing to do"], False
    how = (f"{rep['laplace_sweeps']} sweep{'s' if rep['laplace_sweeps'] != 1 else ''} of the plain Laplacian"
           if rep["laplace_untangled"] else
           f"{rep['rounds']} rounds of L-BFGS on the regularised Winslow energy ({rep['steps']} steps"
           + (f", after {rep['laplace_sweeps']} Laplace sweeps that did not untangle it" if rep["laplace_sweeps"]
              else "") + ")")
    note = (
        f"untangling: {int(inv0.sum())} inverted elements ({n_corners0} corners) untangled in {how}, "
        f"{rep['wall_time']:.2f} s; min det / L^3 {rep['min_det'][0]:.3g} -> {rep['min_scaled_det']:.3g}; boundary "
        f"nodes kept on the original boundary"
    )
    return x, [note], bool(rep["laplace_untangled"])


def on_host(mesh: HexMesh, p: UntangleParams) -> bool:
    """Whether the untangling stage of `mesh` with `p` runs in numpy (`jaxci.optim.host.untangle_rounds_np`)."""
    return runs_on_host(p.backend, mesh.n_hexes, UNTANGLE_HOST_MAX, bool(extra_blocks(mesh)))


def _elements(k: int) -> str:
    return f"{k} element is" if k == 1 else f"{k} elements are"
