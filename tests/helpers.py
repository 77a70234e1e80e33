"""Shared test utilities: a central finite-difference checker and random generators.

Import from tests with ``from helpers import fd_check, random_spd, ...`` (pytest puts the
``tests`` folder on ``sys.path``; the folder has no ``__init__.py``).
"""

import os

import jax
import jax.numpy as jnp
import numpy as np


def default_optimization_env():
    """`subprocess_env()` without the cheap-optimization XLA flags that conftest.py sets
    (`TEST_XLA_FLAGS`): for a subprocess that runs its programs far more often than it
    compiles them (fits)."""
    cheap = ("--xla_backend_optimization_level", "--xla_llvm_disable_expensive_passes")
    env = subprocess_env()
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split() if f.split("=")[0] not in cheap)
    return env


def subprocess_env():
    """Environment for a jaxvisco subprocess: the tests' XLA flags (conftest.py), unbuffered
    output (progress lines arrive as they are printed), the test session's compilation
    cache (conftest.py; never the user's; tests that study the cache set their own
    JAXVISCO_CACHE_DIR)."""
    # XLA_FLAGS: conftest.py's, inherited unchanged. The persistent cache key hashes
    # them, so a subprocess finds the programs the test processes compiled, and they its.
    env = dict(os.environ)
    env["JAXVISCO_CACHE_DIR"] = os.environ.get("JAXVISCO_TEST_SESSION_CACHE", "off")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def capture_time_loop(monkeypatch):
    """Have `simulate` note the arguments of its compiled time loop (`_simulate._run`):
    returns (the loop, a dict that holds ``args`` and ``kwargs`` after a call), so that a
    test can lower the loop a run compiled (``run.lower(*args, **kwargs)``)."""
    from jaxvisco._integrate import _simulate

    captured = {}
    run = _simulate._run

    def capture(*args, **kwargs):
        captured.update(args=args, kwargs=kwargs)
        return run(*args, **kwargs)

    monkeypatch.setattr(_simulate, "_run", capture)
    return run, captured


# ----------------------------------------------------------------- finite differences


def _axpy(x, t, v):
    return jax.tree_util.tree_map(lambda a, b: a + t * b, x, v)


def _random_like(x, rng):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(rng.standard_normal(np.shape(a))), x)


def central_difference(f, x, direction, eps=1e-6, order=2):
    """Directional derivative ``d/dt f(x + t v)|_{t=0}`` by central differences.

    **Arguments:** `f` maps `x` (an array or a pytree of arrays) to an array; `direction`
    has `x`'s structure; `eps` the step; `order` 2 (two evaluations) or 4 (four).
    **Returns:** an array with `f(x)`'s shape.
    """
    if order == 2:
        return (jnp.asarray(f(_axpy(x, eps, direction))) - jnp.asarray(f(_axpy(x, -eps, direction)))) / (
            2.0 * eps
        )
    if order == 4:
        fp1, fm1 = f(_axpy(x, eps, direction)), f(_axpy(x, -eps, direction))
        fp2, fm2 = f(_axpy(x, 2 * eps, direction)), f(_axpy(x, -2 * eps, direction))
        return (8.0 * (jnp.asarray(fp1) - jnp.asarray(fm1)) - (jnp.asarray(fp2) - jnp.asarray(fm2))) / (12.0 * eps)
    raise ValueError(f"order must be 2 or 4, got {order!r}.")


def rel_err(a, b, scale=None):
    """``max|a - b| / scale`` with ``scale = max(max|b|, tiny)`` by default."""
    a, b = np.asarray(a), np.asarray(b)
    if scale is None:
        scale = max(np.max(np.abs(b)), np.finfo(float).tiny)
    return float(np.max(np.abs(a - b)) / scale)


def fd_check(f, x, direction=None, eps=1e-6, derivative=None, rtol=1e-6, atol=0.0, seed=0, order=2):
    """Check a derivative of `f` at `x` along `direction` against central differences.

    **Arguments:**
    - `f`: function of `x` (array or pytree) returning an array.
    - `direction`: perturbation with `x`'s structure; random normal if None (from `seed`).
    - `derivative`: the claimed directional derivative (array with `f(x)`'s shape), or a
      callable `direction -> array`; by default forward-mode AD, ``jax.jvp``.
    - `rtol`, `atol`: pass if ``max|fd - claimed| <= atol + rtol * max|claimed|``.

    **Returns:** ``(fd, claimed, err)`` with `err` the relative error; raises
    `AssertionError` (naming both values) when the check fails.
    """
    if direction is None:
        direction = _random_like(x, np.random.default_rng(seed))
    fd = np.asarray(central_difference(f, x, direction, eps=eps, order=order))
    if derivative is None:
        claimed = jax.jvp(f, (x,), (direction,))[1]
    elif callable(derivative):
        claimed = derivative(direction)
    else:
        claimed = derivative
    claimed = np.asarray(claimed)
    assert fd.shape == claimed.shape, f"shape mismatch: fd {fd.shape}, claimed {claimed.shape}"
    scale = np.max(np.abs(claimed)) if claimed.size else 0.0
    diff = np.max(np.abs(fd - claimed)) if claimed.size else 0.0
    err = float(diff / scale) if scale > 0 else float(diff)
    assert diff <= atol + rtol * scale, (
        f"finite-difference check failed: max|fd - claimed| = {diff:.3e}, max|claimed| = "
        f"{scale:.3e} (rel {err:.3e} > rtol {rtol:.1e});\nfd = {fd}\nclaimed = {claimed}"
    )
    return fd, claimed, err


# ------------------------------------------------------------------ random tensors


def random_sym(rng, n=3, scale=1.0):
    """A random symmetric (n, n) matrix with standard normal-ish entries times `scale`."""
    A = rng.standard_normal((n, n))
    return scale * 0.5 * (A + A.T)


def random_spd(rng, n=3, scale=0.3, min_eig=0.2):
    """A random SPD matrix ``I + scale * sym(N(0,1))`` with eigenvalues >= `min_eig`
    (redrawn until they are): a state near the identity, as C or Gamma."""
    for _ in range(1000):
        A = np.eye(n) + random_sym(rng, n, scale)
        if np.linalg.eigvalsh(A).min() >= min_eig:
            return A
    raise RuntimeError("could not draw an SPD matrix with these bounds")


def random_spd_spectrum(rng, n=3, eig_range=(0.5, 2.0)):
    """A random SPD matrix ``Q diag(e) Q^T`` with eigenvalues uniform in `eig_range`."""
    Q = random_rotation(rng, n)
    e = rng.uniform(*eig_range, size=n)
    return (Q * e) @ Q.T


def random_spd_batch(rng, shape, n=3, scale=0.3, min_eig=0.2):
    """An array of shape ``shape + (n, n)`` of independent `random_spd` matrices
    (vectorized; failing draws are redrawn)."""
    shape = tuple(shape)
    out = np.broadcast_to(np.eye(n), shape + (n, n)).copy()
    todo = np.ones(shape, dtype=bool)
    for _ in range(1000):
        k = int(todo.sum())
        if k == 0:
            return out
        A = rng.standard_normal((k, n, n))
        cand = np.eye(n) + scale * 0.5 * (A + np.swapaxes(A, -1, -2))
        ok = np.linalg.eigvalsh(cand).min(axis=-1) >= min_eig
        idx = tuple(ix[ok] for ix in np.nonzero(todo))
        out[idx] = cand[ok]
        todo[idx] = False
    raise RuntimeError("could not draw SPD matrices with these bounds")


def random_rotation(rng, n=3):
    """A random proper rotation (n, n) (Haar-distributed, det = +1)."""
    A = rng.standard_normal((n, n))
    Q, R = np.linalg.qr(A)
    Q = Q * np.sign(np.diag(R))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def random_deformation_gradient(rng, n=3, scale=0.25):
    """``I + scale * N(0,1)``, redrawn until ``det > 0.2``."""
    for _ in range(1000):
        F = np.eye(n) + scale * rng.standard_normal((n, n))
        if np.linalg.det(F) > 0.2:
            return F
    raise RuntimeError("could not draw a deformation gradient")
