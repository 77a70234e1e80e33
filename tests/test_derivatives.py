"""Derivatives of default `simulate` calls for every kind of run: jax.jvp and jax.grad for
the eG(2) and cG(1) time elements (step halving on), jax.jvp for an error-controlled run
(differentiated along its accepted steps), each against 4th-order central differences
of plain runs. The runs are short: what is checked is that every part of the loop is
differentiated, not the accumulation over many steps (`test_gradients`: 100 steps)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv
from jaxvisco._integrate._solution import DONE

jax.config.update("jax_enable_x64", True)

SOLVER = jv.NewtonKrylov(rtol=1e-12)
EPS = 1e-3


BASE = jv.scenes.lshape(dim=2, refinement=1)


def _scene(theta):
    """theta = (log eta_dev, velocity scale) on the paper's L-shape."""
    base = BASE
    return eqx.tree_at(lambda s: (s.material.eta_dev, s.v0), base, (jnp.exp(theta[0]), theta[1] * base.v0))


THETA = jnp.array([np.log(5e4), 1.0])
DIRECTION = jnp.array([1.0, 0.3])


def _points():
    return [THETA + s * EPS * DIRECTION for s in (2.0, 1.0, -1.0, -2.0)]


def _fd(v):
    """4th-order central difference along DIRECTION from f at `_points()`."""
    v = [float(x) for x in v]
    return (-v[0] + 8 * v[1] - 8 * v[2] + v[3]) / (12 * EPS)


def _observe(sol):
    return sol.dissipated[-1] + sol.energy[-1] + jnp.sum(sol.p[-1] ** 2)


@pytest.mark.parametrize("scheme", [jv.eG(2), jv.cG(1)], ids=["eG2", "cG1"])
def test_jvp_of_a_default_call_matches_finite_differences(scheme):
    """One compiled program: the JVP's primal output is the plain run, so the
    finite-difference points are calls of the same program."""
    def f(theta):
        return _observe(jv.simulate(_scene(theta), scheme, t1=0.6, dt0=0.1, solver=SOLVER))

    jvp = eqx.filter_jit(lambda t: jax.jvp(f, (t,), (DIRECTION,)))
    d = float(jvp(THETA)[1])
    fd = _fd(jvp(t)[0] for t in _points())
    assert abs(d - fd) <= 1e-6 * abs(fd), (d, fd)


@pytest.mark.parametrize("scheme", [jv.eG(2), jv.cG(1)], ids=["eG2", "cG1"])
def test_grad_of_a_default_call_matches_finite_differences(scheme):
    """Reverse mode (`jax.grad`) of the same call. One compiled program: its value is the
    plain run, so the finite-difference points are calls of the same program."""
    def f(theta):
        return _observe(jv.simulate(_scene(theta), scheme, t1=0.6, dt0=0.1, solver=SOLVER))

    value_and_grad = eqx.filter_jit(jax.value_and_grad(f))
    d = float(value_and_grad(THETA)[1] @ DIRECTION)
    fd = _fd(value_and_grad(t)[0] for t in _points())
    assert abs(d - fd) <= 1e-6 * abs(fd), (d, fd)


def test_adaptive_call_differentiates_along_its_accepted_steps():
    ctrl = jv.PIDController(rtol=1e-3, atol=1e-3)

    def adaptive(theta):
        sol = jv.simulate(_scene(theta), jv.eG(1), t1=1.0, dt0=0.1, stepsize_controller=ctrl, solver=SOLVER,
                          max_steps=64)
        return _observe(sol), (sol.step_t, sol.step_h, sol.n_steps, sol.status_code)

    _, d, (step_t, step_h, n, status) = jax.jvp(adaptive, (THETA,), (DIRECTION,), has_aux=True)
    n = int(n)
    assert int(status) == DONE
    assert np.unique(np.round(np.asarray(step_h)[:n], 12)).size > 1  # the steps vary
    steps = jv.StepTo(np.concatenate([[0.0], np.asarray(step_t)[:n]]))

    def along(theta):  # the accepted steps, fixed: what the derivative differentiates
        return _observe(jv.simulate(_scene(theta), jv.eG(1), stepsize_controller=steps, solver=SOLVER))

    fd = _fd(jax.lax.map(eqx.filter_jit(along), jnp.stack(_points())))
    assert abs(float(d) - fd) <= 1e-6 * abs(fd), (float(d), fd)


def test_dense_output_differentiates_inside_its_steps():
    """SaveAt(ts): frames inside steps (two in one step, one at a step's end, one at t0)
    are the steps' time polynomials, differentiated with them. The controller's loose
    tolerance and dtmax pin every step to 0.1 whatever theta (asserted), so finite
    differences of the plain run see the same steps as the derivative."""
    ctrl = jv.PIDController(rtol=1.0, atol=1.0, dtmin=0.05, dtmax=0.1)
    ts = jnp.array([0.0, 0.05, 0.1, 0.23, 0.27, 0.6])
    weights = jnp.array([0.3, 1.0, -0.7, 0.9, 1.3, -0.4])

    def f(theta):
        sol = jv.simulate(_scene(theta), jv.eG(1), t1=0.6, dt0=0.1, stepsize_controller=ctrl,
                          saveat=jv.SaveAt(ts=ts), solver=SOLVER, max_steps=8)
        per_frame = (sol.dissipated + sol.energy + jnp.sum(sol.p**2, axis=(1, 2))
                     + jnp.sum((sol.x - BASE.x0) ** 2, axis=(1, 2)))
        return jnp.dot(weights, per_frame), (sol.step_h, sol.n_steps)

    jvp = eqx.filter_jit(lambda t: jax.jvp(f, (t,), (DIRECTION,), has_aux=True))
    _, d, (step_h, n) = jvp(THETA)
    values = []
    for t in _points():
        v, _, (step_h, n) = jvp(t)
        np.testing.assert_allclose(np.asarray(step_h)[: int(n)], 0.1, rtol=1e-12)
        values.append(v)
    fd = _fd(values)
    assert abs(float(d) - fd) <= 1e-6 * abs(fd), (float(d), fd)
