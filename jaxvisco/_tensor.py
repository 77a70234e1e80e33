"""Small tensor algebra in closed form.

Batched LAPACK calls on stacks of 3x3 matrices are slow on CPU and were seen to hang
inside large jitted programs, so determinants, inverses and the small dense solves of the
local (per quadrature point) systems are written out with plain array arithmetic.
"""

import jax.numpy as jnp

# Voigt order of the six independent components of a symmetric 3x3 tensor.
_VOIGT = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))


def det3(A):
    """Determinant of (..., 3, 3) by cofactor expansion."""
    return (
        A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
        - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
        + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0])
    )


def cofactor3(A):
    """Cofactor matrix of (..., 3, 3): ``cof(A) = det(A) A^{-T}``."""
    c00 = A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1]
    c01 = A[..., 1, 2] * A[..., 2, 0] - A[..., 1, 0] * A[..., 2, 2]
    c02 = A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0]
    c10 = A[..., 0, 2] * A[..., 2, 1] - A[..., 0, 1] * A[..., 2, 2]
    c11 = A[..., 0, 0] * A[..., 2, 2] - A[..., 0, 2] * A[..., 2, 0]
    c12 = A[..., 0, 1] * A[..., 2, 0] - A[..., 0, 0] * A[..., 2, 1]
    c20 = A[..., 0, 1] * A[..., 1, 2] - A[..., 0, 2] * A[..., 1, 1]
    c21 = A[..., 0, 2] * A[..., 1, 0] - A[..., 0, 0] * A[..., 1, 2]
    c22 = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    return jnp.stack(
        [jnp.stack([c00, c01, c02], -1), jnp.stack([c10, c11, c12], -1), jnp.stack([c20, c21, c22], -1)],
        -2,
    )


def inv3(A):
    """Inverse of (..., 3, 3) via the adjugate."""
    return jnp.swapaxes(cofactor3(A), -1, -2) / det3(A)[..., None, None]


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
    pivoting, unrolled in plain array operations (vmap it over a batch).

    **Arguments:** `A` (n, n), `b` (n,) or (n, m). **Returns:** `x` with `b`'s shape.
    """
    n = A.shape[-1]
    vec = b.ndim == 1
    B = b[:, None] if vec else b
    M = jnp.concatenate([A, B], axis=1)
    rows = jnp.arange(n)
    for i in range(n):
        # Partial pivoting: bring the largest remaining entry of column i to row i.
        p = jnp.argmax(jnp.where(rows >= i, jnp.abs(M[:, i]), -1.0))
        ri, rp = M[i], M[p]
        M = M.at[i].set(rp).at[p].set(ri)
        factors = jnp.where(rows > i, M[:, i] / M[i, i], 0.0)
        M = M - factors[:, None] * M[i][None, :]
    # Back substitution.
    X = M[:, n:]
    U = M[:, :n]
    out = jnp.zeros_like(X)
    for i in range(n - 1, -1, -1):
        xi = (X[i] - U[i, i + 1 :] @ out[i + 1 :]) / U[i, i]
        out = out.at[i].set(xi)
    return out[:, 0] if vec else out


def small_inv(A):
    """Inverse of one small dense matrix (see `small_solve`)."""
    return small_solve(A, jnp.eye(A.shape[-1], dtype=A.dtype))
