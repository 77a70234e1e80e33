"""Array updates without scatters.

XLA:CPU expands every scatter (``x.at[i].set(v)``, ``x.at[idx].add(v)``) into a while
loop of its own before it compiles it (`scatter_expander`): each becomes separately
compiled kernels, and a simplification pipeline runs over the program after the
expansion. The paper scene's eG(1) time loop had 65 of them, most of them one-index
updates (records, Krylov bases, rows of the small local solves) and zero-paddings of
plane gradients. A one-index update as a dynamic-update-slice is done in place, and a
padding is an elementwise operation that fuses with its neighbours.

Measured on the paper scene's eG(1) loop (AMD EPYC, 2 cores, load ~1): 65 -> 0 scatter
expansions, 158 -> 124 separately compiled kernels, 781 -> 684 fusions; its cold first
call, four alternating pairs of fresh processes: XLA 4.87 / 5.03 / 4.69 / 4.76 s -> 4.38 /
4.30 / 4.31 / 4.34 s, wall 6.59 / 6.65 / 6.32 / 6.41 s -> 5.96 / 5.93 / 5.94 / 6.03 s.
Steps no slower (`benchmarks/results/rc_dus_2d.json`, `rc_dus_3d.json`, `rc_dus_eg2.json`).
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
    """``x.at[i].set(v, mode="drop")`` along axis 0 for ``i >= 0``: `x` unchanged where
    `i` is out of range, negative too (JAX would wrap a negative index). The last entry
    is then written with its own value."""
    n = x.shape[0]
    j = jnp.clip(i, 0, n - 1)
    return put(x, j, jnp.where((i >= 0) & (i < n), v, x[j]))
