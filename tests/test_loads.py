"""Several dead loads with their own time functions, and supports that move in time
(prescribed motion): the energy balance of eG stays exact with the reactions' work."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv
from jaxvisco import time_functions as tf


@pytest.mark.parametrize("g, ts, expected", [
    (tf.Constant(2.5), [-1.0, 0.0, 7.0], [2.5, 2.5, 2.5]),
    (tf.Step(at=1.0, before=1.0, after=0.0), [0.0, 0.999, 1.0, 3.0], [1.0, 1.0, 0.0, 0.0]),
    (tf.Ramp(t0=1.0, t1=3.0, v0=2.0, v1=4.0), [0.0, 1.0, 2.0, 3.0, 9.0], [2.0, 2.0, 3.0, 4.0, 4.0]),
    (tf.Table([0.0, 1.0, 3.0], [0.0, 2.0, -2.0]), [-1.0, 0.5, 2.0, 5.0], [0.0, 1.0, 0.0, -2.0]),
    (tf.Sine(period=4.0, amplitude=2.0, phase=0.5, offset=1.0), [0.0, 1.0, 2.5],
     [1.0 + 2.0 * math.sin(0.5), 1.0 + 2.0 * math.sin(math.pi / 2 + 0.5), 1.0 + 2.0 * math.sin(1.25 * math.pi + 0.5)]),
])
def test_time_functions_values_and_jit(g, ts, expected):
    out = jax.jit(jax.vmap(g))(jnp.asarray(ts))
    np.testing.assert_allclose(np.asarray(out), expected, rtol=1e-15, atol=1e-15)


def test_time_function_parameters_are_traced():
    """Parameters are arrays: a new value does not recompile, and derivatives reach them."""
    d = jax.grad(lambda at: tf.Ramp(t0=0.0, t1=at)(1.0))(2.0)
    np.testing.assert_allclose(d, -1.0 / 4.0, rtol=1e-14)  # d/dt1 (1/t1)


@pytest.mark.parametrize("spec, pattern", [
    ({"type": "steep"}, r"type must be one of \['constant', 'ramp', 'sine', 'step', 'table'\], got 'steep'"),
    ({"type": "step", "at": 1.0, "when": 2}, r"unknown key 'when' for type 'step'; accepted: \['at', 'before', 'after'\]"),
    ({"type": "ramp", "t0": 0.0}, r"type 'ramp' needs 't1'"),
    ({"type": "ramp", "t0": 1.0, "t1": 1.0}, r"Ramp: t1 must be greater than t0, got t0 = 1.0, t1 = 1.0"),
    ({"type": "sine", "period": -1.0}, r"Sine: period must be > 0, got -1.0"),
    ({"type": "step", "at": "soon"}, r"Step: at must be a number, got 'soon'"),
    ({"type": "table", "times": [0.0, 2.0, 1.0], "values": [0, 1, 2]}, r"Table: times must increase strictly, got 2.0 then 1.0"),
    ({"type": "table", "times": [0.0, 1.0], "values": [0.0]}, r"Table: times and values must be non-empty lists of the same length, got \(2,\) and \(1,\)"),
    ({"type": "constant", "value": math.inf}, r"Constant: value must be finite, got inf"),
    ("ramp", r"expected a table"),
])
def test_time_function_from_dict_errors(spec, pattern):
    with pytest.raises(ValueError, match=r"^scene.toml: time: " + pattern):
        tf.from_dict(spec, "scene.toml: time: ")


def test_from_dict_builds_the_named_function():
    g = tf.from_dict({"type": "step", "at": 2.0, "before": 1.0, "after": 0.0})
    assert isinstance(g, tf.Step) and float(g(1.0)) == 1.0 and float(g(2.0)) == 0.0
    assert float(tf.from_dict(3.0)(10.0)) == 3.0


def _beam(**kw):
    mesh = jv.rectangle(4, 1, lx=4.0, ly=1.0)
    nh = jv.NeoHooke(lam=30.0, mu=7.5)
    mat = jv.ReeseGovindjee(nh, nh, eta_dev=10.0, eta_vol=50.0)
    X = np.asarray(mesh.points)
    fixed = np.zeros(X.shape, dtype=bool)
    fixed[X[:, 0] == 0.0] = True
    return jv.Scene(mesh, mat, 8.93, fixed=fixed, **kw), X, fixed


def test_loads_sum_with_their_time_functions():
    _, X, _ = _beam()
    f1, f2 = np.zeros(X.shape), np.zeros(X.shape)
    f1[X[:, 0] == 4.0, 1] = -0.5
    f2[X[:, 1] == 1.0, 0] = 0.25
    scene, _, _ = _beam(loads=[(f1, tf.Step(at=1.0, before=1.0, after=0.0)), (f2, lambda t: jnp.sin(t))])
    for t in (0.5, 1.5):
        expected = (1.0 if t < 1.0 else 0.0) * f1 + math.sin(t) * f2
        np.testing.assert_allclose(np.asarray(scene.external_force(jnp.asarray(t))), expected, rtol=1e-15)
    np.testing.assert_array_equal(np.asarray(scene.load), f1 + f2)
    with pytest.raises(ValueError, match="either load"):
        _beam(load=f1, loads=[(f2, None)])
    with pytest.raises(ValueError, match=r"loads\[1\] must be a pair"):
        _beam(loads=[(f1, None), f2])
    with pytest.raises(ValueError, match=r"loads\[0\] force must have shape \(10, 2\)"):
        _beam(loads=[(f1[:3], None)])


def test_prescribed_motion_errors():
    _, X, fixed = _beam()
    u = np.zeros(X.shape)
    u[X[:, 0] == 4.0, 1] = 0.1  # a free node
    with pytest.raises(ValueError, match=r"prescribed\[0\] displacement is 0.1 at node \d+, component 1, which is not held"):
        _beam(prescribed=[(u, tf.Ramp(0.0, 1.0))])
    mesh = jv.rectangle(4, 1, lx=4.0, ly=1.0)
    with pytest.raises(ValueError, match="no component is held"):
        jv.Scene(mesh, jv.NeoHooke(lam=1.0, mu=1.0), 1.0, prescribed=[(np.zeros(X.shape), None)])


@pytest.mark.timeout(300)
@pytest.mark.parametrize("k", [1, 2])
def test_moving_support_eG_energy_balance_is_exact(k):
    """The clamped edge is shaken up and down (starting at rest); the support does work on
    the beam, counted as external work: H_{n+1} - H_n = W_n - D_n to rounding, and the held
    nodes follow the prescribed motion."""
    _, X, fixed = _beam()
    u = np.zeros(X.shape)
    u[X[:, 0] == 0.0, 1] = 0.3
    shake = tf.Sine(period=2.0, amplitude=-0.5, phase=math.pi / 2, offset=0.5)  # (1 - cos(pi t)) / 2
    f = np.zeros(X.shape)
    f[X[:, 0] == 4.0, 0] = 0.2
    scene, _, _ = _beam(prescribed=[(u, shake)], loads=[(f, tf.Ramp(0.0, 1.0))])
    sol = jv.simulate(scene, jv.eG(k), t1=2.0, dt0=0.25, root_finder=jv.NewtonKrylov(rtol=1e-11))
    x, t = np.asarray(sol.x), np.asarray(sol.t)
    target = X[None] + (0.5 - 0.5 * np.cos(np.pi * t))[:, None, None] * u[None]
    assert np.max(np.abs(x[:, fixed] - target[:, fixed])) <= 1e-12
    H, D, W = (np.asarray(a) for a in (sol.energy, sol.dissipated, sol.external_work))
    assert np.max(np.abs(np.diff(W))) > 1e-2  # the support and the load do work
    scale = np.max(np.abs(H))
    assert np.max(np.abs(np.diff(H) + np.diff(D) - np.diff(W))) <= 1e-9 * scale
    assert np.all(np.diff(D) >= -1e-14 * scale)


# ------------------------------------------------------------------ materials per part


def _two_part_scene(mat_left, mat_right, rho_left=8.93, rho_right=8.93):
    mesh = jv.rectangle(4, 1, lx=4.0, ly=1.0)
    centres = np.asarray(mesh.points)[np.asarray(mesh.cells)].mean(axis=1)
    left = np.flatnonzero(centres[:, 0] < 2.0)
    right = np.flatnonzero(centres[:, 0] >= 2.0)
    X = np.asarray(mesh.points)
    v0 = jnp.stack([jnp.zeros(len(X)), 0.4 * jnp.asarray(X[:, 0]) - 0.8], -1)
    density = np.where(centres[:, 0] < 2.0, rho_left, rho_right)  # one per cell
    return jv.Scene(mesh, [(mat_left, left), (mat_right, right)], density, velocities=v0), mesh


def _viscous(lam, mu, eta_dev, eta_vol):
    nh = jv.NeoHooke(lam=lam, mu=mu)
    return jv.ReeseGovindjee(nh, nh, eta_dev=eta_dev, eta_vol=eta_vol)


@pytest.mark.timeout(300)
def test_materials_per_part_equal_one_material_and_keep_the_balance():
    """Two parts with the same material and density run exactly like one material; with a
    stiff, slow, heavy left part and a soft, fast right part the run differs, and eG's
    energy balance, D >= 0 and the momenta still hold exactly (the tangent stays exact:
    few iterations)."""
    mat = _viscous(30.0, 7.5, 10.0, 50.0)
    run = dict(t1=1.0, dt0=0.25, root_finder=jv.NewtonKrylov(rtol=1e-11))
    same, mesh = _two_part_scene(mat, mat)
    one = jv.Scene(mesh, mat, 8.93, velocities=same.v0)
    assert same.cell_material is not None  # the per-cell path, with equal parameters
    a, b = jv.simulate(same, jv.eG(1), **run), jv.simulate(one, jv.eG(1), **run)
    np.testing.assert_allclose(np.asarray(a.x), np.asarray(b.x), rtol=0, atol=1e-12)

    two, _ = _two_part_scene(_viscous(60.0, 15.0, 5.0, 25.0), _viscous(30.0, 7.5, 10.0, 50.0), rho_left=20.0)
    assert two.cell_material is not None
    np.testing.assert_allclose(float(two.mass()), 2.0 * 20.0 + 2.0 * 8.93, rtol=1e-14)
    p0 = np.asarray(two.initial_state().p)  # p = M v: each part's mass moves with it
    v_left = 0.4 * 1.0 - 0.8  # mean of v_y = 0.4 x - 0.8 over the left part, x in [0, 2]
    v_right = 0.4 * 3.0 - 0.8
    np.testing.assert_allclose(p0[:, 1].sum(), 40.0 * v_left + 17.86 * v_right, rtol=1e-12)
    sol = jv.simulate(two, jv.eG(1), **run)
    assert np.max(np.abs(np.asarray(sol.x) - np.asarray(b.x))) > 1e-3
    H, D = np.asarray(sol.energy), np.asarray(sol.dissipated)
    assert np.max(np.abs(np.diff(H) + np.diff(D))) <= 1e-9 * H[0]
    assert np.all(np.diff(D) >= 0) and D[-1] > 0
    L = np.asarray(sol.linear_momentum)
    momentum_scale = float(two.mass()) * float(jnp.max(jnp.abs(two.v0)))  # mass times top speed
    assert np.max(np.abs(L - L[0])) <= 1e-12 * momentum_scale
    assert np.max(np.asarray(sol.newton_iterations)) <= 6
    # each cell's stress comes from its own material
    x = two.x0 + 0.01 * jnp.asarray(np.asarray(mesh.points))  # uniform 1 % stretch
    S = np.asarray(two.stress(x, two.gamma0))
    S_left = np.asarray(_viscous(60.0, 15.0, 5.0, 25.0).stress(jnp.eye(3).at[:2, :2].mul(1.01**2), jnp.eye(3)))
    cells_left = np.flatnonzero(np.asarray(two.cell_material.array) == 0)
    np.testing.assert_allclose(S[cells_left], np.broadcast_to(S_left, S[cells_left].shape), rtol=1e-12, atol=1e-12)


def test_materials_per_part_errors():
    mesh = jv.rectangle(4, 1, lx=4.0, ly=1.0)
    a, b = _viscous(30.0, 7.5, 10.0, 50.0), _viscous(60.0, 15.0, 5.0, 25.0)
    with pytest.raises(ValueError, match=r"3 of 4 cells have no material \(the first: cell 1\)"):
        jv.Scene(mesh, [(a, [0])], 1.0)
    with pytest.raises(ValueError, match=r"material\[1\]: cell 1 already has material\[0\]"):
        jv.Scene(mesh, [(a, [0, 1]), (b, [1, 2, 3])], 1.0)
    with pytest.raises(ValueError, match=r"material\[1\] cells: index 7 is outside \[0, 3\]"):
        jv.Scene(mesh, [(a, [0, 1]), (b, [2, 7])], 1.0)
    elastic = jv.ReeseGovindjee(jv.NeoHooke(lam=1.0, mu=1.0))
    with pytest.raises(ValueError, match=r"material\[1\] differs in form from material\[0\]"):
        jv.Scene(mesh, [(a, [0, 1]), (elastic, [2, 3])], 1.0)
    scene = jv.Scene(mesh, [(a, [0, 1]), (b, [2, 3])], 1.0)
    with pytest.raises(ValueError, match=r"density must be one number or one per cell, shape \(4,\); got shape \(3,\)"):
        jv.Scene(mesh, a, np.ones(3))
    with pytest.raises(ValueError, match="take a scene of one material; this one has 2"):
        jv.with_parameters(scene, {"eta_dev": 1.0})


# ------------------------------------------------------------------ surface loads


@pytest.mark.timeout(300)
def test_traction_gives_the_exact_impulse_and_eG_balances_its_work():
    """A free block pulled on its right face by a uniform traction ramped up over t in
    [0, 1] and then held: the total momentum grows by the exact impulse
    t0 * length * int g dt (1.5 at t = 2), and H_{n+1} - H_n = W_n - D_n to rounding."""
    mesh = jv.rectangle(3, 2, lx=3.0, ly=2.0, cell_type="quad8")
    right = jv.facets_from_nodes(mesh, jv.nodes_where(mesh, lambda X: np.isclose(X[:, 0], 3.0)))
    assert len(right) == 2 and np.isclose(jv.facet_area(mesh, right), 2.0)
    t0 = np.array([0.3, -0.1])
    scene = jv.Scene(mesh, _viscous(30.0, 7.5, 10.0, 50.0), 8.93,
                     loads=[(jv.traction_load(mesh, right, t0), tf.Ramp(0.0, 1.0))])
    sol = jv.simulate(scene, jv.eG(1), t1=2.0, dt0=0.25, root_finder=jv.NewtonKrylov(rtol=1e-11))
    t = np.asarray(sol.t)
    impulse = np.where(t < 1.0, 0.5 * t**2, 0.5 + (t - 1.0))[:, None] * (2.0 * t0)[None]
    L = np.asarray(sol.linear_momentum)
    np.testing.assert_allclose(L - L[0], impulse, rtol=0, atol=1e-12)
    H, D, W = (np.asarray(a) for a in (sol.energy, sol.dissipated, sol.external_work))
    assert W[-1] > 1e-3 and D[-1] > 0
    assert np.max(np.abs(np.diff(H) + np.diff(D) - np.diff(W))) <= 1e-9 * np.max(np.abs(H))
