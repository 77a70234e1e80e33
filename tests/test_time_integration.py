"""Time integration: the identities that define the schemes (THEORY §3)."""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv

# Momenta are conserved by the discrete equations; how well a run shows it follows the
# Newton tolerance: a step accepted at a relative residual r moves the angular momentum
# by up to ~10 r relative on the L-shape (measured 1.05e-10 in one h = 1 step at
# rtol 1e-11, 3.3e-13 at 1e-12), so the 1e-10 checks below run at 1e-12.
TIGHT = jv.NewtonKrylov(rtol=1e-12)
DATA = pathlib.Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def lshape():
    return jv.scenes.lshape(dim=2, refinement=1)


def _momentum_drift(sol):
    P = np.asarray(sol.linear_momentum)
    L = np.asarray(sol.angular_momentum)
    return (np.max(np.abs(P - P[0])) / np.max(np.abs(P[0])), np.max(np.abs(L - L[0])) / np.max(np.abs(L[0])))


@pytest.mark.timeout(300)
@pytest.mark.parametrize("k", [1, 2, 3])
def test_eG_energy_balance_and_momenta(lshape, k):
    # Small steps, then h = 1: a free-flying body turning 0.6 rad per step. Then steps of
    # 2 and 4 (1.2 and 2.4 rad per step, far beyond tau_vol = 0.29), where an earlier
    # eG(2) paired Gamma' with a force its flow rule did not use and dissipated
    # -6.5e-3 H_0 in one step: D_n >= 0 must hold at any step size. Both runs share one
    # compiled program (same capacity max_steps), and other files' runs of the same
    # scheme, scene and solver share it too: capacity 128 for eG(1) (the 100-step runs of
    # test_gradients), 192 for eG(2) (the 150-step reference of test_adaptive's
    # test_dense_output), 32 for eG(3) (the 30-step run of test_ode).
    cap = {1: 128, 2: 192, 3: 32}[k]
    runs = [jv.simulate(lshape, jv.eG(k), t1=2.3, stepsize_controller=jv.Schedule([(0.3, 0.1), (2.3, 1.0)]),
                        root_finder=TIGHT, max_steps=cap),
            jv.simulate(lshape, jv.eG(k), t1=12.0, stepsize_controller=jv.Schedule([(4.0, 2.0), (12.0, 4.0)]),
                        root_finder=TIGHT, max_steps=cap)]
    for sol, n in zip(runs, (6, 5)):
        assert sol.status == "done"
        H, D = np.asarray(sol.energy), np.asarray(sol.dissipated)
        H0 = H[0]
        assert len(H) == n
        step_D = np.diff(D)
        assert np.all(step_D >= 0.0), step_D / H0
        assert np.all(step_D > 0.0)  # the viscous body does dissipate
        balance = np.abs(np.diff(H) + step_D)
        assert np.max(balance) <= 1e-9 * H0, balance / H0
        assert np.all(np.diff(H) <= 1e-12 * H0)
        dP, dL = _momentum_drift(sol)
        assert dP <= 1e-10 and dL <= 1e-10, (dP, dL)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("k", [1, 2, 3])
def test_cG_conserves_momenta(lshape, k):
    sol = jv.simulate(lshape, jv.cG(k), t1=0.5, dt0=0.1, root_finder=TIGHT)
    dP, dL = _momentum_drift(sol)
    assert dP <= 1e-10 and dL <= 1e-10, (dP, dL)
    # cG is not energy consistent: its balance error is not at rounding level.
    H, D = np.asarray(sol.energy), np.asarray(sol.dissipated)
    assert np.max(np.abs(np.diff(H) + np.diff(D))) > 1e-9 * H[0]


@pytest.mark.timeout(300)
def test_elastic_limit_eG_conserves_energy():
    scene = jv.scenes.lshape(dim=2, refinement=1, viscous=False)
    assert scene.initial_state().gamma is None  # nothing stored for Γ
    sol = jv.simulate(scene, jv.eG(1), t1=3.3, stepsize_controller=jv.Schedule([(0.3, 0.1), (3.3, 1.0)]), root_finder=TIGHT)
    H = np.asarray(sol.energy)
    assert sol.gamma is None
    assert np.max(np.abs(H - H[0])) <= 1e-9 * H[0]
    assert np.all(np.asarray(sol.dissipated) == 0.0)


@pytest.mark.timeout(300)
def test_prestretched_body_relaxes_to_equilibrium_under_eG():
    """A body released at rest from a stretched state: points start with C' = 0 while Γ
    relaxes (the case where the paper's beta would divide by zero)."""
    # Soft enough that the slowest vibration is resolved at h = 1 and damped by the
    # viscous branch within a few hundred time units.
    mesh = jv.rectangle(3, 1, lx=3.0, ly=1.0)
    nh = jv.NeoHooke(lam=30.0, mu=7.5)
    mat = jv.ReeseGovindjee(nh, nh, eta_dev=10.0, eta_vol=50.0)
    x0 = mesh.points * jnp.array([1.1, 0.95])
    scene = jv.Scene(mesh, mat, 8.93, positions=x0)
    sol = jv.simulate(scene, jv.eG(1), t1=500.0, dt0=1.0, event=jv.Equilibrium(1e-4), root_finder=TIGHT)
    H, D = np.asarray(sol.energy), np.asarray(sol.dissipated)
    assert sol.status == "equilibrium", (sol.status, H[-1])
    assert np.all(np.diff(H) <= 1e-12 * H[0])
    assert np.max(np.abs(np.diff(H) + np.diff(D))) <= 1e-9 * H[0]
    assert np.all(np.asarray(sol.rejections) == 0)
    assert np.all(np.isfinite(np.asarray(sol.x)))
    assert H[-1] < 1e-2 * H[0]  # measured: 3.6e-3 H0 when the criterion is met


@pytest.mark.timeout(300)
def test_newmark_runs_and_conserves_linear_momentum(lshape):
    sol = jv.simulate(lshape, jv.Newmark(), t1=0.5, dt0=0.1, root_finder=TIGHT)
    dP, _ = _momentum_drift(sol)
    assert sol.status == "done" and dP <= 1e-10


# The runs of tests/data/make_loop_reference.py, on the API of 0.2 (its "eG1_halved", eG(1) at
# h = 2 with every step halved, is left out since session 34: eG(1)'s predictor turns by the
# scheme's own angle and takes those steps without halving, a different trajectory; "eG2"
# keeps a halved step, h = 1, against the old loop): capacities as in the
# tests above and test_gradients (padding changes no result), so these runs reuse those
# compiled programs.
LOOP_REFERENCE_RUNS = {
    "eG1": lambda s: jv.simulate(s, jv.eG(1), t1=2.3, stepsize_controller=jv.Schedule([(0.3, 0.1), (2.3, 1.0)]),
                                 root_finder=TIGHT, max_steps=128),
    "eG2": lambda s: jv.simulate(s, jv.eG(2), t1=2.3, stepsize_controller=jv.Schedule([(0.3, 0.1), (2.3, 1.0)]),
                                 root_finder=TIGHT, max_steps=192),
    "cG1": lambda s: jv.simulate(s, jv.cG(1), t1=0.5, dt0=0.1, root_finder=TIGHT),
    "cG2": lambda s: jv.simulate(s, jv.cG(2), t1=0.5, dt0=0.1, root_finder=TIGHT),
    "Midpoint": lambda s: jv.simulate(s, jv.Midpoint(), t1=0.5, dt0=0.1, root_finder=TIGHT),
    "Newmark": lambda s: jv.simulate(s, jv.Newmark(), t1=0.5, dt0=0.1, root_finder=TIGHT),
}


@pytest.mark.timeout(600)
@pytest.mark.parametrize("name", list(LOOP_REFERENCE_RUNS))
def test_forward_results_equal_the_loop_before_issue_17(lshape, name):
    """The one time loop of 0.2 gives the results of 0.1's forward loop (stored in
    tests/data/loop_reference.npz by make_loop_reference.py at 0e7253e) for every
    integrator, with and without step halving: frames, energies, momenta to the Newton
    tolerance (rtol 1e-12 per step, 1e-9 relative to each field's scale after the steps),
    and the same rejected attempts."""
    ref = np.load(DATA / "loop_reference.npz")
    sol = LOOP_REFERENCE_RUNS[name](lshape)
    assert sol.status == "done"
    np.testing.assert_array_equal(np.asarray(sol.rejections), ref[f"{name}/rejections"])
    np.testing.assert_array_equal(np.asarray(sol.t), ref[f"{name}/t"])
    for field in ("x", "p", "energy", "dissipated", "linear_momentum", "angular_momentum"):
        a, b = np.asarray(getattr(sol, field)), ref[f"{name}/{field}"]
        scale = np.max(np.abs(b))
        if field == "dissipated":
            scale = np.max(np.abs(ref[f"{name}/energy"]))  # D starts at 0: measure it against H
        err = np.max(np.abs(a - b)) / scale
        print(f"{name} {field}: {err:.1e}")
        assert err <= 1e-9, (field, err)


@pytest.mark.timeout(300)
def test_eg_residual_has_no_rounding_floor_above_1e_13(lshape):
    """eG(1) on the L-shape at h = 0.1 converges to rtol = 1e-13 in every step (the scaled
    residual each step reports is below it), not to the floor that the "no longer halves
    below 1000 rtol" rule accepts. The energy defect used to be a difference of two
    energies near C = I, whose ~1e-16 mu rounding eG's algorithmic stress divides by the
    squared strain increment: this run's residual stalled at 6e-12 - 2.5e-11 (now
    <= 5.2e-14), and at the default rtol 1e-10 the 2D L-shape at refinement 4 ended
    every step with Newton iterations against that floor."""
    sol = jv.simulate(lshape, jv.eG(1), t1=1.0, dt0=0.1, root_finder=jv.NewtonKrylov(rtol=1e-13))
    r = np.asarray(sol.residual)
    assert sol.status == "done" and len(r) == 10  # one per step
    assert np.all(r <= 1e-13), r


def _local_flow_solutions(scheme, material, F, G0, h, iterations=30):
    """Gamma at the new time nodes of one spatial point whose F (k+1, 3, 3) is
    prescribed: Newton on the point's weak flow rule R_G = 0 (exact Jacobian)."""
    from jaxvisco._fem._tensor import sym_to_vec, vec_to_sym

    k = scheme.k

    def nodes(g):
        return jnp.concatenate([G0[None], vec_to_sym(g.reshape(k, 6))])

    def R(g):
        return scheme.point_kernel(material, F, nodes(g), h)[1].reshape(-1)

    def newton(_, g):
        return g - jnp.linalg.solve(jax.jacfwd(R)(g), R(g))

    g = jax.lax.fori_loop(0, iterations, newton, jnp.tile(sym_to_vec(G0), k))
    return jnp.max(jnp.abs(R(g))), scheme.point_dissipation(material, F, nodes(g), h)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("k, q", [(1, 1), (1, 2), (1, 3), (2, 4)])
def test_eG_point_dissipation_is_nonnegative_whatever_its_quadrature(k, q):
    """eG's flow rule is collocated at the k Gauss points also when the momentum and
    energy terms take more points (`eG(k, quadrature=q)`), so the dissipation of every
    spatial point over a step is a sum of non-negative terms. Drawn point histories (F at
    the time nodes, Gamma_n) of a fast-relaxing material over h = 1, the flow rule solved
    at the point: D >= 0 in every one. With one rule for both (until session 33) and
    q > k the weak law was not collocation, and each q > k case here failed (a first
    probe with other draws: eG(1, quadrature=2) D < 0 in 32 of 115 solved histories, down
    to -3.6e4; quadrature=3 in 27 of 104; q = k in none)."""
    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=50.0, eta_vol=10.0)
    rng = np.random.default_rng(0)
    n = 160 * k * k  # the 12 x 12 local Newton of k = 2 converges from fewer draws
    F = np.eye(3) + rng.normal(size=(n, k + 1, 3, 3)) * rng.uniform(0.01, 0.3, size=(n, 1, 1, 1))
    B = rng.normal(size=(n, 3, 3)) * 0.1
    G0 = np.eye(3) + (B + np.swapaxes(B, 1, 2)) / 2
    usable = (np.min(np.linalg.eigvalsh(G0), axis=1) > 0.5) & (np.min(np.linalg.det(F), axis=1) > 0.5)
    scheme = jv.eG(k, quadrature=q)
    res, D = jax.jit(jax.vmap(lambda f, g: _local_flow_solutions(scheme, material, f, g, 1.0)))(
        jnp.asarray(F[usable]), jnp.asarray(G0[usable]))
    res, D = np.asarray(res), np.asarray(D)
    solved = np.isfinite(res) & (res <= 1e-8)
    assert solved.sum() >= 40, solved.sum()
    assert np.all(D[solved] >= -1e-10 * np.max(np.abs(D[solved]))), np.sort(D[solved])[:5]


@pytest.mark.timeout(300)
def test_eG_with_more_time_points_keeps_the_balance_at_large_steps():
    """eG(2, quadrature=4) on the paper's scene at h = 1 (no halving there, unlike
    eG(2)): H_{n+1} - H_n = -D_n with D_n > 0 at every step, linear momentum kept; its
    angular momentum is not conserved (the test functions interpolate the trajectory at
    the 2 Gauss points only): measured up to 3.0e-4 of it per step."""
    sol = jv.simulate(jv.scenes.lshape(dim=2, refinement=1), jv.eG(2, quadrature=4), t1=10.0, dt0=1.0, root_finder=TIGHT)
    assert sol.status == "done" and int(np.sum(sol.rejections)) == 0
    H, D = np.asarray(sol.energy), np.asarray(sol.dissipated)
    step_D = np.diff(D)
    assert np.all(step_D > 0.0), step_D / H[0]
    assert np.max(np.abs(np.diff(H) + step_D)) <= 1e-9 * H[0], (np.diff(H) + step_D) / H[0]
    dP, _ = _momentum_drift(sol)
    assert dP <= 1e-10, dP


@pytest.mark.timeout(300)
@pytest.mark.parametrize("k", [1, 2])
def test_solve_carries_the_dissipation_of_its_solution(lshape, k):
    """eG's Newton loop keeps the dissipation that its last residual evaluation computed
    (the time loop uses it for D_n instead of evaluating the point kernel again): it is
    the step's dissipation at the solution it returns."""
    import equinox as eqx

    from jaxvisco._solver._newton import solve_step
    from jaxvisco._solver._tangent import empty_tangent
    from jaxvisco._time_element._step import make_context, predictor, step_dissipation

    scheme = jv.eG(k)
    state = lshape.initial_state()

    @eqx.filter_jit
    def both(h):
        ctx = make_context(lshape, state, jnp.asarray(0.0), h)
        # stall_limit=0: eG(2) at h = 0.5 from the predictor creeps (line-search halvings)
        # before it converges, and the default gives such a step up (to be halved)
        r = solve_step(jv.NewtonKrylov(stall_limit=0), scheme, lshape, ctx,
                       predictor(scheme, lshape, ctx, lshape.velocity(state.p)), empty_tangent(scheme, lshape))
        return r.converged, r.dissipation, step_dissipation(scheme, lshape, ctx, r.U)

    for h in (0.1, 0.5):  # (eG(2) does not converge at h = 1 without halving)
        converged, carried, direct = both(jnp.asarray(h))
        assert bool(converged) and float(direct) > 0.0
        np.testing.assert_allclose(float(carried), float(direct), rtol=1e-13)
