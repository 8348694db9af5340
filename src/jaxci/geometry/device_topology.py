"""The boundary faces of a hexahedral mesh found on the device, and the nodes of no cell: only O(boundary) comes
down to the host.

`device_mesh_topology` keys each of the 6 M faces of the device connectivity by its 4 sorted nodes, as
`jaxci.geometry.topology.boundary_topology` does on the host, and groups equal keys by ONE sort of 64-bit words
(a program, `_face_groups`): the face's position in the low bits, above it a multiplicative hash of the key,
and on top the leading bits of the face's lowest node (windows of faces of nearby hexahedra, whose keys the
program then reads from cache). XLA:CPU sorts one array of words several times faster than it sorts two keys
with a payload (0.8 s against 3.4 s for the 6 x 10^6 faces of 10^6 hexahedra). Equal keys then lie side by side
in runs of one word; the keys themselves are compared to make the grouping exact. A run that holds different
keys (a collision of the truncated hash: expect a few among 10^6 hexahedra) is resolved by comparing each face
with its neighbours up to `_WINDOW` - 1 places away; should such a run be longer than that, the program runs
again with the keys themselves sorted (three keys: slower, exact by construction). A face of a group of one is
a boundary face; one face of each group of three or more is a non-manifold face. The same program marks the
nodes no hexahedron uses.

A second program (`_face_lists`) gathers the boundary faces in the host function's order (by face number:
hexahedron-major, `HEX_FACES` order within one), oriented as the hexahedron lists them, the non-manifold faces
and the unused nodes, into arrays padded to the size classes (`jaxci.runtime.sizes.bucket`) of their counts, which come
down first as 4 integers. The host then builds the edges (`jaxci.geometry.topology.topology_from_faces`,
O(boundary)). The result equals ``boundary_topology(hexes, n_nodes)`` array for array.

The device path is for hexahedral meshes: meshes with wedges, pyramids, tetrahedra or quadratic cells keep
the host's `jaxci.geometry.boundary.mesh_topology`.
"""

from __future__ import annotations

import functools

import numpy as np

from ..mesh.sorting import HASH_MIX, position_bits
from ..runtime._lazy import enable_x64, jax, jnp
from ..runtime.sizes import bucket
from ..runtime.transfer import program, to_device, to_host
from .topology import HEX_FACES, BoundaryTopology, topology_from_faces

#: A run of one hash holding different keys is resolved by comparing each face with the faces up to this many
#: places away minus one; a longer such run sends the program to the exact sort. Such a run takes 4 keys of one
#: hash (interior faces come in pairs): about 10^-6 of the 3 x 10^7 distinct faces of 10^7 hexahedra (38 bits of
#: hash), but some among 10^8 (34 bits), where the exact sort runs. 6 comparisons and 2 flags fill the uint8
#: `_face_codes`.
_WINDOW = 6
#: The sort puts the faces in windows of about ``2**_LOCAL_BITS`` positions of close lowest nodes (as
#: `jaxci.mesh.sorting.group_pairs` does): faces of nearby hexahedra, whose keys are then gathered from cache
#: (0.2 s against 0.7 s for the two gathers at 10^6 hexahedra).
_LOCAL_BITS = 16


def _sorted_face_keys(conn, n_nodes):
    """The two int64 keys ``(s0 n + s1, s2 n + s3)`` of every face's sorted nodes ``s0 <= s1 <= s2 <= s3``:
    `conn` ``(8, M)`` -> two arrays ``(6 M,)``, position ``f M + c`` holding face f (`HEX_FACES`) of hexahedron
    c (face-major: a concatenation, where the host's hexahedron-major order would be an interleave)."""
    cols = [jnp.concatenate([conn[int(HEX_FACES[f, i])] for f in range(6)]).astype(jnp.int64) for i in range(4)]
    for i, j in ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)):  # a sorting network, as `jaxci.mesh.sorting.sort4`
        cols[i], cols[j] = jnp.minimum(cols[i], cols[j]), jnp.maximum(cols[i], cols[j])
    return cols[0] * n_nodes + cols[1], cols[2] * n_nodes + cols[3]


def _shift(x, d: int, fill):
    """``x[i + d]`` for every i (`d` of either sign), `fill` outside."""
    pad = [(0, d, 0)] if d > 0 else [(-d, 0, 0)]
    return jax.lax.pad(x[d:] if d > 0 else x[: x.shape[0] + d], jnp.asarray(fill, x.dtype), pad)


#: The bits of `_face_codes`' codes: face i has the key of face i + d (d = 1 .. _WINDOW) at bit d - 1; faces
#: i and i + _WINDOW are in one run of the hash at `_RUN`; face i is real at `_REAL`.
_RUN, _REAL = _WINDOW, _WINDOW + 1


def _face_codes(conn, n_nodes, n_hexes, *, exact: bool = False, hash_bits: int | None = None):
    """Sort the faces of `conn` ``(8, M)`` (its first `n_hexes` columns; int64 device scalars, as `n_nodes`) by
    their keys and compare each with the next `_WINDOW` in that order. `exact`: sort the keys themselves;
    `hash_bits`: keep only so many bits of the hash (tests: collisions on purpose).

    **Returns:** ``(order, codes)``: the face positions (`_sorted_face_keys`) in sorted order, int32 ``(6 M,)``,
    and per position a uint8 of bits (`_RUN`, `_REAL`: what it shares with the next ones)."""
    m = 6 * conn.shape[1]
    k1, k2 = _sorted_face_keys(conn, n_nodes)
    pos = jnp.arange(m, dtype=jnp.int64)
    real = (pos % conn.shape[1]) < n_hexes
    if exact:
        top = jnp.iinfo(jnp.int64).max
        k1, k2, order = jax.lax.sort((jnp.where(real, k1, top), jnp.where(real, k2, top), pos), num_keys=3)
        h = None
    else:
        bits = position_bits(m)
        lead = min(max(bits - _LOCAL_BITS, 0), 64 - bits - 32)
        u = jnp.uint64
        h = (k1.astype(u) * u(int(HASH_MIX[0])) + k2.astype(u)) * u(int(HASH_MIX[1]))
        h = h >> u(bits + lead if hash_bits is None else 64 - hash_bits)
        if lead and hash_bits is None:  # the leading bits: those of the face's lowest node, s0 / n_nodes
            h = h | ((((k1 // n_nodes) << lead) // n_nodes).astype(u) << u(64 - bits - lead))
        h = jnp.where(real, h, u((1 << (64 - bits)) - 1))  # padding faces last
        words = jnp.sort((h << u(bits)) | pos.astype(u))
        order = (words & u((1 << bits) - 1)).astype(jnp.int64)
        h = words >> u(bits)
        k1, k2 = k1[order], k2[order]
    real = (order % conn.shape[1]) < n_hexes
    u8 = jnp.uint8
    codes = real.astype(u8) << _REAL  # one fused pass over the sorted keys
    for d in range(1, _WINDOW + 1):
        key = (k1 == _shift(k1, d, -1)) & (k2 == _shift(k2, d, -1))
        run = real & _shift(real, d, False) & (key if h is None else h == _shift(h, d, 0))
        codes = codes | ((run & key).astype(u8) << (d - 1))
        if d == _WINDOW:
            codes = codes | (run.astype(u8) << _RUN)
    return order.astype(jnp.int32), codes


def _face_masks(codes):
    """The boundary faces and the non-manifold faces (one of each group of three or more) among `codes`
    (`_face_codes`), bool ``(6 M,)`` each, and int64 ``[their counts, 1 if a run of one hash was too long]``.

    Each face sees its neighbours in sorted order up to `_WINDOW` - 1 places away (no prefix scan: XLA:CPU runs
    a cumulative sum of 6 x 10^6 entries in 0.2-0.4 s): a group of at most `_WINDOW` equal keys is seen whole by
    each of them; a longer group of one key (a non-manifold face of many cells) shows each face at least
    `_WINDOW` - 1 others; a run of one hash of more than `_WINDOW` faces holding two keys is the overflow."""
    u8 = jnp.uint8

    def bit(x, b):
        return (x >> b) & u8(1)

    ahead = sum(bit(codes, d - 1) for d in range(1, _WINDOW))
    behind = sum(bit(_shift(codes, -d, 0), d - 1) for d in range(1, _WINDOW))
    mult = 1 + ahead + behind  # the face's group, as far as it sees
    uniform = bit(codes, 0)
    for j in range(1, _WINDOW):
        uniform = uniform & bit(_shift(codes, j, 0), 0)
    overflow = (bit(codes, _RUN) == 1) & (uniform == 0)  # faces i .. i + _WINDOW: one run, not one key
    real = bit(codes, _REAL) == 1
    boundary = real & (mult == 1)
    nonmanifold = real & (behind == 0) & (mult >= 3)
    counts = jnp.stack([jnp.count_nonzero(boundary), jnp.count_nonzero(nonmanifold), jnp.count_nonzero(overflow)])
    return boundary, nonmanifold, counts.astype(jnp.int64)


def compact(mask, size: int):
    """``jnp.nonzero(mask, size=size, fill_value=len(mask))[0]`` (int32) for a `mask` ``(m,)`` with at most `size`
    True entries, in two levels (jit-able; `size` static): the blocks of `_BLOCK` entries holding one, then the
    entries of those blocks, each level by a sort of the True entries' positions (the others past the end). It
    sorts ``m / _BLOCK + size * _BLOCK`` entries, not m; and compiles in 0.2 s where ``jnp.nonzero``'s prefix
    sums compile in 0.5-0.7 s each (XLA:CPU; 0.15 s against 0.06 s to run at m = 6 x 10^6, size 65536)."""
    m = mask.shape[0]
    if size == 0:
        return jnp.zeros(0, jnp.int32)
    rows = -(-m // _BLOCK)
    blocks = jnp.concatenate([mask, jnp.zeros(rows * _BLOCK - m + _BLOCK, bool)]).reshape(rows + 1, _BLOCK)
    hit = first_true(blocks[:rows].any(axis=1), size)
    inner = first_true(blocks[hit].ravel(), size)
    found = jnp.append(hit, rows)[inner // _BLOCK] * _BLOCK + inner % _BLOCK
    return jnp.where(found < m, found, m)


def first_true(mask, size: int):
    """The positions of the first `size` True entries of `mask` ``(m,)``, int32, padded with m (jit-able; `size`
    static): one sort (it compiles in 0.07 s, ``jnp.nonzero`` in 0.5 s on XLA:CPU)."""
    m = mask.shape[0]
    first = jnp.sort(jnp.where(mask, jnp.arange(m, dtype=jnp.int32), m))[:size]
    return jnp.concatenate([first, jnp.full(size - first.shape[0], m, jnp.int32)])


#: `compact`'s block size.
_BLOCK = 8


def _face_nodes(conn, fid):
    """The nodes ``(k, 4)`` of the faces numbered `fid` ``(k,)`` as `boundary_topology` numbers them (face f of
    hexahedron c: 6 c + f; padding: any number >= 6 M, given face 0's) as their hexahedra list them, and the
    hexahedra ``(k,)``."""
    cell, local = jnp.divmod(fid, 6)
    ok = cell < conn.shape[1]
    cell, local = jnp.where(ok, cell, 0), jnp.where(ok, local, 0)
    table = jnp.asarray(HEX_FACES.T)  # (4, 6): corner i of face f is HEX_FACES[f, i]
    return jnp.stack([conn[table[i][local], cell] for i in range(4)], axis=1), cell


@program
@functools.partial(jax.jit, static_argnames=("size", "exact", "hash_bits"))
def _face_groups(conn, n_nodes, n_hexes, *, size: int, exact: bool = False, hash_bits: int | None = None):
    """`_face_codes` and `_face_masks` of `conn` ``(8, M)`` (its first `n_hexes` columns; `n_nodes` nodes, both
    int64 device scalars), and `_unused_mask` (`size`: its size class): ``(order, boundary, nonmanifold,
    unused, counts)``, counts int64 ``[n boundary, n non-manifold, overflow, n unused]``."""
    order, codes = _face_codes(conn, n_nodes, n_hexes, exact=exact, hash_bits=hash_bits)
    boundary, nonmanifold, counts = _face_masks(codes)
    unused, n_unused = _unused_mask(conn, n_hexes, n_nodes, size)
    # `codes` is an output only to be materialised: XLA:CPU otherwise recomputed it within `_face_masks` (2 s
    # more at 10^6 hexahedra, with or without an optimization barrier)
    return order, boundary, nonmanifold, unused, jnp.append(counts, n_unused), codes


def _unused_mask(conn, n_hexes, n_nodes, size: int):
    """Which of `n_nodes` nodes no hexahedron of `conn` ``(8, M)`` (its first `n_hexes`) uses, as a mask of
    `size` >= `n_nodes` entries (a size class: the entries past `n_nodes` False), and how many."""
    real = jnp.arange(conn.shape[1]) < n_hexes
    idx = jnp.where(real[None, :], conn, size).ravel()
    used = jnp.zeros(size, bool).at[idx].set(True, mode="drop")
    unused = ~used & (jnp.arange(size) < n_nodes)
    return unused, jnp.count_nonzero(unused).astype(jnp.int64)


@program
@functools.partial(jax.jit, static_argnames=("n_boundary", "n_nonmanifold", "n_unused"))
def _face_lists(conn, order, boundary, nonmanifold, unused, *, n_boundary: int, n_nonmanifold: int, n_unused: int):
    """The boundary faces (by face number, as `boundary_topology` orders them), the non-manifold faces and the
    unused nodes of `_face_groups`' output, padded to `n_boundary`, `n_nonmanifold` and `n_unused` rows:
    ``(faces (n_boundary, 4), face_hex (n_boundary,), nonmanifold (n_nonmanifold, 4), unused (n_unused,))``."""
    m = order.shape[0]
    big = conn.shape[1]

    def numbers(mask, size):  # face position f M + c -> the host's number 6 c + f (padding: 6 M)
        p = jnp.append(order, m)[compact(mask, size)]
        return jnp.where(p < m, 6 * (p % big) + p // big, m)

    faces, cell = _face_nodes(conn, jnp.sort(numbers(boundary, n_boundary)))
    nm, _ = _face_nodes(conn, numbers(nonmanifold, n_nonmanifold))
    return faces, cell, nm, compact(unused, n_unused)


def device_mesh_topology(conn, n_nodes: int, *, n_hexes: int | None = None,
                         _hash_bits: int | None = None) -> tuple[BoundaryTopology, np.ndarray]:
    """The boundary topology of a hexahedral mesh whose connectivity is on the device, and its unused nodes.

    **Arguments:**

    - `conn`: a device integer array of shape ``(8, M)``: hexahedron e's nodes (VTK order) are ``conn[:, e]``
      (the kernels' layout, `jaxci.metrics.hexahedron.transposed`).
    - `n_nodes`: the number of nodes (one more than the largest index).
    - `n_hexes`: the real hexahedra are the first `n_hexes` columns (default all: M); the others (the padding of
      a size class) are ignored.

    **Returns:** ``(topology, unused)``: the `BoundaryTopology`, equal to ``boundary_topology(hexes, n_nodes)``
    (`jaxci.geometry.topology`) array for array; and the sorted int64 indices of the nodes no hexahedron uses
    (`jaxci.geometry.boundary.classify_boundary`'s `unused`).

    Moves host <- device: 4 integers, then the boundary faces and their hexahedra, the non-manifold faces and
    the unused nodes (each padded to a size class); host -> device: 2 scalars. Host work: O(boundary faces).
    Runs inside ``jax.enable_x64(True)`` (64-bit keys).
    """
    m = int(conn.shape[1]) if n_hexes is None else int(n_hexes)
    with enable_x64():
        nn, nh = to_device(np.int64(n_nodes)), to_device(np.int64(m))
        size = bucket(n_nodes)
        *groups, counts, _ = _face_groups(conn, nn, nh, size=size, hash_bits=_hash_bits)
        nb, nk, overflow, n_unused = to_host(counts).tolist()
        if overflow:  # a long run of one hash with different keys: sort the keys themselves
            *groups, counts, _ = _face_groups(conn, nn, nh, size=size, exact=True)
            nb, nk, _, n_unused = to_host(counts).tolist()
        faces, face_hex, nm, unused = to_host(_face_lists(
            conn, *groups, n_boundary=bucket(nb), n_nonmanifold=bucket(nk), n_unused=bucket(n_unused)))
    nm = np.sort(np.asarray(nm[:nk], dtype=np.int64), axis=1)
    nm = nm[np.lexsort(nm.T[::-1])]  # in the order of their sorted nodes, as boundary_topology's
    topo = topology_from_faces(np.asarray(faces[:nb], dtype=np.int64), np.asarray(face_hex[:nb], dtype=np.int64),
                               nm, n_nodes)
    return topo, np.asarray(unused[:n_unused], dtype=np.int64)
