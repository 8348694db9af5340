"""Where a smoothing run runs: one `Plan`, resolved once by `resolve_plan`, followed by every stage.

jaxci has two engines that minimise the same objective with the same algorithms:

- ``"host"``: numpy in float64 with the fused C kernels of `jaxci.native` (or numpy's own where the extension
  is not built). No compilation, no JAX import: the fastest engine on a CPU for every mesh size measured
  (`jaxci.optim.host.HOST_MAX`).
- ``"jax"``: the compiled JAX programs (`jax.jit` with `jax.lax` loops, the corner kernel in closed form),
  on one device or sharded over several, on a CPU (where the C kernel runs inside the programs as an XLA FFI
  call, `jaxci.metrics.native_grad`) or an accelerator.

`resolve_plan` picks the engine, the device, the dtype and the kernel from the mesh, the method and its
parameters, the user's requests (``engine=``, ``device=``, ``devices=``) and the devices JAX sees, once per run;
every stage (untangling, presmoothing, the method) then runs on that engine (`stage_params` forces each stage's
``backend``), but for the default pipeline's worst-element polish, which always runs on the host (its small
sub-problems would each be compiled anew), as the plan's notes then say. A request that cannot be honoured is a
`jaxci.errors.ConfigError` naming what stands in the way. The plan travels with the result
(`jaxci.interface.smooth.SmoothResult.plan`), so every report says what ran.

With ``engine="auto"``: where JAX sees an accelerator (a GPU or TPU; ``device="auto"`` or ``"gpu"``) and the
mesh has at least `ACCELERATOR_FROM` cells, or the user asked for ``device="gpu"``, the JAX engine on the
accelerator; else the host engine where it can run every stage and the mesh is within the host limits of the
method (`host_limit`), else the JAX engine on the CPU.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.metadata
import importlib.util
import os

from .. import native
from ..errors import ConfigError
from ..metrics import objective as mixed
from ..runtime import compile_cache
from ..runtime.process import schedulable_cpus

#: The engines a user may ask for.
ENGINES = ("auto", "host", "jax")

#: The devices a user may ask for: ``"gpu"`` is any accelerator JAX sees (CUDA or ROCm GPU, or TPU).
DEVICES = ("auto", "cpu", "gpu")

#: Cells (all types) from which ``engine="auto"`` runs the JAX engine on an accelerator rather than the host
#: engine on the CPU, where JAX sees one. Measured by ``scripts/bench_gpu.py`` on an NVIDIA H200 with 16 CPU
#: cores (2026-11-27; docs/engines.md), the default pipeline in a fresh process with an empty compilation cache,
#: perturbed boxes: 10,648 hexahedra 13.6 s on the GPU against 1.5 s on the host; 97,336: 14.7 against 4.8 s;
#: cube60_pert (216,000, tangled) 21.4 against 9.5 s; 10^6: 31.8 against 35.3 s. The GPU's cold run is mostly
#: compilation (8-9 s), so it wins from about 10^6 cells.
ACCELERATOR_FROM = 1_000_000

#: Seeds from which ``engine="auto"`` runs global CI on several seeds of one mesh (``jaxci run``,
#: `jaxci.interface.seeds.smooth_seeds`) on the JAX engine as one batched program (`jaxci.optim.global_ci`), where the
#: host engine would run one seed after the other. Measured (2-core CPU, cube729, the defaults' 1000 attempts):
#: the host engine 4.3 s a seed; the batched program compiles in 4-5 s, then 1.5-1.9 s a seed (30 seeds: 50 s
#: against the host's 130 s); on an H200, 30 seeds in 7.0 s cold against 5.0 s a seed on its CPU
#: (docs/engines.md, scripts/bench_batched_ci.py).
BATCH_SEEDS_FROM = 4

#: The methods the host engine runs (hexahedral meshes; L-BFGS on mixed ones with the C kernels).
HOST_METHODS = ("lbfgs", "ci", "ci-global", "laplace", "smart-laplace")

#: The kernels: the host engine's fused C loops or numpy's array code; the JAX engine's XLA program, or the C
#: kernel inside it as an XLA FFI custom call (CPU devices, F and its gradient: `jaxci.metrics.native_grad`).
KERNELS = ("C", "numpy", "XLA", "FFI")


@dataclasses.dataclass(frozen=True)
class Plan:
    """What runs a smoothing run, decided once (`resolve_plan`).

    - `engine`: ``"host"`` (numpy and C, float64) or ``"jax"`` (compiled programs).
    - `device`: the platform: ``"cpu"``, ``"gpu"`` or ``"tpu"``; `device_kind` what it is (JAX's
      ``device_kind``, or the CPU model for the host engine); `devices` how many (more than one: sharded).
    - `dtype`: ``"float64"`` or ``"float32"``: the shape improvement's arithmetic (the untangling stage and the
      final checks are float64 on either engine).
    - `kernel`: one of `KERNELS`: what evaluates F and its gradient.
    - `threads`: the kernel's threads on a CPU (the C kernel's, or XLA:CPU's pool); None on an accelerator.
    - `reason`: why this engine and device (a request of the user's, or the rule of ``"auto"``).
    - `notes`: what a user should know (a fallback, e.g. an FFI handler this jaxlib refused).
    """

    engine: str
    device: str
    device_kind: str
    devices: int
    dtype: str
    kernel: str
    threads: int | None
    reason: str
    notes: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """JSON-ready: ``name`` (the engine), ``device``, ``device_kind``, ``devices``, ``dtype``, ``kernel``,
        ``threads``, ``reason``, ``notes``."""
        d = dataclasses.asdict(self)
        return {"name": d.pop("engine"), **d, "notes": list(self.notes)}

    def describe(self) -> str:
        """One line: ``"host engine: C kernel (2 threads), float64, cpu (AMD EPYC ...)"``."""
        threads = f" ({self.threads} thread{'s' if self.threads != 1 else ''})" if self.threads else ""
        where = f"{self.devices} {self.device} devices" if self.devices > 1 else self.device
        return (f"{self.engine} engine: {self.kernel} kernel{threads}, {self.dtype}, {where} ({self.device_kind}); "
                f"{self.reason}")

    @property
    def backend(self) -> str:
        """The stages' ``backend`` parameter that runs them on this engine: ``"numpy"`` or ``"jax"``."""
        return "numpy" if self.engine == "host" else "jax"

    def context(self):
        """The context a stage runs in: on the JAX engine, where the plan's platform is not JAX's default one
        (a GPU machine asked for ``device="cpu"``), JAX's default device set to this process's first device of
        it; else nothing. The JAX engine's first stage sets up the compilation cache (`jaxci.runtime.compile_cache`)."""
        if self.engine == "host":
            return contextlib.nullcontext()
        import jax

        compile_cache.enable()
        if _platform_name(jax.default_backend()) == self.device:
            return contextlib.nullcontext()
        return jax.default_device(jax.local_devices(backend=_jax_platform(self.device))[0])


def _jax_platform(device: str) -> str:
    return {"gpu": "gpu", "tpu": "tpu"}.get(device, "cpu")


# ------------------------------------------------------------------------------------------ what JAX sees
def _plugins_installed() -> bool:
    """Whether an accelerator plugin of JAX is installed (a ``jax_plugins`` entry point, the CUDA / ROCm
    plugin packages, or libtpu): without one JAX has only its CPU and need not be imported to know it."""
    try:
        if list(importlib.metadata.entry_points(group="jax_plugins")):
            return True
    except Exception:  # noqa: BLE001 - broken metadata: look for the modules instead
        pass
    names = ("jax_plugins", "jax_cuda12_plugin", "jax_cuda13_plugin", "jax_rocm60_plugin", "jax_rocm7_plugin",
             "libtpu")
    return any(importlib.util.find_spec(n) is not None for n in names)


@functools.cache
def accelerator() -> tuple[str, str] | None:
    """``(platform, device_kind)`` of the accelerator JAX would use (``("gpu", "NVIDIA H100 80GB HBM3")``), or
    None where it has only CPUs. JAX is imported only where an accelerator plugin is installed and
    ``JAX_PLATFORMS`` does not say ``cpu``."""
    platforms = os.environ.get("JAX_PLATFORMS", os.environ.get("JAX_PLATFORM_NAME", ""))
    if platforms.strip().lower() == "cpu" or not _plugins_installed():
        return None
    import jax

    try:
        backend = jax.default_backend()
    except RuntimeError:  # pragma: no cover - a plugin that fails to start: JAX falls back to its CPU
        return None
    if backend == "cpu":
        return None
    dev = jax.devices()[0]
    return ("tpu" if backend == "tpu" else "gpu"), str(getattr(dev, "device_kind", backend))


@functools.cache
def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or ``"cpu"``."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or "cpu"


# -------------------------------------------------------------------------------------- what the host can do
def host_limit(method: str, built: bool) -> int:
    """The most cells on which ``engine="auto"`` runs `method` on the host engine, on a CPU (the C kernels
    `built` or not): L-BFGS `jaxci.optim.host.HOST_MAX`, the local methods and global CI
    `jaxci.optim.host_local.HOST_LOCAL_MAX` (measured: docstrings there)."""
    from ..optim.host import HOST_MAX
    from ..optim.host_local import HOST_LOCAL_MAX

    if method == "lbfgs":
        return HOST_MAX
    return HOST_LOCAL_MAX if built else 0


def host_obstacle(mesh, method: str, params: dict, untangling: bool) -> str | None:
    """Why the host engine cannot run every stage of `method` with `params` on `mesh` (None: it can).
    `untangling`: the untangling stage runs first (inverted input, or ``untangle="always"``)."""
    extra = mixed.extra_blocks(mesh)
    if method not in HOST_METHODS:
        return f"method {method!r} has no host implementation (host: {', '.join(HOST_METHODS)})"
    local = method != "lbfgs" or params.get("presmooth", 0) not in (0, None, False)  # checked later
    if local and not native.AVAILABLE:
        what = "its smart-Laplace presmoothing" if method == "lbfgs" else method
        return f"{what} needs the C kernels on the host, and this install has none (jaxci.native)"
    if extra and local:
        what = "presmoothing" if method == "lbfgs" else method
        return f"{what} on the host is for hexahedral meshes; this one has {', '.join(extra)} cells"
    if extra and method == "lbfgs" and not native.AVAILABLE:
        return "L-BFGS on a mixed mesh needs the C kernels on the host, and this install has none"
    if untangling and extra:
        return "the untangling stage of a mixed mesh runs on the JAX engine only"
    return None


# --------------------------------------------------------------------------------------------- the decision
def check_choice(name: str, value, choices) -> None:
    """`ConfigError` naming `name` unless `value` is a string of `choices`."""
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(f"{name} must be one of {', '.join(map(repr, choices))}, got {value!r}")


def engine_request(engine: str, params: dict) -> tuple[str, dict]:
    """``(engine, params)``: the user's engine request with the stages' own ``backend`` parameters folded into
    it (``backend`` and ``untangle_backend``: ``"numpy"`` means the host engine, ``"jax"`` the JAX engine), and
    removed from `params`. `ConfigError` where they disagree with each other or with `engine`."""
    check_choice("engine", engine, ENGINES)
    params = dict(params)
    asked = {} if engine == "auto" else {"engine": engine}
    for key in ("backend", "untangle_backend"):
        if key not in params:
            continue
        value = params.pop(key)
        check_choice(key, value, ("auto", "numpy", "jax"))
        if value != "auto":
            asked[key] = "host" if value == "numpy" else "jax"
    if len(set(asked.values())) > 1:
        said = ", ".join(f"{k}={'numpy' if k != 'engine' and v == 'host' else v!r}" for k, v in asked.items())
        raise ConfigError(f"engine requests disagree ({said}): one engine runs every stage; give engine= alone")
    return next(iter(asked.values()), "auto"), params


def resolve_plan(mesh, method: str, params: dict, *, engine: str = "auto", device: str = "auto",
                 dtype: str = "float32", devices=None, untangling: bool = False, seeds: int = 1) -> Plan:
    """The one decision of where a run of `method` on `mesh` runs (see the module docstring).

    **Arguments:** `mesh` the `HexMesh`; `method` a resolved method name (not ``"auto"``); `params` its
    parameters (without ``backend``: `engine_request`); `engine` one of `ENGINES`; `device` one of `DEVICES`;
    `dtype` the requested dtype of the JAX engine; `devices` None (one device) or the `jax.sharding.Mesh` to
    shard over; `untangling` whether the untangling stage runs first; `seeds` how many seeds of this mesh run
    together (global CI from `BATCH_SEEDS_FROM` seeds runs them as one batched program on the JAX engine).

    **Returns:** a `Plan`. Raises `ConfigError` for a request that cannot be honoured.
    """
    check_choice("engine", engine, ENGINES)
    check_choice("device", device, DEVICES)
    n_cells = mesh.n_hexes + sum(len(c) for c in mixed.extra_blocks(mesh).values())
    obstacle = host_obstacle(mesh, method, params, untangling)
    if devices is not None:
        platform = str(devices.devices.ravel()[0].platform)
        if engine == "host":
            raise ConfigError("engine 'host' runs on one CPU and cannot be sharded over devices; leave devices out "
                              "or use engine 'jax'")
        if device != "auto" and _jax_platform(device) != _jax_platform(_platform_name(platform)):
            raise ConfigError(f"device {device!r}, but the devices to shard over are {platform} devices")
        return _jax_plan(method, params, dtype, _platform_name(platform), int(devices.devices.size),
                         f"sharded over {int(devices.devices.size)} devices (devices=)")
    if engine == "host":
        if device == "gpu":
            raise ConfigError("engine 'host' runs on the CPU (numpy and C); device 'gpu' needs engine 'jax' or "
                              "'auto'")
        if obstacle:
            raise ConfigError(f"engine 'host' cannot run this: {obstacle}; use engine 'jax' or 'auto'")
        return host_plan("engine 'host' asked for")
    accel = accelerator() if device != "cpu" else None
    if device == "gpu" and accel is None:
        raise ConfigError(no_accelerator_message())
    where = accel[0] if accel else "cpu"  # the JAX engine's platform, whatever leads to it
    if engine == "jax":
        return _jax_plan(method, params, dtype, where, 1, "engine 'jax' asked for" + (
            f", on the {where} (device {device!r})" if accel else ""))
    # engine auto
    if accel is not None and (device == "gpu" or n_cells >= ACCELERATOR_FROM):
        why = ("device 'gpu' asked for" if device == "gpu" else
               f"an accelerator is visible and the mesh has {n_cells:,} >= {ACCELERATOR_FROM:,} cells "
               f"(jaxci.interface.engine.ACCELERATOR_FROM)")
        return _jax_plan(method, params, dtype, where, 1, why)
    if method == "ci-global" and seeds >= BATCH_SEEDS_FROM and not untangling:
        return _jax_plan(method, params, dtype, where, 1, f"auto: {seeds} seeds of global CI run as one batched "
                         f"program on the JAX engine (from {BATCH_SEEDS_FROM} seeds: "
                         "jaxci.interface.engine.BATCH_SEEDS_FROM)")
    limit = host_limit(method, native.AVAILABLE)
    if untangling:
        from ..optim.host import UNTANGLE_HOST_MAX

        limit = min(limit, UNTANGLE_HOST_MAX)
    if obstacle is None and n_cells <= limit:
        small = f" below {ACCELERATOR_FROM:,} cells" if accel else ""
        return host_plan(f"auto: the host engine is the fastest for {method} on a CPU up to {limit:,} cells"
                          f"{small}; this mesh has {n_cells:,}")
    why = obstacle or f"auto: {n_cells:,} cells > the host engine's {limit:,} for {method}"
    return _jax_plan(method, params, dtype, where, 1, why)


def _platform_name(platform: str) -> str:
    return {"cuda": "gpu", "rocm": "gpu", "gpu": "gpu", "tpu": "tpu"}.get(platform, "cpu")


def no_accelerator_message(asked: str = "device 'gpu'") -> str:
    """Why `asked` (a request for an accelerator) cannot be honoured here: one sentence, with what to do."""
    have = "no accelerator plugin of JAX is installed" if not _plugins_installed() else "JAX sees only CPUs"
    return (f"{asked} asked for, but {have} (a GPU needs JAX's CUDA or ROCm build, e.g. pip install "
            f"'jax[cuda12]'); use device 'cpu' or 'auto'")


def host_plan(reason: str = "engine 'host' asked for") -> Plan:
    """The host engine's `Plan` (C kernels where built, else numpy's; float64 on the CPU)."""
    kernel = "C" if native.AVAILABLE else "numpy"
    notes = () if native.AVAILABLE else ("the C kernels of jaxci.native are not built (or JAXCI_NATIVE=0): numpy's "
                                         "kernels run on the host",)
    return Plan("host", "cpu", cpu_model(), 1, "float64", kernel, native.THREADS if native.AVAILABLE else 1, reason,
                notes)


def uses_ffi(method: str, params: dict) -> bool:
    """Whether the JAX engine on a CPU takes F and its gradient from the C kernel as an XLA FFI call for `method`
    (the gradient minimisers on F over hexahedra: `jaxci.optim.gradient`), where the handler is registered."""
    return method in ("bfgs", "lbfgs", "cg") and params.get("objective", "mean") == "mean"


def _jax_plan(method: str, params: dict, dtype: str, device: str, n_devices: int, reason: str) -> Plan:
    acc = accelerator()
    kind = cpu_model() if device == "cpu" else (acc[1] if acc else device)
    kernel, notes, threads = "XLA", [], None
    if device == "cpu":
        threads = max(schedulable_cpus(), n_devices)
        if uses_ffi(method, params) and native.AVAILABLE:
            from ..metrics import native_grad

            if native_grad.available("cpu"):
                kernel, threads = "FFI", native.THREADS
            else:
                notes.append(f"the C kernel's XLA FFI handler was not registered ({native_grad.refusal()}): XLA's "
                             f"kernel runs")
        elif not native.AVAILABLE:
            notes.append("the C kernels of jaxci.native are not built (or JAXCI_NATIVE=0): XLA's kernels run")
    return Plan("jax", device, kind, n_devices, dtype, kernel, threads, reason, tuple(notes))


def stage_params(plan: Plan, params: dict, untangle_params: dict) -> tuple[dict, dict]:
    """`params` and `untangle_params` with every stage's ``backend`` set to the plan's engine, so that the
    untangling stage, the presmoothing and the method all run where the plan says."""
    return {**params, "backend": plan.backend}, {**untangle_params, "untangle_backend": plan.backend}
