"""Process set-up for speed: transparent huge pages for glibc's large allocations (Linux).

XLA:CPU allocates the temporary buffers of a compiled function on every call through glibc's ``malloc``; above
glibc's mmap threshold each is a fresh ``mmap``, so every call page-faults all of its temporaries in again, 4 KB
at a time. Measured on this 2-core CPU (float32, perturbed 100^3 box, 10^6 hexahedra): F alone 47 ms per call
with 31,000 page faults (all of it system time), 24 ms with ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` (glibc
then asks for transparent huge pages: 250 faults); F and its gradient 460 -> 222 ms. The tunable is read when a
process starts, so the ``jaxci`` command re-executes itself once with it (`reexec_with_hugepages`, first thing
in ``jaxci/__init__``: only for the command, never for a program that imports jaxci); a library user sets it in
the environment (README). ``JAXCI_HUGEPAGES=0`` turns this off.
"""

from __future__ import annotations

import os
import sys

#: The glibc tunable (glibc >= 2.35): ``madvise(MADV_HUGEPAGE)`` on the memory malloc maps.
TUNABLE = "glibc.malloc.hugetlb=1"
_THP = "/sys/kernel/mm/transparent_hugepage/enabled"


def _glibc_version() -> tuple[int, int] | None:
    try:
        name, version = os.confstr("CS_GNU_LIBC_VERSION").split()
        major, minor = version.split(".")[:2]
        return (int(major), int(minor)) if name == "glibc" else None
    except (AttributeError, ValueError, OSError):
        return None


def hugepage_environment(env: dict | None = None) -> dict | None:
    """`env` (default ``os.environ``) with `TUNABLE` added to ``GLIBC_TUNABLES``, or None where it does not apply:
    not Linux with glibc >= 2.35, transparent huge pages ``never``, the tunable already set, or
    ``JAXCI_HUGEPAGES=0``."""
    env = dict(os.environ if env is None else env)
    if not sys.platform.startswith("linux") or env.get("JAXCI_HUGEPAGES", "1") == "0":
        return None
    version = _glibc_version()
    if version is None or version < (2, 35) or "glibc.malloc.hugetlb" in env.get("GLIBC_TUNABLES", ""):
        return None
    try:
        with open(_THP) as f:
            if "[never]" in f.read():
                return None
    except OSError:
        return None
    current = env.get("GLIBC_TUNABLES")
    env["GLIBC_TUNABLES"] = f"{current}:{TUNABLE}" if current else TUNABLE
    return env


def is_jaxci_command(orig_argv: list[str]) -> bool:
    """Whether `orig_argv` (``sys.orig_argv``) runs the jaxci command: ``python [options] -m jaxci ...`` or the
    ``jaxci`` console script."""
    if len(orig_argv) >= 2 and os.path.basename(orig_argv[1]) == "jaxci":
        return True
    i, n = 1, len(orig_argv)
    while i < n and orig_argv[i].startswith("-") and orig_argv[i] not in ("-", "--"):  # options before -m
        if orig_argv[i] == "-m":
            return i + 1 < n and orig_argv[i + 1] == "jaxci"
        if orig_argv[i] in ("-X", "-W"):
            i += 1
        elif orig_argv[i] == "-c":
            return False
        i += 1
    return False


#: Commands whose first argument is the mesh they read, and the file size below which they do not re-execute:
#: meshes this small (about 35,000 hexahedra in legacy VTK) are solved on the host, where the tunable changed
#: nothing measurable (cube30_pert, 27,000 hexahedra, 3 MB: 4.3 CPU s either way), and the second interpreter
#: start cost 0.06 CPU s of a 0.6 s `jaxci quality` (this 2-core CPU).
MESH_COMMANDS = ("smooth", "quality", "classify")
SMALL_INPUT_BYTES = 4 * 2**20


def small_input(args: list[str]) -> bool:
    """Whether the command line `args` (``sys.argv[1:]``) is a `MESH_COMMANDS` command whose first argument is an
    existing file smaller than `SMALL_INPUT_BYTES` (anything else, e.g. an option before the input: False)."""
    if len(args) < 2 or args[0] not in MESH_COMMANDS or args[1].startswith("-"):
        return False
    try:
        return os.path.isfile(args[1]) and os.path.getsize(args[1]) < SMALL_INPUT_BYTES
    except OSError:
        return False


def reexec_with_hugepages() -> None:
    """If this process is the jaxci command and `hugepage_environment` applies, replace it by the same command
    with the tunable (called first thing by ``jaxci/__init__``, before numpy or JAX allocate anything); else, or
    if the exec fails, or for a small mesh (`small_input`), return."""
    orig = list(getattr(sys, "orig_argv", ()))
    if not sys.executable or not is_jaxci_command(orig) or small_input(sys.argv[1:]):
        return
    env = hugepage_environment()
    if env is None:
        return
    try:
        os.execve(sys.executable, [sys.executable, *orig[1:]], env)
    except OSError:  # pragma: no cover - then run without
        return


def quiet_interrupts_while_starting() -> None:
    """For the jaxci command only: until the command installs its own handlers (`jaxci.cli._interrupt`), a
    SIGINT or SIGTERM ends the process at once with 130 / 143 and no output (Ctrl-C during the first second,
    while Python imports numpy and JAX, printed a KeyboardInterrupt traceback). A signal the parent set to be
    ignored stays ignored; nothing was written yet, so there is nothing to clean up."""
    if not is_jaxci_command(list(getattr(sys, "orig_argv", ()))):
        return
    import signal

    def leave(signum, frame):  # pragma: no cover - exercised through a subprocess
        os._exit(128 + signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            if signal.getsignal(sig) is not signal.SIG_IGN:
                signal.signal(sig, leave)
        except (ValueError, OSError):  # not the main thread, or no such signal here
            pass


def single_threaded_blas() -> None:
    """For the jaxci command only, and unless the user set it: ``OPENBLAS_NUM_THREADS=1`` before numpy loads
    OpenBLAS. jaxci's numpy work never multiplies matrices large enough for BLAS threads to pay (its kernels are
    its own C loops), but OpenBLAS starts a thread per core when numpy is imported and each spins ~0.1 s of a core
    after loading and after every call: measured on this 2-core CPU, importing numpy alone cost 0.11 CPU s in that
    thread, and on `jaxci smooth` of a 2,644-hex mesh the spinning thread took 7% of the samples, on the cores the
    C kernels' threads run on."""
    orig = list(getattr(sys, "orig_argv", ()))
    if is_jaxci_command(orig) and "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


#: XLA:CPU's pass that splits every large fusion into as many parallel parts as its intra-op pool has threads.
#: That pool has max(cores or ``NPROC``, CPU devices) threads (`jaxci.optim.sharding.xla_cpu_threads`), so with
#: more forced CPU devices than cores each fusion's parts wait on threads the cores cannot run. Measured on
#: this 2-core CPU, 4 forced devices, 30^3 box (2026-11-25, 0c90f3f; docs/sharding.md): one F + gradient call 56 ms ->
#: 16-24 ms (one device: 18-19 ms), 40 sharded L-BFGS steps 5.4 -> 2.1-3.0 s (one device: 1.4-2.0 s).
PARTITION_PASS = "cpu-parallel-task-assigner"
_FORCE = "--xla_force_host_platform_device_count="
_DISABLE = "--xla_disable_hlo_passes="


def schedulable_cpus() -> int:
    """The cores this process may run on (its affinity; else ``os.cpu_count()``)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def forced_cpu_devices(env: dict | None = None) -> int:
    """The CPU device count that `env` (default ``os.environ``) asks JAX for: the last
    ``--xla_force_host_platform_device_count`` of ``XLA_FLAGS``, or ``JAX_NUM_CPU_DEVICES``; 0 if neither."""
    env = os.environ if env is None else env
    n = 0
    for flag in env.get("XLA_FLAGS", "").split():
        if flag.startswith(_FORCE):
            try:
                n = int(flag[len(_FORCE):])
            except ValueError:
                pass
    try:
        n = max(n, int(env.get("JAX_NUM_CPU_DEVICES", "0")))
    except ValueError:
        pass
    return n


def cpu_device_flags(env: dict | None = None, cpus: int | None = None) -> str | None:
    """``XLA_FLAGS`` of `env` (default ``os.environ``) with `PARTITION_PASS` disabled, where the forced CPU
    devices (`forced_cpu_devices`) outnumber `cpus` (default `schedulable_cpus`); None where they do not, where
    the pass is already disabled, or with ``JAXCI_XLA_PARTITIONS=1``. An ``--xla_disable_hlo_passes`` already
    there is extended. With no more devices than cores the pass stays: it is XLA:CPU's only intra-op
    parallelism (one CPU device on 2 cores: 40 L-BFGS steps 1.4-2.0 s with it, 1.7-2.6 s without)."""
    env = os.environ if env is None else env
    cpus = schedulable_cpus() if cpus is None else cpus
    if env.get("JAXCI_XLA_PARTITIONS") == "1" or forced_cpu_devices(env) <= cpus:
        return None
    flags = env.get("XLA_FLAGS", "").split()
    for i, flag in enumerate(flags):
        if flag.startswith(_DISABLE):
            passes = [p for p in flag[len(_DISABLE):].split(",") if p]
            if PARTITION_PASS in passes:
                return None
            flags[i] = _DISABLE + ",".join([*passes, PARTITION_PASS])
            return " ".join(flags)
    return " ".join([*flags, _DISABLE + PARTITION_PASS])


def apply_cpu_device_flags() -> bool:
    """Put `cpu_device_flags` into ``os.environ`` (True) where it applies. XLA reads ``XLA_FLAGS`` when JAX makes
    its first backend, so this must run before anything creates a device or compiles (the jaxci command does it
    first; ``import jax`` alone is early enough); later it changes nothing."""
    flags = cpu_device_flags()
    if flags is None:
        return False
    os.environ["XLA_FLAGS"] = flags
    return True
