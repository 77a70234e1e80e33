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
    `size` rows; the outputs have the rows of `xs`.

    Each pass reads its rows of `xs` in place and writes its rows of the output in place
    (a `lax.scan` whose carry is the output), and the last pass starts `size` rows
    before the end, so it overlaps the one before and writes the same values again:
    no padded copy of the inputs and no stacked copy of the outputs. (The padded
    version, `lax.map` over a padded copy and a slice of the stacked result, held the
    outputs twice: the time loop of the 3D L-shape hex8 r6 on the multigrid path, eG(1),
    needed 1123 MB of XLA temporary buffers with it and 914 MB now, by XLA's memory
    analysis of the compiled loop.) Derivatives are exact: the overlapped rows' second
    write replaces the first, so their cotangent reaches the last pass only."""
    n = jax.tree_util.tree_leaves(xs)[0].shape[0]
    if n <= size:
        return fn(xs)
    starts = jnp.minimum(jnp.arange(-(-n // size)) * size, n - size)
    take = lambda s: jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, s, size), xs)  # noqa: E731
    one_pass = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct((size,) + a.shape[1:], a.dtype), xs)
    shapes = jax.eval_shape(fn, one_pass)
    out = jax.tree_util.tree_map(lambda o: jnp.zeros((n,) + o.shape[1:], o.dtype), shapes)

    def one(out, s):
        put = lambda o, v: jax.lax.dynamic_update_slice_in_dim(o, v, s, 0)  # noqa: E731
        return jax.tree_util.tree_map(put, out, fn(take(s))), None

    return jax.lax.scan(one, out, starts)[0]
