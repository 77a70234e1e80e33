"""What a lab measures, as fields of a run (issue #60): the forces the supports exert
(`SaveAt(reactions=True)`) and frames at the data's own times with fixed steps
(`SaveAt(ts)`), with their derivatives."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv

SOLVER = jv.NewtonKrylov(rtol=1e-12)


def _gripped(load=True, grip=0.05, t_grip=1.0):
    """The L-shape held at its bottom edge, which slides sideways at a constant speed
    until `t_grip` (a prescribed motion), with a dead load (constant) on its top edge."""
    scene = jv.scenes.lshape(dim=2, refinement=1)
    X = np.asarray(scene.mesh.points)
    fixed = np.zeros(X.shape, bool)
    bottom = X[:, 1] == X[:, 1].min()
    fixed[bottom] = True
    top = X[:, 1] == X[:, 1].max()
    motion = np.zeros(X.shape)
    motion[bottom, 0] = grip
    f = np.zeros(X.shape)
    f[top] = [30.0 / top.sum(), -20.0 / top.sum()]
    return jv.Scene(scene.mesh, scene.material, scene.density, fixed=fixed,
                    loads=[(f, jv.time_functions.Constant(1.0))] if load else None,
                    prescribed=[(motion, jv.time_functions.Ramp(0.0, t_grip))]), bottom, motion / t_grip, f


@pytest.mark.parametrize("k", [1, 2])
def test_reactions_balance_the_momentum_of_every_step(k):
    """Over every step, the supports' impulse equals the change of the body's linear
    momentum minus the loads' impulse (the internal forces sum to zero): h sum_held r =
    dP - h F. A body at rest (dP = 0) has reactions and loads summing to zero."""
    scene, _, _, f = _gripped()
    sol = jv.simulate(scene, jv.eG(k), t1=1.5, dt0=0.1, solver=SOLVER, saveat=jv.SaveAt(reactions=True))
    h = np.diff(np.asarray(sol.t))
    P = np.asarray(sol.linear_momentum)
    R = np.asarray(sol.reaction_force(mean=True))
    F = f.sum(axis=0)
    balance = h[:, None] * R[1:] - (np.diff(P, axis=0) - h[:, None] * F)
    assert np.max(np.abs(balance)) <= 1e-9 * np.max(np.abs(h[:, None] * R[1:])), balance
    # the reactions sit on the held components only
    free = ~np.asarray(scene.fixed.array)
    assert np.all(np.asarray(sol.reaction)[:, free] == 0.0) and np.all(np.asarray(sol.reaction_mean)[:, free] == 0.0)
    # within a step too: the force at a frame's time is the rate of the momentum
    # polynomial minus the loads (degree k-1 in time; the central difference of the
    # momentum, a polynomial of degree k <= 2, is exact), its mean is the step's
    t, d = 0.43, 1e-3
    s = jv.simulate(scene, jv.eG(k), t1=0.6, dt0=0.1, solver=SOLVER, saveat=jv.SaveAt([t - d, t, t + d], reactions=True))
    P, R = np.asarray(s.linear_momentum), np.asarray(s.reaction_force())
    np.testing.assert_allclose(R[1], (P[2] - P[0]) / (2 * d) - F, rtol=0, atol=1e-9 * np.max(np.abs(R[1])))
    np.testing.assert_allclose(np.asarray(s.reaction_force(mean=True))[1], np.asarray(sol.reaction_force(mean=True))[5],
                               rtol=1e-9)


def test_a_clamped_body_at_rest_balances_its_dead_load():
    """A clamped body whose inertia is negligible under a dead load: the supports' forces
    over every step and the load sum to zero, but for the momentum change of the vibration
    the sudden load starts, which vanishes with the density (measured: 1.2e-5 of the load
    at 1e-8 of the L-shape's density, 1.2e-7 at 1e-10)."""
    scene, _, _, f = _gripped(grip=0.0)
    F = f.sum(axis=0)
    off = []
    for factor in (1e-8, 1e-10):
        s = eqx.tree_at(lambda s: s.density, scene, scene.density * factor)
        sol = jv.simulate(s, jv.eG(1), t1=1.0, dt0=0.1, solver=SOLVER, saveat=jv.SaveAt(reactions=True))
        assert sol.status == "done"
        off.append(np.max(np.abs(np.asarray(sol.reaction_force(mean=True))[1:] + F)) / np.max(np.abs(F)))
    assert off[1] <= 0.2 * off[0] and off[1] <= 1e-5, off


@pytest.mark.parametrize("k", [1, 2])
def test_the_work_of_the_reactions_is_the_energy_balance_term(k):
    """A grip moved at a constant speed, then held: the work of the reported reactions,
    sum over steps of h r . v, equals the run's external work (no dead load), the term
    that closes eG's energy balance."""
    scene, bottom, v, _ = _gripped(load=False, t_grip=0.6)
    sol = jv.simulate(scene, jv.eG(k), t1=1.2, dt0=0.1, solver=SOLVER, saveat=jv.SaveAt(reactions=True))
    t = np.asarray(sol.t)
    h = np.diff(t)
    moving = t[1:] <= 0.6 + 1e-12  # steps that end within the ramp move at speed v
    r = np.asarray(sol.reaction_mean)[1:]
    work = np.sum(h[:, None, None] * r * np.where(moving[:, None, None], v[None], 0.0))
    W = float(sol.external_work[-1])
    assert abs(W) > 1e-3
    assert abs(work - W) <= 1e-10 * abs(W), (work, W)
    H = np.asarray(sol.energy)
    np.testing.assert_allclose(H[-1] - H[0], W - float(sol.dissipated[-1]), rtol=0, atol=1e-9 * abs(W))


def _fd(f, z, eps):
    """Fourth-order central differences of f at z (the columns of the Jacobian)."""
    cols = []
    for i in range(z.shape[0]):
        e = np.zeros(z.shape[0])
        e[i] = eps
        cols.append((8 * (f(z + e) - f(z - e)) - (f(z + 2 * e) - f(z - 2 * e))) / (12 * eps))
    return np.stack(cols, -1)


@pytest.mark.timeout(900)
def test_reaction_forces_and_frames_at_data_times_differentiate():
    """The grip's force history at the data's own times (inside fixed steps) as a
    function of (log eta_dev, log mu): `jax.jacfwd` and `jax.jacrev` against fourth-order
    central differences."""
    scene, bottom, _, _ = _gripped(t_grip=0.6)
    ts = np.array([0.0, 0.25, 0.6, 0.83, 1.0])

    def forces(z):
        sc = eqx.tree_at(lambda s: (s.material.eta_dev, s.material.equilibrium.mu), scene,
                         (jnp.exp(z[0]), jnp.exp(z[1])))
        sol = jv.simulate(sc, jv.eG(1), t1=1.0, dt0=0.1, solver=SOLVER, saveat=jv.SaveAt(ts, reactions=True))
        return jnp.concatenate([sol.reaction_force(bottom, component=0), sol.x[:, 3, 1]])

    m = scene.material
    z = jnp.log(jnp.array([m.eta_dev, m.equilibrium.mu]))
    values = forces(z)
    assert values.shape == (2 * len(ts),)
    fd = _fd(lambda z: np.asarray(forces(jnp.asarray(z))), np.asarray(z), 1e-3)
    for J in (eqx.filter_jit(jax.jacfwd(forces))(z), eqx.filter_jit(jax.jacrev(forces))(z)):
        err = np.max(np.abs(np.asarray(J) - fd)) / np.max(np.abs(fd))
        assert err <= 1e-6, (np.asarray(J), fd)


def test_frames_at_given_times_with_fixed_steps():
    """`SaveAt(ts)` with fixed steps: a time at a step's end is that step's frame, a time
    inside a step is its time polynomial there (between the neighbouring frames of a run
    that saves every step), and a time at t0 is the initial state."""
    scene = jv.scenes.lshape(dim=2, refinement=1)
    every = jv.simulate(scene, jv.eG(2), t1=1.0, dt0=0.25)
    at = jv.simulate(scene, jv.eG(2), t1=1.0, dt0=0.25, saveat=jv.SaveAt([0.0, 0.25, 0.4, 1.0]))
    assert at.t.shape == (4,) and at.status == "done"
    np.testing.assert_allclose(np.asarray(at.x)[[0, 1, 3]], np.asarray(every.x)[[0, 1, 4]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(at.energy)[[0, 1, 3]], np.asarray(every.energy)[[0, 1, 4]], rtol=1e-12)
    # inside the second step: its quadratic in time through the step's nodes, not the chord
    x_mid = np.asarray(at.x)[2]
    lo, hi = np.asarray(every.x)[1], np.asarray(every.x)[2]
    chord = lo + (0.4 - 0.25) / 0.25 * (hi - lo)
    assert 1e-6 < np.max(np.abs(x_mid - chord)) < 0.1 * np.max(np.abs(hi - lo))
    with pytest.raises(ValueError, match="ts must lie within"):
        jv.simulate(scene, jv.eG(2), t1=1.0, dt0=0.25, saveat=jv.SaveAt([0.5, 1.5]))


def test_reactions_need_held_components():
    with pytest.raises(ValueError, match="needs a scene with held components"):
        jv.simulate(jv.scenes.lshape(dim=2, refinement=1), jv.eG(1), t1=0.2, dt0=0.1,
                    saveat=jv.SaveAt(reactions=True))
    with pytest.raises(ValueError, match="reactions must be True or False"):
        jv.SaveAt(reactions=1)
    sol = jv.simulate(jv.scenes.lshape(dim=2, refinement=1), jv.eG(1), t1=0.2, dt0=0.1)
    with pytest.raises(ValueError, match="holds no reaction forces"):
        sol.reaction_force()


def test_reactions_in_results_files(tmp_path):
    scene, _, _, _ = _gripped()
    sol = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, saveat=jv.SaveAt(reactions=True))
    jv.save(sol, scene, tmp_path / "run.h5")
    back = jv.read_results(tmp_path / "run.h5")
    np.testing.assert_array_equal(back["reaction"], np.asarray(sol.reaction))
    np.testing.assert_array_equal(back["reaction_mean"], np.asarray(sol.reaction_mean))


@pytest.mark.timeout(900)
def test_frames_without_diagnostics_are_the_same_run():
    """`SaveAt(diagnostics=False)`: the same steps and frames (positions, momenta,
    cumulative dissipation and work, reactions) to rounding, the energies and momenta None,
    with fixed steps and data times, every step, and error control; the reverse-mode
    derivative of the grip force against fourth-order central differences; a results file
    refuses such a run.
    (`Experiment` runs this way; tests/test_identify.py checks its derivatives against
    central differences.)"""
    scene, bottom, _, _ = _gripped(t_grip=0.6)
    ts = np.array([0.0, 0.25, 0.6, 0.83, 1.0])
    cases = [dict(saveat=dict(ts=ts, reactions=True)), dict(saveat=dict(reactions=True)),
             dict(saveat=dict(ts=ts, reactions=True), stepsize_controller=jv.PIDController(rtol=1e-3, atol=1e-3))]
    for case in cases:
        kw = {k: v for k, v in case.items() if k != "saveat"}
        full = jv.simulate(scene, jv.eG(1), t1=1.0, dt0=0.1, root_finder=SOLVER, saveat=jv.SaveAt(**case["saveat"]), **kw)
        lean = jv.simulate(scene, jv.eG(1), t1=1.0, dt0=0.1, root_finder=SOLVER,
                           saveat=jv.SaveAt(**case["saveat"], diagnostics=False), **kw)
        assert lean.energy is None and lean.kinetic is None and lean.angular_momentum is None
        assert full.energy is not None and lean.t.shape == full.t.shape
        for k in ("t", "x", "p", "dissipated", "external_work", "reaction", "step_h"):
            a, b = np.asarray(getattr(full, k)), np.asarray(getattr(lean, k))
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-13 * max(1.0, np.max(np.abs(a))), err_msg=k)

    def force(z):
        sc = eqx.tree_at(lambda s: s.material.eta_dev, scene, jnp.exp(z[0]))
        sol = jv.simulate(sc, jv.eG(1), t1=1.0, dt0=0.1, root_finder=SOLVER,
                          saveat=jv.SaveAt(ts, reactions=True, diagnostics=False))
        return jnp.sum(sol.reaction_force(bottom, component=0) ** 2)

    z = jnp.log(jnp.array([scene.material.eta_dev]))
    g = np.asarray(jax.grad(force)(z))
    fd = _fd(lambda z: np.asarray(force(jnp.asarray(z)))[None], np.asarray(z), 1e-3)[0]
    assert np.abs(fd).max() > 0
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    with pytest.raises(ValueError, match="diagnostics must be True or False"):
        jv.SaveAt(diagnostics="no")
    with pytest.raises(ValueError, match="holds no diagnostics"):
        jv.save(lean, scene, "unused.h5")
    assert "diagnostics=False" in repr(jv.SaveAt(diagnostics=False))
