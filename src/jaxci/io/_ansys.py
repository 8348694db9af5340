"""ANSYS meshes: the brick model shared by the NLIST/ELIST listing reader and the APDL NBLOCK/EBLOCK reader/writer.

Both ANSYS text formats describe a mesh the same way: node numbers with coordinates, and solid bricks (SOLID185,
or SOLID186 with its 12 midside nodes) with an element number, the attributes MAT TYP REL ESY SEC and the eight
corner nodes I J K L M N O P. I J K L go around one face, M N O P around the opposite one, M above I: that is
VTK's hexahedron order 0..7 unchanged. ANSYS writes wedges, pyramids and tetrahedra as degenerate bricks, which
jaxci turns into proper cells (kept and written back, not smoothed as hexahedra):

| ANSYS nodes I..P  | shape        | jaxci cell block, VTK node order |
|-------------------|--------------|----------------------------------|
| I J K K M N O O   | wedge/prism  | ``wedge``   (I, J, K, M, N, O)   |
| I J K L M M M M   | pyramid      | ``pyramid`` (I, J, K, L, M)      |
| I J K K M M M M   | tetrahedron  | ``tetra``   (I, J, K, M)         |

The wedge keeps the brick's winding: triangle 0 1 2 turns counter-clockwise seen from triangle 3 4 5, as in Gmsh,
ANSYS and VTK >= 9.7 (VTK before 9.7 numbered wedges the opposite way round and shows these with negative volume).
Any other repeated-node pattern is an error. ANSYS node numbers become `HexMesh.node_ids`, element numbers
`CellBlock.ids`, and MAT TYP REL ESY SEC the integer cell data ``ansys:mat``, ``ansys:typ``, ``ansys:rel``,
``ansys:esy``, ``ansys:sec``.

**Quadratic elements.** The midside nodes Q R S T (edges IJ JK KL LI), U V W X (MN NO OP PM), Y Z A B (IM JN KO LP)
of a 20-node brick become `CellBlock.midside` of its cell, in `jaxci.cells.EDGES` order (the same order for a
hexahedron); a node number 0 (a dropped midside node) becomes -1. The degenerate forms follow ANSYS's SOLID186
pattern (`MIDSIDE_FROM_BRICK`): wedge ``Q R K T U V O X Y Z A A``, pyramid ``Q R S T M M M M Y Z A B``,
tetrahedron ``Q R K T M M M M Y Z A A`` (a merged midside position may also be 0); anything else is refused.
A 10-node tetrahedron (SOLID187: I J K L, then M N O P Q R on edges IJ JK KI IL JL KL) is read as the brick
I J K K L L L L with those midside nodes. `jaxci.mesh.HexMesh.with_points` moves the midside nodes with their
edges, and the writer writes the elements back with the same node count.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ..errors import MeshReadError
from ..mesh import CellBlock, HexMesh
from ._deck import element_ids, first_duplicate, refuse_bad_ids

#: Names of the cell data that hold an ANSYS element's attributes, in ELIST column order.
ATTRIBUTES = ("ansys:mat", "ansys:typ", "ansys:rel", "ansys:esy", "ansys:sec")
#: Cell data of the other EBLOCK fields: birth/death flag, solid model reference, element shape flag (kept only
#: when some element has a non-zero value).
EXTRA_ATTRIBUTES = ("ansys:birth", "ansys:solid", "ansys:shape")
#: Attribute values given to elements that have none (a mesh read from another format).
DEFAULT_ATTRIBUTES = (1, 1, 1, 0, 1)

#: Columns of a brick's I..P that make each jaxci cell type.
_FROM_BRICK = {"hexahedron": [0, 1, 2, 3, 4, 5, 6, 7], "wedge": [0, 1, 2, 4, 5, 6], "pyramid": [0, 1, 2, 3, 4],
               "tetra": [0, 1, 2, 4]}
#: For each jaxci cell type, the brick midside columns (0..11 = Q..B) that hold the cell's midside nodes in
#: `jaxci.cells.EDGES` order, and the (column, what it must equal) pattern of the merged positions: a corner column
#: 0..7 of I..P (or 0, no node) or ``("mid", c)``: the same node as midside column c.
MIDSIDE_FROM_BRICK = {
    "hexahedron": (list(range(12)), []),
    "wedge": ([0, 1, 3, 4, 5, 7, 8, 9, 10], [(2, 2), (6, 6), (11, ("mid", 10))]),
    "pyramid": ([0, 1, 2, 3, 8, 9, 10, 11], [(4, 4), (5, 4), (6, 4), (7, 4)]),
    "tetra": ([0, 1, 3, 8, 9, 10], [(2, 2), (4, 4), (5, 4), (6, 4), (7, 4), (11, ("mid", 10))]),
}
#: Inverse: which node of each cell goes to I..P of the degenerate brick ANSYS stores.
TO_BRICK = {
    "hexahedron": [0, 1, 2, 3, 4, 5, 6, 7],
    "wedge": [0, 1, 2, 2, 3, 4, 5, 5],
    "pyramid": [0, 1, 2, 3, 4, 4, 4, 4],
    "tetra": [0, 1, 2, 2, 3, 3, 3, 3],
}
#: Inverse for midside nodes: the source of each brick midside column Q..B: ``("mid", i)`` the cell's midside
#: node i, ``("node", j)`` the cell's corner node j (a merged position).
MIDSIDE_TO_BRICK = {
    "hexahedron": [("mid", i) for i in range(12)],
    "wedge": [("mid", 0), ("mid", 1), ("node", 2), ("mid", 2), ("mid", 3), ("mid", 4), ("node", 5), ("mid", 5),
              ("mid", 6), ("mid", 7), ("mid", 8), ("mid", 8)],
    "pyramid": [("mid", 0), ("mid", 1), ("mid", 2), ("mid", 3)] + [("node", 4)] * 4
    + [("mid", 4), ("mid", 5), ("mid", 6), ("mid", 7)],
    "tetra": [("mid", 0), ("mid", 1), ("node", 2), ("mid", 2)] + [("node", 3)] * 4
    + [("mid", 3), ("mid", 4), ("mid", 5), ("mid", 5)],
}

#: ANSYS element routines (the number of ``ET,itype,number``) jaxci reads, by family: 8-node solid bricks,
#: 20-node bricks (midside nodes), 4-node and 10-node tetrahedra. Any other type used by an element is refused.
BRICK8 = {45: "SOLID45", 65: "SOLID65", 70: "SOLID70", 164: "SOLID164", 185: "SOLID185", 278: "SOLID278"}
BRICK20 = {90: "SOLID90", 95: "SOLID95", 186: "SOLID186", 279: "SOLID279"}
TET4 = {285: "SOLID285"}
TET10 = {92: "SOLID92", 187: "SOLID187"}
#: Names of element routines, for messages and ``ET`` lines (others are written as their number).
ELEMENT_NAMES = {**BRICK8, **BRICK20, **TET4, **TET10, 200: "MESH200"}


@dataclasses.dataclass(frozen=True)
class Bricks:
    """An ANSYS mesh as its text formats hold it; rows keep where they came from for error messages.

    **Arguments:**

    - `node_ids`: node numbers, shape ``(n,)``; `points`: their coordinates, shape ``(n, 3)``.
    - `elem_ids`: element numbers, shape ``(m,)``; `attrs`: MAT TYP REL ESY SEC, shape ``(m, 5)``.
    - `corners`: node numbers I..P of each brick, shape ``(m, 8)``.
    - `files`: the files read; `node_src`, `elem_src`: (file index, line number) of each row, shapes ``(n, 2)``
      and ``(m, 2)``.
    - `n_midside`: how many elements were listed with 20 nodes (SOLID186 bricks); `n_tet10`: with 10 (SOLID187).
    - `midside`: node numbers Q..B of each brick's midside nodes, shape ``(m, 12)``, 0 where none; None when no
      element has any.
    - `angles`: nodal rotation angles THXY THYZ THZX (NBLOCK), shape ``(n, 3)``; None when all are 0.
    - `extra`: EBLOCK birth/death flag, solid model reference and shape flag, shape ``(m, 3)``; None when all 0.
    - `etypes`: ``ET`` records, ``[itype, routine]`` rows of shape ``(k, 2)``; `keyopts`: ``KEYOPT`` records,
      ``[itype, knum, value]`` rows of shape ``(j, 3)``; None when the file has none.
    - `components`: CMBLOCK components, ``(name, "NODE" | "ELEM", ids, where)`` with the numbers expanded.
    """

    node_ids: np.ndarray
    points: np.ndarray
    elem_ids: np.ndarray
    attrs: np.ndarray
    corners: np.ndarray
    files: tuple[str, ...]
    node_src: np.ndarray
    elem_src: np.ndarray
    n_midside: int = 0
    n_tet10: int = 0
    midside: np.ndarray | None = None
    angles: np.ndarray | None = None
    extra: np.ndarray | None = None
    etypes: np.ndarray | None = None
    keyopts: np.ndarray | None = None
    components: tuple = ()

    def where_node(self, k: int) -> str:
        return f"{self.files[self.node_src[k, 0]]}, line {self.node_src[k, 1]}"

    def where_elem(self, k: int) -> str:
        return f"{self.files[self.elem_src[k, 0]]}, line {self.elem_src[k, 1]}"


def _lookup(sorted_ids: np.ndarray, order: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """0-based positions of `ids` among the node (or element) numbers, and where they are missing."""
    if len(sorted_ids) == 0:
        return np.zeros(ids.shape, np.int64), np.ones(ids.shape, bool)
    pos = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
    return order[pos], sorted_ids[pos] != ids


def to_hexmesh(b: Bricks, source: str, node_list: str, notes: Sequence[str] = (),
               extra_field_data: dict | None = None, input_files: Sequence[str] = ()) -> HexMesh:
    """Build the `HexMesh` of an ANSYS mesh: map node numbers, turn degenerate bricks into cells.

    **Arguments:** `b` the parsed rows; `source` the value of `HexMesh.source` (the file or files read);
    `node_list` what the nodes came from, for messages (``"NLIST"``, ``"NBLOCK"``); `notes` the reader's own
    notes; `extra_field_data` more field data (the APDL reader's ``ansys:deck``, the file's text); `input_files`
    the files read (`HexMesh.input_files`: both listings of an NLIST + ELIST pair).

    **Returns:** a `HexMesh` with blocks ``hexahedron``, then ``wedge``, ``pyramid``, ``tetra`` when present (with
    their midside nodes), ``ansys:*`` cell data, ``ansys:angles`` point data, ``ansys:et`` / ``ansys:keyopt``
    field data and the components as point and cell sets.
    """
    for ids, what, where in ((b.node_ids, "node", b.where_node), (b.elem_ids, "element", b.where_elem)):
        if (dup := first_duplicate(ids)) is not None:
            i, j = dup
            raise MeshReadError(f"{where(j)}: {what} {ids[j]} listed twice (first at {where(i)})")
    order = np.argsort(b.node_ids)
    sorted_ids = b.node_ids[order]
    conn, missing = _lookup(sorted_ids, order, b.corners)  # (m, 8) 0-based node indices
    mid_conn = None
    if b.midside is not None:
        mid_conn, mid_missing = _lookup(sorted_ids, order, b.midside)
        mid_missing &= b.midside != 0
        mid_conn = np.where(b.midside != 0, mid_conn, -1)
        if mid_missing.any() and not missing.any():
            k, c = (int(v) for v in np.argwhere(mid_missing)[0])
            raise MeshReadError(
                f"{b.where_elem(k)}: element {b.elem_ids[k]} references midside node {b.midside[k, c]}, which is "
                f"not in the {node_list} ({int(mid_missing.any(axis=1).sum())} such elements)"
            )
    if missing.any():
        k, c = (int(v) for v in np.argwhere(missing)[0])
        raise MeshReadError(
            f"{b.where_elem(k)}: element {b.elem_ids[k]} references node {b.corners[k, c]}, which is not in "
            f"the {node_list} ({int(missing.any(axis=1).sum())} such elements)"
        )

    srt = np.sort(conn, axis=1)
    distinct = 1 + (srt[:, 1:] != srt[:, :-1]).sum(axis=1)
    c = conn
    kl, op, mn, no = c[:, 2] == c[:, 3], c[:, 6] == c[:, 7], c[:, 4] == c[:, 5], c[:, 5] == c[:, 6]
    kind = {
        "hexahedron": distinct == 8,
        "wedge": kl & op & (distinct == 6),
        "pyramid": mn & no & op & (distinct == 5),
        "tetra": kl & mn & no & op & (distinct == 4),
    }
    known = np.logical_or.reduce(list(kind.values()))
    if not known.all():
        k = int(np.flatnonzero(~known)[0])
        raise MeshReadError(
            f"{b.where_elem(k)}: element {b.elem_ids[k]} repeats nodes (I..P = "
            f"{' '.join(str(v) for v in b.corners[k])}) in a way that is not a wedge (K=L, O=P), pyramid "
            f"(M=N=O=P) or tetrahedron (K=L, M=N=O=P)"
        )

    blocks, cell_data = [], {name: [] for name in ATTRIBUTES}
    extra = {name: [] for name in EXTRA_ATTRIBUTES} if b.extra is not None else {}
    rows_of = []  # element rows of each block, for the components
    for cell_type, mask in kind.items():
        if not mask.any():
            continue
        mid = None
        if mid_conn is not None and (b.midside[mask] != 0).any():
            mid = _cell_midside(b, mask, mid_conn, cell_type)
        blocks.append(CellBlock(cell_type, c[mask][:, _FROM_BRICK[cell_type]], b.elem_ids[mask], mid))
        rows_of.append(np.flatnonzero(mask))
        for a, name in enumerate(ATTRIBUTES):
            cell_data[name].append(b.attrs[mask, a])
        for a, name in enumerate(extra):
            extra[name].append(b.extra[mask, a])
    cell_data.update(extra)
    notes = list(notes)
    converted = {t: int(kind[t].sum()) for t in ("wedge", "pyramid", "tetra") if kind[t].any()}
    if converted:
        parts = ", ".join(f"{n} to {t}" for t, n in converted.items())
        notes.append(
            f"{sum(converted.values())} degenerate bricks converted ({parts}); kept and written back, not "
            f"smoothed as hexahedra"
        )
    if b.n_midside or b.n_tet10:
        listed = " and ".join(([f"{b.n_midside} elements listed with 20 nodes (SOLID186)"] if b.n_midside else [])
                              + ([f"{b.n_tet10} with 10 nodes (SOLID187)"] if b.n_tet10 else []))
        notes.append(
            f"{listed}: measured and smoothed by their corner nodes; their midside nodes follow their edges "
            f"(re-placed at the midpoints of the moved corner nodes) and are written back"
        )
    point_sets, cell_sets = _components(b, order, sorted_ids, rows_of, notes)
    field_data = {}
    if b.etypes is not None:
        field_data["ansys:et"] = np.asarray(b.etypes, np.int64).reshape(-1, 2)
    if b.keyopts is not None:
        field_data["ansys:keyopt"] = np.asarray(b.keyopts, np.int64).reshape(-1, 3)
    field_data.update(extra_field_data or {})
    return HexMesh(
        np.asarray(b.points, dtype=np.float64),
        tuple(blocks),
        point_data={} if b.angles is None else {"ansys:angles": np.asarray(b.angles, np.float64)},
        cell_data=cell_data,
        point_sets=point_sets,
        cell_sets=cell_sets,
        field_data=field_data,
        node_ids=b.node_ids,
        source=source,
        input_files=tuple(input_files),
        notes=tuple(notes),
    )


def _cell_midside(b: Bricks, mask: np.ndarray, mid_conn: np.ndarray, cell_type: str) -> np.ndarray:
    """The midside nodes (0-based, -1 for none) of the bricks `mask` of one cell type, in `EDGES` order; refuses a
    degenerate brick whose merged midside positions do not follow ANSYS's pattern."""
    cols, pattern = MIDSIDE_FROM_BRICK[cell_type]
    raw, corners = b.midside[mask], b.corners[mask]
    bad = np.zeros(len(raw), bool)
    for col, src in pattern:
        want = raw[:, src[1]] if isinstance(src, tuple) else corners[:, src]
        bad |= (raw[:, col] != want) & (raw[:, col] != 0)
    if bad.any():
        k = int(np.flatnonzero(mask)[np.flatnonzero(bad)[0]])
        letters = "QRSTUVWXYZAB"
        expect = " ".join(
            (f"{letters[src[1]]}" if isinstance(src, tuple) else "IJKLMNOP"[src]) + f"={letters[col]}"
            for col, src in pattern
        )
        raise MeshReadError(
            f"{b.where_elem(k)}: 20-node element {b.elem_ids[k]} is a degenerate brick ({cell_type}) whose midside "
            f"nodes Q..B = {' '.join(str(v) for v in b.midside[k])} do not follow ANSYS's pattern for it "
            f"({expect}); jaxci cannot tell which edge they belong to"
        )
    return mid_conn[mask][:, cols]


def expand_ranges(items: list[int]) -> np.ndarray:
    """CMBLOCK items as inclusive number ranges, shape ``(k, 2)``: a negative item -j after i means i..j, any other
    item i the range i..i. Never expanded (a range of 10^9 numbers costs one row; `resolve_ranges` finds which of
    its numbers exist)."""
    out, prev = [], None
    for v in items:
        if v < 0 and prev is not None:
            out[-1][1] = max(-v, prev)
            prev = None
        else:
            out.append([v, v])
            prev = v
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def resolve_ranges(ranges: np.ndarray, sorted_ids: np.ndarray) -> tuple[np.ndarray, int, int | None]:
    """The numbers of `ranges` (`expand_ranges`) among `sorted_ids` (sorted, unique): their positions in
    `sorted_ids` (sorted, unique), how many numbers of the ranges are not among them, and the first such number
    (None when none is). Costs what the ids cost, whatever the ranges' lengths."""
    merged = _merge(ranges)  # disjoint: the positions below are unique and at most len(sorted_ids)
    lo = np.searchsorted(sorted_ids, merged[:, 0], side="left")
    hi = np.searchsorted(sorted_ids, merged[:, 1], side="right")
    pos = np.concatenate([np.arange(a, b, dtype=np.int64) for a, b in zip(lo.tolist(), hi.tolist(), strict=True)]
                         or [np.zeros(0, np.int64)])
    missing = sum(b - a + 1 for a, b in merged.tolist()) - len(pos)
    first = None
    if missing:
        for a, b in merged.tolist():
            i, j = np.searchsorted(sorted_ids, [a, b + 1])
            have = sorted_ids[i:j]
            gap = np.flatnonzero(have != a + np.arange(len(have)))
            if len(gap) or len(have) < b - a + 1:
                first = int(a + (gap[0] if len(gap) else len(have)))
                break
    return pos, missing, first


def _merge(ranges: np.ndarray) -> np.ndarray:
    """Overlapping or touching inclusive ranges merged, sorted."""
    if not len(ranges):
        return ranges.reshape(0, 2)
    r = ranges[np.argsort(ranges[:, 0], kind="stable")]
    out = [list(r[0])]
    for a, b in r[1:].tolist():
        if a <= out[-1][1] + 1:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return np.asarray(out, dtype=np.int64)


def _components(b: Bricks, order, sorted_ids, rows_of: list[np.ndarray], notes: list[str]) -> tuple[dict, dict]:
    """CMBLOCK components as point sets (node indices) and cell sets (row indices per block)."""
    point_sets, cell_sets = {}, {}
    if not b.components:
        return point_sets, cell_sets
    eorder = np.argsort(b.elem_ids)
    block_of = np.zeros(len(b.elem_ids), np.int64)
    row_in = np.zeros(len(b.elem_ids), np.int64)
    for bi, rows in enumerate(rows_of):
        block_of[rows], row_in[rows] = bi, np.arange(len(rows))
    esorted = b.elem_ids[eorder]
    for name, kind, ranges, _where in b.components:
        if kind == "NODE":
            pos, missing, first = resolve_ranges(ranges, sorted_ids)
            point_sets[name] = np.sort(order[pos])
        else:
            pos, missing, first = resolve_ranges(ranges, esorted)
            idx = eorder[pos]
            cell_sets[name] = [np.sort(row_in[idx[block_of[idx] == bi]]) for bi in range(len(rows_of))]
        if missing:
            notes.append(
                f"component {name} lists {missing} {'node' if kind == 'NODE' else 'element'} numbers "
                f"that the file does not define (first {first}); left out"
            )
    return point_sets, cell_sets


def element_routines(mesh: HexMesh, typ: np.ndarray, has_mid: np.ndarray) -> dict[int, int]:
    """ANSYS element routine of every element type number: the mesh's ``ansys:et`` records, else SOLID186 for a
    type with midside nodes and SOLID185 for the others."""
    out = {}
    et = mesh.field_data.get("ansys:et")
    if et is not None:
        out = {int(t): int(r) for t, r in np.asarray(et, np.int64).reshape(-1, 2)}
    for t in np.unique(typ).tolist():
        if t not in out:
            out[t] = 186 if has_mid[typ == t].any() else 185
    return out


def from_hexmesh(mesh: HexMesh, cells: list[CellBlock], where: str) -> tuple[Bricks, list[str]]:
    """The ANSYS bricks of `mesh` for writing, and the cell types that ANSYS bricks cannot hold.

    **Arguments:**

    - `mesh`: the mesh (node ids, ``ansys:*`` cell data, ``ansys:angles``, ``ansys:et`` / ``ansys:keyopt``).
    - `cells`: its cell blocks as the file should hold them (hexahedra in the file's handedness).
    - `where`: the file being written, for messages.

    **Returns:** `(bricks, dropped)`; `dropped` names the blocks left out (``"12 quad"``). Nodes without ids are
    numbered 1..n, elements without ids from one past the largest element id. `bricks.midside` holds the midside
    node numbers in brick form (0 for none), `bricks.etypes` every element type's routine.
    """
    node_ids = np.arange(1, mesh.n_nodes + 1) if mesh.node_ids is None else np.asarray(mesh.node_ids, np.int64)
    kept = [(i, blk) for i, blk in enumerate(cells) if blk.type in TO_BRICK]
    dropped = [f"{len(blk.data)} {blk.type}" for blk in cells if blk.type not in TO_BRICK]
    numbers = element_ids([blk.ids for _, blk in kept], [len(blk.data) for _, blk in kept])
    corners, mids, elem_ids, attrs, extra = [], [], [], [], []
    for (i, blk), ids in zip(kept, numbers, strict=True):
        n = len(blk.data)
        corners.append(node_ids[blk.data[:, TO_BRICK[blk.type]]])
        mids.append(_brick_midside(blk, node_ids))
        elem_ids.append(np.asarray(ids, np.int64))
        cols = []
        for name, default in zip(ATTRIBUTES, DEFAULT_ATTRIBUTES, strict=True):
            values = mesh.cell_data[name][i] if name in mesh.cell_data else np.full(n, default)
            cols.append(np.asarray(values).astype(np.int64))
        attrs.append(np.stack(cols, axis=1))
        extra.append(np.stack([np.asarray(mesh.cell_data[name][i]).astype(np.int64) if name in mesh.cell_data
                               else np.zeros(n, np.int64) for name in EXTRA_ATTRIBUTES], axis=1))
    m = sum(map(len, elem_ids))
    angles = mesh.point_data.get("ansys:angles")
    b = Bricks(
        node_ids=node_ids,
        points=mesh.points,
        elem_ids=np.concatenate(elem_ids) if elem_ids else np.zeros(0, np.int64),
        attrs=np.concatenate(attrs) if attrs else np.zeros((0, 5), np.int64),
        corners=np.concatenate(corners) if corners else np.zeros((0, 8), np.int64),
        files=(where,),
        node_src=np.zeros((mesh.n_nodes, 2), np.int64),
        elem_src=np.zeros((m, 2), np.int64),
        midside=np.concatenate(mids) if mids else np.zeros((0, 12), np.int64),
        angles=None if angles is None else np.asarray(angles, np.float64).reshape(-1, 3),
        extra=np.concatenate(extra) if extra else np.zeros((0, 3), np.int64),
        keyopts=mesh.field_data.get("ansys:keyopt"),
    )
    refuse_bad_ids(where, ((b.node_ids, "node"), (b.elem_ids, "element")), "ANSYS")
    routines = element_routines(mesh, b.attrs[:, 1], has_midside(b))
    return dataclasses.replace(b, etypes=np.array(sorted(routines.items()), np.int64).reshape(-1, 2)), dropped


def has_midside(b: Bricks) -> np.ndarray:
    """Which bricks have a midside node of their own (not a merged corner position), shape ``(m,)``."""
    mid = b.midside
    if mid is None or not len(mid):
        return np.zeros(len(b.elem_ids), bool)
    return ((mid != 0) & ~(mid[:, :, None] == b.corners[:, None, :]).any(axis=2)).any(axis=1)


def _brick_midside(blk: CellBlock, node_ids: np.ndarray) -> np.ndarray:
    """Midside node numbers Q..B of the degenerate bricks of a block (0 where none), shape ``(N, 12)``."""
    n = len(blk.data)
    if blk.midside is None:
        return np.zeros((n, 12), np.int64)
    mid = np.asarray(blk.midside)
    has = mid >= 0
    num = np.where(has, node_ids[np.where(has, mid, 0)], 0)
    out = np.zeros((n, 12), np.int64)
    for col, (src, j) in enumerate(MIDSIDE_TO_BRICK[blk.type]):
        out[:, col] = num[:, j] if src == "mid" else node_ids[blk.data[:, j]]
    return out
