"""Checks of user input that name the bad value and what is accepted.

Checks run only on concrete values: inside `jax.jit`/`jax.vmap`/`jax.grad` parameters are
tracers and cannot be inspected, so they pass through unchecked (they were checked when
the object was first built from concrete numbers).
"""

import jax
import numpy as np


def _concrete(value):
    try:
        return np.asarray(value)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return None


def check_finite(name, value):
    v = _concrete(value)
    if v is not None and v.dtype.kind in "fc" and not np.all(np.isfinite(v)):
        bad = v[~np.isfinite(v)].ravel()[0]
        raise ValueError(f"{name} must be finite, got {bad!r} in {name}.")


def check_positive(name, value, allow_inf=False):
    """`value` (scalar or array) must be > 0; `inf` only where `allow_inf`."""
    v = _concrete(value)
    if v is None:
        return
    if np.any(np.isnan(v)):
        raise ValueError(f"{name} must be a positive number, got NaN.")
    if not allow_inf and np.any(np.isinf(v)):
        raise ValueError(f"{name} must be a finite positive number, got {v!r}.")
    if np.any(v <= 0):
        accepted = "a positive number (inf for no viscous flow)" if allow_inf else "a positive number"
        raise ValueError(f"{name} must be {accepted}, got {v.ravel()[np.argmin(v.ravel())]!r}.")
