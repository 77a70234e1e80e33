"""Derivatives of whole trajectories: implicit step derivatives through >= 100 steps
against central finite differences (issue: gradients and identification)."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv

N_STEPS, H = 100, 0.1
SOLVER = jv.NewtonKrylov(rtol=1e-12)


def _scene():
    return jv.scenes.lshape(dim=2, refinement=1)


def _with(scene, theta):
    """theta = (log eta_dev, log eta_vol, velocity scale)."""
    base = scene
    return eqx.tree_at(lambda s: (s.material.eta_dev, s.material.eta_vol, s.v0), base,
                       (jnp.exp(theta[0]), jnp.exp(theta[1]), theta[2] * base.v0))


def _loss_fn(scheme, checkpoint_every=None):
    scene = _scene()

    def loss(theta):
        sol = jv.simulate(_with(scene, theta), scheme, t_end=N_STEPS * H, dt=H, solver=SOLVER,
                          differentiable=True, checkpoint_every=checkpoint_every)
        # Dissipated energy and final free energy (sensitive to both viscosities) and a
        # position functional (sensitive to the initial velocity).
        X = scene.x0
        return sol.dissipated[-1] + sol.free_energy[-1] + 1e-3 * jnp.mean((sol.x[-1] - X) ** 2)

    return loss


def _theta0():
    s = _scene()
    return jnp.array([jnp.log(s.material.eta_dev), jnp.log(s.material.eta_vol), 1.0])


@functools.lru_cache(maxsize=None)
def _programs(scheme, checkpoint_every=None):
    """Compiled reverse-mode gradient and forward-mode (value, directional derivative) of
    the loss, shared by the tests of one scheme (compilation dominates their time)."""
    loss = _loss_fn(scheme, checkpoint_every)
    grad = eqx.filter_jit(jax.grad(loss))
    jvp = eqx.filter_jit(lambda t, d: jax.jvp(loss, (t,), (d,)))
    return grad, jvp


@pytest.mark.parametrize(
    "scheme",
    [pytest.param(jv.cG(1), marks=pytest.mark.slow), jv.eG(1), pytest.param(jv.eG(2), marks=pytest.mark.slow)],
    ids=["cG1", "eG1", "eG2"])
def test_reverse_gradient_matches_finite_differences(scheme):
    grad, jvp = _programs(scheme)
    theta = _theta0()
    g = np.asarray(grad(theta))
    zero = jnp.zeros(3)

    def f(t):  # the loss value (the primal output of the forward-mode program)
        return float(jvp(t, zero)[0])

    # Fourth-order central differences: the truncation error is negligible at eps = 1e-3,
    # where the Newton tolerance's noise in the loss (~1e-10) is still far below 1e-6.
    eps = 1e-3
    for i in range(3):
        e = zero.at[i].set(eps)
        fd = (8 * (f(theta + e) - f(theta - e)) - (f(theta + 2 * e) - f(theta - 2 * e))) / (12 * eps)
        rel = abs(g[i] - fd) / abs(fd)
        assert rel <= 1e-6, f"d loss / d theta[{i}]: reverse {g[i]!r}, central FD {fd!r}, rel. error {rel:.2e}"


def test_forward_mode_equals_reverse_mode_and_checkpointing_changes_nothing():
    """jax.jvp through the run equals the gradient's projection; the segment length of
    the checkpointed loop does not change the result."""
    theta = _theta0()
    grad, jvp = _programs(jv.eG(1))
    d = jnp.array([0.3, -0.7, 0.2])
    _, tangent = jvp(theta, d)
    g = grad(theta)
    assert abs(float(tangent) - float(g @ d)) <= 1e-9 * abs(float(tangent))
    g5 = _programs(jv.eG(1), checkpoint_every=5)[0](theta)
    np.testing.assert_allclose(np.asarray(g5), np.asarray(g), rtol=1e-10)
def test_differentiable_run_equals_adaptive_run():
    scene = _scene()
    a = jv.simulate(scene, jv.eG(1), t_end=2.0, dt=0.25, solver=SOLVER)
    b = jv.simulate(scene, jv.eG(1), t_end=2.0, dt=0.25, solver=SOLVER, differentiable=True, save_every=2)
    assert b.status == "done" and b.n_steps == 8
    np.testing.assert_allclose(b.t, a.t[::2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.x, a.x[::2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.energy, a.energy[::2], rtol=1e-11)
    np.testing.assert_allclose(b.dissipated, a.dissipated[::2], rtol=1e-9, atol=1e-9)
