import os

# Tests are dominated by XLA compile time, not run time: compile with cheap optimization.
# Each flag is added once: pytest-xdist workers inherit the variable from the first
# process and load this file again, and JAX's persistent cache key hashes XLA_FLAGS word
# by word, so a doubled flag gave the workers' programs other keys than those of the
# command-line subprocesses (helpers.subprocess_env passes this same variable on), and
# neither found the other's compiled programs.
TEST_XLA_FLAGS = ["--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true"]
_flags = os.environ.get("XLA_FLAGS", "").split()
os.environ["XLA_FLAGS"] = " ".join(_flags + [f for f in TEST_XLA_FLAGS if f not in _flags])

# One persistent compilation cache for the whole test session, new and empty each time:
# the suite compiles the same programs again and again (in every module, after
# `jax.clear_caches()` below; in both pytest-xdist workers; in every command-line
# subprocess), so this saves compile time without reusing anything from outside the
# session. The first process creates it; xdist workers and subprocesses inherit the
# variable. Tests that study the cache itself give their own directory.
if "JAXVISCO_TEST_SESSION_CACHE" not in os.environ:
    import atexit
    import shutil
    import tempfile

    _session_cache = tempfile.mkdtemp(prefix="jaxvisco-test-cache-")
    os.environ["JAXVISCO_TEST_SESSION_CACHE"] = _session_cache
    atexit.register(shutil.rmtree, _session_cache, ignore_errors=True)
os.environ["JAXVISCO_CACHE_DIR"] = os.environ["JAXVISCO_TEST_SESSION_CACHE"]

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", os.environ["JAXVISCO_TEST_SESSION_CACHE"])


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Each test module compiles large programs; drop them afterwards so one process
    running the whole suite does not accumulate them (a full run once crashed inside
    XLA's compiler late in the suite)."""
    yield
    jax.clear_caches()
