"""Floating-point policy, and JAX's persistent compilation cache.

jaxvisco computes in float64 only: energy balances to 1e-9 and Newton tolerances near
1e-10 are out of reach in float32. It never switches precision behind your back (no
import side effect); enable it yourself, before creating any array:

    import os

import jax
    jax.config.update("jax_enable_x64", True)

or set the environment variable ``JAX_ENABLE_X64=1``. The command line does this for you.
"""

import os

import jax


def require_x64() -> None:
    """Raise a clear error if JAX is not running in float64."""
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            "jaxvisco needs float64 but JAX runs in float32. Enable it before building "
            "meshes or scenes: `jax.config.update('jax_enable_x64', True)` or set "
            "JAX_ENABLE_X64=1 in the environment."
        )


def default_cache_dir():
    """Where `enable_compilation_cache` keeps compiled programs by default:
    ``$JAXVISCO_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxvisco``, else
    ``~/.cache/jaxvisco``. None when ``JAXVISCO_CACHE_DIR`` is ``off``."""
    env = os.environ.get("JAXVISCO_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "none") else os.path.expanduser(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxvisco")


def enable_compilation_cache(path=None):
    """Keep compiled programs on disk (JAX's persistent compilation cache), so that a new
    process does not compile the time loop again: the paper's L-shape, eG(1), first
    `simulate` call 17.1 s cold, 3.2-3.7 s from the cache in later processes (2-core
    CPU, quiet; what remains is mostly tracing the program).

    `path`: the cache directory (default `default_cache_dir()`, which honours
    ``JAXVISCO_CACHE_DIR``; ``JAXVISCO_CACHE_DIR=off`` turns it off). Call it once,
    before the first `simulate`; it sets JAX's ``jax_compilation_cache_dir`` for the
    whole process. Programs are cached when they took at least a second to compile.
    The ``jaxvisco`` command calls it for you. **Returns:** the directory, or None.
    """
    path = default_cache_dir() if path is None else os.path.expanduser(os.fspath(path))
    if path is None:
        return None
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    return path
