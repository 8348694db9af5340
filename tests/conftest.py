import os
import shutil
import tempfile

# XLA:CPU compiles the suite's thousands of distinct small programs (most of its time) with LLVM's cheaper
# pipeline: the same programs, on arrays too small for the code's speed to matter (about a quarter less time on the
# mixed-mesh tests); the tests' own processes inherit it.
os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0",
                                    "--xla_llvm_disable_expensive_passes=true"]).strip()

import jax  # noqa: E402
import pytest
from helpers import SHARED_REASON, shared_missing

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
