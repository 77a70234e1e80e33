"""Dirichlet conditions and lumped mass inside the time integration."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv


def _clamped_beam(mass="consistent"):
    mesh = jv.rectangle(4, 1, lx=4.0, ly=1.0)
    nh = jv.NeoHooke(lam=30.0, mu=7.5)
    mat = jv.ReeseGovindjee(nh, nh, eta_dev=10.0, eta_vol=50.0)
    X = np.asarray(mesh.points)
    fixed = np.zeros(X.shape, dtype=bool)
    fixed[X[:, 0] == 0.0] = True
    v0 = jnp.stack([jnp.zeros(len(X)), 0.4 * jnp.asarray(X[:, 0])], -1)
    return jv.Scene(mesh, mat, 8.93, velocities=v0, fixed=fixed, mass=mass), fixed


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mass", ["consistent", "lumped"])
def test_clamped_body_eG_balance_and_held_nodes(mass):
    scene, fixed = _clamped_beam(mass)
    sol = jv.simulate(scene, jv.eG(1), t1=3.0, dt0=0.25, solver=jv.NewtonKrylov(rtol=1e-11))
    x = np.asarray(sol.x)
    X = np.asarray(scene.mesh.points)
    assert np.max(np.abs(x[:, fixed] - X[fixed])) <= 1e-12
    assert np.max(np.abs(x[-1, ~fixed] - X[~fixed])) > 0.1  # the free end moved
    H, D = np.asarray(sol.energy), np.asarray(sol.dissipated)
    assert np.max(np.abs(np.diff(H) + np.diff(D))) <= 1e-9 * H[0]
    assert np.all(np.diff(H) <= 1e-12 * H[0])
    # The exact condensed tangent with constraints keeps Newton quadratic.
    assert np.max(np.asarray(sol.newton_iterations)) <= 6


def test_lumped_mass_is_positive_and_exact_in_total():
    for element in ("quad4", "quad8", "tri6", "quad9"):
        mesh = jv.lshape_mesh(2, 1, cell_type=element)
        scene = jv.Scene(mesh, jv.NeoHooke(lam=1.0, mu=1.0), 2.0, mass="lumped")
        m = np.asarray(scene.disc.mass_diagonal(scene.density))
        assert np.all(m > 0), element
        assert abs(m.sum() - 2.0 * 39.0) <= 1e-10 * 78.0
        M = np.asarray(scene.disc.mass_el)
        assert np.allclose(M, np.einsum("eaa->ea", M)[:, :, None] * np.eye(M.shape[-1])), element


def test_bad_fixed_mask_and_mass_kind():
    mesh = jv.rectangle(2, 1)
    with pytest.raises(ValueError, match="fixed"):
        jv.Scene(mesh, jv.NeoHooke(lam=1.0, mu=1.0), 1.0, fixed=np.zeros((3, 2), dtype=bool))
    with pytest.raises(ValueError, match="mass"):
        jv.Scene(mesh, jv.NeoHooke(lam=1.0, mu=1.0), 1.0, mass="diagonal")


@pytest.mark.timeout(300)
def test_dead_load_energy_balance_includes_external_work():
    """eG with a time-varying dead load at the free end: H_{n+1} - H_n = W_n - D_n."""
    scene, fixed = _clamped_beam()
    X = np.asarray(scene.mesh.points)
    load = np.zeros(X.shape)
    load[X[:, 0] == 4.0, 1] = -0.5
    loaded = jv.Scene(scene.mesh, scene.material, scene.density, fixed=fixed, load=load,
                      load_time=lambda t: jnp.sin(2.0 * t))
    sol = jv.simulate(loaded, jv.eG(2), t1=2.0, dt0=0.25, solver=jv.NewtonKrylov(rtol=1e-11))
    H, D, W = (np.asarray(a) for a in (sol.energy, sol.dissipated, sol.external_work))
    assert np.max(np.abs(W)) > 1e-3  # the load does work
    scale = np.max(np.abs(H))
    assert np.max(np.abs(np.diff(H) + np.diff(D) - np.diff(W))) <= 1e-9 * scale
    assert np.max(np.abs(np.asarray(sol.x)[:, fixed] - X[fixed])) <= 1e-12
