"""Array updates without scatters.

XLA:CPU expands every scatter (``x.at[i].set(v)``, ``x.at[idx].add(v)``) into a while
loop of its own before it compiles it (`scatter_expander`): each becomes separately
compiled kernels, and a simplification pipeline runs over the program after the
expansion. The paper scene's eG(1) time loop had 65 of them, most of them one-index
updates (records, Krylov bases, rows of the small local solves) and zero-paddings of
plane gradients. A one-index update as a dynamic-update-slice is done in place, and a
padding is an elementwise operation that fuses with its neighbours.
"""

import jax
import jax.numpy as jnp


def put(x, i, v, axis=0):
    """``x.at[i].set(v)`` for one index `i` along `axis` (a dynamic-update-slice). `i`
    must lie in range: an index out of range is clamped, not dropped."""
    return jax.lax.dynamic_update_index_in_dim(x, jnp.asarray(v, x.dtype), i, axis)


def pad_to_3d(a):
    """(..., d, d) -> (..., 3, 3), zero outside the leading d x d block."""
    d = a.shape[-1]
    if d == 3:
        return a
    return jnp.pad(a, [(0, 0)] * (a.ndim - 2) + [(0, 3 - d), (0, 3 - d)])


def put_or_drop(x, i, v):
    """``x.at[i].set(v, mode="drop")`` along axis 0: `x` unchanged where `i` is out of
    range (the last entry is written with its own value then)."""
    n = x.shape[0]
    j = jnp.clip(i, 0, n - 1)
    return put(x, j, jnp.where((i >= 0) & (i < n), v, x[j]))
