"""`jaxci.runtime`: the jaxci command re-executes itself with huge pages for glibc's allocations; nothing else."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from jaxci.runtime import TUNABLE, _glibc_version, hugepage_environment, is_jaxci_command


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


def test_a_small_mesh_is_not_worth_a_second_start(tmp_path):
    """`jaxci smooth / quality / classify` on a mesh file below `SMALL_INPUT_BYTES` runs in the first process
    (such meshes are solved on the host: the tunable changes nothing there); a large file, an option before the
    input, a missing file or another command keep the re-execution."""
    from jaxci.runtime import SMALL_INPUT_BYTES, small_input

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
