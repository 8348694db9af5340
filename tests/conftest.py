import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop JAX's in-memory caches of compiled programs after each test module: the suite compiles thousands of
    XLA:CPU programs in one process, each holding its own memory mappings, and late in the run the process
    crashed inside XLA's compiler (a segmentation fault, near vm.max_map_count's 65530 mappings)."""
    yield
    jax.clear_caches()
