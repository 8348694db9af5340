import os
import shutil
import subprocess
import sys
import tempfile

import pytest
from helpers import SHARED_REASON, shared_missing

#: XLA:CPU's older element-wise code generation: about half the compile time of its default fusion emitters on the
#: suite's programs (the suite 8 min 35 s against 11 min 36 s, 2026-11-29, 2-core VM), the same programs. The flag
#: is used where this jaxlib knows it (an unknown XLA flag aborts the process), probed once per run.
LEGACY_CODEGEN = "--xla_cpu_use_fusion_emitters=false"


def _legacy_codegen_known() -> bool:
    code = "import jax; jax.numpy.zeros(1).block_until_ready()"
    env = dict(os.environ, XLA_FLAGS=LEGACY_CODEGEN, JAX_PLATFORMS="cpu")
    try:
        return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=120).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


# JAXCI_SUITE_CODEGEN: "legacy" or "default", decided by the run's first process and inherited by its workers;
# "default" in the fresh processes of `codegen` tests (pytest_pyfunc_call below).
if "JAXCI_SUITE_CODEGEN" not in os.environ:
    os.environ["JAXCI_SUITE_CODEGEN"] = "legacy" if _legacy_codegen_known() else "default"
# XLA:CPU compiles the suite's thousands of distinct small programs (most of its time) with LLVM's cheaper
# pipeline: the same programs, on arrays too small for the code's speed to matter (about a quarter less time on the
# mixed-mesh tests); the tests' own processes inherit it.
os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0",
                                    "--xla_llvm_disable_expensive_passes=true",
                                    LEGACY_CODEGEN if os.environ["JAXCI_SUITE_CODEGEN"] == "legacy" else ""]).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
# The suite's own process runs the JAX engine's programs as plain jit, without the compilation cache
# (jaxci.runtime.compile_cache): its tests spy on and patch traced code, which a program loaded from the cache would not
# run. tests/test_compile_cache.py, and the tests that start processes, give their own cache folders.
os.environ["JAXCI_CACHE_DIR"] = ""
# One XLA compile per distinct program for the whole run, not one per test module (each module's end drops the
# in-memory programs, below) and per worker: JAX's persistent compilation cache in a folder of this run, shared by
# the workers (the first process makes it; the workers inherit its name). Tracing and lowering still run, so the
# spies see every call; the processes the tests start are not given it (they run with the caches they ask for).
if "JAXCI_SUITE_XLA_CACHE" not in os.environ:
    os.environ["JAXCI_SUITE_XLA_CACHE"] = tempfile.mkdtemp(prefix="jaxci-suite-xla-")
_XLA_CACHE = os.environ["JAXCI_SUITE_XLA_CACHE"]
jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)


def pytest_configure(config):
    config.addinivalue_line("markers", "shared: reads the real meshes of ../shared/data or ../shared/peers; "
                                       "skipped (one line says why) where ../shared is not beside the repository")
    config.addinivalue_line("markers", "codegen: compares the bits of two different compiled programs, which depend "
                                       "on XLA's code generation: runs in a fresh process with XLA's default one")


def pytest_pyfunc_call(pyfuncitem):
    """A ``codegen`` test, in a run with the legacy code generation, runs in a fresh pytest process with XLA's
    default one (as users run it; the suite's LLVM options kept) and passes where it passes there."""
    if pyfuncitem.get_closest_marker("codegen") is None or os.environ.get("JAXCI_SUITE_CODEGEN") != "legacy":
        return None
    env = dict(os.environ, JAXCI_SUITE_CODEGEN="default",
               XLA_FLAGS=" ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f != LEGACY_CODEGEN))
    env.pop("JAXCI_SUITE_XLA_CACHE", None)  # its own cache folder (it removes it when it ends)
    env.pop("PYTEST_XDIST_WORKER", None)
    cmd = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", pyfuncitem.nodeid]
    r = subprocess.run(cmd, cwd=pyfuncitem.config.rootpath, env=env, capture_output=True, text=True, timeout=600)
    if r.returncode == 0 and " skipped" in r.stdout and " passed" not in r.stdout:
        pytest.skip(f"skipped in its fresh process: {r.stdout.strip().splitlines()[-1]}")
    assert r.returncode == 0 and " passed" in r.stdout, (r.stdout + r.stderr)[-6000:]
    return True


def pytest_unconfigure(config):
    """The run's compilation cache goes with the process that made it (not a worker)."""
    if not hasattr(config, "workerinput"):
        shutil.rmtree(_XLA_CACHE, ignore_errors=True)
        os.environ.pop("JAXCI_SUITE_XLA_CACHE", None)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``shared`` are skipped, with `helpers.SHARED_REASON`, where ../shared is missing; with
    ../shared present nothing is skipped for that reason."""
    if not shared_missing():
        return
    skip = pytest.mark.skip(reason=SHARED_REASON)
    for item in items:
        if item.get_closest_marker("shared") is not None:
            item.add_marker(skip)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """One line for every test skipped for want of ../shared (pytest -q shows no skip reasons by default)."""
    skipped = [r for r in terminalreporter.stats.get("skipped", []) if SHARED_REASON in str(r.longrepr)]
    if skipped:
        terminalreporter.write_line(f"{len(skipped)} tests skipped: {SHARED_REASON}")


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop JAX's in-memory caches of compiled programs after each test module: the suite compiles thousands of
    XLA:CPU programs in one process, each holding its own memory mappings, and late in the run the process
    crashed inside XLA's compiler (a segmentation fault, near vm.max_map_count's 65530 mappings)."""
    yield
    jax.clear_caches()
