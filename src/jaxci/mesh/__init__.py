"""The hexahedral mesh model: node coordinates, VTK-ordered hexahedra, and whatever else the file carried.

Node order of a hexahedron is VTK's (VTK_HEXAHEDRON, cell type 12): nodes 0,1,2,3 go around one face, 4,5,6,7
around the opposite face, node i+4 joined to node i, and 0->1->2->3 turns counter-clockwise seen from the side
of 4..7 (unit cube: P0=(0,0,0), P1=(1,0,0), P2=(1,1,0), P3=(0,1,0), P4..P7 the same at z=1).

A `HexMesh` keeps every cell block, point/cell data array and named set it was read with, so that a smoothed
mesh is written back unchanged except for the node coordinates. Smoothing never changes connectivity: use
`HexMesh.with_points` to make the moved mesh.

**Quadratic cells** (ANSYS SOLID186 20-node bricks and their wedge/pyramid/tetrahedron forms, SOLID187 10-node
tetrahedra) are held as their linear cell (`CellBlock.data`, the corner nodes: what is measured and smoothed) plus
`CellBlock.midside`: the node on each edge, in the edge order of `EDGES` (VTK's quadratic cells and ANSYS's
midside order Q R S T U V W X Y Z A B of a brick), -1 where an edge has none (ANSYS allows dropping midside
nodes). A midside node belongs to one edge: two cells that share it must share that edge, and no cell may use it as
a corner (checked on construction). `HexMesh.with_points` moves every midside node with its edge: to the midpoint of
the edge's moved corner nodes, plus the offset it had from the old midpoint when that edge was curved
(`jaxci.mesh.midside`).

The mesh model's parts live in their own modules, re-exported here: `jaxci.mesh.blocks` (`CellBlock`),
`jaxci.mesh.frame` (the unit frame), `jaxci.mesh.coincident` (coincident nodes), `jaxci.mesh.midside` (midside
nodes).
"""

from __future__ import annotations

import dataclasses
import os
import warnings
import weakref
from collections.abc import Mapping, Sequence

import numpy as np

from ..cells import corner_determinants
from ..errors import MeshError
from .blocks import MIRROR_HEX as MIRROR_HEX
from .blocks import NODES_PER_CELL, CellBlock, block_label, int_array, mirrored_block
from .coincident import COINCIDENT_TOLERANCE, coincident_groups, coincident_pairs
from .coincident import close_pairs as close_pairs
from .frame import from_unit as from_unit
from .frame import to_unit, unit_frame
from .midside import MIDPOINT_TOLERANCE as MIDPOINT_TOLERANCE
from .midside import check_midside, midside_table, place_midside

#: A node farther than this many median edge lengths from the mesh's median node is refused on construction:
#: across such a range float64 keeps no digits of an element's shape (a stray node, or mixed units).
MAX_COORDINATE_RANGE = 1e12

#: The type of a mesh's connectivity (every `CellBlock`'s data once `HexMesh` has checked it): int32, half the
#: bytes of int64 (6.6 MB of cube60_pert's 216,000 hexahedra, held through every phase of a run); the C kernels take
#: it as it is. A key made of two node numbers (``low * n + high``) is made in int64.
CONN_DTYPE = np.int32


@dataclasses.dataclass(frozen=True, eq=False)
class HexMesh:
    """A (hex-dominant) volume mesh whose hexahedra jaxci smooths.

    **Arguments:**

    - `points`: node coordinates, float array of shape ``(n_nodes, 3)``.
    - `cells`: the cell blocks in file order; at least one block of type ``"hexahedron"`` in VTK node order.
    - `point_data`: name -> array with leading axis ``n_nodes``.
    - `cell_data`: name -> list with one array per cell block.
    - `point_sets`: name -> array of node indices (Abaqus NSET, Gmsh physical group on nodes, ANSYS component).
    - `cell_sets`: name -> list with one index array per cell block (meshio's convention).
    - `field_data`: anything else the file carried (Gmsh physical names).
    - `node_ids`: optional external node ids, shape ``(n_nodes,)`` (ANSYS / Abaqus numbering).
    - `source`: the path it was read from, used in messages.
    - `face_sets`: name -> ``(k, 4)`` node indices of faces (Exodus side sets; a triangle repeats its last node):
      where they lie on the boundary, `jaxci.geometry.boundary.classify_boundary` keeps the border of each set a
      feature curve, so that the surfaces a solver's loads and conditions are given on keep their extent.
    - `held_nodes`: indices of nodes that cells jaxci does not smooth tie to their place (an Exodus shell, beam or
      sphere block): smoothing never moves them.
    - `input_files`: every other file the reader opened to build it (an Abaqus ``*INCLUDE``, an XDMF file's HDF5
      data, ...), as given or resolved by the reader; with `source`, the files a write must never replace.
    - `hex_mirrored`: True when the file stored every hexahedron left-handed and they were mirrored on
      construction; `jaxci.io.write_mesh` mirrors them back so the file keeps its convention.
    - `fix_orientation`: mirror left-handed hexahedra when ALL of them are left-handed (default True).
    - `check_coincident`: look for coincident nodes (default True; `with_points` skips it).

    Construction validates: node indices in range, no node repeated within a hexahedron, finite coordinates, no
    node more than `MAX_COORDINATE_RANGE` median edge lengths from the median node, and midside nodes of
    quadratic cells (`CellBlock.midside`) in range, each on one edge and no cell's corner. It records notes
    (`notes`) for unreferenced nodes (midside nodes are referenced), degenerate corners (det == 0, measured in the
    `unit_frame`), inverted elements and coincident nodes (`coincident_nodes`: an unmerged interface). A mesh made
    of the very `CellBlock` objects of a mesh already made with as many nodes (`with_points`, ``dataclasses.replace``
    of the points) checks only its points: the connectivity checks and the count of unreferenced nodes are not
    repeated (the blocks' arrays are read-only: the mesh keeps its own copy of a caller's writeable array).
    """

    points: np.ndarray
    cells: tuple[CellBlock, ...]
    point_data: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    cell_data: Mapping[str, Sequence[np.ndarray]] = dataclasses.field(default_factory=dict)
    point_sets: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    cell_sets: Mapping[str, Sequence[np.ndarray]] = dataclasses.field(default_factory=dict)
    field_data: Mapping[str, object] = dataclasses.field(default_factory=dict)
    face_sets: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    held_nodes: np.ndarray | None = None
    node_ids: np.ndarray | None = None
    source: str | None = None
    input_files: tuple[str, ...] = ()
    hex_mirrored: bool = False
    fix_orientation: dataclasses.InitVar[bool] = True
    notes: tuple[str, ...] = ()
    check_coincident: dataclasses.InitVar[bool] = True

    def __post_init__(self, fix_orientation: bool, check_coincident: bool) -> None:
        where = f"{self.source}: " if self.source else ""
        pts = np.asarray(self.points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            if pts.ndim == 2 and pts.shape[1] == 2:
                raise MeshError(f"{where}the mesh is 2-D (points of shape {pts.shape}); jaxci needs 3-D hexahedra")
            raise MeshError(f"{where}points must have shape (n_nodes, 3), got {pts.shape}")
        if pts.dtype.kind != "f":
            pts = pts.astype(np.float64)
        if not np.isfinite(pts).all():
            bad = ~np.isfinite(pts).all(axis=1)
            k = int(np.flatnonzero(bad)[0])
            raise MeshError(
                f"{where}node {self.node_label(k)} has non-finite coordinates {pts[k].tolist()} "
                f"({int(bad.sum())} such nodes)"
            )
        n = pts.shape[0]
        unused = _checked_unused(self.cells, n)  # blocks another mesh of n nodes checked: not again
        blocks = list(self.cells) if unused is not None else self._checked_blocks(n, where)
        notes = list(self.notes)
        hex_data = [b.data for b in blocks if b.type == "hexahedron"]
        hexes = hex_data[0] if len(hex_data) == 1 else np.concatenate(hex_data)
        if unused is None:
            srt = np.sort(hexes, axis=1)
            rep = (srt[:, 1:] == srt[:, :-1]).any(axis=1)
            del srt
            if rep.any():
                k = int(np.flatnonzero(rep)[0])
                raise MeshError(
                    f"{where}hexahedron {self._hex_label(blocks, k)} repeats a node ({hexes[k].tolist()}); a "
                    f"degenerate brick is a wedge, pyramid or tetrahedron, not a hexahedron "
                    f"({int(rep.sum())} such elements)"
                )
        mirrored = self.hex_mirrored
        _check_node_lists(self.face_sets, self.held_nodes, n, where)
        _check_range(pts, hexes, where, self.node_label)
        unit = to_unit(pts, unit_frame(pts))  # no overflow at 1e300, no underflow
        all_left, scale = _determinant_extent(unit, hexes)  # (the largest |det|)
        sign = 1.0
        if fix_orientation and all_left:  # every hexahedron left-handed
            blocks = [_frozen_block(mirrored_block(b)) if b.type == "hexahedron" else b for b in blocks]
            mirrored = not mirrored
            msg = "every hexahedron was left-handed (all corner determinants < 0): node order mirrored to VTK's"
            notes.append(msg)
            warnings.warn(f"{where}{msg}", stacklevel=3)
            sign = -1.0
        degenerate, inverted, bad_corners = _determinant_flags(unit, hexes, scale, sign)
        del unit
        self.__dict__["_inverted_hexes"] = int(inverted.sum())
        if degenerate.any():
            notes.append(
                f"{int(degenerate.sum())} degenerate hexahedra (a corner with det == 0), first: element "
                f"{self._hex_label(blocks, int(np.flatnonzero(degenerate)[0]))}"
            )
        if inverted.any():
            notes.append(
                f"{int(inverted.sum())} inverted hexahedra ({bad_corners} corners with det <= 0), "
                f"first: element {self._hex_label(blocks, int(np.flatnonzero(inverted)[0]))}"
            )
        corners = None
        if unused is None:
            used = _cell_nodes(blocks, n)
            corners = np.flatnonzero(used)  # the nodes of the cells (what `coincident_nodes` looks at)
            midside, _ = midside_table(blocks, used, where, self.node_label)
            used[midside] = True
            unused = int(n - np.count_nonzero(used))
        if unused:
            notes.append(f"{unused} unreferenced nodes (kept, never moved)")
        object.__setattr__(self, "points", pts)
        if check_coincident:
            if corners is not None:
                self.__dict__["_coincident"] = coincident_pairs(pts, corners)
            pairs = self.coincident_nodes()
            if len(pairs):
                notes.append(coincident_note(self, pairs))
        object.__setattr__(self, "cells", tuple(blocks))
        object.__setattr__(self, "hex_mirrored", mirrored)
        object.__setattr__(self, "notes", tuple(notes))
        _CHECKED_CELLS[blocks[0]] = (n, tuple(weakref.ref(b) for b in blocks), unused)

    def _checked_blocks(self, n: int, where: str) -> list[CellBlock]:
        """The cell blocks as `CONN_DTYPE` (int32) `CellBlock`s, checked: shapes, node indices in ``[0, n)``, ids,
        midside nodes (`check_midside`) and at least one hexahedron; `MeshError` naming the block and element
        otherwise."""
        if n > np.iinfo(CONN_DTYPE).max:
            raise MeshError(f"{where}{n} nodes: jaxci numbers nodes in int32, up to {np.iinfo(CONN_DTYPE).max}")
        blocks = []
        for bi, blk in enumerate(self.cells):
            raw = np.asarray(blk.data)
            data = int_array(raw, f"{where}cell block {bi} ({blk.type})", dtype=None)
            width = NODES_PER_CELL.get(blk.type)
            if data.ndim != 2 or (width is not None and data.shape[1] != width):
                raise MeshError(
                    f"{where}cell block {bi} ({blk.type}) has shape {data.shape}, expected (n, {width})"
                )
            if data.size:
                lo, hi = int(data.min()), int(data.max())
                if lo < 0 or hi >= n:
                    row = int(np.flatnonzero((data < 0).any(axis=1) | (data >= n).any(axis=1))[0])
                    val = int(data[row][(data[row] < 0) | (data[row] >= n)][0])
                    raise MeshError(
                        f"{where}{blk.type} element {self.block_label(blk, row)} references node index {val}, "
                        f"out of range [0, {n})"
                    )
            data = data.astype(CONN_DTYPE, copy=False)  # (in range: below n)
            data = _frozen(data, ours=data is not raw and data.base is None)
            ids = None if blk.ids is None else np.asarray(blk.ids)
            if ids is not None and ids.shape != (data.shape[0],):
                raise MeshError(f"{where}cell block {bi}: {ids.shape[0]} ids for {data.shape[0]} cells")
            mid = None if blk.midside is None else _frozen(check_midside(blk, bi, data, ids, n, where))
            blocks.append(CellBlock(blk.type, data, ids, mid))
        if not any(b.type == "hexahedron" and len(b.data) for b in blocks):
            found = sorted({b.type for b in blocks if len(b.data)}) or ["no cells"]
            raise MeshError(f"{where}the mesh has no hexahedra (found: {', '.join(found)})")
        return blocks

    # ------------------------------------------------------------------ labels for messages
    def node_label(self, k: int) -> str:
        if self.node_ids is not None:
            return f"{int(np.asarray(self.node_ids)[k])} (index {k})"
        return str(k)

    block_label = staticmethod(block_label)  # `jaxci.mesh.blocks.block_label`

    @staticmethod
    def _hex_label(blocks, k: int) -> str:
        for b in blocks:
            if b.type != "hexahedron":
                continue
            if k < len(b.data):
                return HexMesh.block_label(b, k)
            k -= len(b.data)
        raise IndexError(k)

    def hex_label(self, k: int) -> str:
        """A readable label of hexahedron `k` (0-based over all hexahedron blocks), with its file id if any."""
        return self._hex_label(self.cells, k)

    @property
    def inverted_hexes(self) -> int:
        """How many hexahedra have a corner with det <= 0 (`jaxci.cells.corner_determinants`, in the unit frame),
        counted when the mesh was made."""
        return self.__dict__["_inverted_hexes"]

    def coincident_nodes(self) -> np.ndarray:
        """Pairs of distinct nodes of the mesh's cells at one point (`coincident_pairs` with
        `COINCIDENT_TOLERANCE`), shape ``(k, 2)``; computed once per mesh."""
        cached = self.__dict__.get("_coincident")
        if cached is None:
            cached = coincident_pairs(self.points, np.flatnonzero(_cell_nodes(self.cells, self.n_nodes)))
            self.__dict__["_coincident"] = cached
        return cached

    # ------------------------------------------------------------------ derived views
    @property
    def hexes(self) -> np.ndarray:
        """All hexahedra, VTK node order, shape ``(n_hexes, 8)`` (blocks concatenated in file order), read-only:
        the one block's own array, or the concatenation made once (a copy per use was 64 MB at 10^6 hexahedra,
        and a run asks a dozen times)."""
        cached = self.__dict__.get("_hexes")
        if cached is None:
            blocks = [b.data for b in self.cells if b.type == "hexahedron"]
            cached = np.asarray(blocks[0]).view() if len(blocks) == 1 else np.concatenate(blocks)
            cached.flags.writeable = False
            self.__dict__["_hexes"] = cached
        return cached

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_hexes(self) -> int:
        return int(sum(len(b.data) for b in self.cells if b.type == "hexahedron"))

    @property
    def midside_edges(self) -> tuple[np.ndarray, np.ndarray]:
        """The midside nodes of the mesh's quadratic cells and the corner nodes of their edges.

        **Returns:** ``(nodes, ends)``: node indices of shape ``(m,)`` (each once, sorted) and the two corner nodes
        of each one's edge, shape ``(m, 2)``; empty for a linear mesh.
        """
        return midside_table(self.cells, _cell_nodes(self.cells, self.n_nodes), "", self.node_label)

    @property
    def other_cell_types(self) -> list[str]:
        """Types of the non-hexahedron blocks (kept and written back; not smoothed as hexahedra)."""
        return [b.type for b in self.cells if b.type != "hexahedron"]

    def with_points(
        self, points: np.ndarray, *, notes: Sequence[str] | None = None, midside: str = "follow",
        trusted: bool = False, coincident: np.ndarray | None = None,
    ) -> HexMesh:
        """The same mesh (connectivity, data, sets, ids) with new node coordinates.

        **Arguments:**

        - `points`: the new coordinates, shape ``(n_nodes, 3)``.
        - `notes`: keyword only; the new mesh's notes (default none).
        - `trusted`: keyword only; the caller has checked that `points` are finite and leave no hexahedron
          inverted or degenerate (a smoothing run on the device: `jaxci.interface.device_run`), so the new mesh is made
          without its checks (a pass over every corner: 1 s at 10^6 hexahedra). Meshes with midside nodes are
          checked whatever this says.
        - `midside`: keyword only; what happens to the midside nodes of quadratic cells (`midside_edges`), whose
          coordinates in `points` are ignored unless ``"keep"``: ``"follow"`` (default) puts each at the midpoint
          of its edge's two corner nodes (as given in `points`) plus the offset it had from the old midpoint, so a
          straight edge stays straight with its node in the middle and a curved edge keeps its bow; offsets
          below `MIDPOINT_TOLERANCE` times the edge length count as 0. ``"midpoint"``: exactly the midpoint
          (straightens curved edges). ``"keep"``: the coordinates in `points`.
        - `coincident`: keyword only; the coincident node pairs of `points` (`coincident_nodes`) where the caller
          knows them by construction (a generator whose nodes stay apart), so that they are not searched for
          (an O(n log n) pass: 0.4 s at 10^6 nodes); default: searched on first use.

        **Returns:** a new `HexMesh`; when midside nodes were re-placed, a note says how many.
        """
        pts = np.array(points, dtype=np.float64)
        if pts.shape != self.points.shape:
            raise MeshError(f"new points have shape {pts.shape}, the mesh has {self.points.shape}")
        if midside not in ("follow", "midpoint", "keep"):
            raise ValueError(f"midside must be 'follow', 'midpoint' or 'keep', got {midside!r}")
        out_notes = list(notes) if notes is not None else []
        nodes, ends = self.midside_edges
        if len(nodes) and midside != "keep":
            curved = place_midside(self.points, pts, nodes, ends, midside)
            out_notes.append(
                f"{len(nodes)} midside nodes of quadratic cells re-placed at the midpoints of their edges' corner "
                f"nodes" + (f" ({curved} on curved edges keep their offset from the midpoint)" if curved else "")
            )
        if trusted and not len(nodes):
            out = object.__new__(HexMesh)
            out.__dict__.update({k: v for k, v in self.__dict__.items() if k != "_coincident"})
            object.__setattr__(out, "points", pts)
            object.__setattr__(out, "notes", tuple(out_notes))
            out.__dict__["_inverted_hexes"] = 0
        else:
            out = dataclasses.replace(self, points=pts, fix_orientation=False, notes=tuple(out_notes),
                                      check_coincident=False)
        if coincident is not None:
            out.__dict__["_coincident"] = np.asarray(coincident, np.int64).reshape(-1, 2)
        return out


#: The cell blocks of every `HexMesh` made, by its first block (a weak key: an entry goes with its block): the node
#: count they were checked against, weak references to all of them, and the number of nodes none of them uses.
_CHECKED_CELLS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _frozen(a: np.ndarray, ours: bool = False) -> np.ndarray:
    """`a` made read-only for a mesh to keep: in place where the mesh made it (`ours`), as it is where nothing
    writeable shares its memory, else a read-only copy (the caller's array stays theirs and writeable). A checked
    block can then not change under the mesh (`_checked_unused` trusts the blocks it checked)."""
    if ours:
        a.flags.writeable = False
        return a
    b = a
    while b is not None:
        if not isinstance(b, np.ndarray) or b.flags.writeable:
            a = a.copy()
            a.flags.writeable = False
            return a
        b = b.base
    return a


def _frozen_block(b: CellBlock) -> CellBlock:
    """A block the mesh made (`mirrored_block`), its arrays read-only."""
    return CellBlock(b.type, _frozen(b.data, ours=b.data.base is None), b.ids,
                     None if b.midside is None else _frozen(b.midside, ours=b.midside.base is None))


def _checked_unused(cells, n: int) -> int | None:
    """The number of unreferenced nodes `HexMesh` found when it checked exactly the blocks `cells` (the same
    objects, as `with_points` and ``dataclasses.replace`` pass them on) against `n` nodes; None if it did not.
    Their connectivity checks are then not repeated (about 0.15 s at 10^6 hexahedra)."""
    if not len(cells) or not isinstance(cells[0], CellBlock):
        return None
    rec = _CHECKED_CELLS.get(cells[0])
    if rec is None or rec[0] != n or len(rec[1]) != len(cells):
        return None
    if any(r() is not b for r, b in zip(rec[1], cells, strict=True)):
        return None
    return rec[2]


def _cell_nodes(cells, n: int) -> np.ndarray:
    """Which of the `n` nodes the cell blocks `cells` use (their `CellBlock.data`: not the midside nodes), bool
    ``(n,)``."""
    used = np.zeros(n, bool)
    for b in cells:
        used[np.asarray(b.data).ravel()] = True
    return used


#: `HexMesh` measures the corner determinants of this many hexahedra at a time (every corner's at once: 14 MB and
#: as much again of masks at 216,000 hexahedra, the peak of a run's last steps), in two passes: the first finds the
#: largest |det| the degeneracy test is relative to, the second the flags. One pass would keep each hexahedron's
#: smallest |det| until the end (1.7 MB at 216,000); the second pass takes 9 ms there (cube60_pert, 2026-11-30).
DET_CHUNK = 16_384


def _determinant_extent(unit: np.ndarray, hexes: np.ndarray) -> tuple[bool, float]:
    """``(every corner determinant < 0, the largest |det|)`` of the hexahedra `hexes` at `unit` (``(True,
    -inf)`` for none), a block of `DET_CHUNK` at a time."""
    left, top = True, -np.inf
    for lo in range(0, len(hexes), DET_CHUNK):
        det = corner_determinants(unit, hexes[lo:lo + DET_CHUNK])
        left = left and bool((det < 0).all())
        top = max(top, float(np.maximum(det.max(), -det.min())))
    return left, top


def _determinant_flags(unit: np.ndarray, hexes: np.ndarray, scale: float, sign: float
                       ) -> tuple[np.ndarray, np.ndarray, int]:
    """``(degenerate, inverted, corners)`` of the hexahedra: each one's flags (a corner with ``|det| <= 1e-14``
    `scale`, every one where `scale` is 0; a corner with det <= 0) and the number of corners with det <= 0, of
    the determinants times `sign` (-1: mirrored)."""
    degenerate, inverted = np.empty(len(hexes), bool), np.empty(len(hexes), bool)
    corners = 0
    for lo in range(0, len(hexes), DET_CHUNK):
        det = corner_determinants(unit, hexes[lo:lo + DET_CHUNK])
        if sign < 0:
            np.negative(det, out=det)
        rows = slice(lo, lo + len(det))
        if scale > 0:  # |det| <= 1e-14 scale, without |det|'s copy
            degenerate[rows] = _rows_any((det <= 1e-14 * scale) & (det >= -1e-14 * scale))
        else:
            degenerate[rows] = True
        bad = det <= 0
        inverted[rows] = _rows_any(bad)
        corners += int(bad.sum())
    return degenerate, inverted, corners


def _rows_any(mask: np.ndarray) -> np.ndarray:
    """``mask.any(axis=1)`` of a boolean ``(m, 8)`` array, each row read as one 8-byte word (10x faster than
    numpy's reduction over a short axis)."""
    return np.ascontiguousarray(mask).view(np.uint64)[:, 0] != 0


def hex_mesh(points, hexes, **kwargs) -> HexMesh:
    """A `HexMesh` from a point array of shape ``(n, 3)`` and one hexahedron block of shape ``(N, 8)``."""
    return HexMesh(np.asarray(points, dtype=np.float64), (CellBlock("hexahedron", np.asarray(hexes)),), **kwargs)


def _check_range(pts: np.ndarray, hexes: np.ndarray, where: str, label) -> None:
    """`MeshError` if a node lies more than `MAX_COORDINATE_RANGE` median edge lengths from the median node."""
    if not len(hexes):
        return
    sample = hexes[:: max(len(hexes) // 65536, 1)]  # the medians of a sample of 65536 elements at most
    with np.errstate(over="ignore", invalid="ignore"):
        e = np.abs(pts[sample[:, [1, 3, 4]]] - pts[sample[:, [0]]]).max(axis=2)  # max-norm edge lengths
        h = float(np.median(e))
        if not h > 0:  # most edges of zero length: a degenerate mesh, reported as such (not a range problem)
            return
        mid = np.median(pts[sample[:, 0]], axis=0)
        d = 0.5 * pts - 0.5 * mid
        np.abs(d, out=d)
        dist = np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2])  # the max over each row (numpy's is slow there)
        dist *= 2.0
    k = int(np.argmax(dist))
    if not dist[k] / h <= MAX_COORDINATE_RANGE:
        raise MeshError(
            f"{where}node {label(k)} at {pts[k].tolist()} lies {dist[k]:.3g} from the median node, "
            f"{dist[k] / h:.3g} times the median edge length {h:.3g} (at most {MAX_COORDINATE_RANGE:.0e}): float64 "
            f"cannot measure elements across such a range; a stray node, or coordinates in mixed units?"
        )


def coincident_note(mesh: HexMesh, pairs: np.ndarray) -> str:
    """The sentence of `HexMesh.notes` about coincident nodes (`HexMesh.coincident_nodes`)."""
    n = len(np.unique(pairs))
    a, b = (mesh.node_label(int(k)) for k in pairs[0])
    return (f"{len(pairs)} pairs of coincident nodes ({n} nodes closer than {COINCIDENT_TOLERANCE:g} x the "
            f"bounding-box diagonal: an unmerged interface?), first: nodes {a} and {b}; smoothing moves each set as "
            f"one node (--merge-coincident or jaxci.mesh.merge_coincident merges them)")


def merge_coincident(mesh: HexMesh, tol: float = COINCIDENT_TOLERANCE) -> HexMesh:
    """`mesh` with every group of coincident nodes merged into one node (an unmerged interface joined).

    **Arguments:**

    - `mesh`: the `HexMesh`.
    - `tol`: nodes closer than `tol` times the bounding-box diagonal are merged (`coincident_pairs`; default
      `COINCIDENT_TOLERANCE`; groups are closed transitively).

    **Returns:** a new `HexMesh` with fewer nodes: each group kept as its lowest-numbered node (its coordinates,
    point data and id), cells, midside nodes and point sets renumbered, other nodes in their order; a note says
    how many nodes were merged. `mesh` itself when nothing coincides. Raises `MeshError` if a merge makes a
    hexahedron repeat a node (a collapsed element).
    """
    mesh = as_hex_mesh(mesh, "merge_coincident")
    if tol == COINCIDENT_TOLERANCE:
        pairs = mesh.coincident_nodes()
    else:
        pairs = coincident_pairs(mesh.points, np.flatnonzero(_cell_nodes(mesh.cells, mesh.n_nodes)), tol)
    if not len(pairs):
        return mesh
    n = mesh.n_nodes
    target = coincident_groups(n, pairs)  # each node -> its group's lowest node
    keep = target == np.arange(n)
    new_index = np.cumsum(keep) - 1
    remap = new_index[target]
    cells = tuple(CellBlock(b.type, remap[b.data], b.ids,
                            None if b.midside is None else np.where(b.midside >= 0, remap[np.maximum(b.midside, 0)],
                                                                    -1))
                  for b in mesh.cells)
    merged = int(n - keep.sum())
    first = mesh.node_label(int(pairs[0, 1])), mesh.node_label(int(pairs[0, 0]))
    groups = len(np.unique(target[~keep]))
    note = (f"merged {groups} groups of coincident nodes ({merged + groups} nodes closer than {tol:g} x the "
            f"bounding-box diagonal) into one node each, first: node {first[0]} into {first[1]}; {n} -> "
            f"{int(keep.sum())} nodes")
    return dataclasses.replace(
        mesh,
        points=mesh.points[keep],
        cells=cells,
        point_data={k: np.asarray(v)[keep] for k, v in mesh.point_data.items()},
        point_sets={k: np.unique(remap[np.asarray(v, dtype=np.int64)]) for k, v in mesh.point_sets.items()},
        face_sets={k: remap[np.asarray(v, dtype=np.int64)] for k, v in mesh.face_sets.items()},
        held_nodes=None if mesh.held_nodes is None else np.unique(remap[np.asarray(mesh.held_nodes, np.int64)]),
        node_ids=None if mesh.node_ids is None else np.asarray(mesh.node_ids)[keep],
        notes=(*(m for m in mesh.notes if "coincident nodes" not in m), note),
        fix_orientation=False,
    )


def _check_node_lists(face_sets, held, n: int, where: str) -> None:
    """`MeshError` for face sets that are not ``(k, 4)`` node indices in ``[0, n)`` or held nodes out of range."""
    for name, faces in face_sets.items():
        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 4 or (f.size and (f.dtype.kind not in "iu" or f.min() < 0 or f.max() >= n)):
            raise MeshError(f"{where}face set {name!r} must be (k, 4) node indices in [0, {n}), got an array of "
                            f"shape {f.shape}")
    h = np.asarray([] if held is None else held)
    if h.size and (h.dtype.kind not in "iu" or h.min() < 0 or h.max() >= n):
        raise MeshError(f"{where}held nodes must be node indices in [0, {n})")


def as_hex_mesh(obj, caller: str) -> HexMesh:
    """`obj` as a `HexMesh` for the public function `caller`: a `HexMesh` as is, a `meshio.Mesh` converted (as
    `jaxci.io.read_mesh` converts a file); anything else raises `UsageError` saying how to make one."""
    from ..errors import UsageError

    if isinstance(obj, HexMesh):
        return obj
    cls = type(obj)
    if cls.__name__ == "Mesh" and cls.__module__.split(".")[0] == "meshio":
        from .convert import meshio_fields

        return HexMesh(**meshio_fields(obj, "<meshio.Mesh>"))
    hint = "read a file with jaxci.read_mesh(path) or build one with jaxci.hex_mesh(points, hexes)"
    if isinstance(obj, (str, bytes, os.PathLike)):
        raise UsageError(f"{caller} expects a jaxci HexMesh, got the path {os.fsdecode(obj)!r}; read the file with "
                         f"jaxci.read_mesh(path) first")
    if hasattr(obj, "__array__") or isinstance(obj, (list, tuple)):
        what = f"an array of shape {obj.shape}" if hasattr(obj, "shape") else f"a {cls.__name__}"
        raise UsageError(f"{caller} expects a jaxci HexMesh, got {what}; build one from node coordinates and "
                         f"hexahedra with jaxci.hex_mesh(points, hexes)")
    raise UsageError(f"{caller} expects a jaxci HexMesh, got {cls.__module__}.{cls.__name__}; {hint}")


def check_volume(mesh: HexMesh, moments: tuple[np.ndarray, int] | None = None) -> None:
    """`MeshError` if the nodes of the hexahedra lie in one plane, on one line or at one point (a mesh of zero
    volume, which neither untangling nor smoothing can repair): a 3 x 3 eigenvalue problem, O(n).

    `moments`: ``(m, count)``, the 3 x 3 moment matrix of the hexahedra's nodes about their mean in their unit
    frame and how many nodes they are, where the caller has them (a mesh on a device:
    `jaxci.metrics.device.volume_moments` reduces them there); default: computed here from `mesh`."""
    if moments is None:
        used = np.zeros(mesh.n_nodes, bool)
        used[mesh.hexes] = True  # a scatter, not np.unique's sort (10x faster at 10^6 hexahedra)
        nodes = np.flatnonzero(used)
        p = to_unit(mesh.points[nodes], unit_frame(mesh.points[nodes]))
        p = p - p.mean(axis=0)
        moments = np.einsum("ij,ik->jk", p, p), len(nodes)  # einsum: no BLAS threads (jaxci.optim._anderson)
    m, count = moments
    w, v = np.linalg.eigh(m)  # ascending
    if w[2] <= 0 or w[0] <= (1e-12) ** 2 * w[2]:
        where = f"{mesh.source}: " if mesh.source else ""
        what = ("all at one point" if w[2] <= 0 else "on one line" if w[1] <= (1e-12) ** 2 * w[2]
                else f"in one plane (normal {np.round(v[:, 0], 6).tolist()})")
        raise MeshError(f"{where}the {count} nodes of the hexahedra lie {what}: the mesh has no volume, and "
                        f"no moving of nodes can untangle or smooth it")
