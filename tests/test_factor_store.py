"""The host store of sparse factorizations: each factor call says how many must stay
alive (`retain`); older ones are evicted, and a solve with an evicted token fails loudly."""

import numpy as np
import pytest
import scipy.sparse as sp

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
