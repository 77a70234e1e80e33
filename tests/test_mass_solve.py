"""The consistent-mass solve v = M^{-1} p (`Scene.velocity`): accuracy, and derivatives
in both modes (a kinetic energy inside `jax.grad` needs a reverse-differentiable solve)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv

jax.config.update("jax_enable_x64", True)


@pytest.mark.parametrize("dim, refinement", [(2, 1), (2, 3), (3, 1)])
def test_velocity_solves_the_mass_and_differentiates_in_both_modes(dim, refinement):
    scene = jv.scenes.lshape(dim=dim, refinement=refinement)
    p = jax.random.normal(jax.random.PRNGKey(dim + refinement), scene.x0.shape)
    v = jax.jit(lambda s, q: s.velocity(q))(scene, p)
    residual = scene.disc.mass_matvec(v, scene.density) - p
    assert float(jnp.max(jnp.abs(residual)) / jnp.max(jnp.abs(p))) <= 1e-13

    # T(p) = p.M^{-1}p / 2: dT/dp = v exactly; M is linear in the density, so dT/drho = -T/rho.
    grad_p = jax.grad(scene.kinetic_energy)(p)
    np.testing.assert_allclose(grad_p, v, rtol=0, atol=1e-13 * float(jnp.max(jnp.abs(v))))

    def T(rho):
        return scene.__class__.kinetic_energy(jv.with_parameters(scene, {"density": rho}), p)

    rho = float(scene.density)
    T0 = float(T(rho))
    np.testing.assert_allclose(float(jax.grad(T)(rho)), -T0 / rho, rtol=1e-12)
    np.testing.assert_allclose(float(jax.jvp(T, (rho,), (1.0,))[1]), -T0 / rho, rtol=1e-12)
    assert float(p.ravel() @ v.ravel()) > 0  # M is positive definite

    # Zero momenta: zero velocity (no division by a zero scale).
    np.testing.assert_array_equal(np.asarray(scene.velocity(jnp.zeros_like(p))), 0.0)
