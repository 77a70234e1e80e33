"""Sparse direct factorization on the host, callable from compiled JAX code.

XLA on CPU has no sparse LU, so the assembled tangent of the position block is factored
by SuperLU (scipy) through `jax.pure_callback`. A factorization lives in a small host
cache and is referred to by an integer token that travels in the compiled loop's carry:
this is what lets one factorization be reused across Newton iterations and time steps.
A singular matrix gives the token -1 and solves with it return NaN, which the Newton
loop treats as a failed step.
"""

import collections
import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class HostLU:
    """Factorizations of matrices with one fixed sparsity pattern (COO rows/cols)."""

    def __init__(self, rows, cols, n, cache_size=64):
        rows = np.asarray(rows, dtype=np.int64).ravel()
        cols = np.asarray(cols, dtype=np.int64).ravel()
        key = cols * n + rows
        uniq, self._inverse = np.unique(key, return_inverse=True)
        self._indices = (uniq % n).astype(np.int32)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(uniq // n, minlength=n))]).astype(np.int32)
        self.n = n
        self.nnz = len(uniq)
        self._cache = collections.OrderedDict()
        self._cache_size = cache_size
        self._ids = itertools.count()

    def matrix(self, data):
        vals = np.bincount(self._inverse, weights=np.asarray(data, dtype=np.float64).ravel(), minlength=self.nnz)
        return sp.csc_matrix((vals, self._indices, self._indptr), shape=(self.n, self.n))

    def factor(self, data):
        try:
            lu = spla.splu(self.matrix(data))
        except RuntimeError:  # exactly singular
            return np.int64(-1)
        token = next(self._ids)
        self._cache[token] = lu
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return np.int64(token)

    def solve(self, token, b, trans=False):
        lu = self._cache.get(int(token))
        if lu is None:
            return np.full(b.shape, np.nan)
        return lu.solve(np.asarray(b, dtype=np.float64), trans="T" if trans else "N")


def lu_factor(host: HostLU, data):
    """Factor the matrix with COO values `data`; returns an integer token."""
    data = jax.lax.stop_gradient(data)
    return jax.pure_callback(host.factor, jax.ShapeDtypeStruct((), jnp.int64), data, vmap_method="sequential")


def lu_solve(host: HostLU, token, b, trans=False):
    """Solve with a factorization (linear in `b`, so it may sit inside a linearized
    preconditioner)."""

    @jax.custom_jvp
    def solve(b):
        return jax.pure_callback(
            functools.partial(host.solve, trans=trans), jax.ShapeDtypeStruct(b.shape, b.dtype),
            token, b, vmap_method="sequential",
        )

    @solve.defjvp
    def _jvp(primals, tangents):
        return solve(primals[0]), solve(tangents[0])

    return solve(b)
