"""`Equilibrium` on a body that starts at rest and is then loaded (H0 = 0): measured
against the work of its loads, it stops the run once the body has settled (issue #61;
against H0 alone such a run never stopped)."""

import numpy as np
import pytest

import jaxvisco as jv


def loaded_beam():
    """A soft, viscous cantilever (4 x 1 quad4, clamped at x = 0), at rest, under a
    constant dead load on its tip nodes from t = 0."""
    mesh = jv.rectangle(4, 1, lx=4.0, ly=1.0)
    nh = jv.NeoHooke(lam=30.0, mu=7.5)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=10.0, eta_vol=50.0)
    force = np.zeros((mesh.n_nodes, 2))
    force[jv.nodes_in(mesh, x=4.0)] = [0.0, -0.05]
    return jv.Scene(mesh, material, 1.0, fixed=jv.clamp(mesh, jv.nodes_in(mesh, x=0.0)), loads=[(force, None)])


@pytest.mark.parametrize("adaptive", [False, True])
def test_equilibrium_stops_a_loaded_clamped_beam_that_started_at_rest(adaptive):
    scene = loaded_beam()
    kw = dict(stepsize_controller=jv.PIDController(1e-3, 1e-3), dt0=0.5) if adaptive else dict(dt0=1.0)
    sol = jv.simulate(scene, jv.eG(1), t1=400.0, event=jv.Equilibrium(1e-4), **kw)
    H, K, W, D = (np.asarray(a) for a in (sol.energy, sol.kinetic, sol.external_work, sol.dissipated))
    assert H[0] == 0.0  # at rest and unstrained: the old scale
    assert sol.status == "equilibrium", (sol.status, float(sol.t[-1]), K[-1], W[-1])
    assert float(sol.t[-1]) < 200.0  # measured: t = 72 (constant h = 1)
    # at rest against the work done, and bent: the stored energy is about half the work
    # (a linear spring: W = 2 Psi), the other half dissipated on the way
    assert K[-1] <= 1e-4 * W[-1] and K.max() > 100 * K[-1]
    assert 0.4 < H[-1] / W[-1] < 0.6
    assert abs(H[-1] + D[-1] - W[-1]) <= 1e-8 * W[-1]
