"""Closed-form 3x3 algebra and the unrolled small dense solver against numpy."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helpers import random_rotation, random_spd, random_sym
from jaxvisco._fem._tensor import (
    cofactor3,
    ddot,
    det3,
    dev,
    inv3,
    mm,
    small_inv,
    small_solve,
    sym,
    sym_to_vec,
    vec_to_sym,
)


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


def _random_batch(rng, n=50):
    A = rng.standard_normal((n, 3, 3))
    A[:10] *= 10.0 ** rng.uniform(-3, 3, size=(10, 1, 1))  # badly scaled
    return A


def test_det3_vs_numpy(rng):
    A = _random_batch(rng)
    np.testing.assert_allclose(det3(jnp.asarray(A)), np.linalg.det(A), rtol=1e-12, atol=0)
    # Special cases: singular, and a rotation.
    assert det3(jnp.asarray([[1.0, 2, 3], [4, 5, 6], [7, 8, 9]])) == pytest.approx(0.0, abs=1e-12)
    assert float(det3(jnp.asarray(random_rotation(rng)))) == pytest.approx(1.0, rel=1e-14)


def test_inv3_vs_numpy(rng):
    A = _random_batch(rng)
    Ainv = np.asarray(inv3(jnp.asarray(A)))
    np.testing.assert_allclose(Ainv, np.linalg.inv(A), rtol=1e-9, atol=1e-12 * np.abs(Ainv).max())
    # Residual independent of numpy's own rounding.
    res = np.einsum("nij,njk->nik", A, Ainv) - np.eye(3)
    conds = np.linalg.cond(A)
    assert np.all(np.abs(res).max(axis=(1, 2)) < 1e-14 * conds * 10)


def test_cofactor3_vs_numpy(rng):
    A = _random_batch(rng)
    expected = np.linalg.det(A)[:, None, None] * np.swapaxes(np.linalg.inv(A), -1, -2)
    got = np.asarray(cofactor3(jnp.asarray(A)))
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(got - expected) <= 1e-10 * scale)
    # Cofactor of a singular matrix is still well defined: A^T cof(A) = det(A) I = 0.
    S = np.array([[1.0, 2, 3], [4, 5, 6], [7, 8, 9]])
    cof = np.asarray(cofactor3(jnp.asarray(S)))
    np.testing.assert_allclose(S.T @ cof, np.zeros((3, 3)), atol=1e-12)
    assert np.abs(cof).max() > 1.0


def test_sym_dev_ddot(rng):
    A = rng.standard_normal((4, 3, 3))
    B = rng.standard_normal((4, 3, 3))
    np.testing.assert_allclose(sym(A), 0.5 * (A + np.swapaxes(A, 1, 2)), rtol=0, atol=0)
    np.testing.assert_allclose(np.trace(dev(jnp.asarray(A)), axis1=1, axis2=2), 0.0, atol=1e-14)
    np.testing.assert_allclose(ddot(A, B), np.einsum("nij,nij->n", A, B), rtol=1e-14)


def test_sym_to_vec_round_trip(rng):
    S = np.stack([random_sym(rng) for _ in range(20)])
    v = sym_to_vec(jnp.asarray(S))
    assert v.shape == (20, 6)
    np.testing.assert_array_equal(v[:, :3], np.diagonal(S, axis1=1, axis2=2))
    np.testing.assert_array_equal(v[:, 3], S[:, 1, 2])
    np.testing.assert_array_equal(v[:, 4], S[:, 0, 2])
    np.testing.assert_array_equal(v[:, 5], S[:, 0, 1])
    np.testing.assert_array_equal(vec_to_sym(v), S)
    w = rng.standard_normal((7, 6))
    np.testing.assert_array_equal(sym_to_vec(vec_to_sym(jnp.asarray(w))), w)
    # Non-symmetric input: the symmetric part is kept.
    A = rng.standard_normal((3, 3))
    np.testing.assert_allclose(vec_to_sym(sym_to_vec(jnp.asarray(A))), 0.5 * (A + A.T), rtol=1e-15)


# ------------------------------------------------------------------ small dense solve


# Light XLA options: these programs run once.
_FAST = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


@functools.cache
def _batched_solve():
    return jax.jit(jax.vmap(small_solve), compiler_options=_FAST)


def _systems(rng, n, batch, kind):
    A = rng.standard_normal((batch, n, n))
    if kind == "well":
        A += n * np.eye(n)
    elif kind == "badly_scaled":
        # Rows and columns scaled over 8 orders of magnitude.
        r = 10.0 ** rng.uniform(-4, 4, size=(batch, n, 1))
        c = 10.0 ** rng.uniform(-4, 4, size=(batch, 1, n))
        A = r * A * c
    elif kind == "zero_pivot":
        # Zero leading entry (and a zero leading 2x2 block): elimination without row
        # exchanges would divide by zero.
        A[:, 0, 0] = 0.0
        A[:, 1, 1] = 0.0
        A[:, 0, 1] = 0.0
    elif kind == "permutation":
        # A permuted well-conditioned matrix: every diagonal entry is tiny.
        P = np.stack([np.eye(n)[rng.permutation(n)] for _ in range(batch)])
        A = np.einsum("bij,bjk->bik", P, 1e-3 * A + n * np.eye(n))
    elif kind == "spd_blocks":
        # Block-diagonal SPD of 6x6 Voigt-like blocks (the shape of the local systems).
        A = np.zeros((batch, n, n))
        for b in range(batch):
            for k in range(0, n, 6):
                A[b, k : k + 6, k : k + 6] = np.kron(random_spd(rng), np.eye(2))
    return A


KINDS = ["well", "badly_scaled", "zero_pivot", "permutation", "spd_blocks"]


@pytest.mark.timeout(120)
@pytest.mark.parametrize("n", [6, 12, 18])
def test_small_solve_vs_numpy(rng, n):
    """Matrix right-hand sides [b | B | I] in one batched, jitted solve (one compile per n)."""
    batch = 16
    solve = _batched_solve()
    for kind in KINDS:
        A = _systems(rng, n, batch, kind)
        rhs = rng.standard_normal((batch, n, 4))
        R = np.concatenate([rhs, np.broadcast_to(np.eye(n), (batch, n, n))], axis=2)
        X = np.asarray(solve(jnp.asarray(A), jnp.asarray(R)))
        assert X.shape == R.shape and np.all(np.isfinite(X)), kind
        x, Ainv = X[..., :4], X[..., 4:]
        cond = np.linalg.cond(A)
        # Backward-stable solve: relative forward error bounded by ~ cond * eps.
        for got, ref in ((x, np.linalg.solve(A, rhs)), (Ainv, np.linalg.inv(A))):
            err = np.abs(got - ref).reshape(batch, -1).max(1) / np.abs(ref).reshape(batch, -1).max(1)
            assert np.all(err <= 1e-13 * np.maximum(cond, 1.0) + 1e-13), (kind, err.max(), cond.max())
        # Small normwise backward error, independent of numpy.
        res = np.einsum("bij,bjk->bik", A, x) - rhs
        back = np.abs(res).max((1, 2)) / (
            np.abs(A).max((1, 2)) * np.abs(x).max((1, 2)) + np.abs(rhs).max((1, 2))
        )
        assert np.all(back < 1e-13), (kind, back.max())


@pytest.mark.timeout(120)
def test_small_solve_vector_rhs_and_small_inv(rng):
    """The 1-D right-hand-side path and `small_inv`, batched (n = 6, pivoting needed)."""
    n, batch = 6, 8
    A = _systems(rng, n, batch, "zero_pivot")
    b = rng.standard_normal((batch, n))
    x = np.asarray(jax.jit(jax.vmap(small_solve), compiler_options=_FAST)(jnp.asarray(A), jnp.asarray(b)))
    assert x.shape == (batch, n)
    np.testing.assert_allclose(x, np.linalg.solve(A, b[..., None])[..., 0], rtol=1e-10, atol=1e-12)
    Ainv = np.asarray(jax.jit(jax.vmap(small_inv), compiler_options=_FAST)(jnp.asarray(A)))
    np.testing.assert_allclose(Ainv, np.linalg.inv(A), rtol=1e-10, atol=1e-12 * np.abs(Ainv).max())


def test_small_solve_single_and_exact():
    # An integer system with a known exact solution needing a row exchange.
    A = jnp.asarray([[0.0, 2.0, 1.0], [1.0, 1.0, 0.0], [3.0, 0.0, 1.0]])
    x_true = jnp.asarray([1.0, -2.0, 3.0])
    x = jax.jit(small_solve)(A, A @ x_true)
    np.testing.assert_allclose(x, x_true, rtol=1e-14)
    np.testing.assert_allclose(jax.jit(small_inv)(A) @ A, np.eye(3), atol=1e-15)


def test_mm_is_the_matrix_product(rng):
    """`mm` (broadcast products and a sum) is `@` on stacks of square and rectangular
    blocks, with broadcasting batch axes, and so are its forward and reverse derivatives."""
    for a_shape, b_shape in [((50, 3, 3), (50, 3, 3)), ((4, 6, 6), (4, 6, 4)), ((7, 4, 6), (6, 4)),
                             ((2, 1, 3, 3), (5, 3, 3))]:
        A, B = rng.standard_normal(a_shape), rng.standard_normal(b_shape)
        np.testing.assert_allclose(np.asarray(mm(A, B)), A @ B, rtol=1e-13, atol=1e-13)
        dA, dB = rng.standard_normal(a_shape), rng.standard_normal(b_shape)
        _, tangent = jax.jvp(mm, (jnp.asarray(A), jnp.asarray(B)), (jnp.asarray(dA), jnp.asarray(dB)))
        np.testing.assert_allclose(np.asarray(tangent), dA @ B + A @ dB, rtol=1e-12, atol=1e-12)
        W = rng.standard_normal(np.broadcast_shapes(a_shape[:-2], b_shape[:-2]) + (a_shape[-2], b_shape[-1]))
        gA, gB = jax.grad(lambda a, b: jnp.sum(W * mm(a, b)), argnums=(0, 1))(jnp.asarray(A), jnp.asarray(B))
        wA, wB = jax.grad(lambda a, b: jnp.sum(W * (a @ b)), argnums=(0, 1))(jnp.asarray(A), jnp.asarray(B))
        np.testing.assert_allclose(np.asarray(gA), np.asarray(wA), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(gB), np.asarray(wB), rtol=1e-12, atol=1e-12)
