"""The boundary classification, the constraints and the exact projection of a mesh whose points live on the device,
with O(boundary) host work and traffic.

For a run that keeps its mesh on the device (the JAX engine), these stand for the host functions of the same
results:

- `device_unit_frame`: `jaxci.mesh.unit_frame` from the points' bounds reduced on the device (6 numbers down);
- `device_classify_boundary`: `jaxci.geometry.boundary.classify_boundary` from the boundary nodes' coordinates
  only (downloaded), the topology and unused nodes of `jaxci.geometry.device_topology.device_mesh_topology`;
- `device_constraints`: `jaxci.geometry.projection.build_constraints`: its per-node arrays (``x_orig``,
  ``node_class``, ``group``, ``row``, ``interior_nodes``) are built ON the device by scattering the boundary
  nodes' classes (`jaxci.geometry.boundary.NodeClasses`, uploaded); its tables on the host from the boundary
  nodes' coordinates (`jaxci.geometry.tables.boundary_tables`), uploaded. It also returns those tables in
  float64 (`BoundaryTables`), for
- `project_boundary`: `jaxci.geometry.projection.project_np` (the exact float64 search) of the surface and edge
  nodes only, downloaded, searched on the host (`project_on_groups`) and put back on the device with the
  corners' original positions.

Every transfer goes through `jaxci.runtime.transfer` (`to_device`, `to_host`): the functions run under
``jax.transfer_guard("disallow")``. For results equal to the host functions' the device points are float64
(the coordinates the host functions read from the mesh); with float32 points the tables are built from those
rounded coordinates. The device path is for hexahedral meshes (`hexahedral`): meshes with wedges, pyramids,
tetrahedra or quadratic cells keep the host functions.
"""

from __future__ import annotations

import functools

import numpy as np

from ..cells import QUADRATIC_TYPES
from ..cells import fixed_nodes as fixed_cell_nodes
from ..mesh import HexMesh
from ..mesh.frame import frame_of_bounds
from ..mesh.sorting import sorted_unique
from ..runtime._lazy import enable_x64, jax, jnp
from ..runtime.sizes import bucket
from ..runtime.transfer import program, to_device, to_host
from .boundary import CORNER, EDGE, INTERIOR, SURFACE, BoundaryInfo, classify_boundary, non_hex_cells
from .device_topology import first_true
from .projection import TABLE_FIELDS, Constraints, project_on_groups
from .tables import BoundaryTables, boundary_tables
from .topology import BoundaryTopology


def hexahedral(mesh: HexMesh) -> bool:
    """Whether the volume cells of `mesh` are linear hexahedra only (the device path's meshes)."""
    quadratic = any(len(b.data) and QUADRATIC_TYPES.get(b.type) == "hexahedron" for b in mesh.cells)
    return not quadratic and not non_hex_cells(mesh) and not len(fixed_cell_nodes(mesh))


@program
@jax.jit
def _bounds(points):
    return points.min(axis=0), points.max(axis=0)


@program
@jax.jit
def _rows(points, idx):
    return points[idx]


def device_unit_frame(points) -> tuple[np.ndarray, float]:
    """`jaxci.mesh.unit_frame` of the device points ``(n, 3)``: their bounds reduced on the device, 6 numbers
    down."""
    if not points.shape[0]:
        return np.zeros(3), 1.0
    return frame_of_bounds(*to_host(_bounds(points)))


def _boundary_points(points, nodes: np.ndarray) -> np.ndarray:
    """The device points at the sorted `nodes` ``(k,)``, downloaded: float64 ``(k, 3)``."""
    got = to_host(_rows(points, to_device(np.asarray(nodes), np.int32)))
    return np.asarray(got, dtype=np.float64).reshape(-1, 3)


def device_classify_boundary(mesh: HexMesh, points, topology: BoundaryTopology, unused: np.ndarray, *,
                             feature_angle: float = 40.0, fix_boundary: bool = False, fixed_nodes=None,
                             fixed_sets=()) -> BoundaryInfo:
    """`jaxci.geometry.boundary.classify_boundary` of a hexahedral mesh whose points are on the device.

    **Arguments:**

    - `mesh`: the `HexMesh` (its node count, point sets, face sets and held nodes are read; not its points).
    - `points`: the device coordinates ``(n_nodes, 3)`` whose geometry is classified (as the host function
      classifies ``mesh.points``).
    - `topology`, `unused`: `jaxci.geometry.device_topology.device_mesh_topology`'s results for the mesh.
    - `feature_angle`, `fix_boundary`, `fixed_nodes`, `fixed_sets`: as for `classify_boundary`.

    **Returns:** the `BoundaryInfo` ``classify_boundary(m, ...)`` returns for a mesh ``m`` with these points,
    with its `classes` (`jaxci.geometry.boundary.NodeClasses`, O(boundary)). Moves host <- device: the 6 bounds
    and the boundary nodes' coordinates; host -> device: the boundary nodes' indices. Raises `ValueError` for a
    mesh that is not `hexahedral` or whose node count is not the points'.
    """
    if not hexahedral(mesh):
        raise ValueError("device_classify_boundary: the device path is for meshes of linear hexahedra only; "
                         "classify_boundary handles the others")
    if mesh.n_nodes != points.shape[0]:
        raise ValueError(f"device_classify_boundary: the mesh has {mesh.n_nodes} nodes, the points "
                         f"{points.shape[0]}")
    with enable_x64():
        coords = _boundary_points(points, topology.nodes)
        frame = device_unit_frame(points)
    return classify_boundary(mesh, feature_angle=feature_angle, fix_boundary=fix_boundary, fixed_nodes=fixed_nodes,
                             fixed_sets=fixed_sets, topology=topology, points=coords, frame=frame, unused=unused)


@program
@functools.partial(jax.jit, static_argnames=("n_interior", "dtype", "per_face"))
def _per_node(points, nodes, node_class, group, surf, edge, quad_cand, face_patch, *, n_interior: int, dtype,
              per_face: bool):
    """The per-node arrays of `Constraints` from the classes of the listed `nodes` (every other node INTERIOR),
    and the per-triangle ones from the per-face ones (`quad_cand` ``(ns, K)``: the candidate faces of each
    surface node; `face_patch` ``(n_faces,)``, or without `per_face` the triangles' already; 4 triangles per
    face): ``(x_orig, node_class, group, row, interior_nodes, surface_cand, triangle_patch)``."""
    n = points.shape[0]
    cls = jnp.zeros(n, jnp.int32).at[nodes].set(node_class)
    grp = jnp.full(n, -1, jnp.int32).at[nodes].set(group)
    row = jnp.zeros(n, jnp.int32).at[surf].set(jnp.arange(surf.shape[0], dtype=jnp.int32))
    row = row.at[edge].set(jnp.arange(edge.shape[0], dtype=jnp.int32))
    interior = first_true(cls == INTERIOR, n_interior)  # a sort: jnp.nonzero compiles 7 times slower
    tri_cand = (4 * quad_cand[:, :, None] + jnp.arange(4, dtype=jnp.int32)).reshape(quad_cand.shape[0], -1)
    return points.astype(dtype), cls, grp, row, interior, tri_cand, jnp.repeat(face_patch, 4 if per_face else 1)


def device_constraints(points, info: BoundaryInfo, *, dtype=None) -> tuple[Constraints, BoundaryTables]:
    """`jaxci.geometry.projection.build_constraints` of the mesh whose points are on the device.

    **Arguments:**

    - `points`: the device coordinates ``(n_nodes, 3)``: the original geometry (float64 for the host
      function's tables; see the module docstring).
    - `info`: its `BoundaryInfo` (`device_classify_boundary`; with `classes`, else derived: O(n_nodes)).
    - `dtype`: float dtype of the geometry arrays; default JAX's default float. Keyword only argument.

    **Returns:** ``(constraints, tables)``: the `Constraints` on the device, equal to ``build_constraints(m,
    info, dtype=dtype)`` for a mesh ``m`` with these points; and its tables in float64 on the host
    (`BoundaryTables`: what `project_boundary` searches). Moves host <- device: the coordinates of the boundary
    nodes (and of the other CORNER nodes); host -> device: the classes of those nodes and the tables.
    """
    dtype = np.dtype(jnp.result_type(float) if dtype is None else dtype)
    c = info.boundary_classes
    of = {k: c.node_class == k for k in (SURFACE, EDGE, CORNER)}
    surf, edge, corner = (c.nodes[of[k]] for k in (SURFACE, EDGE, CORNER))
    faces, fedges = info.topology.faces, info.feature_edges
    need = sorted_unique(np.concatenate([faces.ravel(), fedges.ravel(), c.nodes]).astype(np.int64))
    with enable_x64():  # the dtypes as given (float64 tables too)
        coords = _boundary_points(points, need)
        tables = boundary_tables(need, coords, faces, info.face_patch, fedges, info.edge_curve, surf,
                                 c.patch_id[of[SURFACE]], edge, c.curve_id[of[EDGE]], corner)
        group = np.where(of[SURFACE], c.patch_id, np.where(of[EDGE], c.curve_id, -1))
        i32 = dict(nodes=c.nodes, node_class=c.node_class, group=group, surf=surf, edge=edge, corner=corner)
        # the 4 triangles of each face are expanded on the device: their candidates (4 per candidate face: 15 MB
        # at 10^6 hexahedra, against 4 MB of faces) and patches
        if len(faces):
            i32["quad_cand"], i32["face_patch"] = tables.surface_cand[:, ::4] // 4, info.face_patch
        else:  # `boundary_tables`' placeholders: one candidate, one triangle of patch -1
            i32["quad_cand"], i32["face_patch"] = np.zeros((1, 1), np.int32), tables.triangle_patch
        i32 = {k: np.asarray(v, dtype=np.int32) for k, v in i32.items()}
        tab = {k: np.asarray(v, dtype=np.int32 if v.dtype.kind in "iu" else dtype)
               for k, v in ((k, getattr(tables, k)) for k in TABLE_FIELDS if k not in ("surface_cand",
                                                                                       "triangle_patch"))}
        up, tab = to_device((i32, tab))
        x_orig, node_class, grp, row, interior, tab["surface_cand"], tab["triangle_patch"] = _per_node(
            points, up["nodes"], up["node_class"], up["group"], up["surf"], up["edge"], up["quad_cand"],
            up["face_patch"], n_interior=int(points.shape[0]) - len(c.nodes), dtype=dtype, per_face=bool(len(faces)))
    cons = Constraints(x_orig=x_orig, node_class=node_class, group=grp, row=row, interior_nodes=interior,
                       surface_nodes=up["surf"], edge_nodes=up["edge"], corner_nodes=up["corner"], **tab)
    return cons, tables


@program
@jax.jit
def _take(points, surf, edge):
    return points[surf], points[edge]


@program
@jax.jit
def _put(points, surf, ps, edge, pe, corner, pc):
    return points.astype(ps.dtype).at[surf].set(ps).at[edge].set(pe).at[corner].set(pc)


def project_boundary(constraints: Constraints, tables: BoundaryTables, points, flats=None):
    """`jaxci.geometry.projection.project_np` of device points, searching on the host for the boundary nodes only.

    **Arguments:** `constraints`, `tables`: `device_constraints`' results; `points`: device coordinates
    ``(n_nodes, 3)``; `flats` (optional): the flat regions of the surface nodes, ``(origin, normal, radius)``
    device float64 arrays ``(n_nodes, 3)`` (the original coordinates), ``(n_surface, 3)`` and ``(n_surface,)``
    (the planar rings of `jaxci.optim.device_stars.surface_planes`, as `jaxci.interface.methods.Problem` holds
    them; radius 0: none). A surface node whose projection onto the
    plane of its flat region stays inside it (0.999 of its radius, as the parametrisation's shortcut) is projected
    there, on the device: that is its nearest point on its patch; the others, and the edge nodes, are searched.

    **Returns:** the projected device coordinates ``(n_nodes, 3)`` in the dtype of `points` (float64 with
    `flats`): the SURFACE and
    EDGE nodes at the nearest points of their patch and curve (`project_on_groups`, float64, then rounded to
    that dtype), the CORNER nodes at their original positions, the others unchanged; equal to ``project_np``
    of the points for float64 points (to rounding, where `flats` projects a node onto its plane). Moves host <-
    device the searched nodes' coordinates (and with `flats` one flag a surface node), host -> device their
    projections and the corners' positions.
    """
    with enable_x64():
        dt = np.dtype(np.float64 if flats is not None else points.dtype)
        surf, edge = constraints.surface_nodes, constraints.edge_nodes
        sgroup = tables.surface_group
        if flats is not None:
            points, off = _flat_project(as_float64(points), surf, *flats)
            rows = np.flatnonzero(to_host(off))  # the surface nodes left to search: O(boundary) flags down
            sgroup = sgroup[rows]
            # padded to their size class (repeats of the last row: the same value written twice), so that the
            # programs below are compiled for a few sizes only
            surf = _rows(surf, to_device(_padded(rows, bucket(len(rows))), np.int32))
        xs, xe = to_host(_take(points, surf, edge))
        ps, pe = project_on_groups(tables, xs[: len(sgroup)], sgroup, xe, tables.edge_group)
        if flats is not None:
            ps = _padded(ps, len(xs))
        ps, pe, pc = to_device(tuple(np.asarray(a, dtype=dt) for a in (ps, pe, tables.corner_points)))
        return _put(points, surf, ps, edge, pe, constraints.corner_nodes, pc)


def _padded(a: np.ndarray, n: int) -> np.ndarray:
    """`a` with its last row repeated up to `n` rows (an empty `a` stays empty)."""
    return np.pad(a, [(0, n - len(a))] + [(0, 0)] * (a.ndim - 1), mode="edge") if len(a) else a


@program
@jax.jit
def _flat_project(points, surf, origin, normal, radius):
    """The surface nodes projected onto the planes of their flat regions where they stay inside them (float64),
    and the flags of the others ``(n_surface,)``."""
    x, o = points[surf], origin[surf]
    p = x - jnp.sum((x - o) * normal, axis=1)[:, None] * normal
    inside = (radius > 0) & (jnp.sum((p - o) ** 2, axis=1) < (0.999 * radius) ** 2)
    return points.at[surf].set(jnp.where(inside[:, None], p, x)), ~inside


@program
@jax.jit
def as_float64(points):
    """`points` in float64, on the device (call inside ``enable_x64``)."""
    return points.astype(jnp.float64)
