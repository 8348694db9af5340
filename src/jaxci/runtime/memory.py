"""Peak memory estimates, checked before anything large is allocated.

A box of 1000^3 elements, or a file of 10^9 hexahedra, would run for minutes and then die of `MemoryError` (or be
killed) part way through. jaxci refuses such a job up front, with the estimate: where a config is validated
(`jaxci.experiments.config`: generated boxes), in the box builders (`jaxci.mesh.generate`) and in
`jaxci.interface.smooth.smooth`.

The figures were measured on this project's 2-core CPU machine (jax 0.10, XLA CPU): one process per case builds a
perturbed box of n^3 elements (amplitude 0.2) and smooths it (ci with max_sweeps=3, ci-global attempts=3, lbfgs
max_steps=5 with and without presmooth=2, smart-laplace max_sweeps=3; float32, and float64 for ci and lbfgs); the
peak resident memory (``ru_maxrss``) minus the resident memory just before the call, for n = 20, 30, 40, 50. Per
hexahedron (slope between successive sizes, largest over the methods): float32 3.0 kB (ci 2.9, lbfgs 3.1, smart-
laplace 2.6, ci-global 2.6), float64 4.3 kB (ci); fixed part 260-400 MiB (JAX and the compiled loops). Over a
whole run of the 100^3 box the README measures 2.7 GB in all, below these slopes (compilation is amortised).
CI holds C x t trial positions at once (cohort x variations, 16 by default): at n = 30, 40 with C = t = 16 the
slope was 5.2 kB (local) and 8.1 kB (global) per hexahedron, about 25 bytes more per hexahedron and trial above
the default 16 (`CI_BYTES_PER_TRIAL`).
"""

from __future__ import annotations

import ctypes
import functools
import os
import sys

from ..errors import MeshError

#: Measured peak bytes per hexahedron of `jaxci.interface.smooth.smooth` (largest over ci, ci-global, lbfgs with and
#: without presmoothing, smart-laplace on perturbed boxes of 20^3..50^3 elements), by dtype.
SMOOTH_BYTES_PER_HEX = {"float32": 3_000, "float64": 4_300}
#: Measured extra bytes per hexahedron and CI trial (cohort x variations) above the default 16 trials.
CI_BYTES_PER_TRIAL = 25
#: Measured fixed part (JAX's runtime and the compilation of the smoothing loops), bytes.
SMOOTH_FIXED_BYTES = 400 * 2**20
#: Measured peak bytes per hexahedron of a run on the host engine (`jaxci.interface.engine`: numpy and C, no
#: JAX, nothing compiled; float64 whatever `dtype` says), and its fixed part: the default pipeline (3 smart-Laplace
#: sweeps, L-BFGS, reports) on perturbed boxes peaked at 0.98 GB in all at 10^6 (100^3, `jaxci smooth`) and 8.7 GB
#: at 9.9 x 10^6 (215^3, in process), mesh included; the tangled cube60_pert (216,000 hexahedra, untangling first)
#: at 364 MB, 1.22 kB a hexahedron above the fixed part, the largest measured (2026-11-26, 55d02f9; the current
#: figures: docs/results/boxes.md).
HOST_BYTES_PER_HEX = 1_250
HOST_FIXED_BYTES = 100 * 2**20
#: The same for CI on the host (`jaxci.optim.host_local`, `jaxci.optim.host_global`), measured with `jaxci smooth`
#: on a 60^3 box (216,000 hexahedra, the default cohorts; 2026-11-26, dd22c91): local CI 477 MB (Anderson's history of 8
#: sweeps included), global CI 870 MB (each attempt's 25 trial meshes, lifted and projected at once); above the
#: fixed part, 1.8 and 3.7 kB a hexahedron. Global CI's trial meshes grow with the trials (about 24 B a
#: hexahedron and trial: 3 coordinates of 8 bytes a node).
HOST_CI_BYTES_PER_HEX = {"ci": 1_800, "ci-global": 3_700}
HOST_BYTES_PER_TRIAL = 24
#: Measured peak bytes per hexahedron of `jaxci.mesh.generate.perturb_box` (numpy: grid, connectivity, corner
#: determinants of the redraw test, mesh validation; measured the same way for n = 20..80: 715 bytes).
GENERATE_BYTES_PER_HEX = 720
#: Safety factor on the measured figures: unstructured meshes (more elements per node: larger stars), other
#: parameters than the defaults (a larger cohort), allocator fragmentation.
SAFETY = 1.5


def available_bytes() -> int | None:
    """Memory this process can still use: ``MemAvailable`` of /proc/meminfo, capped by a cgroup v2 limit;
    `os.sysconf` where there is no /proc; None if unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError):
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, AttributeError):
            avail = None
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        with open("/sys/fs/cgroup/memory.current") as f:
            used = int(f.read().strip())
        if limit != "max":
            room = int(limit) - used
            avail = room if avail is None else min(avail, room)
    except (OSError, ValueError):
        pass
    return avail


def smooth_bytes(n_hexes: int, dtype: str = "float32", trials: int = 16, host: bool = False,
                 method: str | None = None) -> int:
    """Estimated peak bytes of smoothing a mesh of `n_hexes` hexahedra (safety factor included); `trials`: CI's
    cohort x variations (`ci_trials`), 16 (the default) for the other methods; `host`: the run is entirely on the
    host (`HOST_BYTES_PER_HEX`, or `HOST_CI_BYTES_PER_HEX` for `method` ``"ci"`` and ``"ci-global"``)."""
    if host:
        per = HOST_CI_BYTES_PER_HEX.get(method, HOST_BYTES_PER_HEX)
        if method == "ci-global":
            per += HOST_BYTES_PER_TRIAL * max(int(trials) - 25, 0)
        return int(SAFETY * (per * n_hexes + HOST_FIXED_BYTES))
    per = SMOOTH_BYTES_PER_HEX.get(dtype, max(SMOOTH_BYTES_PER_HEX.values()))
    per += CI_BYTES_PER_TRIAL * max(int(trials) - 16, 0) * (2 if dtype == "float64" else 1)
    return int(SAFETY * (per * n_hexes + SMOOTH_FIXED_BYTES))


#: CI's default cohort and variations per method (`jaxci.optim.ci_params`: local CI 3 x 3, global CI 5 x 5).
CI_DEFAULT_TRIALS = {"ci": (3, 3), "ci-global": (5, 5)}


def ci_trials(method: str, params: dict) -> int:
    """Trial positions CI holds at once (cohort x variations, the method's defaults `CI_DEFAULT_TRIALS` where not
    given) for `method` with `params` (not checked here: a bad value counts as its default); 16 for a method that
    is not CI."""
    if method not in CI_DEFAULT_TRIALS:
        return 16

    def get(key, default):
        v = params.get(key, default)
        return int(v) if isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 4096 else default

    cohort, variations = CI_DEFAULT_TRIALS[method]
    return get("cohort", cohort) * get("variations", variations)


def generate_bytes(n_hexes: int) -> int:
    """Estimated peak bytes of building a perturbed box of `n_hexes` hexahedra (safety factor included)."""
    return int(SAFETY * GENERATE_BYTES_PER_HEX * n_hexes)


def _gb(b: float) -> str:
    return f"{b / 1e9:.3g} GB" if b < 1e12 else f"{b / 1e12:.3g} TB"


def check_fits(need: int, what: str, error=MeshError) -> None:
    """Raise `error` (one line: `what`, the estimate and the memory available) if `need` bytes do not fit."""
    avail = available_bytes()
    if avail is not None and need > avail:
        raise error(f"{what} needs about {_gb(need)} of memory (estimate) and {_gb(avail)} is available; use a "
                    f"smaller mesh or a machine with more memory")


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim`` (None elsewhere: other platforms, musl)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def release_free_memory() -> bool:
    """Give the C heap's free pages back to the operating system (glibc's ``malloc_trim(0)``; a no-op elsewhere),
    so that the temporaries of one phase do not stay resident under the next one's arrays: numpy arrays below
    glibc's mmap threshold (up to 32 MB) come from the heap and stay mapped after they are freed. Called at every
    phase of `jaxci.smooth` (`jaxci.runtime.phases.Clock.phase`) and at the start of the host L-BFGS loop
    (`jaxci.optim.host.lbfgs`): at 10^6 hexahedra it returned 85 MB there (517 -> 432 MB resident), in
    milliseconds. Returns whether it ran."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
