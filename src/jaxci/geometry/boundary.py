"""Classification of the nodes of a hex-dominant mesh by how they may move: interior, surface, edge or corner.

The boundary is the set of faces (quadrilaterals and triangles) used by exactly one volume cell of any type
(`jaxci.geometry.topology`): a face a hexahedron shares with a wedge, pyramid or tetrahedron is interior. A boundary
edge is a *feature edge* when the unit normals of its two boundary faces differ by more than the feature angle, or
when it does not have exactly two boundary faces (a non-manifold or open edge), or when its two boundary faces lie
in different face sets of the mesh (`HexMesh.face_sets`, Exodus side sets: the border of the surface a solver's
load or condition is given on stays where it is). Then, per node:

- CORNER (fixed): 1 or 3+ feature edges meet at it (a curve ends or curves meet), or 2 meet at an angle: the
  direction of the curve turns by more than the feature angle; also a non-manifold boundary vertex (two or more
  separate fans of boundary faces), a node of a face shared by three or more cells, and every node the
  user fixes.
- EDGE (slides on its feature curve): exactly 2 feature edges, nearly aligned.
- SURFACE (slides on its patch): a boundary node with no feature edge.
- INTERIOR (free): the rest.

*Patches* are the connected sets of boundary faces that meet across non-feature edges; *curves* are the
connected chains of feature edges that meet at EDGE nodes (a circle without corners is one closed curve).
Patches and curves are computed from the geometry and the face sets; fixing nodes afterwards does not split them.

Nodes of hexahedra and of linear wedges, pyramids and tetrahedra are classified alike and move. Nodes used by
no volume cell are fixed, and so are the mesh's held nodes (`HexMesh.held_nodes`: those of an Exodus shell or
beam block), and the nodes of QUADRATIC wedges, pyramids and tetrahedra (midside nodes
given, or meshio's ``wedge15``/``pyramid13``/``tetra10``/``hexahedron20`` blocks;
`jaxci.cells.fixed_nodes`), with a note. (Quadratic hexahedra are hexahedra with midside nodes: their corner
nodes move and the midside nodes follow, `jaxci.mesh.HexMesh.with_points`.) A broken boundary (open or non-manifold) is
reported with `warnings.warn` and in `BoundaryInfo.notes`, never raised: such edges and vertices become features and
corners.
"""

from __future__ import annotations

import dataclasses
import types
import warnings
from collections.abc import Sequence

import numpy as np

from ..cells import QUADRATIC_TYPES, volume_cells
from ..cells import fixed_nodes as fixed_cell_nodes
from ..errors import MeshError
from ..mesh import HexMesh, as_hex_mesh, to_unit, unit_frame
from ..mesh.sorting import sorted_unique
from .topology import BoundaryTopology, boundary_topology, components

#: Node classes (values of `BoundaryInfo.node_class`).
INTERIOR = 0
SURFACE = 1
EDGE = 2
CORNER = 3

#: Names of the node classes, indexed by class.
CLASS_NAMES = ("interior", "surface", "edge", "corner")


@dataclasses.dataclass(frozen=True, eq=False)
class NodeClasses:
    """The classification of the nodes that are not INTERIOR, in O(boundary) (`BoundaryInfo.classes`): every
    node not listed is INTERIOR, of no patch and no curve.

    **Arguments:** `nodes` sorted int64 ``(k,)``; `node_class` int8 ``(k,)`` (`SURFACE`, `EDGE` or `CORNER`);
    `patch_id`, `curve_id` int32 ``(k,)`` (-1 but for a SURFACE, an EDGE node).
    """

    nodes: np.ndarray
    node_class: np.ndarray
    patch_id: np.ndarray
    curve_id: np.ndarray

    @classmethod
    def of(cls, node_class: np.ndarray, patch_id: np.ndarray, curve_id: np.ndarray) -> NodeClasses:
        """The `NodeClasses` of per-node arrays ``(n_nodes,)`` (an O(n_nodes) pass)."""
        nodes = np.flatnonzero(np.asarray(node_class) != INTERIOR)
        return cls(nodes, np.asarray(node_class)[nodes].astype(np.int8), np.asarray(patch_id)[nodes].astype(np.int32),
                   np.asarray(curve_id)[nodes].astype(np.int32))


@dataclasses.dataclass(frozen=True, eq=False)
class BoundaryInfo:
    """How every node of a mesh may move, with the patches and feature curves of its boundary.

    **Arguments:**

    - `node_class`: int8 array of shape ``(n_nodes,)``, one of `INTERIOR`, `SURFACE`, `EDGE`, `CORNER`.
    - `patch_id`: int32 array of shape ``(n_nodes,)``: the patch of each SURFACE node, -1 for other nodes.
    - `curve_id`: int32 array of shape ``(n_nodes,)``: the curve of each EDGE node, -1 for other nodes.
    - `topology`: the `BoundaryTopology` (boundary faces and edges) it was computed from.
    - `face_patch`: int32 array of shape ``(n_faces,)``, the patch of each boundary face.
    - `edge_is_feature`: bool array of shape ``(n_edges,)`` over `topology.edges`.
    - `feature_edges`: int64 array of shape ``(n_feature_edges, 2)``, the feature edges (node pairs).
    - `edge_curve`: int32 array of shape ``(n_feature_edges,)``, the curve of each feature edge.
    - `n_patches`, `n_curves`: numbers of patches and curves.
    - `feature_angle`: the feature angle in degrees it was computed with.
    - `notes`: sentences about what was unusual (open or non-manifold boundary, fixed non-hex nodes, ...).
    - `classes`: the same classification restricted to the nodes that are not INTERIOR (`NodeClasses`), or None
      (then `boundary_classes` derives it from the per-node arrays). `classify_boundary` and `fix_nodes` keep
      the two in agreement; whoever replaces the per-node arrays replaces it too (or sets None).
    """

    node_class: np.ndarray
    patch_id: np.ndarray
    curve_id: np.ndarray
    topology: BoundaryTopology
    face_patch: np.ndarray
    edge_is_feature: np.ndarray
    feature_edges: np.ndarray
    edge_curve: np.ndarray
    n_patches: int
    n_curves: int
    feature_angle: float
    notes: tuple[str, ...] = ()
    classes: NodeClasses | None = None

    @property
    def n_nodes(self) -> int:
        return int(self.node_class.shape[0])

    @property
    def boundary_classes(self) -> NodeClasses:
        """`classes`, or (None) the `NodeClasses` of the per-node arrays (an O(n_nodes) pass)."""
        if self.classes is not None:
            return self.classes
        return NodeClasses.of(self.node_class, self.patch_id, self.curve_id)

    def nodes_of(self, cls: int) -> np.ndarray:
        """Sorted indices of the nodes of class `cls`, int64 array."""
        if cls != INTERIOR and self.classes is not None:
            return self.classes.nodes[self.classes.node_class == cls]
        return np.flatnonzero(self.node_class == cls)

    @property
    def counts(self) -> dict[str, int]:
        """Number of nodes per class, by name (``{"interior": ..., "surface": ..., "edge": ..., "corner": ...}``)."""
        if self.classes is not None:
            c = np.bincount(self.classes.node_class, minlength=4)
            c[INTERIOR] = self.n_nodes - len(self.classes.nodes)
        else:
            c = np.bincount(self.node_class, minlength=4)
        return {name: int(c[i]) for i, name in enumerate(CLASS_NAMES)}


def mesh_topology(mesh: HexMesh) -> BoundaryTopology:
    """`jaxci.geometry.topology.boundary_topology` of every volume cell of `mesh` (hexahedra, wedges, pyramids,
    tetrahedra; quadratic cells by their corner nodes)."""
    cells = non_hex_cells(mesh)
    hexes = mesh.hexes
    quad = [np.asarray(b.data)[:, :8] for b in mesh.cells if b.type in ("hexahedron20", "hexahedron27")
            and len(b.data)]
    if quad:  # meshio's quadratic hexahedra bound the volume too (after the hexahedra: face_hex stays valid)
        hexes = np.concatenate([hexes, *quad])
    return boundary_topology(hexes, mesh.n_nodes, cells or None)


def non_hex_cells(mesh: HexMesh) -> dict[str, np.ndarray]:
    """`jaxci.cells.volume_cells` of `mesh` but the hexahedra (linear and quadratic), without the copy of the
    hexahedra it would make (64 MB at 10^6 hexahedra)."""
    blocks = tuple(b for b in mesh.cells if QUADRATIC_TYPES.get(b.type, b.type) != "hexahedron")
    return volume_cells(types.SimpleNamespace(cells=blocks))  # it reads only the blocks


def face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted normals of faces, ``(x2 - x0) x (x3 - x1)`` (twice the area for a planar quadrilateral and for
    a triangle ``[a, b, c, c]``).

    **Arguments:** `points` of shape ``(n_nodes, 3)``; `faces` of shape ``(n_faces, 4)``.

    **Returns:** a float64 array of shape ``(n_faces, 3)``.
    """
    p = np.asarray(points, dtype=np.float64)
    return np.cross(p[faces[:, 2]] - p[faces[:, 0]], p[faces[:, 3]] - p[faces[:, 1]])


def unit_rows(v: np.ndarray) -> np.ndarray:
    """Rows of `v` scaled to unit length (zero rows stay zero)."""
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)


def _local_position(faces: np.ndarray, f: np.ndarray, node: np.ndarray) -> np.ndarray:
    """For each pair (face f[j], node[j]) with the node on the face, the node's position 0..3 in the face."""
    return np.argmax(faces[f] == node[:, None], axis=1)


def classify_boundary(
    mesh: HexMesh,
    *,
    feature_angle: float = 40.0,
    fix_boundary: bool = False,
    fixed_nodes: Sequence[int] | np.ndarray | None = None,
    fixed_sets: Sequence[str] = (),
    topology: BoundaryTopology | None = None,
    points: np.ndarray | None = None,
    frame: tuple[np.ndarray, float] | None = None,
    unused: np.ndarray | None = None,
) -> BoundaryInfo:
    """Classify every node of `mesh` as interior, surface, edge or corner (see this module's docstring).

    The work is O(boundary) but for what the last three arguments stand for when they are not given (the
    frame, the boundary nodes' coordinates, the nodes of no cell: O(mesh)) and the per-node arrays of the
    result (an ``np.full`` of each, then the boundary nodes written).

    **Arguments:**

    - `mesh`: the `HexMesh`; its current coordinates define the boundary geometry (unless `points` is given).
    - `feature_angle`: angle in degrees (0 < angle < 180) above which the normals of two boundary faces across an
      edge, or the directions of two feature edges at a node, make a feature. Keyword only argument.
    - `fix_boundary`: make every boundary node a corner (only interior nodes move). Keyword only argument.
    - `fixed_nodes`: indices of further nodes to fix. Keyword only argument.
    - `fixed_sets`: names of `mesh.point_sets` whose nodes are fixed. Keyword only argument.
    - `topology`: a precomputed `boundary_topology(mesh.hexes, mesh.n_nodes, others)` (`mesh_topology`, or
      `jaxci.geometry.device_topology.device_mesh_topology`). Keyword only argument.
    - `points`: the coordinates of the boundary nodes ``topology.nodes`` (sorted), shape ``(n_boundary_nodes,
      3)``, in place of ``mesh.points[topology.nodes]``. Keyword only argument.
    - `frame`: the ``(centre, scale)`` the angles are measured in (`jaxci.mesh.unit_frame`; scale-invariant
      but for rounding), default ``unit_frame(mesh.points)``. Keyword only argument.
    - `unused`: the sorted indices of the nodes no volume cell uses (they are fixed), default found from the
      mesh's cells. Keyword only argument.

    **Returns:** a `BoundaryInfo` (with its `classes`). Raises `MeshError` for a bad `feature_angle`, an
    out-of-range fixed node or an unknown point set; warns (`UserWarning`) about an open or non-manifold
    boundary.
    """
    mesh = as_hex_mesh(mesh, "classify_boundary")
    if isinstance(feature_angle, (bool, str)) or not isinstance(feature_angle, (int, float, np.integer, np.floating)) \
            or not 0.0 < float(feature_angle) < 180.0:
        raise MeshError(f"feature_angle must be in degrees strictly between 0 and 180, got {feature_angle!r}")
    if isinstance(fixed_sets, str):
        raise MeshError(f"fixed_sets must be a list of node set names, got the string {fixed_sets!r} (write "
                        f"[{fixed_sets!r}])")
    where = f"{mesh.source}: " if mesh.source else ""
    n = mesh.n_nodes
    fixed = np.zeros(0, dtype=np.int64) if fixed_nodes is None else np.asarray(fixed_nodes).ravel()
    if fixed.size and (fixed.dtype.kind not in "iu" or fixed.min() < 0 or fixed.max() >= n):
        raise MeshError(f"{where}fixed_nodes must be node indices in [0, {n}), got {fixed.tolist()[:10]}")
    for name in fixed_sets:
        if not isinstance(name, str) or name not in mesh.point_sets:
            known = ", ".join(sorted(mesh.point_sets)) or "none"
            raise MeshError(f"{where}fixed_sets: the mesh has no point set {name!r} (point sets: {known})")
    topo = mesh_topology(mesh) if topology is None else topology
    # the boundary nodes, numbered 0 .. m - 1 in increasing order (`local`): every array below is O(boundary)
    bnodes = topo.nodes
    local = np.searchsorted(bnodes, topo.faces)
    if points is None:
        points = mesh.points[bnodes]
    elif np.shape(points) != (len(bnodes), 3):
        raise ValueError(f"classify_boundary: points must be the coordinates of the {len(bnodes)} boundary nodes, "
                         f"shape ({len(bnodes)}, 3), got {np.shape(points)}")
    # normals and angles are scale-invariant; no overflow
    pts = to_unit(points, unit_frame(mesh.points) if frame is None else frame)
    geo = _boundary_classes(topo, bnodes, local, pts, mesh.face_sets, feature_angle)
    cls, patch, curve = geo.classes
    notes = list(geo.notes)
    for msg in notes:
        warnings.warn(f"{where}{msg}", stacklevel=2)
    if geo.n_border:
        notes.append(f"{geo.n_border} boundary edges on the borders of the mesh's {len(mesh.face_sets)} face "
                     f"sets (side sets) are feature edges: each set keeps its extent")

    # --- nodes that must not move
    if unused is None:
        used = np.zeros(n, dtype=bool)
        used[mesh.hexes.ravel()] = True
        for cells in non_hex_cells(mesh).values():
            used[cells.ravel()] = True
        unused = np.flatnonzero(~used)
    pinned = [np.asarray(unused, dtype=np.int64)]
    if mesh.held_nodes is not None and len(mesh.held_nodes):
        held = np.asarray(mesh.held_nodes, dtype=np.int64)
        pinned.append(held)
        notes.append(f"{len(np.unique(held))} nodes of cells that are not smoothed (shell, beam or sphere blocks) "
                     f"are held where they are")
    quadratic = fixed_cell_nodes(mesh)
    if len(quadratic):
        pinned.append(quadratic)
        notes.append(f"{len(quadratic)} nodes of quadratic non-hexahedral cells (wedge, pyramid, tetrahedron with "
                     f"midside nodes) are fixed")
    if fix_boundary:  # every boundary node (used by a cell, or pinned as unused anyway)
        cls[:] = CORNER
    pinned += [topo.nonmanifold_nodes, fixed.astype(np.int64)]
    pinned += [np.asarray(mesh.point_sets[name], dtype=np.int64).ravel() for name in fixed_sets]
    pinned = sorted_unique(np.concatenate(pinned))
    nodes = sorted_unique(np.concatenate([bnodes, pinned]))
    classes = NodeClasses(nodes, np.full(len(nodes), CORNER, np.int8), np.full(len(nodes), -1, np.int32),
                          np.full(len(nodes), -1, np.int32))
    at = np.searchsorted(nodes, bnodes)
    classes.node_class[at], classes.patch_id[at], classes.curve_id[at] = cls, patch, curve
    classes.node_class[np.searchsorted(nodes, pinned)] = CORNER
    classes.patch_id[classes.node_class != SURFACE] = -1
    classes.curve_id[classes.node_class != EDGE] = -1
    return BoundaryInfo(
        node_class=_dense(n, classes.nodes, classes.node_class, 0),
        patch_id=_dense(n, classes.nodes, classes.patch_id, -1),
        curve_id=_dense(n, classes.nodes, classes.curve_id, -1),
        topology=topo,
        face_patch=geo.face_patch,
        edge_is_feature=geo.feature,
        feature_edges=topo.edges[geo.feature],
        edge_curve=geo.edge_curve,
        n_patches=geo.n_patches,
        n_curves=geo.n_curves,
        feature_angle=float(feature_angle),
        notes=tuple(notes),
        classes=classes,
    )


def _dense(n: int, nodes: np.ndarray, values: np.ndarray, fill) -> np.ndarray:
    """An array ``(n,)`` of `values`' dtype: `values` at `nodes`, `fill` elsewhere."""
    out = np.full(n, fill, dtype=values.dtype)
    out[nodes] = values
    return out


def _boundary_classes(topo: BoundaryTopology, bnodes: np.ndarray, faces: np.ndarray, pts: np.ndarray, face_sets,
                      feature_angle: float) -> types.SimpleNamespace:
    """The geometric part of `classify_boundary`, on the boundary nodes `bnodes` (sorted, ``(m,)``) numbered
    0 .. m - 1: `faces` ``(n_faces, 4)`` are ``topo.faces`` so numbered, `pts` ``(m, 3)`` the nodes' coordinates
    (unit frame).

    **Returns:** a namespace: ``classes`` (class int8, patch int32, curve int32, each ``(m,)``), ``face_patch``,
    ``feature`` (over ``topo.edges``), ``edge_curve``, ``n_patches``, ``n_curves``, ``notes`` (about a broken
    boundary), ``n_border`` (feature edges on the borders of face sets)."""
    m = len(pts)
    edges = np.searchsorted(bnodes, topo.edges)  # the edges, so numbered
    n_faces = len(faces)
    cos_t = float(np.cos(np.radians(feature_angle)))
    notes: list[str] = []

    # --- feature edges
    valence = topo.edge_valence
    manifold = valence == 2
    ptr = topo.edge_face_ptr
    last = max(len(topo.edge_face) - 1, 0)
    fa = topo.edge_face[ptr[:-1]]  # first and (if any) second boundary face of each edge
    fb = topo.edge_face[np.minimum(ptr[:-1] + 1, last)]
    normal = unit_rows(face_normals(pts, faces))
    cos_e = np.einsum("ij,ij->i", normal[fa], normal[fb])
    feature = ~manifold | (cos_e < cos_t)
    sets = face_set_signature(topo.faces, face_sets)
    border = np.zeros_like(feature) if sets is None else manifold & (sets[fa] != sets[fb]) & ~feature
    feature |= border
    fedges = edges[feature]
    n_open = int(np.count_nonzero(valence % 2 == 1))
    n_nm_edges = int(np.count_nonzero((valence > 2) & (valence % 2 == 0)))

    # --- non-manifold vertices: face corners around a node connected across manifold edges
    me = np.flatnonzero(manifold)
    a_nodes = np.concatenate([edges[me, 0], edges[me, 1]])
    fa_m, fb_m = np.tile(fa[me], 2), np.tile(fb[me], 2)
    ca = 4 * fa_m + _local_position(faces, fa_m, a_nodes)  # a triangle's repeated node: its first position
    cb = 4 * fb_m + _local_position(faces, fb_m, a_nodes)
    tri = np.flatnonzero(faces[:, 3] == faces[:, 2])
    if len(tri):  # the repeated node of a triangle is one corner of it
        ca, cb = np.concatenate([ca, 4 * tri + 2]), np.concatenate([cb, 4 * tri + 3])
    _, corner_comp = components(4 * n_faces, ca, cb)
    node_comp = sorted_unique(faces.ravel() * np.int64(4 * n_faces) + corner_comp)  # distinct (node, fan) pairs
    nm_vertex = np.bincount(node_comp // max(4 * n_faces, 1), minlength=m) > 1

    # --- geometric node classes (every node here is on a boundary face)
    deg = np.bincount(fedges.ravel(), minlength=m)
    cls = np.full(m, SURFACE, dtype=np.int8)
    cls[deg == 2] = EDGE
    cls[(deg == 1) | (deg >= 3) | nm_vertex] = CORNER
    half_node = fedges.ravel()
    half_other = fedges[:, ::-1].ravel()
    half_edge = np.repeat(np.arange(len(fedges)), 2)
    by_node = np.argsort(half_node, kind="stable")
    hn, ho, he = half_node[by_node], half_other[by_node], half_edge[by_node]
    two = np.flatnonzero(np.diff(hn) == 0)
    two = two[cls[hn[two]] == EDGE]  # the pairs (two[j], two[j] + 1) are the two feature edges of an EDGE node
    v = hn[two]
    d_in = unit_rows(pts[v] - pts[ho[two]])
    d_out = unit_rows(pts[ho[two + 1]] - pts[v])
    sharp = np.einsum("ij,ij->i", d_in, d_out) < cos_t
    cls[v[sharp]] = CORNER

    # --- curves: feature edges joined at EDGE nodes
    joined = two[cls[v] == EDGE]
    n_curves, edge_curve = components(len(fedges), he[joined], he[joined + 1])
    curve_id = np.full(m, -1, dtype=np.int32)
    curve_id[hn] = edge_curve[he]

    # --- patches: faces joined across manifold non-feature edges
    smooth = np.flatnonzero(~feature)
    n_patches, face_patch = components(n_faces, fa[smooth], fb[smooth])
    patch_id = np.full(m, -1, dtype=np.int32)
    patch_id[faces.ravel()] = np.repeat(face_patch, 4)

    # --- broken boundaries
    if topo.n_nonmanifold_faces:
        notes.append(
            f"{topo.n_nonmanifold_faces} faces are shared by three or more cells (invalid mesh); they are "
            f"not boundary faces and their nodes are fixed"
        )
    if n_open:
        notes.append(
            f"open boundary: {n_open} boundary edges have an odd number of boundary faces; they are feature "
            f"edges and their curves are fixed at their ends"
        )
    if n_nm_edges:
        notes.append(
            f"non-manifold boundary: {n_nm_edges} boundary edges have 4 or more boundary faces (elements "
            f"touching along an edge); they are feature edges"
        )
    if nm_vertex.any():
        notes.append(
            f"non-manifold boundary: {int(nm_vertex.sum())} boundary nodes join separate fans of boundary faces "
            f"(elements touching at a vertex); they are fixed as corners"
        )
    return types.SimpleNamespace(classes=(cls, patch_id, curve_id), face_patch=face_patch, feature=feature,
                                 edge_curve=edge_curve, n_patches=n_patches, n_curves=n_curves, notes=notes,
                                 n_border=int(border.sum()))


def face_set_signature(faces: np.ndarray, face_sets) -> np.ndarray | None:
    """Per boundary face of `faces` ``(n_faces, 4)`` (a triangle repeats its last node), an int64 that differs
    between faces held by different sets of `face_sets` (name -> ``(k, 4)`` faces, matched by their nodes in any
    order; 0: in none); None without face sets. Up to 62 sets are bits of it; more are mixed in by fixed random
    64-bit keys (a collision is vanishingly unlikely)."""
    if not face_sets or not len(faces):
        return None
    keys = np.random.default_rng(0).integers(1, 2**62, size=len(face_sets), dtype=np.int64)
    order = np.sort(faces, axis=1)
    index = {tuple(r): i for i, r in enumerate(order.tolist())}
    sig = np.zeros(len(faces), dtype=np.int64)
    for k, f in enumerate(face_sets.values()):
        rows = [index.get(tuple(r)) for r in np.sort(np.asarray(f, dtype=np.int64), axis=1).tolist()]
        hit = np.unique(np.asarray([r for r in rows if r is not None], dtype=np.int64))
        sig[hit] ^= np.int64(1 << k) if k < 62 else keys[k]
    return sig


def releasable_feature_nodes(mesh: HexMesh, info: BoundaryInfo, cells_nodes: np.ndarray,
                             keep_fixed: np.ndarray) -> np.ndarray:
    """The nodes among `cells_nodes` that the boundary's geometry alone fixes or ties to a curve (class CORNER or
    EDGE in `info`, on a boundary face, not in `keep_fixed`, not a non-manifold or quadratic-cell node): those
    ``--untangle-boundary`` lets slide on a surface (`slide_on_surface`). Sorted int64."""
    faces = info.topology.faces
    on_face = np.zeros(info.n_nodes, bool)
    on_face[faces.ravel()] = True
    cls = np.asarray(info.node_class)
    ok = on_face & ((cls == CORNER) | (cls == EDGE))
    ok[np.asarray(keep_fixed, dtype=np.int64)] = False
    ok[np.asarray(info.topology.nonmanifold_nodes, dtype=np.int64)] = False
    ok[fixed_cell_nodes(mesh)] = False
    nodes = np.unique(np.asarray(cells_nodes, dtype=np.int64))
    return nodes[ok[nodes]]


def fix_nodes(info: BoundaryInfo, nodes: np.ndarray) -> BoundaryInfo:
    """`info` with `nodes` fixed (class CORNER), as `classify_boundary`'s `fixed_nodes` would fix them."""
    return _reclassify(info, nodes, CORNER, -1)


def _reclassify(info: BoundaryInfo, nodes: np.ndarray, cls: int, patch) -> BoundaryInfo:
    """`info` with `nodes` of class `cls`, on patch `patch` (scalar or per node), on no curve."""
    nodes = np.asarray(nodes, dtype=np.int64)
    node_class, patch_id, curve_id = np.array(info.node_class), np.array(info.patch_id), np.array(info.curve_id)
    node_class[nodes], patch_id[nodes], curve_id[nodes] = cls, patch, -1
    classes = None
    if info.classes is not None:  # the listed nodes and these (none of them INTERIOR)
        at = sorted_unique(np.concatenate([info.classes.nodes, nodes]))
        classes = NodeClasses(at, node_class[at], patch_id[at], curve_id[at])
    return dataclasses.replace(info, node_class=node_class, patch_id=patch_id, curve_id=curve_id, classes=classes)


def slide_on_surface(info: BoundaryInfo, nodes: np.ndarray) -> BoundaryInfo:
    """`info` with the boundary `nodes` made SURFACE nodes, each of the patch of the lowest-numbered boundary face
    around it: a corner or an edge node then slides on that surface (projected onto its original faces) instead
    of staying put or on its curve. What ``--untangle-boundary`` does for the untangling stage."""
    nodes = np.asarray(nodes, dtype=np.int64)
    faces = info.topology.faces
    first = np.full(info.n_nodes, len(faces), dtype=np.int64)
    np.minimum.at(first, faces.ravel(), np.repeat(np.arange(len(faces)), faces.shape[1]))
    if len(nodes) and (first[nodes] >= len(faces)).any():
        raise ValueError("slide_on_surface: a node is on no boundary face")
    return _reclassify(info, nodes, SURFACE, np.asarray(info.face_patch)[first[nodes]])
