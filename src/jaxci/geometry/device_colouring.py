"""Node incidences and a parallel node colouring of a hexahedral mesh, built on the device (the JAX engine).

The host builds both in numpy and C (`jaxci.geometry.topology.colour_nodes`: first-fit in index order;
`jaxci.optim._local.node_stars`: one stable argsort of the 8 N corner nodes). On the JAX engine the mesh stays on
the device, and these are its versions, jitted programs over the transposed connectivity ``(8, N)``:

- `incidences`: every node's incidences ``8 e + s`` (the node is local corner ``s`` of hexahedron ``e``), in
  increasing order as `node_stars(..., incidences=True)` lists them, as a table ``(n, K)`` (K the largest
  valence, the one number that comes down to the host). No sort: XLA's sort of the 8 N incidences took 6 s at
  10^6 hexahedra on a CPU (numpy's 0.5 s), so the table fills one column per round, each node's smallest code
  not yet placed by one scatter-min over the incidences (K rounds, deterministic).
- `colour_nodes_device`: a colouring such that no two nodes of one colour share a hexahedron, by Jones and
  Plassmann's parallel rounds with hashed priorities: a round colours every uncoloured node whose priority beats
  those of its uncoloured neighbours (through hexahedra), each with the lowest colour that none of its coloured
  neighbours has (a bit mask of 32-colour words). The nodes of one round share no hexahedron, so the result is
  valid; it is deterministic (the priorities are a fixed bijective hash of the node index). It uses more colours
  than the host's first-fit in index order (8 on a box numbered lexicographically), whose rounds follow chains
  of increasing indices (hundreds of rounds on a 100^3 box, each a pass over the mesh); hashed priorities take
  a few dozen.

Hexahedral meshes only; a mixed mesh keeps the host's colouring (`jaxci.interface.methods.Problem.colour`).
"""

from __future__ import annotations

from ..runtime._lazy import jax, jit, jnp, pytree_dataclass
from ..runtime.transfer import program, to_host

#: Bits of a colour word of `colour_nodes_device` (uint32 masks of the colours a node's neighbours hold).
WORD = 32


@pytree_dataclass
class Incidences:
    """Every node's incidences, on the device.

    - `table` ``(n, K)`` int32: the incidences ``8 e + s`` of each node in increasing order in its first
      `valence` entries; the rest repeat the first (0 for a node of no hexahedron).
    - `valence` ``(n,)`` int32: the number of hexahedra at each node.
    """

    table: jax.Array
    valence: jax.Array

    @property
    def width(self) -> int:
        return int(self.table.shape[1])

    def mask(self):
        """The real entries of `table`, bool ``(n, K)``."""
        return jnp.arange(self.width, dtype=jnp.int32)[None, :] < self.valence[:, None]


def _corner_codes(n_hex: int):
    """The incidence code ``8 e + s`` of every entry of a transposed connectivity ``(8, N)``, int32."""
    return 8 * jnp.arange(n_hex, dtype=jnp.int32)[None, :] + jnp.arange(8, dtype=jnp.int32)[:, None]


def valence(conn, n_nodes: int):
    """The valence of every node ``(n,)`` (device) and the largest (a Python int, at least 1: the one scalar that
    comes down), for the hexahedra `conn` (device, transposed ``(8, N)``)."""
    v, kmax = _valence(conn, int(n_nodes))
    return v, max(int(to_host(kmax)), 1)


@program
@jit(static_argnames=("n_nodes",))
def _valence(conn, n_nodes: int):
    v = jnp.zeros(n_nodes, jnp.int32).at[conn.reshape(-1).astype(jnp.int32)].add(1)
    return v, jnp.max(v, initial=0)


def incidence_table(conn, valence, width: int):
    """`Incidences.table` ``(n, width)`` (traceable: call it inside a jitted function; `width` at least the
    largest valence): column k holds each node's k-th smallest incidence code (one scatter-min of the codes
    above column k-1's per column)."""
    n = valence.shape[0]
    nodes = conn.reshape(-1).astype(jnp.int32)
    codes = _corner_codes(conn.shape[1]).reshape(-1)
    big = jnp.iinfo(jnp.int32).max

    def column(k, carry):
        table, last = carry
        cand = jnp.where(codes > last[nodes], codes, big)
        m = jnp.full(n, big, jnp.int32).at[nodes].min(cand)
        return table.at[:, k].set(m), jnp.where(m < big, m, last)

    table = jnp.zeros((n, width), jnp.int32)
    table, _ = jax.lax.fori_loop(0, width, column, (table, jnp.full(n, -1, jnp.int32)))
    real = jnp.arange(width, dtype=jnp.int32)[None, :] < valence[:, None]
    return jnp.where(real, table, jnp.where(valence[:, None] > 0, table[:, :1], 0))


@program
@jit(static_argnames=("width",))
def _incidence_table(conn, valence, width: int):
    return incidence_table(conn, valence, width)


def incidences(conn, n_nodes: int) -> Incidences:
    """The `Incidences` of the hexahedra `conn` (device, transposed ``(8, N)``) over `n_nodes` nodes (two
    programs; the largest valence comes down between them: the table's width)."""
    v, width = valence(conn, n_nodes)
    return Incidences(table=_incidence_table(conn, v, width), valence=v)


def _hash(v):
    """A bijective hash of uint32 (MurmurHash3's finaliser): distinct priorities for distinct nodes."""
    v = v ^ (v >> 16)
    v = v * jnp.uint32(0x85EBCA6B)
    v = v ^ (v >> 13)
    v = v * jnp.uint32(0xC2B2AE35)
    return v ^ (v >> 16)


def _bit(c):
    """The uint32 bit of colour `c` (int32, any shape) in word 0; 0 for ``c < 0`` or beyond the word."""
    inword = (c >= 0) & (c < WORD)
    return jnp.where(inword, jnp.uint32(1) << jnp.clip(c, 0, WORD - 1).astype(jnp.uint32), jnp.uint32(0))


def _lowest_zero_bit(words):
    """Index of the lowest zero bit over the uint32 words ``(W, n)`` (word 0 first), ``(n,)`` int32; ``32 W``
    where every bit is set."""
    free = ~words & (words + jnp.uint32(1))  # the lowest zero bit alone, 0 where none
    bit = WORD - 1 - jax.lax.clz(free).astype(jnp.int32)
    out = jnp.full(words.shape[1], WORD * words.shape[0], jnp.int32)
    for w in range(words.shape[0] - 1, -1, -1):
        out = jnp.where(free[w] != 0, WORD * w + bit[w], out)
    return out


def _or_over(a, axis: int):
    return jax.lax.reduce(a, jnp.uint32(0), jax.lax.bitwise_or, (axis,))


def _tentative(used, key, palette: int):
    """Each node's proposal: from a colour drawn from ``[0, palette)`` by `key` (uint32 ``(n,)``), the first one
    none of its coloured neighbours holds (`used` ``(W, n)``), cyclically; past the palette the lowest free colour
    (where the palette is full)."""
    pal = jnp.uint32((1 << palette) - 1)
    avail = ~used[0] & pal
    start = (key % jnp.uint32(palette)).astype(jnp.uint32)
    rot = ((avail >> start) | (avail << ((jnp.uint32(palette) - start) % jnp.uint32(palette)))) & pal
    low = rot & (~rot + jnp.uint32(1))
    pick = (WORD - 1 - jax.lax.clz(low).astype(jnp.int32) + start.astype(jnp.int32)) % palette
    return jnp.where(avail != 0, pick, _lowest_zero_bit(used))


def speculative_colouring(conn, inc: Incidences, n_words: int, palette: int):
    """`colour_nodes_device`'s rounds (traceable): the colours ``(n,)`` int32, their count (a scalar; more than
    ``32 n_words`` when the words ran out) and the number of rounds."""
    conn = conn.astype(jnp.int32)
    n = inc.valence.shape[0]
    hexes = inc.table >> 3  # (n, K) the hexahedron of each incidence
    real = inc.mask()
    prio = _hash(jnp.arange(n, dtype=jnp.uint32))
    pc = prio[conn]  # (8, N)
    shifts = jnp.arange(n_words, dtype=jnp.int32)[:, None, None] * WORD

    def body(state):
        colour, r = state
        # the colours held around each node: per hexahedron, then over the node's hexahedra
        held = _or_over(_bit(colour[conn][None] - shifts), 1)  # (W, N)
        used = _or_over(jnp.where(real[None], held[:, hexes], jnp.uint32(0)), 2)  # (W, n)
        free = colour < 0
        tent = jnp.where(free, _tentative(used, _hash(prio ^ (jnp.uint32(0x9E3779B9) * r.astype(jnp.uint32))),
                                          palette), -1)
        # a proposal stands unless a neighbour of higher priority proposed the same colour (pairs within each
        # hexahedron, then over the node's hexahedra)
        t = tent[conn]  # (8, N)
        beats = (t[:, None] == t[None, :]) & (t[:, None] >= 0) & (pc[None, :] > pc[:, None])  # (8, 8, N)
        lost = jnp.any(beats, axis=1).T.reshape(-1)  # by incidence code 8 e + s
        lost = jnp.any(real & lost[inc.table], axis=1)
        return jnp.where(free & ~lost, tent, colour), r + 1

    colour, rounds = jax.lax.while_loop(lambda s: jnp.any(s[0] < 0), body,
                                        (jnp.full(n, -1, jnp.int32), jnp.int32(1)))
    return colour, jnp.max(colour, initial=-1) + 1, rounds - 1


@program
@jit(static_argnames=("n_words", "palette"))
def _speculative(conn, inc: Incidences, n_words: int, palette: int):
    return speculative_colouring(conn, inc, n_words, palette)


#: Colours `colour_nodes_device` proposes from at random: 16 on a box (chromatic number 8, 26 neighbours a node)
#: gave 19-20 colours in 6 rounds, the first 16 of one size (measured 2026-11-29: 100^3 box, 10^6 hexahedra);
#: first-fit proposals (the lowest free colour) took 17 rounds for 17 colours on a 20^3 box, most of its nodes
#: proposing the same colour as their neighbours.
PALETTE = 16


def colour_nodes_device(conn, inc: Incidences, n_words: int = 1, palette: int = PALETTE):
    """Colour the nodes of the hexahedra `conn` (device, transposed ``(8, N)``) on the device: no two nodes of
    one colour share a hexahedron (nodes of no hexahedron get colour 0); deterministic.

    Speculative rounds (Gebremedhin and Manne's scheme, data-parallel): every uncoloured node proposes a colour
    none of its coloured neighbours holds, drawn from the first `palette` colours by a hash of the node and the
    round (the lowest free one past them); a proposal stands unless a neighbour of higher (hashed) priority
    proposed the same colour. The highest-priority uncoloured node always keeps its proposal, so every round
    colours at least one node; in practice a handful of rounds colour all, in colours of nearly equal size.

    **Arguments:** `conn`; `inc` its `Incidences`; `n_words`: 32-colour words of the masks to start with
    (doubled and run again while a node finds every colour taken); `palette` (<= 32).

    **Returns:** ``(colour, n_colours)``: int32 device array ``(n,)`` and the colour count (a Python int: the
    one small array that comes down holds it and the round count).
    """
    while True:
        colour, count, rounds = _speculative(conn, inc, int(n_words), int(palette))
        count, _ = (int(v) for v in to_host((count, rounds)))
        if count <= WORD * n_words:
            return colour, count
        n_words *= 2
