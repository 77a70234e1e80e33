import os

# Tests are dominated by XLA compile time, not run time: compile with cheap optimization.
os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
).strip()

# The jaxvisco command turns on JAX's persistent compilation cache in the user's cache
# directory; tests stay hermetic (tests that need a cache give their own directory).
os.environ["JAXVISCO_CACHE_DIR"] = "off"

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Each test module compiles large programs; drop them afterwards so one process
    running the whole suite does not accumulate them (a full run once crashed inside
    XLA's compiler late in the suite)."""
    yield
    jax.clear_caches()
