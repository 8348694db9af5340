"""`make_parametrisation` on the device (the JAX engine; hexahedral meshes): the same `Parametrisation` from the
device's mesh, with no O(mesh) work or transfer on the host.

- the scale of every free coordinate: the mean hexahedron edge length at its node (`node_lengths_traced`, a sum
  over each node's incidences: no scatter, so the sums are the same from run to run on any device);
- the flat regions: the planar rings of the surface nodes and the straight intervals of the edge nodes are
  O(boundary) and stay on the host (`jaxci.optim._moves.surface_rings`,
  `jaxci.optim.parametrisation.flat_intervals`), from the boundary faces and the boundary nodes' coordinates
  alone (`jaxci.optim.device_stars.boundary_view`); their radii go up, and the test of the base points against
  them runs on the device;
- what comes down: the boundary view (O(boundary)) and one boolean (`Parametrisation.shortcut`, static).

Decisions are taken in float64 as `make_parametrisation`'s (inside ``jax.enable_x64``); the parametrisation is
in the run's dtype.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cells import CORNER_NEIGHBOURS
from ..geometry.device_colouring import Incidences, incidences
from ..geometry.projection import Constraints
from ..runtime._lazy import enable_x64, jit, jnp
from ..runtime.transfer import program, to_device, to_host
from .device_stars import BoundaryView, boundary_view, surface_planes
from .parametrisation import Parametrisation, flat_intervals

#: The 12 edges of a hexahedron (local corners i < j) and, per corner, the index of its 3 edges in that list
#: (to its neighbours `CORNER_NEIGHBOURS`, in their order).
_EDGES = sorted({(min(i, int(j)), max(i, int(j))) for i in range(8) for j in CORNER_NEIGHBOURS[i]})
_CORNER_EDGES = np.array([[_EDGES.index((min(i, int(j)), max(i, int(j)))) for j in CORNER_NEIGHBOURS[i]]
                          for i in range(8)], np.int32)


def node_lengths_traced(conn, points, inc: Incidences):
    """`jaxci.optim.parametrisation.node_lengths` on the device (traceable): the mean length of the hexahedron edges
    at each node ``(n,)`` (the three edges at the node of each of its hexahedra; 0 for a node of none), in the dtype
    of `points`; `conn` ``(8, N)``, `inc` the `Incidences`. The same values to rounding (the sums run in another
    order): the 12 edge lengths of every hexahedron, then each node's sum over the 3 edges at it of each of its
    incidences (a gather, no scatter)."""
    n_hex = conn.shape[1]
    at = [points[:, d][conn.astype(jnp.int32)] for d in range(3)]  # (8, N) each
    length = jnp.stack([jnp.sqrt(sum((c[j] - c[i]) ** 2 for c in at)) for i, j in _EDGES])  # (12, N)
    edges = jnp.asarray(_CORNER_EDGES)[inc.table & 7]  # (n, K, 3)
    per = length.reshape(-1)[edges * n_hex + (inc.table >> 3)[..., None]]
    total = jnp.sum(jnp.where(inc.mask()[..., None], per, 0.0), axis=(1, 2))
    count = 3 * inc.valence
    return jnp.where(count > 0, total / jnp.maximum(count, 1).astype(points.dtype), 0.0)


def make_parametrisation_device(points, conn, faces: np.ndarray, feature_edges: np.ndarray, cons: Constraints,
                                x0=None, *, scaled: bool = True, dtype=None, inc: Incidences | None = None,
                                view: BoundaryView | None = None, planes: np.ndarray | None = None) -> Parametrisation:
    """`jaxci.optim.parametrisation.make_parametrisation` from device arrays.

    **Arguments:**

    - `points` ``(n, 3)``: the original coordinates (device, float64: the constraints' geometry); `conn`
      ``(8, N)`` the hexahedra (device); `faces` ``(n_faces, 4)`` and `feature_edges` ``(m, 2)`` the boundary
      faces and feature edges (host: ``BoundaryInfo.topology.faces``, ``BoundaryInfo.feature_edges``); `cons`
      the `Constraints` (device arrays).
    - `x0`: base coordinates ``(n, 3)`` (device; default `points`); boundary nodes must lie on the boundary.
    - `scaled`, `dtype` (default: that of `cons`): as `make_parametrisation`.
    - `inc`: the `Incidences` if at hand (default: built; only with `scaled`; `jaxci.optim.device_stars.SweepData`
      holds them); `view`, `planes`: the `jaxci.optim.device_stars.BoundaryView` of `points` and its
      `jaxci.optim.device_stars.surface_planes` if at hand (default: the view comes down and the planes are
      found; a `SweepData` built with ``plane_points=points`` holds both).

    Programs: the incidences unless given (`jaxci.geometry.device_colouring.incidences`), the boundary view (its
    O(boundary) arrays come down), the parametrisation (the flat regions' radii go up; one boolean comes down).

    **Returns:** a `Parametrisation` of device arrays.
    """
    dtype = np.dtype(cons.x_orig.dtype if dtype is None else dtype)
    base = points if x0 is None else x0
    with enable_x64():
        if scaled and inc is None:
            inc = incidences(conn, int(points.shape[0]))
        view = boundary_view(points, faces, cons) if view is None else view
        rings = surface_planes(view) if planes is None else planes
        fe = view.local(np.asarray(feature_edges, np.int64).reshape(-1, 2)) if len(view.edge) else np.zeros((0, 2),
                                                                                                             np.int64)
        ns = len(view.surf)
        radius = np.concatenate([rings[:ns, 6], flat_intervals(view.points, fe, view.edge_at)])
        par, shortcut = _parametrisation(points, base, conn, inc if scaled else None, cons,
                                         to_device(radius, np.float64), to_device(rings[:ns, 3:6], np.float64),
                                         dtype=dtype)
        return dataclasses.replace(par, shortcut=bool(to_host(shortcut)))


@program
@jit(static_argnames=("dtype",))
def _parametrisation(points, base, conn, inc, cons: Constraints, radius, normal, dtype):
    """The `Parametrisation` (its `shortcut` False: the second output says whether every moving boundary node
    keeps its flat region); scaled by the node lengths of `base` where `inc` is given."""
    f64 = jnp.float64
    pts, base = points.astype(f64), base.astype(f64)
    inter, surf, edge = cons.interior_nodes, cons.surface_nodes, cons.edge_nodes
    if inc is None:
        scale = jnp.ones(3 * inter.shape[0] + 2 * surf.shape[0] + edge.shape[0], f64)
    else:
        h = node_lengths_traced(conn, base, inc)
        scale = jnp.concatenate([jnp.repeat(h[inter], 3), jnp.repeat(h[surf], 2), h[edge]])
        scale = jnp.where(scale > 0, scale, 1.0)
    nodes = jnp.concatenate([surf, edge]).astype(jnp.int32)
    # base points must lie on their plane / line for x0 + B u to stay on it, to the precision of the working dtype
    tol = jnp.maximum(1e-12 * radius, 64 * jnp.finfo(dtype).eps * jnp.max(jnp.abs(base[nodes]), axis=1, initial=0.0))
    off = jnp.abs(jnp.sum((base[surf] - pts[surf]) * normal, axis=1))
    tangent = cons.edge_tangent.astype(f64)
    rel = base[edge] - pts[edge]
    perp = jnp.linalg.norm(rel - jnp.sum(rel * tangent, axis=1)[:, None] * tangent, axis=1)
    radius = jnp.where(jnp.concatenate([off, perp]) <= tol, radius, 0.0)
    par = Parametrisation(cons=cons, x0=base.astype(dtype), scale=scale.astype(dtype), flat_nodes=nodes,
                          flat_origin=pts[nodes].astype(dtype), flat_radius=radius.astype(dtype), shortcut=False)
    return par, (nodes.shape[0] > 0) & jnp.all(radius > 0)
