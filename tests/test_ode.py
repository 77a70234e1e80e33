"""The semi-discrete ODE (jaxvisco.semidiscrete): Jacobian, energy rate, agreement with eG."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxvisco as jv


def _lshape(mass="lumped", viscous=True, refinement=1):
    mesh = jv.lshape_mesh(dim=2, refinement=refinement)
    X = mesh.points
    v0 = jnp.stack([6.0 - 0.6 * X[:, 1], 0.6 * X[:, 0]], axis=-1)
    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    material = jv.ReeseGovindjee(nh, nh if viscous else None, eta_dev=50000.0, eta_vol=10000.0)
    return jv.Scene(mesh, material, 8.93, velocities=v0, mass=mass)


@pytest.fixture(scope="module")
def ode():
    return jv.semidiscrete(_lshape())


def _perturbed(ode, seed=0):
    rng = np.random.default_rng(seed)
    scale = np.r_[1e-2 * np.ones(ode.n_x), np.ones(ode.n_x), 1e-3 * np.ones(ode.n_g)]
    return ode.y0 + scale * rng.standard_normal(ode.n)


@pytest.mark.parametrize("viscous", [True, False])
def test_jacobian_matches_finite_differences(viscous):
    ode = jv.semidiscrete(_lshape(viscous=viscous))
    assert ode.n == 2 * ode.n_x + ode.n_g and (ode.n_g > 0) == viscous
    y = _perturbed(ode)
    J = ode.jac(0.0, y)
    assert J.shape == (ode.n, ode.n) and J.format == "csc"
    assert J.nnz < 0.05 * ode.n**2  # sparse, not a dense global matrix
    rng = np.random.default_rng(1)
    for _ in range(3):
        v = rng.standard_normal(ode.n)
        eps = 1e-6
        fd = (ode.fun(0.0, y + eps * v) - ode.fun(0.0, y - eps * v)) / (2 * eps)
        np.testing.assert_allclose(J @ v, fd, atol=1e-7 * np.max(np.abs(fd)))
    # Every entry of J lies inside the declared pattern.
    S = ode.sparsity
    assert abs(J).multiply(S).sum() == pytest.approx(abs(J).sum())


def test_pack_unpack_and_rates(ode):
    state = ode.unpack(ode.y0)
    np.testing.assert_allclose(ode.pack(state), ode.y0)
    scene = ode.scene
    np.testing.assert_allclose(state.x, scene.x0)
    f = ode.fun(0.0, ode.y0)
    # xdot = M^-1 p = v0 for the lumped mass; at rest in the undeformed state no force.
    np.testing.assert_allclose(f[: ode.n_x].reshape(-1, 2), scene.v0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(f[ode.n_x:], 0.0, atol=1e-8)


def test_energy_rate_is_minus_dissipation(ode):
    y = jnp.asarray(_perturbed(ode, seed=2))
    f = ode.rhs(0.0, y)
    _, dH = jax.jvp(lambda u: ode.energy(u), (y,), (f,))
    D = ode.dissipation_rate(y)
    assert float(D) > 0
    assert float(dH) == pytest.approx(-float(D), rel=1e-7, abs=1e-9 * float(ode.energy(y)))


def test_consistent_mass_rhs_but_no_sparse_jacobian():
    ode = jv.semidiscrete(_lshape(mass="consistent"))
    assert not ode.lumped
    f = ode.fun(0.0, ode.y0)
    np.testing.assert_allclose(f[: ode.n_x].reshape(-1, 2), ode.scene.v0, rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="lumped"):
        ode.jac(0.0, ode.y0)


@pytest.mark.timeout(300)
def test_radau_agrees_with_eG3(ode):
    t_end = 0.3
    ref = solve_ivp(ode.fun, (0.0, t_end), ode.y0, method="Radau", jac=ode.jac, rtol=1e-10, atol=1e-10)
    assert ref.success
    sol = jv.simulate(ode.scene, jv.eG(3), t1=t_end, dt0=0.01, root_finder=jv.NewtonKrylov(rtol=1e-12))
    end = ode.unpack(ref.y[:, -1])
    x, p = np.asarray(sol.x[-1]), np.asarray(sol.p[-1])
    assert np.linalg.norm(x - end.x) / np.linalg.norm(end.x) < 2e-8  # 7e-9 measured (order ~6)
    assert np.linalg.norm(p - end.p) / np.linalg.norm(end.p) < 1e-5  # 3.3e-6 measured
    assert float(sol.energy[-1]) == pytest.approx(float(ode.energy(ref.y[:, -1])), rel=1e-8)


def test_methods_work_inside_a_users_jit(ode):
    """`rhs`, `energy` and `jac_values` are compiled with jaxvisco's XLA options when called
    from the host; inside a user's `jax.jit` (where JAX refuses compile options: it raised
    "compiler_options can only be passed to top-level jax.jit") they are plain nested jits."""
    y = jnp.asarray(_perturbed(ode, seed=3))
    f = jax.jit(lambda u: (ode.rhs(0.0, u), ode.energy(u), ode.jac_values(0.0, u)))(y)
    for a, b in zip(f, (ode.rhs(0.0, y), ode.energy(y), ode.jac_values(0.0, y))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-13 * float(np.max(np.abs(b))))
