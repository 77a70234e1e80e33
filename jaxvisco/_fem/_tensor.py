"""Small tensor algebra in closed form.

Batched LAPACK calls on stacks of 3x3 matrices are slow on CPU and were seen to hang
inside large jitted programs, so determinants, inverses and the small dense solves of the
local (per quadrature point) systems are written out with plain array arithmetic.
"""

import jax
import jax.numpy as jnp

# Voigt order of the six independent components of a symmetric 3x3 tensor.
_VOIGT = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))


# Determinant and cofactor are cross products of rows (cyclic shifts). As contractions
# with the permutation symbol (an einsum over 27 mostly-zero products per entry) XLA ran
# them as batched `dot_general` library calls over thousands of 3x3 blocks: in the eG(1)
# step of the 2D L-shape (refinement 4) a linearization with two JVPs took 24 ms that way
# and 13 ms with the shifts, the same programs otherwise. Products of 3x3 stacks likewise
# (`mm`).
def _cross(a, b):
    """Cross product along the last axis (length 3) by cyclic shifts."""
    return jnp.roll(a, -1, axis=-1) * jnp.roll(b, -2, axis=-1) - jnp.roll(a, -2, axis=-1) * jnp.roll(b, -1, axis=-1)


def cofactor3(A):
    """Cofactor matrix of (..., 3, 3): ``cof(A) = det(A) A^{-T}``; row i is the cross
    product of rows i+1 and i+2 (indices mod 3)."""
    return _cross(jnp.roll(A, -1, axis=-2), jnp.roll(A, -2, axis=-2))


# Derivatives in closed form: d det(A) = cof(A) : dA and d A^{-1} = -A^{-1} dA A^{-1}.
# Differentiated through the shifts, each material point's stress (a gradient of the
# free energy) and tangent (its forward derivative) carried slice/pad/concatenate
# chains that made up a third of the compiled time loop's kernels; the rules below are
# products of the 3x3 blocks the primal already computes.
@jax.custom_jvp
def det3(A):
    """Determinant of (..., 3, 3): ``A_0 . (A_1 x A_2)`` of its rows."""
    return jnp.sum(A[..., 0, :] * _cross(A[..., 1, :], A[..., 2, :]), axis=-1)


def _det_by_cofactors(A, cof):
    """det A expanded along its first row, with the cofactors already at hand."""
    return jnp.sum(A[..., 0, :] * cof[..., 0, :], axis=-1)


@det3.defjvp
def _det3_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    cof = cofactor3(A)
    return _det_by_cofactors(A, cof), jnp.sum(cof * dA, axis=(-2, -1))


@jax.custom_jvp
def inv3(A):
    """Inverse of (..., 3, 3) via the adjugate."""
    cof = cofactor3(A)
    return jnp.swapaxes(cof, -1, -2) / _det_by_cofactors(A, cof)[..., None, None]


@inv3.defjvp
def _inv3_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    Ainv = inv3(A)
    return Ainv, -mm(mm(Ainv, dA), Ainv)


def mm(A, B):
    """Matrix product of the last two axes, ``A @ B``, as a broadcast product and a sum.

    Why: XLA:CPU runs every batched `dot` of small blocks as a kernel of its own (with
    layout copies around it), where products and sums fuse with the element-wise
    arithmetic around them, in the primal and in its derivatives. Every 3x3 product of
    the point kernels (`_materials`, `_time_element`, `_scene`, the right-hand side
    `_tools._ode`, `inv3`'s derivative) and the local condensation of the tangent
    (`_solver._tangent`) is written with it. Measured (2D L-shape refinement 4, lumped
    mass, eG(1), h = 0.1, alternating processes, XLA options of `_config`): step
    residual 1.08-1.11 -> 0.73-0.74 ms (50 chained in one program, min of 15); one
    right-hand side 0.45-0.46 -> 0.395 ms; tangent formation 31 -> 16.5 ms; 120 steps
    12.40 / 12.44 -> 9.87 / 9.34 ms per step (medians of 5), same iteration counts;
    the paper scene's cold first call 7.28 / 7.32 / 7.31 -> 7.08 / 7.11 / 7.28 s. (The
    comment above had broadcast sums 1.3-1.5x slower than `@` when XLA's fusion emitters
    were in use, before `_config` chose the loop emitters.)"""
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


def right_cauchy_green(F):
    """$C = F^T F$ of (..., 3, 3)."""
    return mm(jnp.swapaxes(F, -1, -2), F)


def sym(A):
    return 0.5 * (A + jnp.swapaxes(A, -1, -2))


def dev(A):
    return A - jnp.trace(A, axis1=-2, axis2=-1)[..., None, None] / 3.0 * jnp.eye(3, dtype=A.dtype)


def ddot(A, B):
    """Double contraction ``A : B`` over the last two axes."""
    return jnp.sum(A * B, axis=(-2, -1))


def sym_to_vec(A):
    """(..., 3, 3) symmetric -> (..., 6) Voigt vector (no factors of two)."""
    return jnp.stack([0.5 * (A[..., i, j] + A[..., j, i]) for i, j in _VOIGT], axis=-1)


def vec_to_sym(v):
    """(..., 6) Voigt vector -> (..., 3, 3) symmetric tensor."""
    a, b, c, d, e, f = (v[..., i] for i in range(6))
    return jnp.stack(
        [jnp.stack([a, f, e], -1), jnp.stack([f, b, d], -1), jnp.stack([e, d, c], -1)], -2
    )


def small_solve(A, b):
    """Solve ``A x = b`` for one small dense system by Gaussian elimination with partial
    pivoting in plain array operations (vmap it over a batch).

    The eliminations and back substitutions are `fori_loop`s, not unrolled: unrolled,
    the 12 x 12 local systems of eG(2)'s tangent were a fifth of its compiled time loop.

    **Arguments:** `A` (n, n), `b` (n,) or (n, m). **Returns:** `x` with `b`'s shape.
    """
    n = A.shape[-1]
    vec = b.ndim == 1
    B = b[:, None] if vec else b
    rows = jnp.arange(n)

    def eliminate(i, M):
        # Partial pivoting: bring the largest remaining entry of column i to row i.
        p = jnp.argmax(jnp.where(rows >= i, jnp.abs(M[:, i]), -1.0))
        ri, rp = M[i], M[p]
        # (row swaps by selects: the pivot p varies between the points this runs for under
        # `vmap`, where an indexed update becomes a scatter, `_update`)
        M = jnp.where((rows == p)[:, None], ri[None, :], jnp.where((rows == i)[:, None], rp[None, :], M))
        factors = jnp.where(rows > i, M[:, i] / M[i, i], 0.0)
        return M - factors[:, None] * M[i][None, :]

    M = jax.lax.fori_loop(0, n, eliminate, jnp.concatenate([A, B], axis=1))
    U, X = M[:, :n], M[:, n:]

    def substitute(j, out):
        i = n - 1 - j  # rows below i are solved; out[i] and above are still zero
        return jnp.where((rows == i)[:, None], ((X[i] - U[i] @ out) / U[i, i])[None, :], out)

    out = jax.lax.fori_loop(0, n, substitute, jnp.zeros_like(X))
    return out[:, 0] if vec else out


def small_inv(A):
    """Inverse of one small dense matrix (see `small_solve`)."""
    return small_solve(A, jnp.eye(A.shape[-1], dtype=A.dtype))
