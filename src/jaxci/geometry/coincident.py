"""Coincident nodes that move as one: an unmerged interface smoothed without being fixed, written back unmerged.

Nodes at one point (`jaxci.mesh.HexMesh.coincident_nodes`: two parts meshed apart and written into one file, a
paver's seam) would drift apart if each moved on its own. `join_coincident` makes one unknown of each coincident
set: the smoothing runs on the mesh with each set merged into one node (`jaxci.mesh.merge_coincident`), and
every member of a set that moved is given the set's new position (`Joined.expand`); the file keeps its nodes,
ids and the interface.

How a set may move is decided on the UNMERGED mesh (`joined_info`), so that the interface stays where it is:
each part's side of it is a boundary surface there, and a member on it slides on that surface. The set takes
the most constrained class of its members (interior < surface < edge < corner) with that member's patch or
curve, provided the other members' constraints agree with it (surface members' normals and edge members'
tangents parallel within the feature angle, an edge member's tangent in a surface member's plane); else the
set is fixed. A node the user fixes fixes its set.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import MeshError
from ..mesh import HexMesh
from .boundary import CLASS_NAMES, CORNER, EDGE, SURFACE, BoundaryInfo, face_normals
from .topology import components


@dataclasses.dataclass(frozen=True)
class Joined:
    """A mesh with its coincident sets merged (`join_coincident`).

    - `mesh`: the merged mesh (`jaxci.mesh.merge_coincident`; same cells, in the same order).
    - `node_of`: ``(n,)`` the merged node of every node of the original.
    - `members`: sorted nodes of the original that are in a coincident set.
    - `sets`: how many sets.
    """

    mesh: HexMesh
    node_of: np.ndarray
    members: np.ndarray
    sets: int

    def note(self, original: HexMesh) -> str:
        """The sentence of the run's notes."""
        a = original.node_label(int(self.members[0]))
        first = self.members[self.node_of[self.members] == self.node_of[self.members[0]]]
        b = original.node_label(int(first[-1]))
        return (f"{len(self.members)} coincident nodes in {self.sets} sets (first: nodes {a} and {b}) move as one "
                f"node each, on the interface they lie on, and are written back unmerged (fixed_nodes holds them; "
                f"--merge-coincident merges them in the output)")

    def expand(self, original_points: np.ndarray, merged_start: np.ndarray, merged: np.ndarray) -> np.ndarray:
        """The original's coordinates after smoothing: each member of a set whose merged node moved (`merged`
        differs from `merged_start`) at the set's new position; every other node as in `original_points`."""
        out = np.array(original_points, dtype=np.float64)
        moved = (np.asarray(merged) != np.asarray(merged_start)).any(axis=1)[self.node_of]
        out[moved] = np.asarray(merged, np.float64)[self.node_of[moved]]
        return out

    def unjoin(self, original: HexMesh, solved: HexMesh, points: np.ndarray, res):
        """``(points, result)`` of `jaxci.smooth` on the merged mesh `solved` (`points` its coordinates, `res` its
        `jaxci.interface.smooth.SmoothResult`) taken back to `original` (the same frame): `expand`ed points, node
        classes and counts per original node, node counts in the reports, and the worst elements' limits naming the
        sets."""
        from ..cells import element_blocks

        x = self.expand(original.points, solved.points, points)
        node_class = None if res.node_class is None else np.asarray(res.node_class)[self.node_of]
        boundary = res.boundary
        if node_class is not None and boundary:
            c = np.bincount(node_class, minlength=4)
            boundary = {name: int(c[i]) for i, name in enumerate(CLASS_NAMES)}
        after = res.after
        if after.worst_elements is not None:
            held = np.zeros(len(solved.points), bool)
            held[self.node_of[self.members]] = True
            blocks = element_blocks(solved)
            first = np.empty(len(solved.points), np.int64)  # each merged node's lowest original node
            first[self.node_of[::-1]] = np.arange(len(self.node_of))[::-1]
            worst = []
            for w in after.worst_elements:
                extra = ["coincident nodes"] if held[blocks[w["type"]][w["index"]]].any() else []
                worst.append({**w, "nodes": first[np.asarray(w["nodes"], np.int64)].tolist(),
                              "limits": list(dict.fromkeys([*w["limits"], *extra]))})
            after = dataclasses.replace(after, worst_elements=tuple(worst))
        n = original.n_nodes
        return x, dataclasses.replace(res, node_class=node_class, boundary=boundary,
                                      before=dataclasses.replace(res.before, n_nodes=n),
                                      after=dataclasses.replace(after, n_nodes=n))


def join_coincident(mesh: HexMesh) -> Joined | None:
    """`Joined` of `mesh`, or None where it has no coincident nodes or where merging a set would make a cell
    repeat a node (the nodes of one cell at one point: that cell is left as it is, the sets fixed)."""
    from ..mesh import merge_coincident
    from ..mesh.coincident import coincident_groups

    pairs = mesh.coincident_nodes()
    if not len(pairs):
        return None
    target = coincident_groups(mesh.n_nodes, pairs)
    for b in mesh.cells:  # a cell with two nodes of one set would collapse
        t = target[np.asarray(b.data)]
        if t.shape[1] > 1 and (np.sort(t, axis=1)[:, 1:] == np.sort(t, axis=1)[:, :-1]).any():
            return None
    try:
        merged = merge_coincident(mesh)
    except MeshError:
        return None
    keep = target == np.arange(mesh.n_nodes)
    node_of = (np.cumsum(keep) - 1)[target]
    members = np.flatnonzero(np.bincount(target, minlength=mesh.n_nodes)[target] > 1)
    return Joined(merged, node_of, members, int(len(np.unique(target[members]))))


def joined_info(joined: Joined, info: BoundaryInfo, points: np.ndarray) -> BoundaryInfo:
    """The classification of `joined.mesh` from `info`, that of the original mesh at `points` (see the module
    docstring): the original's boundary faces, feature edges and patches renumbered to the merged nodes, each set
    of the class, patch and curve of its most constrained member, or fixed where its members disagree."""
    node_of = joined.node_of
    m = len(joined.mesh.points)
    cls = np.asarray(info.node_class)
    # per merged node, its most constrained member (the lowest-numbered of them): the first of its run when
    # sorted by merged node, then class (descending), then index
    order = np.lexsort((np.arange(len(cls)), -cls.astype(np.int64), node_of))
    head = np.ones(len(order), bool)
    head[1:] = node_of[order][1:] != node_of[order][:-1]
    rep = np.empty(m, np.int64)
    rep[node_of[order][head]] = order[head]
    new_cls = cls[rep].copy()
    patch = np.asarray(info.patch_id)[rep].copy()
    curve = np.asarray(info.curve_id)[rep].copy()
    disagree = _disagreeing_sets(joined, info, points)
    new_cls[disagree] = CORNER
    patch[new_cls != SURFACE] = -1
    curve[new_cls != EDGE] = -1
    # feature edges: each side of an interface has its own copy of a curve along it; one curve of them, each
    # segment once (a node on a curve has its two segments)
    fe = np.sort(node_of[np.asarray(info.feature_edges, np.int64)], axis=1)
    edge_curve = np.asarray(info.edge_curve, np.int64)
    if len(fe):
        _, first_of, inverse = np.unique(fe, axis=0, return_index=True, return_inverse=True)
        same = edge_curve[first_of][inverse.ravel()]  # the curve of each segment's first copy
        n_c = max(int(info.n_curves), int(edge_curve.max(initial=-1)) + 1, 1)
        _, joined_curve = components(n_c, edge_curve, same)  # curves that share a segment are one
        keep = np.sort(first_of)
        fe, edge_curve = fe[keep], joined_curve[edge_curve[keep]]
        curve = np.where(curve >= 0, joined_curve[np.maximum(curve, 0)], -1)
    topo = info.topology
    remap_faces = dataclasses.replace(
        topo, faces=node_of[topo.faces], edges=np.sort(node_of[topo.edges], axis=1),
        nonmanifold_faces=np.where(topo.nonmanifold_faces >= 0, node_of[np.maximum(topo.nonmanifold_faces, 0)], -1))
    return dataclasses.replace(info, node_class=new_cls.astype(cls.dtype), patch_id=patch.astype(np.int32),
                               curve_id=curve.astype(np.int32), topology=remap_faces, feature_edges=fe, classes=None,
                               edge_curve=edge_curve.astype(np.asarray(info.edge_curve).dtype))


def _disagreeing_sets(joined: Joined, info: BoundaryInfo, points: np.ndarray) -> np.ndarray:
    """The merged nodes of the sets whose members' boundary constraints disagree (module docstring)."""
    cos_t = float(np.cos(np.radians(info.feature_angle)))
    cls = np.asarray(info.node_class)
    members = joined.members
    faces = info.topology.faces
    pts = np.asarray(points, np.float64)
    normal = np.zeros((len(cls), 3))
    if len(faces):  # each surface member's normal over its own patch's faces
        fn = face_normals(pts, faces)
        own = np.asarray(info.face_patch)[:, None] == np.asarray(info.patch_id)[faces]
        for j in range(faces.shape[1]):
            sel = own[:, j]
            np.add.at(normal, faces[sel, j], fn[sel])
    tangent = np.zeros((len(cls), 3))
    fe = np.asarray(info.feature_edges, np.int64)
    edge_members = members[cls[members] == EDGE]
    if len(fe) and len(edge_members):  # each edge member's tangent: from one neighbour on its curve to the other
        ends = np.concatenate([fe[:, 0], fe[:, 1]])
        other = np.concatenate([fe[:, 1], fe[:, 0]])
        by = np.argsort(ends, kind="stable")
        lo = np.searchsorted(ends[by], edge_members, side="left")
        hi = np.searchsorted(ends[by], edge_members, side="right")
        for v, a, b in zip(edge_members, lo, hi, strict=True):
            nb = other[by[a:b]]
            if len(nb) == 2:
                tangent[v] = pts[nb[1]] - pts[nb[0]]

    def unit(v):
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)

    bad = []
    node_of = joined.node_of
    for v in np.unique(node_of[members]):
        group = members[node_of[members] == v]
        c = cls[group]
        surf, edge = group[c == SURFACE], group[c == EDGE]
        ns, ts = unit(normal[surf]), unit(tangent[edge])
        ok = True
        if len(ns) > 1:
            ok &= bool((np.abs(ns @ ns[0]) >= cos_t).all())
        if len(ts) > 1:
            ok &= bool((np.abs(ts @ ts[0]) >= cos_t).all())
        if len(ns) and len(ts):
            ok &= bool((np.abs(ts @ ns[0]) <= np.sqrt(1.0 - cos_t * cos_t)).all())
        if not ok:
            bad.append(v)
    return np.asarray(bad, np.int64)
