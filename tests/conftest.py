import os

import jax
import pytest

jax.config.update("jax_enable_x64", True)
# The suite's own process runs the JAX engine's programs as plain jit, without the compilation cache
# (jaxci.compile_cache): its tests spy on and patch traced code, which a program loaded from the cache would not
# run. tests/test_compile_cache.py, and the tests that start processes, give their own cache folders.
os.environ["JAXCI_CACHE_DIR"] = ""


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop JAX's in-memory caches of compiled programs after each test module: the suite compiles thousands of
    XLA:CPU programs in one process, each holding its own memory mappings, and late in the run the process
    crashed inside XLA's compiler (a segmentation fault, near vm.max_map_count's 65530 mappings)."""
    yield
    jax.clear_caches()
