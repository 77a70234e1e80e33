"""Per-point work over large meshes in passes.

XLA runs the products of 3 x 3 matrices in a point kernel as library calls whose
results it cannot fuse, so a kernel vmapped over every quadrature point of a mesh keeps
one array per intermediate and point alive. In passes (a `lax.map` over blocks of
points) only one block's intermediates are: the step residual of the 3D L-shape hex8 r4
(59 904 points, eG(1), inside its JVP) took 585 MB of XLA buffers at the peak of the run
with all points at once and 427 MB in passes of 512 or 2048 cells, peak RSS 1490-1497 ->
1336-1344 MB, ms per step the same within the machine's noise (1103-1330 vs 1197-1450).
"""

import jax
import jax.numpy as jnp

# Spatial quadrature points of the step residual's point kernel per pass (`Scene.map_points`).
POINTS_PER_PASS = 4096


def map_in_passes(fn, xs, size):
    """`fn` (batched over the leading axis) applied to the pytree `xs` in passes of
    `size` rows (`lax.map`), the last pass padded with copies of the first row; the
    outputs concatenated back to the rows of `xs`."""
    n = jax.tree_util.tree_leaves(xs)[0].shape[0]
    m = -(-n // size)
    pad = m * size - n

    def split(a):
        if pad:
            a = jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])])
        return a.reshape((m, size) + a.shape[1:])

    out = jax.lax.map(fn, jax.tree_util.tree_map(split, xs))
    return jax.tree_util.tree_map(lambda o: o.reshape((m * size,) + o.shape[2:])[:n], out)
