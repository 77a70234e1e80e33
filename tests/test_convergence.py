"""Measured convergence orders (THEORY §3): cG(k) is of order 2k at the time nodes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxvisco as jv


def _soft_scene():
    # A small, soft body so that h*omega is small at the tested steps (asymptotic regime).
    mesh = jv.rectangle(2, 1, lx=2.0, ly=1.0)
    nh = jv.NeoHooke(lam=30.0, mu=7.5)
    mat = jv.ReeseGovindjee(nh, nh, eta_dev=50.0, eta_vol=10.0)
    X = mesh.points
    v0 = jnp.stack([0.3 - 0.5 * X[:, 1] + 0.2 * X[:, 0] * X[:, 1], 0.5 * X[:, 0] - 0.1 * X[:, 1] ** 2], -1)
    return jv.Scene(mesh, mat, 8.93, velocities=v0)


T = 0.8
# Newton with direct linear solves to rtol 1e-12: the errors measured here are the
# discretization's (>= 1e-7 at the finest steps, measured), far above the Newton tolerance with
# either linear solver. Direct solves make the eG(1) runs the program of
# test_reliability's small-body runs (same mesh shape, solver, SaveAt and capacity 64), so
# the suite compiles it once.
SOLVER = jv.NewtonKrylov(linear_solver=jv.Direct(), rtol=1e-12)
# Steps in the asymptotic range (measured: cG(1)'s Γ error is pre-asymptotic above h = 0.05).
STEPS = {1: (0.05, 0.025, 0.0125), 2: (0.2, 0.1, 0.05), 3: (0.4, 0.2, 0.1)}


@pytest.fixture(scope="module")
def reference():
    scene = _soft_scene()
    sol = jv.simulate(scene, jv.cG(3), t1=T, dt0=0.0125, saveat=jv.SaveAt(gamma=True), max_steps=64,
                      root_finder=SOLVER)
    return scene, np.asarray(sol.x[-1]), np.asarray(sol.gamma[-1])


def _orders(scene, scheme, ref_x, ref_g):
    ex, eg = [], []
    for h in STEPS[scheme.k]:
        sol = jv.simulate(scene, scheme, t1=T, dt0=h, saveat=jv.SaveAt(gamma=True), max_steps=64,
                          root_finder=SOLVER)
        ex.append(np.max(np.abs(np.asarray(sol.x[-1]) - ref_x)))
        eg.append(np.max(np.abs(np.asarray(sol.gamma[-1]) - ref_g)))
    ex, eg = np.array(ex), np.array(eg)
    return np.log2(ex[:-1] / ex[1:]), np.log2(eg[:-1] / eg[1:]), ex, eg


@pytest.mark.timeout(600)
@pytest.mark.parametrize("k", [1, 2, 3])
def test_cG_order_2k(reference, k):
    scene, ref_x, ref_g = reference
    ox, og, ex, eg = _orders(scene, jv.cG(k), ref_x, ref_g)
    assert ox[-1] >= 2 * k - 0.3, (ox, ex)
    assert og[-1] >= 2 * k - 0.3, (og, eg)


@pytest.mark.timeout(600)
@pytest.mark.parametrize("k", [1, 2, 3])
def test_eG_order_2k(reference, k):
    """eG(k) evaluates stresses at strains interpolated over the (Gauss–Lobatto) time
    nodes; it keeps the order 2k of cG(k)."""
    scene, ref_x, ref_g = reference
    ox, og, ex, eg = _orders(scene, jv.eG(k), ref_x, ref_g)
    assert ox[-1] >= 2 * k - 0.3, (ox, ex)
    assert og[-1] >= 2 * k - 0.3, (og, eg)


_A = jnp.array([[0.3, 0.1, 0.0], [0.05, -0.1, 0.02], [0.0, 0.04, 0.15]])


def _history(t):
    return jnp.eye(3) + jnp.sin(2.0 * t) * _A


@pytest.fixture(scope="module")
def gamma_reference():
    """Γ(1) of the driven point by scipy's Radau at rtol 1e-13 (rate jitted once)."""
    mat = jv.paper_material()
    rate = jax.jit(lambda t, g: mat.gamma_rate(_history(t).T @ _history(t), g.reshape(3, 3)).ravel())
    sol = solve_ivp(lambda t, g: np.asarray(rate(t, jnp.asarray(g))), (0.0, 1.0), np.eye(3).ravel(),
                    method="Radau", rtol=1e-13, atol=1e-15)
    return mat, sol.y[:, -1].reshape(3, 3)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("scheme", [jv.cG(1), jv.cG(2), jv.cG(3), jv.eG(1), jv.eG(2), jv.eG(3)],
                         ids=lambda s: s.name)
def test_drive_order_2k(gamma_reference, scheme):
    mat, ref = gamma_reference
    errs = []
    for n in (4, 8, 16):
        # Always 16 steps of h = 1/n (t = 0 .. 16/n), so that the three runs share one
        # compiled program (drive compiles per number of steps); the run to t = 1 is the
        # first n steps, whose results do not depend on the steps after them.
        out = jv.drive(mat, _history, np.arange(17) / n, scheme)
        assert bool(np.all(out["converged"][:n + 1]))
        errs.append(np.max(np.abs(np.asarray(out["gamma"][n]) - ref)))
    order = np.log2(errs[-2] / errs[-1])
    assert order >= 2 * scheme.k - 0.3, (order, errs)
    # Outputs are consistent with the material at the driven state.
    assert np.all(np.asarray(out["D"]) >= 0.0)
