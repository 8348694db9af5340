"""Node incidences of a hexahedral mesh: per-element values summed into the nodes without contended scatter-adds.

The gradient of F (`jaxci.metrics.hexahedron.objective_terms_and_grad`) is formed per element: three ``(8, N)``
arrays, the x, y, z components at local node m of element e at ``[m, e]`` (slot ``s = m N + e`` of the flattened
array, the slot of ``conn.reshape(-1)``). They are summed into the nodes in one of three forms (`FORMS`):

- ``"scatter"``: 24 scatter-adds (`.at[].add`, a local node and a coordinate each), no table. On a GPU these are
  contended atomic adds (a node's up to 8 incident slots at once) whose order, hence the rounding, varies from
  run to run; padding elements (weight 0) add their zeros to element 0's nodes.
- ``"gather"``: a table ``(K, n)`` of each node's incident slots (K the largest valence, rounded up), unused
  entries ``8N`` (read as 0): the node's sum is the sum of K gathers in a fixed order (row 0 first), with no
  write conflict at all.
- ``"segment"``: the slots sorted by node (a stable sort: by slot within a node), then ONE
  `jax.ops.segment_sum` with ``indices_are_sorted=True``.

Padding elements (weight 0) take no part in either table: their slots get the key ``n`` (past every node), which
the gather table never lists and the segment sum drops. The tables are built once per problem, on the device,
from the connectivity (`node_incidence`: one sort of the 8N ``(node, slot)`` pairs, packed in 64-bit keys, and
a search for each node's first slot; one scalar, the largest valence, comes back to the host), and are passed
to the compiled functions as an argument (an `Incidence`, a pytree of integer arrays; None: the scatter form).

The gather form sums in a fixed order and is bit-identical from run to run on any device. The segment sum is a
scatter too: sequential on a CPU, so also bit-identical there; on a GPU XLA may lower it to atomic adds.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

from ..runtime._lazy import compute_platform, jax, jit, jnp

#: The ways `accumulate` sums per-element values into the nodes.
FORMS = ("scatter", "gather", "segment")


def default_form(platform: str | None = None) -> str:
    """The form the JAX engine's closed-form gradient uses on `platform` (default: the one JAX computes on): the
    one rule, from scripts/bench_kernel.py (F + gradient, warm, median of alternated rounds; docs/results/kernel.md).

    - CPU: ``"scatter"``. XLA:CPU's scatter is a sequential loop (no atomics, deterministic), and the other forms
      must first write the per-element gradients out. Measured 2026-11-29 at 272eb82 on 2 shared cores (load
      ~10), M corners/s scatter / gather / segment (the C kernel, which `jaxci.optim.gradient` runs instead on
      CPU devices where it is built): 10^5 hexahedra float32 4.1 / 3.2 / 3.1 (14.6) and 2.9 / 2.8 / 2.6 (10.4),
      float64 2.6 / 2.2 / 2.2 (16.4) and 1.3 / 0.9 / 0.8 (6.7); 10^6 float32 3.1 / 2.4 / 2.5 (8.8) and
      2.5 / 2.3 / 1.9 (7.6), float64 1.5 / 1.3 / 1.3 (9.6) and 1.4 / 1.2 / 1.2 (8.0).
    - Any other platform (GPU): ``"gather"``: no atomics, no write conflicts, bit-identical from run to run,
      where the scatter-adds are contended atomics. Not yet measured against the others on a GPU (the H200's
      scatter form: 14.8 G corners/s float32 at 10^7 hexahedra, docs/results/gpu.md).
    """
    platform = compute_platform() if platform is None else platform
    return "scatter" if platform == "cpu" else "gather"


class Incidence(NamedTuple):
    """The nodes' incident slots for `accumulate`, one form's fields set, the others None.

    - `table` ``(K, n)`` (gather form): row k, column v the k-th slot ``m N + e`` incident to node v, or ``8N``.
    - `order` ``(8N,)`` and `keys` ``(8N,)`` (segment form): every slot sorted by node, and the node of each
      sorted slot (``n`` for a padding element's slots: dropped).
    """

    table: object = None
    order: object = None
    keys: object = None


def _index_dtype(size: int):
    return jnp.int32 if size < 2**31 - 1 else jnp.int64


def _sorted_slots(conn, weight, n_nodes: int):
    """The slots of `conn` ``(8, N)`` sorted by node, by slot within a node: ``(keys, order, largest valence)``;
    the slots of elements with weight 0 get key `n_nodes` (sorted last, counted in no valence). Traced with
    64-bit integers: one sort of the packed keys ``node 8N + slot`` (on a CPU 4x faster than XLA's sort of the
    (node, slot) pairs: 0.13 s against 0.50 s at 10^5 hexahedra, 2 shared cores)."""
    with jax.enable_x64(True):
        return _sorted_packed(conn, weight, n_nodes)


@jit(static_argnames="n_nodes")
def _sorted_packed(conn, weight, n_nodes: int):
    size = conn.size
    key = conn.reshape(-1).astype(jnp.int64)
    if weight is not None:
        key = jnp.where(jnp.tile(weight > 0, conn.shape[0]), key, n_nodes)
    packed = jax.lax.sort(key * size + jnp.arange(size, dtype=jnp.int64))
    idx = _index_dtype(size + 1)
    keys, order = (packed // size).astype(idx), (packed % size).astype(idx)
    start, end = _bounds(keys, n_nodes)
    return keys, order, jnp.max(end - start, initial=0)


def _bounds(keys, n_nodes: int):
    """First and one-past-last position of each node's slots in the sorted `keys`, each ``(n_nodes,)``."""
    nodes = jnp.arange(n_nodes, dtype=keys.dtype)
    return (jnp.searchsorted(keys, nodes, side="left").astype(keys.dtype),
            jnp.searchsorted(keys, nodes, side="right").astype(keys.dtype))


@jit(static_argnames=("n_nodes", "k"))
def _gather_table(keys, order, n_nodes: int, k: int):
    """The ``(k, n_nodes)`` gather table from the sorted slots (`_sorted_slots`): a gather, no scatter."""
    start, end = _bounds(keys, n_nodes)
    pos = start[None, :] + jnp.arange(k, dtype=keys.dtype)[:, None]
    return jnp.where(pos < end[None, :], order[jnp.minimum(pos, order.size - 1)], order.size)


def valence_class(k: int) -> int:
    """The table height for a largest valence `k`: at least 8 (a hexahedral mesh's interior node), else `k`
    rounded up to a multiple of 4, so that meshes of one size class mostly share one compiled program."""
    return max(8, -(-int(k) // 4) * 4)


def node_incidence(conn, n_nodes: int, weight=None, form: str | None = None) -> Incidence | None:
    """The incidences of `conn` ``(8, N)`` (a JAX array: built where it lives) over `n_nodes` nodes for the
    `form` (default `default_form`): an `Incidence`, or None for ``"scatter"``. `weight` optional ``(N,)``: the
    slots of elements of weight 0 (padding) are left out. One sort on the device; only the largest valence
    (a scalar) comes to the host, for the gather table's static height. Warm on 2 shared CPU cores (load ~10):
    0.05-0.21 s at 10^5 hexahedra, 2.2-4.5 s at 10^6 (docs/results/kernel.md)."""
    form = default_form() if form is None else form
    if form not in FORMS:
        raise ValueError(f"unknown kernel form {form!r}; choose one of {', '.join(FORMS)}")
    if form == "scatter":
        return None
    keys, order, kmax = _sorted_slots(conn, weight, int(n_nodes))
    if form == "segment":
        return Incidence(order=order, keys=keys)
    return Incidence(table=_gather_table(keys, order, int(n_nodes), valence_class(int(kmax))))


def accumulate(values, conn, n_nodes: int, incidence: Incidence | None):
    """Sum per-slot `values` into the nodes: `values` a sequence of ``(8, N)`` arrays (one per component, slot
    ``[m, e]`` at node ``conn[m, e]``), returns ``(n_nodes, len(values))`` in their dtype. `incidence`: None
    (scatter-adds) or `node_incidence`'s for `conn` (its padding slots never reach a node).

    With an incidence, one component per iteration of a loop, its sum chosen by `jax.lax.switch`: the values are
    then operands of the loop, computed once. Written as one expression, XLA fuses their computation into the
    gathers and recomputes every corner's quantities per gathered slot (on a CPU, where XLA drops
    `jax.lax.optimization_barrier` before fusing: 4-7x slower than the scatter-adds at 27,000 hexahedra)."""
    if incidence is None:
        return jnp.stack([scatter_add(jnp.zeros(n_nodes, v.dtype), conn, v) for v in values], axis=1)
    values = tuple(values)
    sums = [functools.partial(_node_sum, d=d, n_nodes=n_nodes, incidence=incidence) for d in range(len(values))]
    out = jax.lax.fori_loop(0, len(values), lambda d, g: g.at[d].set(jax.lax.switch(d, sums, values)),
                            jnp.zeros((len(values), n_nodes), values[0].dtype))
    return out.T


def _node_sum(values, d: int, n_nodes: int, incidence: Incidence):
    """Component `d` of `values` summed into the nodes by the `incidence`, ``(n_nodes,)``."""
    flat = values[d].reshape(-1)
    if incidence.table is None:
        return jax.ops.segment_sum(flat[incidence.order], incidence.keys, n_nodes, indices_are_sorted=True)
    table = incidence.table
    g = flat.at[table[0]].get(mode="fill", fill_value=0)
    for k in range(1, table.shape[0]):  # a fixed order: row by row
        g = g + flat.at[table[k]].get(mode="fill", fill_value=0)
    return g


def scatter_add(g, conn, val):
    """`g` ``(n,)`` plus the slots `val` ``(8, N)`` scattered to their nodes `conn` ``(8, N)`` (one scatter-add
    per local node: the scatter form)."""
    for m in range(conn.shape[0]):
        g = g.at[conn[m]].add(val[m])
    return g
