"""Multi-device execution: elements (and cohort candidates) sharded over every visible device.

A mesh too large for one device is split by ELEMENTS: the transposed connectivity ``(8, N)`` is padded to a
multiple of the device count and sharded along N (`jax.sharding.NamedSharding`), node coordinates are
replicated, and XLA's SPMD partitioner turns the gathers into local work and the reductions (the objective's
sum, the gradient's scatter into nodes) into all-reduces. Padding elements repeat element 0 with weight 0, so
the result equals the single-device one. Cohort candidates ``(C, n, 3)`` are split by CANDIDATE with
`jax.shard_map`: each device evaluates its own candidates.

On one host, every local device is used (GPUs, or CPU devices made with
``XLA_FLAGS=--xla_force_host_platform_device_count=4``). On several hosts, call `init_distributed` first in
every process (it wraps `jax.distributed.initialize`, which reads the coordinator address, process count and
id from the cluster environment or its arguments); then `jax.devices()` spans all hosts and the same code runs.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..cells import corner_invariants
from ..metrics.hexahedron import (
    corner_columns,
    gather_corners,
    objective_t,
    squared_condition_from_invariants,
)

AXIS = "d"


def init_distributed(**kwargs) -> None:
    """Join a multi-host JAX job (`jax.distributed.initialize(**kwargs)`); call once per process, first."""
    jax.distributed.initialize(**kwargs)


def device_mesh(devices=None) -> Mesh:
    """A 1-D `Mesh` over `devices` (default: all of `jax.devices()`), axis name ``"d"``."""
    devs = np.asarray(jax.devices() if devices is None else devices)
    return Mesh(devs, (AXIS,))


def shard_elements(points, hexes, mesh: Mesh | None = None):
    """Place a problem on `mesh`: points replicated, connectivity sharded by element.

    **Arguments:** `points` of shape ``(n, 3)``; `hexes` of shape ``(N, 8)``; `mesh` (default `device_mesh()`).

    **Returns:** ``(points, conn, weight)``: replicated points; transposed connectivity ``(8, N_pad)`` sharded
    along its second axis; element weights ``(N_pad,)`` (1 for real, 0 for padding elements), sharded alike.
    """
    mesh = device_mesh() if mesh is None else mesh
    n_dev = mesh.devices.size
    hexes = np.asarray(hexes)
    n = len(hexes)
    n_pad = -(-n // n_dev) * n_dev
    conn = np.concatenate([hexes, np.repeat(hexes[:1], n_pad - n, axis=0)]).T.copy()
    weight = np.concatenate([np.ones(n), np.zeros(n_pad - n)])
    along = NamedSharding(mesh, P(None, AXIS))
    return (
        jax.device_put(jnp.asarray(points), NamedSharding(mesh, P())),
        jax.device_put(jnp.asarray(conn), along),
        jax.device_put(jnp.asarray(weight, dtype=jnp.asarray(points).dtype), NamedSharding(mesh, P(AXIS))),
    )


@jax.jit
def weighted_objective(points, conn, weight):
    """F (Eq. 3.1) over the elements with weight 1 (padding elements, weight 0, are left out). Any sharding.

    **Arguments:** `points` ``(n, 3)``; `conn` ``(8, N)``; `weight` ``(N,)``. **Returns:** a scalar.
    """
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(points, conn)))
    term = squared_condition_from_invariants(det, fro2, adj2)  # (8, N)
    total = jnp.sum(jnp.where(weight > 0, term, 0.0))
    return total / (8.0 * jnp.sum(weight)) - 1.0


def sharded_candidates_objective(candidates, conn, mesh: Mesh | None = None):
    """F of every candidate of a cohort, candidates split over the devices of `mesh`.

    **Arguments:** `candidates` of shape ``(C, n, 3)`` with C a multiple of the device count; `conn` ``(8, N)``.

    **Returns:** shape ``(C,)``, equal to `jaxci.metrics.hexahedron.objective_t` per candidate.
    """
    mesh = device_mesh() if mesh is None else mesh

    @functools.partial(jax.shard_map, mesh=mesh, in_specs=(P(AXIS), P()), out_specs=P(AXIS))
    def per_device(local, conn):
        return jax.lax.map(lambda x: objective_t(x, conn), local)

    return jax.jit(per_device)(candidates, conn)
