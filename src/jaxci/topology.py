"""Mesh topology in vectorised numpy: boundary quadrilaterals and edges, node adjacency, node colouring.

Everything here depends on the connectivity only (never on coordinates) and scales to millions of hexahedra:
no Python loop runs per element or per node. The face of a hexahedron is keyed by its four sorted node indices
(two int64 keys, so up to about 3e9 nodes); node adjacency is the sparsity pattern of ``A A^T`` for the
node-element incidence matrix ``A`` (scipy's sparse product, much faster than sorting the 56 node pairs of
every element).

Faces of a hexahedron (`HEX_FACES`) are VTK's, each listed counter-clockwise seen from outside a right-handed
element, so ``(x2 - x0) x (x3 - x1)`` of a boundary face points out of the mesh.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

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


@dataclasses.dataclass(frozen=True, eq=False)
class BoundaryTopology:
    """Boundary quadrilaterals and boundary edges of a hexahedral mesh.

    **Arguments:**

    - `faces`: the boundary quadrilaterals (faces used by exactly one hexahedron), int64 array of shape
      ``(n_faces, 4)``, oriented outward (counter-clockwise seen from outside a right-handed element).
    - `face_hex`: the hexahedron each boundary face belongs to, shape ``(n_faces,)``.
    - `edges`: the boundary edges (sides of boundary faces), int64 array of shape ``(n_edges, 2)`` with
      ``edges[:, 0] < edges[:, 1]``.
    - `face_edges`: for each boundary face, the index into `edges` of its sides ``(f0,f1), (f1,f2), (f2,f3),
      (f3,f0)``; shape ``(n_faces, 4)``.
    - `edge_face_ptr`, `edge_face`: CSR lists of the boundary faces around each boundary edge: the faces of
      edge ``e`` are ``edge_face[edge_face_ptr[e]:edge_face_ptr[e + 1]]``; shapes ``(n_edges + 1,)`` and
      ``(4 n_faces,)``.
    - `nonmanifold_faces`: the distinct faces shared by three or more hexahedra (an invalid mesh), as sorted
      node indices, shape ``(k, 4)``; they are not boundary faces.
    """

    faces: np.ndarray
    face_hex: np.ndarray
    edges: np.ndarray
    face_edges: np.ndarray
    edge_face_ptr: np.ndarray
    edge_face: np.ndarray
    nonmanifold_faces: np.ndarray

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
        return np.unique(self.faces)


def boundary_topology(hexes: np.ndarray, n_nodes: int) -> BoundaryTopology:
    """Find the boundary quadrilaterals and edges of a hexahedral mesh.

    **Arguments:**

    - `hexes`: connectivity in VTK node order, integer array of shape ``(n_hexes, 8)``.
    - `n_nodes`: number of nodes (one more than the largest index).

    **Returns:** a `BoundaryTopology`.
    """
    hexes = np.asarray(hexes, dtype=np.int64)
    n = np.int64(max(int(n_nodes), 1))
    all_faces = np.stack([hexes[:, HEX_FACES[:, i]] for i in range(4)], axis=-1).reshape(-1, 4)
    srt = np.sort(all_faces, axis=1)
    k1 = srt[:, 0] * n + srt[:, 1]
    k2 = srt[:, 2] * n + srt[:, 3]
    order = np.lexsort((k2, k1))
    k1o, k2o = k1[order], k2[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = (k1o[1:] != k1o[:-1]) | (k2o[1:] != k2o[:-1])
    group = np.cumsum(first) - 1
    count = np.bincount(group) if len(group) else np.zeros(0, np.int64)
    single = order[count[group] == 1]
    single.sort()
    faces = all_faces[single]
    face_hex = single // 6
    nonmanifold = srt[order[first & (count[group] >= 3)]]
    del all_faces, srt, k1, k2, order, k1o, k2o, first, group

    sides = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)  # (4F, 2)
    lo, hi = sides.min(axis=1), sides.max(axis=1)
    keys, inverse = np.unique(lo * n + hi, return_inverse=True)
    edges = np.stack([keys // n, keys % n], axis=1).astype(np.int64)
    face_edges = inverse.reshape(-1, 4).astype(np.int64)
    by_edge = np.argsort(inverse, kind="stable")
    edge_face = (by_edge // 4).astype(np.int64)
    edge_face_ptr = np.zeros(len(edges) + 1, dtype=np.int64)
    np.cumsum(np.bincount(inverse, minlength=len(edges)), out=edge_face_ptr[1:])
    return BoundaryTopology(
        faces=faces,
        face_hex=face_hex.astype(np.int64),
        edges=edges,
        face_edges=face_edges,
        edge_face_ptr=edge_face_ptr,
        edge_face=edge_face,
        nonmanifold_faces=nonmanifold,
    )


def incidence(cells: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """The node-cell incidence matrix of shape ``(n_nodes, n_cells)``, int32 ones, CSR.

    **Arguments:** `cells` an integer array of shape ``(n_cells, k)`` (hexahedra, faces, edges); `n_nodes`.
    """
    cells = np.asarray(cells, dtype=np.int64)
    n_cells, k = cells.shape
    return sp.csr_matrix(
        (np.ones(n_cells * k, dtype=np.int32), (cells.ravel(), np.repeat(np.arange(n_cells), k))),
        shape=(int(n_nodes), n_cells),
    )


def node_adjacency(hexes: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Node-node adjacency through shared hexahedra, in CSR form (a node is not its own neighbour).

    **Arguments:**

    - `hexes`: integer array of shape ``(n_hexes, 8)``.
    - `n_nodes`: number of nodes.

    **Returns:** ``(indptr, indices)``, int64 arrays of shapes ``(n_nodes + 1,)`` and ``(nnz,)``: the
    neighbours of node ``i`` are ``indices[indptr[i]:indptr[i + 1]]``, sorted.
    """
    a = incidence(hexes, n_nodes)
    g = (a @ a.T).tocsr()
    g.sort_indices()
    rows = np.repeat(np.arange(int(n_nodes)), np.diff(g.indptr))
    keep = g.indices != rows
    indices = g.indices[keep].astype(np.int64)
    indptr = np.zeros(int(n_nodes) + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows[keep], minlength=int(n_nodes)), out=indptr[1:])
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

    Nodes of one colour can be moved simultaneously: no element sees two of them move.

    **Arguments:**

    - `colour`: colour of every node, int32 array of shape ``(n_nodes,)`` (unreferenced nodes get colour 0).
    - `groups`: one sorted int64 array of node indices per colour.
    - `padded`: the groups padded to a fixed width, int32 array of shape ``(n_colours, max_group_size)``;
      padding entries hold ``n_nodes`` (one past the last node), so that ``x.at[idx].set(v, mode="drop")``
      ignores them and gathers need ``mode="fill"`` or the `mask`.
    - `mask`: True where `padded` holds a real node, bool array of the same shape.
    """

    colour: np.ndarray
    groups: tuple[np.ndarray, ...]
    padded: np.ndarray
    mask: np.ndarray

    @property
    def n_colours(self) -> int:
        return len(self.groups)


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

    **Returns:** a `Colouring`.
    """
    n = int(n_nodes)
    indptr, indices = node_adjacency(hexes, n) if adjacency is None else adjacency
    rows = np.repeat(np.arange(n), np.diff(indptr))
    pending = np.bincount(rows[indices < rows], minlength=n).astype(np.int64)
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
    colour = np.maximum(colour, 0).astype(np.int32)
    n_colours = int(colour.max()) + 1 if n else 0
    order = np.argsort(colour, kind="stable")
    sizes = np.bincount(colour, minlength=n_colours)
    groups = tuple(np.split(order.astype(np.int64), np.cumsum(sizes)[:-1])) if n else ()
    width = int(sizes.max()) if n else 0
    padded = np.full((n_colours, width), n, dtype=np.int32)
    mask = np.zeros((n_colours, width), dtype=bool)
    slot = np.arange(n) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    padded[colour[order], slot] = order
    mask[colour[order], slot] = True
    return Colouring(colour=colour, groups=groups, padded=padded, mask=mask)
