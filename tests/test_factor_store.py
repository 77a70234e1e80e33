"""The host store of sparse factorizations: each factor call says how many must stay
alive (`retain`); older ones are evicted, and a solve with an evicted token fails loudly.
Where the extension is built it holds the triangular factors and solves with them."""

import gc

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import jaxvisco._solver._sparse as sparse
from jaxvisco._solver._sparse import RETAIN, HostLU


def _tridiagonal(n):
    A = sp.diags([-1.0, 4.0, -1.0], [-1, 0, 1], shape=(n, n)).tocoo()
    return A.row, A.col, A.data


def test_factor_keeps_what_each_call_retains():
    n = 6
    rows, cols, data = _tridiagonal(n)
    store = HostLU(rows, cols, n)
    b = np.arange(1.0, n + 1)
    tokens = [int(store.factor(data * (1 + i), retain=3)) for i in range(5)]
    for i in (2, 3, 4):  # the three most recent
        x = store.solve(tokens[i], b)
        np.testing.assert_allclose(store.matrix(data * (1 + i)) @ x, b, rtol=1e-14)
    with pytest.raises(RuntimeError, match=r"no longer cached \(the last factor call kept the 3 most recent ones"):
        store.solve(tokens[1], b)
    # A call that needs more keeps more (the replay of a differentiated run asks for a
    # whole segment's worth); the default is RETAIN.
    more = [int(store.factor(data * (10 + i), retain=8)) for i in range(8)]
    assert all(np.isfinite(store.solve(t, b)).all() for t in more)
    assert RETAIN >= 2
    # A singular matrix gives the token -1; solving with it gives NaN (a failed step).
    assert int(store.factor(np.zeros_like(data))) == -1
    assert np.isnan(store.solve(-1, b)).all()


needs_extension = pytest.mark.skipif(sparse._hostlu is None, reason="jaxvisco was built without its extension")


def _pivoting_matrix(n, seed):
    """Nonsymmetric, with small diagonal entries: SuperLU permutes rows and columns."""
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=8.0 / n, random_state=rng) + sp.diags(1e-3 * rng.standard_normal(n))
    A = (A + sp.eye(n, k=1) - 2.0 * sp.eye(n, k=-3)).tocoo()
    return A.row, A.col, A.data


@needs_extension
@pytest.mark.parametrize("trans", [False, True])
def test_published_solves_match_superlu(trans):
    """The extension's triangular solves with SuperLU's published factors give SuperLU's
    own solution (forward and transposed) to rounding."""
    n = 300
    rows, cols, data = _pivoting_matrix(n, 3)
    store = HostLU(rows, cols, n)
    A = store.matrix(data)
    lu = spla.splu(A, permc_spec=HostLU.permc_spec)
    assert not (np.array_equal(lu.perm_r, np.arange(n)) or np.array_equal(lu.perm_c, np.arange(n)))
    token = int(store.factor(data))
    assert token in store._published
    b = np.random.default_rng(4).standard_normal(n)
    x = store.solve(token, b, trans=trans)
    ref = lu.solve(b, trans="T" if trans else "N")
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_allclose((A.T if trans else A) @ x, b, rtol=0, atol=1e-10 * np.abs(b).max())


@needs_extension
def test_published_store_evicts_least_recently_used():
    """A solve through the extension counts as a use: the factorization solved with last
    stays when a new one pushes the store past `retain`; its copies go with the pattern."""
    n = 6
    rows, cols, data = _tridiagonal(n)
    store = HostLU(rows, cols, n)
    b = np.ones(n)
    t0, t1 = (int(store.factor(data * s, retain=2)) for s in (1.0, 2.0))
    store.solve(t0, b)  # t1 is now the least recently used
    t2 = int(store.factor(data * 3.0, retain=2))
    assert sparse._hostlu.last_use(store.key, t1) == -1
    np.testing.assert_allclose(store.matrix(data) @ store.solve(t0, b), b, rtol=1e-14)
    np.testing.assert_allclose(store.matrix(3.0 * data) @ store.solve(t2, b), b, rtol=1e-14)
    with pytest.raises(RuntimeError, match="no longer cached"):
        store.solve(t1, b)
    key = store.key
    del store
    gc.collect()
    assert sparse._hostlu.last_use(key, t0) == -1 and sparse._hostlu.last_use(key, t2) == -1


@needs_extension
def test_large_factors_stay_with_superlu(monkeypatch):
    """Factors above `PUBLISH_NNZ` are not published: SuperLU solves with them."""
    n = 300
    rows, cols, data = _pivoting_matrix(n, 5)
    monkeypatch.setattr(sparse, "PUBLISH_NNZ", 10)
    store = HostLU(rows, cols, n)
    token = int(store.factor(data))
    assert token not in store._published and sparse._hostlu.last_use(store.key, token) == -1
    b = np.ones(n)
    np.testing.assert_allclose(store.matrix(data) @ store.solve(token, b), b, rtol=0, atol=1e-10)


@needs_extension
def test_a_pattern_made_again_keeps_its_published_factors():
    """Two stores of one pattern share its key: the older one going away retracts only
    its own factorizations (tokens are unique in the process)."""
    n = 6
    rows, cols, data = _tridiagonal(n)
    old = HostLU(rows, cols, n)
    t_old = int(old.factor(data))
    new = HostLU(rows, cols, n)
    assert new.key == old.key
    t_new = int(new.factor(2.0 * data))
    assert t_new != t_old
    del old
    gc.collect()
    b = np.ones(n)
    np.testing.assert_allclose(new.matrix(2.0 * data) @ new.solve(t_new, b), b, rtol=1e-14)
    assert sparse._hostlu.last_use(new.key, t_old) == -1


@needs_extension
def test_the_factorization_just_made_is_never_evicted(monkeypatch):
    """Even where another thread solved with an older factorization after the new one was
    published (the extension's clock then ranks the new one below it), eviction keeps
    the one the factor call returns."""
    real = sparse._hostlu

    class OlderUsedLater:
        def __getattr__(self, name):
            return getattr(real, name)

        def last_use(self, key, token):
            return -token  # every older token counts as used more recently

    monkeypatch.setattr(sparse, "_hostlu", OlderUsedLater())
    n = 6
    rows, cols, data = _tridiagonal(n)
    store = HostLU(rows, cols, n)
    t0 = int(store.factor(data, retain=1))
    t1 = int(store.factor(2.0 * data, retain=1))
    b = np.ones(n)
    np.testing.assert_allclose(store.matrix(2.0 * data) @ store.solve(t1, b), b, rtol=1e-14)
    with pytest.raises(RuntimeError, match="no longer cached"):
        store.solve(t0, b)
