"""The GMRES of the Newton iterations (`_fem._krylov.gmres`): restarted cycles solve to
the tolerance within `max_steps` vectors in all, and a solve that converges within one
cycle is the one without restarts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvisco._fem._krylov import gmres


def _system(n=120, seed=0):
    """A nonsymmetric, well-posed system with a rough (Jacobi) preconditioner, so that
    GMRES needs a few dozen vectors."""
    rng = np.random.default_rng(seed)
    A = np.diag(np.linspace(1.0, 30.0, n)) + 2.0 * rng.standard_normal((n, n)) / np.sqrt(n)
    b = rng.standard_normal(n)
    A, b = jnp.asarray(A), jnp.asarray(b)
    d = jnp.diag(A)
    return (lambda v: A @ v), (lambda v: v / d), A, b


@pytest.mark.parametrize("recompute", [False, True])
@pytest.mark.parametrize("restart", [None, 4, 10])
def test_restarted_gmres_reaches_the_tolerance(restart, recompute):
    matvec, precond, A, b = _system()
    x, its, rel = jax.jit(lambda b: gmres(matvec, precond, b, 1e-10, 400, recompute, restart))(b)
    true = float(jnp.linalg.norm(b - A @ x) / jnp.linalg.norm(b))
    assert true <= 1e-10 * 1.01 and abs(float(rel) - true) <= 1e-12, (true, float(rel))
    if restart is not None:
        assert int(its) > restart  # it did restart
    full = gmres(matvec, precond, b, 1e-10, 400)[1]
    assert int(its) >= int(full)  # a restart can only cost vectors


def test_restart_caps_the_vectors_in_all():
    matvec, precond, A, b = _system()
    x, its, rel = gmres(matvec, precond, b, 1e-14, 13, True, 5)
    assert int(its) == 13
    true = float(jnp.linalg.norm(b - A @ x) / jnp.linalg.norm(b))
    assert 1e-14 < true < 1.0 and abs(float(rel) - true) <= 1e-12 * max(1.0, true)


def test_one_cycle_is_the_unrestarted_solve():
    matvec, precond, A, b = _system()
    x0, its0, _ = gmres(matvec, precond, b, 1e-3, 400)
    x1, its1, _ = gmres(matvec, precond, b, 1e-3, 400, False, int(its0) + 1)
    assert int(its1) == int(its0)
    np.testing.assert_allclose(np.asarray(x1), np.asarray(x0), rtol=0, atol=1e-14 * float(jnp.abs(x0).max()))
