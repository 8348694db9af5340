"""`jaxci.runtime.process`: the jaxci command re-executes itself with huge pages for glibc's allocations;
nothing else."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from helpers import cpu_env

from jaxci.runtime.process import TUNABLE, _glibc_version, hugepage_environment, is_jaxci_command


@pytest.mark.parametrize("argv,expected", [
    (["python", "-m", "jaxci", "smooth"], True),
    (["python", "-X", "importtime", "-m", "jaxci"], True),
    (["python", "/venv/bin/jaxci", "quality", "a.vtk"], True),
    (["python", "script.py", "-m", "jaxci"], False),
    (["python", "-", "-m", "jaxci"], False),  # a script read from stdin, with its own arguments
    (["python", "-u", "--", "-m", "jaxci"], False),
    (["python", "-m", "pytest"], False),
    (["python", "-c", "import jaxci"], False),
    (["python"], False),
    ([], False),
])
def test_only_the_jaxci_command_is_recognised(argv, expected):
    assert is_jaxci_command(argv) is expected


def test_hugepage_environment_respects_opt_out_and_an_existing_setting():
    assert hugepage_environment({"JAXCI_HUGEPAGES": "0"}) is None
    assert hugepage_environment({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}) is None
    env = hugepage_environment({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2", "OTHER": "x"})
    if env is not None:  # Linux, glibc >= 2.35, transparent huge pages not 'never'
        assert env["GLIBC_TUNABLES"] == f"glibc.malloc.arena_max=2:{TUNABLE}" and env["OTHER"] == "x"
        assert sys.platform.startswith("linux") and _glibc_version() >= (2, 35)


def _child_env():
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "JAXCI_HUGEPAGES")}
    return env


def test_a_program_importing_jaxci_is_never_reexecuted():
    code = "import os, jaxci; print(os.environ.get('GLIBC_TUNABLES'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_child_env(), check=True)
    assert out.stdout.strip() == "None"


def test_the_command_runs_with_the_tunable_where_it_applies():
    out = subprocess.run([sys.executable, "-m", "jaxci", "--version"], capture_output=True, text=True,
                         env=_child_env())
    assert out.returncode == 0 and out.stdout.startswith("jaxci ")
    state = "on" if hugepage_environment(_child_env()) is not None else "off"
    assert f"huge pages for glibc allocations {state}" in out.stdout
    off = subprocess.run([sys.executable, "-m", "jaxci", "--version"], capture_output=True, text=True,
                         env={**_child_env(), "JAXCI_HUGEPAGES": "0"})
    assert "huge pages for glibc allocations off" in off.stdout


def test_the_command_loads_openblas_single_threaded_unless_told_otherwise():
    """`jaxci.runtime.process.single_threaded_blas`: the jaxci command (here a process whose ``sys.orig_argv`` says so,
    not re-executed) loads numpy with ``OPENBLAS_NUM_THREADS=1``, so no OpenBLAS thread spins beside the C
    kernels; a user's setting stays, and a program that imports jaxci is left alone."""
    code = ("import sys; sys.orig_argv = {argv!r}; import os, jaxci; "
            "print(os.environ.get('OPENBLAS_NUM_THREADS'), 'numpy' in sys.modules)")
    env = {**_child_env(), "JAXCI_HUGEPAGES": "0"}
    env.pop("OPENBLAS_NUM_THREADS", None)

    def run(argv, **extra):
        out = subprocess.run([sys.executable, "-c", code.format(argv=argv)], capture_output=True, text=True,
                             env={**env, **extra}, check=True)
        return out.stdout.split()

    assert run(["python", "-m", "jaxci", "smooth"]) == ["1", "True"]
    assert run(["python", "-m", "jaxci", "smooth"], OPENBLAS_NUM_THREADS="2") == ["2", "True"]
    assert run(["python", "-c", "import jaxci"]) == ["None", "True"]


def test_a_small_mesh_is_not_worth_a_second_start(tmp_path):
    """`jaxci smooth / quality / classify` on a mesh file below `SMALL_INPUT_BYTES` runs in the first process
    (such meshes are solved on the host: the tunable changes nothing there); a large file, an option before the
    input, a missing file or another command keep the re-execution."""
    from jaxci.runtime.process import SMALL_INPUT_BYTES, small_input

    small, big = tmp_path / "small.vtk", tmp_path / "big.vtk"
    small.write_text("x")
    with open(big, "wb") as f:
        f.truncate(SMALL_INPUT_BYTES + 1)
    for cmd in ("smooth", "quality", "classify"):
        assert small_input([cmd, str(small), "out.vtk"])
        assert not small_input([cmd, str(big), "out.vtk"])
    assert not small_input(["smooth", "--method", "ci", str(small), "out.vtk"])
    assert not small_input(["smooth", str(tmp_path / "missing.vtk"), "out.vtk"])
    assert not small_input(["run", str(small)])
    assert not small_input([])


# ------------------------------------------------------------------------- more forced CPU devices than cores
def test_cpu_device_flags_only_where_forced_devices_outnumber_the_cores():
    from jaxci.runtime.process import PARTITION_PASS, cpu_device_flags, forced_cpu_devices

    four = {"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    assert forced_cpu_devices(four) == 4 and forced_cpu_devices({}) == 0
    assert forced_cpu_devices({"JAX_NUM_CPU_DEVICES": "3"}) == 3
    assert cpu_device_flags(four, cpus=2) == four["XLA_FLAGS"] + " --xla_disable_hlo_passes=" + PARTITION_PASS
    assert cpu_device_flags(four, cpus=4) is None  # no more devices than cores: XLA keeps its intra-op parallelism
    assert cpu_device_flags({}, cpus=1) is None
    assert cpu_device_flags({**four, "JAXCI_XLA_PARTITIONS": "1"}, cpus=2) is None  # opt out
    other = {"XLA_FLAGS": "--xla_disable_hlo_passes=a,b --xla_force_host_platform_device_count=4"}
    assert cpu_device_flags(other, cpus=2) == ("--xla_disable_hlo_passes=a,b," + PARTITION_PASS
                                               + " --xla_force_host_platform_device_count=4")
    done = {"XLA_FLAGS": four["XLA_FLAGS"] + " --xla_disable_hlo_passes=" + PARTITION_PASS}
    assert cpu_device_flags(done, cpus=2) is None


PARTS = """
import sys
from jaxci.runtime.process import apply_cpu_device_flags
import jax, jax.numpy as jnp
applied = apply_cpu_device_flags() if sys.argv[1] == "apply" else False
text = jax.jit(lambda x: jnp.sin(x) * 2 + jnp.cos(x)).lower(jnp.ones(2**20)).compile().as_text()
print("APPLIED", applied, "PARTS", 'outer_dimension_partitions":["' in text, "DEVICES", jax.device_count())
"""


def test_more_forced_devices_than_cores_compile_without_per_fusion_partitions():
    """XLA:CPU's pool has one thread per forced device; with more devices than cores every large fusion was split
    into that many parts that wait on each other (4 devices on 2 cores: 2.4-3x the CPU time, docs/sharding.md).
    `apply_cpu_device_flags` (run after ``import jax``, before any device exists) turns that split off; without it
    the same program is split."""
    from jaxci.runtime.process import schedulable_cpus

    n = schedulable_cpus() + 1
    env = cpu_env(n)
    env.pop("JAXCI_XLA_PARTITIONS", None)
    got = {}
    for mode in ("apply", "leave"):
        r = subprocess.run([sys.executable, "-c", PARTS, mode], env=env, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr[-3000:]
        got[mode] = r.stdout.split("APPLIED")[-1].split()
    assert got["apply"] == ["True", "PARTS", "False", "DEVICES", str(n)]
    assert got["leave"] == ["False", "PARTS", "True", "DEVICES", str(n)]


def test_the_jaxci_command_applies_the_cpu_device_flags(tmp_path):
    from jaxci.runtime.process import PARTITION_PASS, schedulable_cpus

    n = schedulable_cpus() + 1
    env = cpu_env(n)
    env.pop("JAXCI_XLA_PARTITIONS", None)
    code = ("import os, sys; from jaxci.cli import main; code = main(['quality', sys.argv[1]]); "
            "print('FLAGS', os.environ['XLA_FLAGS'])")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "missing.vtk")], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "--xla_disable_hlo_passes=" + PARTITION_PASS in r.stdout.split("FLAGS")[-1]
