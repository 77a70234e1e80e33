"""Floating-point policy.

jaxvisco computes in float64 only: energy balances to 1e-9 and Newton tolerances near
1e-10 are out of reach in float32. It never switches precision behind your back (no
import side effect); enable it yourself, before creating any array:

    import jax
    jax.config.update("jax_enable_x64", True)

or set the environment variable ``JAX_ENABLE_X64=1``. The command line does this for you.
"""

import jax


def require_x64() -> None:
    """Raise a clear error if JAX is not running in float64."""
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            "jaxvisco needs float64 but JAX runs in float32. Enable it before building "
            "meshes or scenes: `jax.config.update('jax_enable_x64', True)` or set "
            "JAX_ENABLE_X64=1 in the environment."
        )
