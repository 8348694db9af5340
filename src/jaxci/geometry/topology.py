"""Mesh topology in vectorised numpy: boundary faces and edges, node adjacency, node colouring.

Everything here depends on the connectivity only (never on coordinates) and scales to millions of hexahedra:
no Python loop runs per element or per node. A face is keyed by its sorted node indices (two int64 keys, so up
to about 3e9 nodes), and equal keys are found by one sort of hashed 64-bit words, checked exactly
(`jaxci.mesh.sorting.group_pairs`:
`boundary_topology` takes 0.5 s at 10^6 hexahedra, 1.5 s with ``np.sort(axis=1)`` and ``np.lexsort``); the
node-cell incidence is a CSR structure made by one stable sort (`incidence`); node
adjacency is the set of distinct node pairs of the cells, sorted, or on large meshes the sparsity pattern of
``A A^T`` for the node-element incidence matrix ``A`` (scipy's sparse product, much faster than the sort there;
scipy is imported only then: its import is 0.25-0.5 s of a command's start).

Faces of every linear volume cell (`CELL_FACES`: hexahedron 6 quadrilaterals, wedge 2 triangles + 3
quadrilaterals, pyramid 1 quadrilateral + 4 triangles, tetrahedron 4 triangles) are listed counter-clockwise
seen from outside a valid cell (VTK node orders, `jaxci.metrics.elements`). Faces are stored as 4 nodes: a TRIANGLE
repeats its last node (``[a, b, c, c]``), so ``(x2 - x0) x (x3 - x1)`` is twice the area times the outward unit
normal for triangles and (planar) quadrilaterals alike, and splitting a face into the triangles (centre,
corner i, corner i+1) covers it exactly (one of them degenerate for a triangle). A face shared by two cells of
any types is interior.
"""

from __future__ import annotations

import dataclasses
import sys
import weakref

import numpy as np

from ..mesh.sorting import group_pairs, sort4, sorted_unique

#: The six faces of a VTK hexahedron (local node indices), each oriented outward for a right-handed element:
#: -x, +x, -y, +y, -z, +z on the unit cube of `jaxci.mesh`. Shape ``(6, 4)``.
HEX_FACES = np.array(
    [
        [0, 4, 7, 3],
        [1, 2, 6, 5],
        [0, 1, 5, 4],
        [3, 7, 6, 2],
        [0, 3, 2, 1],
        [4, 5, 6, 7],
    ],
    dtype=np.int64,
)


#: `boundary_topology` makes its face keys this many cells at a time.
KEY_CHUNK = 16_384

#: The faces of every linear volume cell type (local node indices, outward for a valid cell, triangles padded by
#: repeating their last node), shape ``(n_faces, 4)``; the types' node orders are `jaxci.metrics.elements`'.
CELL_FACES = {
    "hexahedron": HEX_FACES,
    "wedge": np.array([[0, 2, 1, 1], [3, 4, 5, 5], [0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]], dtype=np.int64),
    "pyramid": np.array([[0, 3, 2, 1], [0, 1, 4, 4], [1, 2, 4, 4], [2, 3, 4, 4], [3, 0, 4, 4]], dtype=np.int64),
    "tetra": np.array([[0, 2, 1, 1], [0, 1, 3, 3], [1, 2, 3, 3], [2, 0, 3, 3]], dtype=np.int64),
}

#: Index of each cell type in `BoundaryTopology.face_type`.
FACE_CELL_TYPES = ("hexahedron", "wedge", "pyramid", "tetra")


@dataclasses.dataclass(frozen=True, eq=False)
class BoundaryTopology:
    """Boundary faces (quadrilaterals and triangles) and boundary edges of a volume mesh.

    **Arguments:**

    - `faces`: the boundary faces (faces used by exactly one cell), int64 array of shape ``(n_faces, 4)``,
      oriented outward (counter-clockwise seen from outside a valid cell); a triangle repeats its last node.
    - `face_hex`: the hexahedron each boundary face belongs to (index into the hexahedra), -1 for a face of
      another cell type; shape ``(n_faces,)``.
    - `edges`: the boundary edges (sides of boundary faces), int64 array of shape ``(n_edges, 2)`` with
      ``edges[:, 0] < edges[:, 1]``.
    - `face_edges`: for each boundary face, the index into `edges` of its sides ``(f0,f1), (f1,f2), (f2,f3),
      (f3,f0)``, -1 for the side ``(c, c)`` of a triangle; shape ``(n_faces, 4)``.
    - `edge_face_ptr`, `edge_face`: CSR lists of the boundary faces around each boundary edge: the faces of
      edge ``e`` are ``edge_face[edge_face_ptr[e]:edge_face_ptr[e + 1]]``; shapes ``(n_edges + 1,)`` and
      ``(n_sides,)`` (4 per quadrilateral, 3 per triangle).
    - `nonmanifold_faces`: the distinct faces shared by three or more cells (an invalid mesh), as sorted node
      indices, shape ``(k, 4)`` (a triangle: -1 then its 3 nodes); they are not boundary faces.
    - `face_type`: the cell type of each boundary face's cell (index into `FACE_CELL_TYPES`), int8; `face_cell`:
      that cell's index within its type; both of shape ``(n_faces,)``. Default: every face a hexahedron's.
    """

    faces: np.ndarray
    face_hex: np.ndarray
    edges: np.ndarray
    face_edges: np.ndarray
    edge_face_ptr: np.ndarray
    edge_face: np.ndarray
    nonmanifold_faces: np.ndarray
    face_type: np.ndarray | None = None
    face_cell: np.ndarray | None = None

    @property
    def nonmanifold_nodes(self) -> np.ndarray:
        """Sorted nodes of `nonmanifold_faces` (without the -1 padding of triangles)."""
        v = sorted_unique(self.nonmanifold_faces)
        return v[v >= 0]

    @property
    def edge_valence(self) -> np.ndarray:
        """Number of boundary faces around each boundary edge, shape ``(n_edges,)`` (2 on a manifold)."""
        return np.diff(self.edge_face_ptr)

    @property
    def n_nonmanifold_faces(self) -> int:
        return int(self.nonmanifold_faces.shape[0])

    @property
    def nodes(self) -> np.ndarray:
        """Sorted indices of the nodes on the boundary, shape ``(n_boundary_nodes,)``."""
        return sorted_unique(self.faces)


def boundary_topology(hexes: np.ndarray, n_nodes: int, others=None) -> BoundaryTopology:
    """Find the boundary faces and edges of a hexahedral or hex-dominant mesh.

    **Arguments:**

    - `hexes`: connectivity in VTK node order, integer array of shape ``(n_hexes, 8)``.
    - `n_nodes`: number of nodes (one more than the largest index).
    - `others`: optional mapping ``{"wedge": (N, 6), "pyramid": (N, 5), "tetra": (N, 4)}`` of the other linear
      volume cells (corner nodes; `jaxci.metrics.elements` node orders): their faces bound the volume too, and a face
      they share with a hexahedron (or each other) is interior.

    **Returns:** a `BoundaryTopology`.
    """
    hexes = np.asarray(hexes)  # (int32: the keys are made in int64, n's type)
    n = np.int64(max(int(n_nodes), 1))
    blocks = [("hexahedron", hexes)]
    for t, cells in (others or {}).items():
        if t not in CELL_FACES or t == "hexahedron":
            raise ValueError(f"boundary_topology: unknown extra cell type {t!r}; expected wedge, pyramid or tetra")
        cells = np.asarray(cells, dtype=np.int64)
        if cells.ndim != 2 or cells.shape[1] != int(CELL_FACES[t].max()) + 1:
            raise ValueError(f"boundary_topology: {t} cells must have shape (N, {int(CELL_FACES[t].max()) + 1}), "
                             f"got {cells.shape}")
        if len(cells):
            blocks.append((t, cells))
    mixed = len(blocks) > 1
    # each face's sorted nodes (a triangle's: -1, then its 3 nodes) as two int64 keys; the faces are numbered
    # cell-major within a block (face j of cell c at c * faces per cell + j), one block after another; made
    # `KEY_CHUNK` cells at a time (the four node columns of every face at once were 41 MB at 216,000 hexahedra)
    m = sum(len(cells) * len(CELL_FACES[t]) for t, cells in blocks)
    k1, k2 = np.empty(m, np.int64), np.empty(m, np.int64)
    at = 0
    for t, cells in blocks:
        table = CELL_FACES[t] if mixed else HEX_FACES
        for lo in range(0, len(cells), KEY_CHUNK):
            part = cells[lo:lo + KEY_CHUNK]
            key = [part[:, table[:, i]].ravel() for i in range(4)]
            if mixed:  # a triangle's key: its 3 sorted nodes after a -1 (whatever node it repeats)
                key[3][key[3] == key[2]] = -1
            sort4(key)
            rows = slice(at, at + len(key[0]))
            np.multiply(key[0], n, out=k1[rows])
            k1[rows] += key[1]
            np.multiply(key[2], n, out=k2[rows])
            k2[rows] += key[3]
            at += len(key[0])
            del key
    order, starts = group_pairs(k1, k2)
    del k1, k2
    size = np.diff(starts, append=len(order))
    single = order[starts[size == 1]]  # the faces of one cell: the boundary
    single.sort()
    rep = order[starts[size >= 3]]  # one of each face shared by three or more cells
    del order, starts, size
    offset = np.cumsum([0] + [len(c) * len(CELL_FACES[t]) for t, c in blocks])
    faces, blk, face_cell = _face_nodes(blocks, offset, single)
    nonmanifold = _face_nodes(blocks, offset, rep)[0]
    if mixed:
        nonmanifold[nonmanifold[:, 3] == nonmanifold[:, 2], 3] = -1
    nonmanifold.sort(axis=1)
    nonmanifold = nonmanifold[np.lexsort(nonmanifold.T[::-1])]  # in the order of their sorted nodes
    face_type = np.array([FACE_CELL_TYPES.index(t) for t, _ in blocks], np.int8)[blk]
    face_hex = np.where(face_type == 0, face_cell, -1)
    return topology_from_faces(faces, face_hex, nonmanifold, int(n), face_type=face_type, face_cell=face_cell)


def topology_from_faces(faces: np.ndarray, face_hex: np.ndarray, nonmanifold: np.ndarray, n_nodes: int, *,
                        face_type: np.ndarray | None = None, face_cell: np.ndarray | None = None) -> BoundaryTopology:
    """The `BoundaryTopology` of given boundary faces (their edges, each face's edges, each edge's faces: one sort
    of the sides, O(boundary)), for `boundary_topology` and `jaxci.geometry.device_topology`. `faces` ``(n_faces,
    4)`` outward, `face_hex` ``(n_faces,)``, `nonmanifold` ``(k, 4)``, `face_type` (default 0: hexahedra) and
    `face_cell` (default `face_hex`) as the `BoundaryTopology` fields; `n_nodes` one more than the largest index.
    """
    faces = np.asarray(faces, dtype=np.int64)
    face_hex = np.asarray(face_hex, dtype=np.int64)
    n = np.int64(max(int(n_nodes), 1))
    if face_type is None:
        face_type = np.zeros(len(faces), np.int8)
    rolled = np.roll(faces, -1, axis=1)  # the sides (f0,f1), (f1,f2), (f2,f3), (f3,f0) of each face, face-major
    lo, hi = np.minimum(faces, rolled).ravel(), np.maximum(faces, rolled).ravel()
    del rolled
    real = lo != hi  # the side (c, c) of a triangle is not an edge
    all_real = bool(real.all())
    side_face = np.arange(len(lo)) // 4
    if not all_real:
        lo, hi, side_face = lo[real], hi[real], side_face[real]
    ekey = lo * n + hi
    by_edge = np.argsort(ekey, kind="stable")  # the sides of each edge together, in side order
    ekey = ekey[by_edge]
    efirst = np.ones(len(ekey), dtype=bool)
    efirst[1:] = ekey[1:] != ekey[:-1]
    keys = ekey[efirst]
    inverse = np.empty(len(ekey), dtype=np.int64)
    inverse[by_edge] = np.cumsum(efirst) - 1
    edges = np.stack([keys // n, keys % n], axis=1).astype(np.int64)
    if all_real:
        face_edges = inverse.reshape(-1, 4)
    else:
        face_edges = np.full(len(real), -1, np.int64)
        face_edges[real] = inverse
        face_edges = face_edges.reshape(-1, 4)
    edge_face = side_face[by_edge].astype(np.int64)
    edge_face_ptr = np.append(np.flatnonzero(efirst), len(ekey)).astype(np.int64)
    return BoundaryTopology(
        faces=faces,
        face_hex=face_hex,
        edges=edges,
        face_edges=face_edges,
        edge_face_ptr=edge_face_ptr,
        edge_face=edge_face,
        nonmanifold_faces=np.asarray(nonmanifold, dtype=np.int64),
        face_type=face_type,
        face_cell=(face_hex if face_cell is None else np.asarray(face_cell)).astype(np.int64),
    )


def _face_nodes(blocks: list, offset: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nodes ``(len(idx), 4)`` of the faces numbered `idx` (as `boundary_topology` numbers the faces of the
    cell `blocks`, block b's from ``offset[b]``), with each one's block and cell index within its block."""
    blk = np.searchsorted(offset, idx, "right") - 1
    nodes = np.empty((len(idx), 4), dtype=np.int64)
    cell = np.empty(len(idx), dtype=np.int64)
    for b, (t, cells) in enumerate(blocks):
        sel = np.flatnonzero(blk == b) if len(blocks) > 1 else slice(None)
        cell[sel], local = np.divmod(idx[sel] - offset[b], len(CELL_FACES[t]))
        nodes[sel] = cells[cell[sel][:, None], CELL_FACES[t][local]]
    return nodes, blk, cell


def unique_edges(pairs: np.ndarray) -> np.ndarray:
    """The distinct undirected node pairs of `pairs` ``(E, 2)``, each as (low, high), sorted: shape ``(U, 2)``.

    One int64 key per pair (``low * n + high``), sorted, repeats dropped: 0.07 s for the 2.6 M hexahedron edges
    of a 60^3 box, against 1.3 s for ``np.unique(..., axis=0)`` (rows through a structured view) and 0.6 s for
    ``np.unique`` of the keys (numpy 2).
    """
    e = np.sort(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=1)
    return np.stack(_distinct_pairs(e[:, 0], e[:, 1]), axis=1)


def _distinct_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct pairs ``(a[j], b[j])`` (non-negative int64), in lexicographic order: one sort of the int64
    keys ``a * (max b + 1) + b`` with repeats dropped."""
    width = max(int(b.max(initial=-1)) + 1, 1)
    key = sorted_unique(a * width + b)
    return key // width, key % width


def incidence(cells: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """The node-cell incidence in CSR form: the cells of node ``i`` are ``indices[indptr[i]:indptr[i + 1]]``,
    in increasing order (a node listed twice by one cell lists that cell twice).

    **Arguments:** `cells` an integer array of shape ``(n_cells, k)`` (hexahedra, faces, edges); `n_nodes`.

    **Returns:** ``(indptr, indices)``, int64 arrays of shapes ``(n_nodes + 1,)`` and ``(n_cells * k,)``.
    """
    cells = np.asarray(cells, dtype=np.int64)
    k = cells.shape[1] if cells.ndim == 2 else 1
    order = np.argsort(cells.ravel(), kind="stable")
    indptr = np.zeros(int(n_nodes) + 1, dtype=np.int64)
    np.cumsum(np.bincount(cells.ravel(), minlength=int(n_nodes)), out=indptr[1:])
    return indptr, order // max(k, 1)


def node_adjacency(hexes, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Node-node adjacency through shared cells, in CSR form (a node is not its own neighbour).

    **Arguments:**

    - `hexes`: integer array of shape ``(n_hexes, 8)``, or a list of cell arrays ``(N_t, k_t)`` of any widths
      (hexahedra, wedges, ...: nodes sharing any cell are adjacent).
    - `n_nodes`: number of nodes.

    **Returns:** ``(indptr, indices)``, integer arrays of shapes ``(n_nodes + 1,)`` and ``(nnz,)`` (int64, and
    `indices` int32 from scipy's product on large meshes): the neighbours of node ``i`` are
    ``indices[indptr[i]:indptr[i + 1]]``, sorted.
    """
    n = int(n_nodes)
    blocks = [np.asarray(c, dtype=np.int64) for c in (hexes if isinstance(hexes, list | tuple) else [hexes])]
    if "scipy.sparse" in sys.modules or sum(c.size for c in blocks) > SORTED_ADJACENCY_MAX:
        return _adjacency_product(blocks, n)
    a, b = [], []
    for c in blocks:  # every pair of nodes of a cell, both ways
        i, j = np.triu_indices(c.shape[1], 1)
        a += [c[:, i].ravel(), c[:, j].ravel()]
        b += [c[:, j].ravel(), c[:, i].ravel()]
    a, b = np.concatenate(a), np.concatenate(b)
    keep = a != b  # a cell that lists a node twice does not make it its own neighbour
    return unique_per_row(a[keep], b[keep], n)


#: `node_adjacency` sorts the node pairs of the cells in numpy up to this many cell-node entries (8 per
#: hexahedron) and otherwise takes the pattern of scipy's sparse product ``A A^T``: the sort costs 0.16 s at
#: 27,000 hexahedra (the product 0.02 s, but importing scipy.sparse 0.25-0.5 s) and 1.8 s at 216,000 (0.22 s).
SORTED_ADJACENCY_MAX = 320_000


def _adjacency_product(blocks: list, n: int) -> tuple[np.ndarray, np.ndarray]:
    """`node_adjacency` as the sparsity pattern of ``A A^T`` (A the node-cell incidence of `blocks`)."""
    import scipy.sparse as sp

    mats = [sp.csr_matrix((np.ones(c.size, dtype=np.int32), (c.ravel(), np.repeat(np.arange(len(c)), c.shape[1]))),
                          shape=(n, len(c))) for c in blocks]
    a = sp.hstack(mats).tocsr() if len(mats) > 1 else mats[0]
    del mats
    g = (a @ a.T).tocsr()
    del a
    # the diagonal (every used node shares a cell with itself) out in place: no per-entry row array (8 bytes a
    # pair, 216 MB at 10^6 hexahedra) and no int64 copy of the pattern, the peak of a host run there
    g.setdiag(0)
    g.eliminate_zeros()
    g.sort_indices()
    return g.indptr.astype(np.int64), g.indices


def unique_per_row(owner: np.ndarray, values: np.ndarray, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct `values` of each row as CSR, sorted: ``(indptr, indices)`` of shapes ``(n_rows + 1,)`` and
    ``(nnz,)``, from entries ``(owner[j], values[j])`` (owner in [0, n_rows), values >= 0), one sort of int64
    keys."""
    rows, indices = _distinct_pairs(np.asarray(owner, dtype=np.int64), np.asarray(values, dtype=np.int64))
    indptr = np.zeros(int(n_rows) + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=int(n_rows)), out=indptr[1:])
    return indptr, indices


def csr_gather(indptr: np.ndarray, indices: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The entries of some rows of a CSR structure, flattened.

    **Arguments:** `indptr`, `indices` a CSR structure; `rows` an integer array of shape ``(m,)``.

    **Returns:** ``(owner, values)``, both of shape ``(total,)``: `values` lists the entries of ``rows[0]``,
    then of ``rows[1]``, ...; ``owner[j]`` is the position in `rows` whose entry ``values[j]`` is.
    """
    starts = indptr[rows]
    counts = indptr[rows + 1] - starts
    owner = np.repeat(np.arange(len(rows)), counts)
    offsets = np.cumsum(counts) - counts
    pos = np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(offsets - starts, counts)
    return owner, indices[pos]


@dataclasses.dataclass(frozen=True, eq=False)
class Colouring:
    """A colouring of the nodes such that no two nodes of one colour share a hexahedron.

    Nodes of one colour can be moved simultaneously: no element sees two of them move. `colour`: the colour of
    every node, int32 array of shape ``(n_nodes,)`` (unreferenced nodes get colour 0). (The sweeps group the nodes
    of a colour themselves, by class: `jaxci.optim._moves.coloured_stars`, `jaxci.optim.host_local`.)
    """

    colour: np.ndarray

    @property
    def n_colours(self) -> int:
        return int(self.colour.max()) + 1 if len(self.colour) else 0


def _lowest_free_colour(used: np.ndarray) -> np.ndarray:
    """Index of the lowest zero bit of each uint64 in `used` (-1 where all 64 bits are set)."""
    free = ~used & (used + np.uint64(1))
    out = np.frexp(free.astype(np.float64))[1].astype(np.int64) - 1
    return np.where(free == 0, -1, out)


def colour_nodes(
    hexes: np.ndarray,
    n_nodes: int,
    adjacency: tuple[np.ndarray, np.ndarray] | None = None,
) -> Colouring:
    """Greedy (first-fit) colouring of the nodes in index order, computed in parallel rounds.

    This is the Jones-Plassmann scheme with the node index as priority: a round colours every node whose
    lower-numbered neighbours all have a colour, each with the smallest colour none of them has. The nodes of a
    round are pairwise non-adjacent, so the result is exactly the sequential first-fit colouring in index order;
    on a structured box (lexicographic numbering) that is the 8-colouring by index parity. The work per round
    touches only the nodes coloured in it; the number of rounds is the longest chain of neighbours with
    increasing indices (a few hundred for a 100^3 box).

    **Arguments:**

    - `hexes`: integer array of shape ``(n_hexes, 8)``.
    - `n_nodes`: number of nodes.
    - `adjacency`: optional precomputed ``node_adjacency(hexes, n_nodes)``.

    **Returns:** a `Colouring`. The last one of a read-only `hexes` array (`HexMesh.hexes`) is kept, so the
    untangling stage and the shape improvement of one run colour once (0.8 s at 216,000 hexahedra).
    """
    n = int(n_nodes)
    cached = _LAST_COLOURING.get("key")
    same = adjacency is None and isinstance(hexes, np.ndarray) and not hexes.flags.writeable
    if same and cached is not None and cached[0]() is hexes and cached[1] == n:
        return _LAST_COLOURING["value"]
    out = _colour_nodes(hexes, n, adjacency)
    if same:  # dropped with the array (a callback): the cache never keeps a colouring past its mesh
        _LAST_COLOURING.clear()
        _LAST_COLOURING.update(key=(weakref.ref(hexes, _forget_colouring), n), value=out)
    return out


def _forget_colouring(ref) -> None:
    """The callback of the cached array's weak reference: forget its colouring (not a newer one's)."""
    if _LAST_COLOURING.get("key", (None,))[0] is ref:
        _LAST_COLOURING.clear()


#: `colour_nodes`' last result for a read-only connectivity array (a weak reference to it, and the node count).
_LAST_COLOURING: dict = {}


def _colour_nodes(hexes, n: int, adjacency) -> Colouring:
    """`colour_nodes` without its cache: in C (`jaxci.native.greedy_colour`, one pass: 3 ms against 0.18 s at
    27,000 hexahedra) for one cell array without a given adjacency, else by the numpy rounds; the same colours."""
    from .. import native

    if adjacency is None and native.AVAILABLE and isinstance(hexes, np.ndarray) and hexes.ndim == 2:
        return Colouring(native.greedy_colour(hexes, n))
    return Colouring(_first_fit_rounds(hexes, n, adjacency))


def _first_fit_rounds(hexes, n: int, adjacency) -> np.ndarray:
    """The first-fit colours ``(n,)`` by `colour_nodes`' parallel rounds (numpy)."""
    indptr, indices = node_adjacency(hexes, n) if adjacency is None else adjacency
    rows = np.repeat(np.arange(n, dtype=indices.dtype), np.diff(indptr))
    pending = np.bincount(rows[indices < rows], minlength=n).astype(np.int64)
    del rows
    colour = np.full(n, -1, dtype=np.int64)
    ready = np.flatnonzero(pending == 0)
    while ready.size:
        owner, nb = csr_gather(indptr, indices, ready)
        c = colour[nb]
        chosen = np.full(len(ready), -1, dtype=np.int64)
        word = 0
        while (chosen < 0).any():
            lo = 64 * word
            inword = (c >= lo) & (c < lo + 64)
            bits = np.zeros(len(c), dtype=np.uint64)
            bits[inword] = np.left_shift(np.uint64(1), (c[inword] - lo).astype(np.uint64))
            used = np.zeros(len(ready), dtype=np.uint64)
            np.bitwise_or.at(used, owner, bits)
            low = _lowest_free_colour(used)
            take = (chosen < 0) & (low >= 0)
            chosen[take] = lo + low[take]
            word += 1
        colour[ready] = chosen
        higher = nb[nb > ready[owner]]
        np.subtract.at(pending, higher, 1)
        ready = np.unique(higher[pending[higher] == 0])
    return np.maximum(colour, 0).astype(np.int32)


def components(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the undirected graph on `n` vertices with edges ``(a[j], b[j])``: ``(count,
    labels)``, labels int32 numbered by each component's lowest vertex (as `scipy.sparse.csgraph`'s, without
    importing it: 0.1 s of every command's start).

    Hooking and pointer jumping: every vertex points to a vertex of lower or equal index in its component; each
    round hooks the larger of two roots joined by an edge under the smaller, then compresses every path."""
    parent = np.arange(n)
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    while len(a):
        ra, rb = parent[a], parent[b]
        differ = ra != rb
        if not differ.any():
            break
        a, b, ra, rb = a[differ], b[differ], ra[differ], rb[differ]
        np.minimum.at(parent, np.maximum(ra, rb), np.minimum(ra, rb))
        while True:
            up = parent[parent]
            if np.array_equal(up, parent):
                break
            parent = up
    roots, labels = np.unique(parent, return_inverse=True)
    return len(roots), labels.astype(np.int32)
