"""Multi-device execution: elements (and cohort candidates) sharded over every visible device.

A mesh too large for one device is split by ELEMENTS: the transposed connectivity ``(8, N)`` is padded to a
multiple of the device count and sharded along N (`jax.sharding.NamedSharding`), node coordinates are
replicated, and XLA's SPMD partitioner turns the gathers into local work and the reductions (the objective's
sum, the gradient's scatter into nodes) into all-reduces. Padding elements repeat element 0 with weight 0, so
the result equals the single-device one. Cohort candidates ``(C, n, 3)`` are split by CANDIDATE with
`jax.shard_map`: each device evaluates its own candidates.

On one host, every local device is used (GPUs, or CPU devices made with
``XLA_FLAGS=--xla_force_host_platform_device_count=4``; with more of those than cores, also
``--xla_disable_hlo_passes=cpu-parallel-task-assigner``: `jaxci.runtime.process.cpu_device_flags`). On several
hosts, call `init_distributed` first in every process (it wraps `jax.distributed.initialize`, which reads the
coordinator address, process count and id from the cluster environment or its arguments); then
`jax.devices()` spans all hosts and the same code runs.

**Sharded smoothing** (`jaxci.smooth(..., devices=...)`, ``jaxci smooth --devices N|all``): `resolve_devices`
turns the request into a `Mesh`; `sharded_params` checks the method and sends L-BFGS to a compiled loop
(never the numpy host path, which runs on one CPU); `jaxci.optim.gradient.minimise` and the smart-Laplace
presmoothing (`jaxci.optim.laplace.laplace`) pad the elements to a multiple of the device count and place their
arguments with `place_problem`: the element arrays (and the sweeps' node slots of every colour) sharded, the
rest (coordinates, constraints) replicated. L-BFGS runs `jaxci.optim.lbfgs.lbfgs_loop`, whose memory is
split by free coordinate over the devices (BFGS and CG: optimistix's loop, its vectors replicated). The solver's
loop and the sweeps then compile once each, as one SPMD program over every device. docs/sharding.md has the
measurements and the multi-host launch.
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from .. import native
from ..errors import ConfigError
from ..metrics import native_grad
from ..metrics.hexahedron import objective_terms_and_grad

AXIS = "d"


def init_distributed(coordinator_address: str | None = None, num_processes: int | None = None,
                     process_id: int | None = None, **kwargs) -> None:
    """Join a multi-process JAX job; call once per process, before anything else uses JAX.

    `jax.distributed.initialize` with these arguments (None: read from the cluster environment, e.g. SLURM or
    Open MPI; `kwargs` go through, e.g. ``initialization_timeout``). On CPUs the processes' collectives go
    through gloo (``jax_cpu_collectives_implementation``, JAX's default in 0.10). Then `jax.devices()` lists
    every process's devices, and ``jaxci.smooth(mesh, ..., devices="all")``, called by every process with the
    same mesh, runs one program over all of them; each process gets the whole result (tested with two
    processes on one host: the same mesh as on one device).
    """
    jax.distributed.initialize(coordinator_address=coordinator_address, num_processes=num_processes,
                               process_id=process_id, **kwargs)


def device_mesh(devices=None) -> Mesh:
    """A 1-D `Mesh` over `devices` (default: all of `jax.devices()`), axis name ``"d"``."""
    devs = np.asarray(jax.devices() if devices is None else devices)
    return Mesh(devs, (AXIS,))


#: The methods that run sharded (`sharded_params`): the compiled optimistix loop, the (smart) Laplacian (also
#: the presmoothing of the first four), local CI (elements and node slots) and global CI (its trial meshes).
SHARDED_METHODS = ("auto", "lbfgs", "bfgs", "cg", "laplace", "smart-laplace", "ci", "ci-global")

#: The sharded methods that small meshes run on the host without ``devices`` (``backend="auto"``): with it they
#: get ``backend="jax"``.
HOST_METHODS = ("auto", "lbfgs", "laplace", "smart-laplace", "ci", "ci-global")

#: How to get several devices on one CPU (said when too few exist).
FORCE_HINT = ("on a CPU, XLA_FLAGS=--xla_force_host_platform_device_count=N set before JAX starts makes N "
              "devices of its cores")


#: What Linux calls the threads of XLA:CPU's intra-op pool (``tf_`` + the pool's name ``XLAEigen``).
XLA_POOL_THREAD = "tf_XLAEigen"


def xla_cpu_threads() -> int | None:
    """The threads of XLA:CPU's intra-op pool in this process (creating JAX's CPU client if need be), counted
    in ``/proc/self/task``; None where that cannot be read (not Linux).

    XLA sizes this pool to max(``NPROC`` or ``PJRT_NPROC`` if set, else the schedulable cores; the number of
    CPU devices) and compiles every large fusion into that many parallel parts. So 4 forced CPU devices on a
    2-core machine make 4 threads on 2 cores for EVERY program of the process, sharded or not: the cause of the
    2.3-2.6x slower 4-device runs in docs/sharding.md (a one-device process with ``NPROC=4`` is as slow). No
    setting lowers it below the device count (XLA needs one thread per device to run a collective); what
    helps is not splitting the fusions (`jaxci.runtime.process.cpu_device_flags`)."""
    jax.devices("cpu")
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return None
    n = 0
    for t in tasks:
        try:
            with open(f"/proc/self/task/{t}/comm") as f:
                n += f.read().strip() == XLA_POOL_THREAD
        except OSError:  # the thread ended meanwhile
            pass
    return n if tasks else None


def resolve_devices(devices, platform: str | None = None) -> Mesh:
    """The 1-D device `Mesh` of a ``devices=`` request (`ConfigError` for a bad one, saying what exists).

    **Arguments:** `devices`: a positive int N (the first N of `jax.devices()`), ``"all"`` (every device, of
    every host after `init_distributed`), or a sequence of `jax.Device` objects or of indices into
    `jax.devices()`; `platform`: ``"cpu"`` (or another JAX platform) to take that platform's devices instead of
    the default platform's.
    """
    have = jax.devices(platform) if platform else jax.devices()
    what = f"{len(have)} {have[0].platform} device{'s' if len(have) != 1 else ''}"
    exist = f"{what} {'exist' if len(have) != 1 else 'exists'}"
    if isinstance(devices, str) and devices == "all":
        return device_mesh(have)
    if isinstance(devices, (str, bool)) or not isinstance(devices, (int, np.integer, list, tuple)):
        raise ConfigError(f"devices must be a positive integer, 'all' or a list of devices, got {devices!r}")
    if not isinstance(devices, (list, tuple)):
        n = int(devices)
        if n < 1:
            raise ConfigError(f"devices must be at least 1, got {n}")
        if n > len(have):
            raise ConfigError(f"devices={n}, but only {exist}; {FORCE_HINT}")
        return device_mesh(have[:n])
    if not devices:
        raise ConfigError("devices is an empty list")
    chosen = []
    for d in devices:
        if isinstance(d, (int, np.integer)) and not isinstance(d, bool):
            if not 0 <= int(d) < len(have):
                raise ConfigError(f"device index {d} is out of range: {exist} (indices 0 to {len(have) - 1})")
            d = have[int(d)]
        if d not in have:
            raise ConfigError(f"{d!r} is not one of the {what} of this process ({FORCE_HINT})")
        chosen.append(d)
    if len(set(chosen)) != len(chosen):
        raise ConfigError(f"devices lists a device twice: {devices!r}")
    return device_mesh(chosen)


def sharded_params(method: str, params: dict, mesh: Mesh) -> tuple[dict, str]:
    """`params` for a sharded run of `method` on `mesh` and the note that says how it runs.

    L-BFGS, the Laplacians and the default pipeline (`HOST_METHODS`) get ``backend="jax"``: the compiled loop,
    never the numpy host path (one CPU, no devices), so that small and large meshes run the same sharded
    program. `ConfigError` for a method that does not run sharded and for ``backend="numpy"`` (`jaxci.smooth`
    refuses mixed meshes: the element weights that padding needs are the hexahedra's).
    """
    if method not in SHARDED_METHODS:
        raise ConfigError(f"devices is for the methods {', '.join(SHARDED_METHODS)}, not {method!r}")
    params = dict(params)
    if method in HOST_METHODS:
        if params.get("backend", "auto") == "numpy":
            raise ConfigError("backend='numpy' runs on the host, one CPU: it cannot be sharded over devices; "
                              "leave devices out or use backend='jax'")
        params["backend"] = "jax"
    devs = mesh.devices.ravel()
    host = "; the numpy host path for small meshes is not used" if method in HOST_METHODS else ""
    what = ("the trial meshes of every learning attempt split evenly, the mesh replicated" if method == "ci-global"
            else "elements (and the node slots of the colour sweeps) split evenly (padded with weight-0 copies), "
                 "node data replicated")
    where = (f"sharded over {len(devs)} {devs[0].platform} devices: {what}" if len(devs) > 1
             else f"on 1 {devs[0].platform} device")
    return params, f"{where}; compiled JAX path{host}"


def put(tree, sharding: NamedSharding):
    """Every array of `tree` (a pytree) placed with `sharding`, through the host unless it is there already: a
    device array resharded on the device compiles a slicing program per shape (measured: 14 ``_multi_slice``
    compilations in one sharded L-BFGS run with presmoothing), a numpy array is split on the host. Only an array
    with exactly this sharding is kept: an equivalent one of another kind (a loop's output on a one-device mesh)
    is a new input type to `jax.jit`, and compiles the loop again."""
    def one(a):
        if isinstance(a, jax.Array) and a.sharding == sharding:
            return a
        return jax.device_put(np.asarray(a), sharding)

    return jax.tree.map(one, tree)


def replicate(tree, mesh: Mesh):
    """Every array of `tree` (a pytree) replicated on every device of `mesh`."""
    return put(tree, NamedSharding(mesh, P()))


def place_problem(conn, weight, replicated, mesh: Mesh, slots=None):
    """The arguments of a compiled loop placed on `mesh`: ``(conn, weight, replicated)``, and `slots` placed
    too if given.

    **Arguments:** `conn` ``(8, N)`` transposed connectivity and `weight` ``(N,)`` element weights, N a multiple
    of the device count (`jaxci.optim._buckets.bucket` with ``multiple``): sharded along N; `replicated`: a
    pytree of everything else (coordinates, constraints ...): replicated; `slots`: a pytree of arrays
    ``(n_colours, M, ...)`` (the colour classes' node slots and stars, `jaxci.optim._moves.ColouredStars`, and
    the edge neighbours): sharded along M where M is a multiple of the device count (the ladder's sizes are
    multiples of 4), else replicated. Measured (5 smart-Laplace sweeps at 30^3 on 4 forced CPU
    devices, 2 cores): slots replicated 2.4-2.8 s (every device repeats every sweep), sharded 1.06 s; one
    device 1.11 s.
    """
    n_dev = mesh.devices.size
    if conn.shape[1] % n_dev:
        raise ValueError(f"{conn.shape[1]} elements do not split over {n_dev} devices")
    placed = (put(conn, NamedSharding(mesh, P(None, AXIS))), put(weight, NamedSharding(mesh, P(AXIS))),
              replicate(replicated, mesh))
    if slots is None:
        return placed
    m = {a.shape[1] for a in jax.tree.leaves(slots)}
    split = len(m) == 1 and next(iter(m)) % n_dev == 0
    return (*placed, put(slots, NamedSharding(mesh, P(None, AXIS) if split else P())))


def local_terms_and_grad(points, conn, weight, n_dev: int, platform: str):
    """Inside `jax.shard_map` over axis `AXIS` of `n_dev` devices of `platform`: F, max kappa/3 and dF/dx of the
    WHOLE mesh from this device's hexahedra `conn` ``(8, N/D)`` with weights `weight` ``(N/D,)`` (0: padding) at
    replicated `points` ``(n, 3)``. The device sums its own elements' terms and gradient (the C kernel on CPU,
    with its share of the kernel threads), then ONE exchange (a `psum` of the gradient, F's sum, the real
    corners' count and each device's max in its own slot) gives every device the whole mesh's F, max and
    gradient."""
    if native_grad.available(platform):
        f, k, g = native_grad.terms_and_grad(points, conn, weight, 1.0, max(1, native.THREADS // n_dev))
    else:  # sums: divided by the count below
        f, k, g = objective_terms_and_grad(points, conn, weight, None, 0, 1.0)
    count = 8.0 * jnp.sum((weight > 0).astype(points.dtype))
    slots = jnp.zeros(n_dev, points.dtype).at[jax.lax.axis_index(AXIS)].set(k)
    total = jax.lax.psum(jnp.concatenate([g.reshape(-1), jnp.stack([f, count]), slots]), AXIS)
    n = g.size
    return total[n] / total[n + 1], jnp.max(total[n + 2:]), total[:n].reshape(g.shape) / total[n + 1]


def sharded_terms_and_grad(points, conn, weight, mesh: Mesh):
    """F, max kappa/3 and the gradient of F (`jaxci.metrics.hexahedron.objective_terms_and_grad`) of the
    hexahedra `conn` ``(8, N)`` with weights `weight` ``(N,)``, both sharded along N over `mesh`, at replicated
    `points` ``(n, 3)``: `local_terms_and_grad` on every device (`jax.shard_map`), one exchange in all. Left to
    XLA's partitioner, the gradient's 24 scatters into the nodes (a local node and a coordinate each) were each
    followed by an all-reduce: 25 rendezvous of the device threads in a step, which with more devices than cores
    cost most of a sharded L-BFGS step."""
    local = functools.partial(local_terms_and_grad, n_dev=mesh.devices.size, platform=mesh.devices.flat[0].platform)
    return jax.shard_map(local, mesh=mesh,
                         in_specs=(P(), P(None, AXIS), P(AXIS)), out_specs=(P(), P(), P()))(points, conn, weight)
