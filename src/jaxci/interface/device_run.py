"""A smoothing run on the JAX engine whose mesh lives on the device from its upload to its result's download.

`jaxci.smooth` takes this path (`applies`) for a mesh of linear hexahedra on the JAX engine (one device, not
sharded) smoothed by L-BFGS (the default pipeline or ``method="lbfgs"``), without coincident nodes and without
inverted elements. The mesh's coordinates (float64) and hexahedra (int32) go up once (`DeviceMesh.upload`);
every O(mesh) stage then runs as compiled programs on the device:

- the quality report before and after, the worst elements, the final checks (`jaxci.metrics.device`,
  `jaxci.interface.invariants.enforce_device`), in float64;
- the boundary faces (a sort of face keys, `jaxci.geometry.device_topology`), the constraints' per-node arrays
  (`jaxci.geometry.device_constraints`);
- the presmoothing, the parametrisation and L-BFGS (`jaxci.optim.gradient.run_gradient`);
- the unit frame's mapping both ways.

What the host does is O(boundary) or O(worst elements): the boundary's classification from the boundary faces and the
boundary nodes' coordinates (feature edges, patches, curves: graph work on the boundary), the tables of the constraints
(triangles, segments, candidates) built from them, the exact float64 projection of the boundary nodes that are not
inside their flat regions (`jaxci.geometry.device_constraints.project_boundary`: a k-d tree search per patch; the others
are projected onto their planes on the device), the worst-element polish on a window of the worst cells
(`jaxci.optim.polish_window`), and the figures the reports and checks bring down. The result's coordinates come down
once, float64. `jaxci.runtime.transfer` counts every byte each way and the time inside compiled programs; the run passes
under ``jax.transfer_guard("disallow")`` (tested).

Other runs on the JAX engine (mixed or quadratic meshes, coincident nodes, sharded runs, inverted input, other
methods) take `jaxci.smooth`'s general path, whose host stages are numpy.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry.device_constraints import (
    device_classify_boundary,
    device_constraints,
    device_unit_frame,
    hexahedral,
)
from ..geometry.device_topology import device_mesh_topology
from ..geometry.projection import n_free
from ..mesh import HexMesh, check_volume
from ..metrics.device import quality_report_device, volume_moments, worst_elements_device
from ..runtime._lazy import enable_x64, jax, jit, jnp
from ..runtime.transfer import program, to_device, to_host
from .invariants import enforce_device
from .methods import OPTIMAL_F, MethodRun, Problem, cap_note, standard_history
from .result import SmoothResult, unchanged_result

#: The methods whose run lives on the device (`applies`).
DEVICE_METHODS = ("lbfgs",)

#: Hexahedra from which the run lives on the device (`applies`). Its programs are compiled for the mesh's own
#: sizes (the boundary's, the colours', the worst window's), so a mesh of a new size compiles about 38 of them
#: (7.5 s on a 2-core Xeon; 0.7 s to load them from the persistent cache at a size seen before), where the general
#: path's compiled programs are shared by every mesh of a size class and its O(mesh) host stages take well under
#: that on a smaller mesh.
DEVICE_RUN_FROM = 100_000


def applies(mesh: HexMesh, method: str, plan, shard, n_pairs: int, tangled: bool, untangle: str) -> bool:
    """Whether `jaxci.smooth` runs `method` on `mesh` with its mesh on the device (see the module docstring):
    the JAX engine's `plan`, one device (`shard` None), linear hexahedra only, at least `DEVICE_RUN_FROM` of
    them, no coincident node pairs (`n_pairs`), no inverted element (`tangled`) and no untangling asked for, a
    method of `DEVICE_METHODS`."""
    return (plan.engine == "jax" and shard is None and method in DEVICE_METHODS and not n_pairs and not tangled
            and untangle in ("auto", "never") and hexahedral(mesh) and mesh.n_hexes >= DEVICE_RUN_FROM)


@dataclasses.dataclass(frozen=True)
class DeviceMesh:
    """A mesh on the device: `x_in` ``(n, 3)`` its coordinates as given (float64); `x` ``(n, 3)`` the same in
    the unit frame `frame` (``(centre, scale)``, `jaxci.mesh.unit_frame`); `conn` ``(8, N)`` its hexahedra
    (int32, transposed: the kernels' layout)."""

    x_in: jax.Array
    x: jax.Array
    conn: jax.Array
    frame: tuple

    @classmethod
    def upload(cls, mesh: HexMesh) -> DeviceMesh:
        """The coordinates (float64) and the hexahedra (int32) of `mesh` up, once; the unit frame from the
        points' bounds (6 numbers down) and the mapping into it on the device."""
        with enable_x64():
            x_in, hexes = to_device((np.asarray(mesh.points, np.float64), np.asarray(mesh.hexes, np.int32)))
            frame = device_unit_frame(x_in)
            x, conn = _into_frame(x_in, hexes, to_device(np.asarray(frame[0], np.float64)),
                                  to_device(np.float64(frame[1])))
        return cls(x_in, x, conn, frame)

    def download(self, points) -> np.ndarray:
        """The coordinates of `points` ``(n, 3)`` (the unit frame) in the mesh's frame, float64 on the host: the
        nodes that did not move keep their input coordinates bit for bit."""
        with enable_x64():
            out = _out_of_frame(self.x_in, self.x, points, to_device(np.asarray(self.frame[0], np.float64)),
                                to_device(np.float64(self.frame[1])))
            return np.asarray(to_host(out), np.float64)


@program
@jit
def _into_frame(x_in, hexes, centre, scale):
    return (x_in - centre) / scale, hexes.T


@program
@jit
def _out_of_frame(x_in, x, points, centre, scale):
    moved = jnp.any(points != x, axis=1)
    return jnp.where(moved[:, None], points * scale + centre, x_in)


@program
@jit
def _as_dtype(x, like):
    return x.astype(like.dtype)


def smooth_unit_device(mesh: HexMesh, method: str, seed: int, plan, feature_angle, fix_boundary, fixed_nodes,
                       fixed_sets, params: dict, notes: list, clock, keep_worst: bool):
    """`jaxci.interface.smooth._smooth_unit` with the mesh on the device (a generator: it yields the
    `jaxci.interface.methods.MethodRun` of the method and receives its output). Returns ``(points, result)``: the
    result's coordinates in the mesh's own frame (float64, host) and the `SmoothResult` (its mesh and wall time are
    filled in by `jaxci.smooth`)."""

    np_dtype = np.float64 if plan.dtype == "float64" else np.float32
    with clock.phase("upload"):
        dm = DeviceMesh.upload(mesh)
        check_volume(mesh, volume_moments(dm.x_in, dm.conn))  # the moments reduced on the device
    with clock.phase("report"):
        before = quality_report_device(mesh, dm.x, dm.conn)
    f_before = before.objective
    if f_before is not None and f_before <= OPTIMAL_F:
        return unchanged_result(mesh, method, before, f_before, notes)
    with jax.enable_x64(plan.dtype == "float64"), plan.context():
        with clock.phase("setup"):
            topology, unused = device_mesh_topology(dm.conn, mesh.n_nodes)
            info = device_classify_boundary(mesh, dm.x, topology, unused, feature_angle=feature_angle,
                                            fix_boundary=fix_boundary, fixed_nodes=fixed_nodes,
                                            fixed_sets=tuple(fixed_sets))
            cons, tables = device_constraints(dm.x, info, dtype=np_dtype)
            with enable_x64():  # the float64 points converted, not narrowed by the x64 mode
                x0 = _as_dtype(dm.x, cons.x_orig)
            problem = Problem(mesh, info, cons, dm.conn, x0, np_dtype, plan=plan, tables=tables, points64=dm.x)
        if n_free(cons) == 0:
            return unchanged_result(mesh, method, before, f_before, notes, info)
    x, iterations, history, resolved = yield MethodRun(problem, method, seed, params, clock)
    notes.extend(info.notes)
    cap = cap_note(method, resolved, iterations, history)
    if cap:
        notes.append(cap)
    with clock.phase("checks"), enable_x64():
        power = float(resolved["p"]) if resolved.get("objective") == "pmean" else None
        points, check_notes = enforce_device(
            mesh, dm.conn, dm.x, x, project=problem.project_device,
            keep_worst=keep_worst, worst_start=before.max_condition, power=power,
            worst_first=bool(resolved.get("polish")) and power is None)
        notes.extend(check_notes)
        after = quality_report_device(mesh, points, dm.conn)
        after = dataclasses.replace(after, worst_elements=worst_elements_device(
            mesh, points, dm.conn, cons.node_class, info.feature_edges))
    with clock.phase("download"):
        real = dm.download(points)
    res = SmoothResult(
        mesh=mesh, history=standard_history(history), iterations=int(iterations), wall_time=0.0, method=method,
        params=resolved, before=before, after=after, boundary=info.counts, node_class=info.node_class,
    )
    return real, res
