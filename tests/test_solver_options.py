"""Solver options: lineax's GMRES as the Krylov method and chord iterations give the same
steps."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv


def test_lineax_gmres_backend_matches_default():
    scene = jv.scenes.lshape(dim=2, refinement=1)
    # max_steps=24: the capacity of the 20-step default runs below, so that the default
    # solver's runs of this file share one compiled program.
    a = jv.simulate(scene, jv.eG(1), t1=1.0, dt0=0.25, max_steps=24)
    # chord=0: every step runs Newton–Krylov, so every step uses lineax's GMRES.
    b = jv.simulate(scene, jv.eG(1), t1=1.0, dt0=0.25, solver=jv.NewtonKrylov(linear_solver=jv.GMRES(backend="lineax"), chord=0))
    assert b.status == "done" and int(b.n_steps) == 4
    assert np.all(b.krylov_iterations > 0)
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-8)
    np.testing.assert_allclose(b.energy, a.energy, rtol=1e-10)
    H, D = np.asarray(b.energy), np.diff(np.asarray(b.dissipated))
    assert np.max(np.abs(np.diff(H) + D)) <= 1e-9 * H[0]


def test_chord_iterations_reach_the_newton_solution():
    """Chord iterations on the stored factorization replace most Newton–Krylov
    iterations and end at the same steps (to the Newton tolerance), with eG's energy
    balance intact."""
    scene = jv.scenes.lshape(dim=2, refinement=1)
    a = jv.simulate(scene, jv.eG(1), t1=2.0, dt0=0.1, solver=jv.NewtonKrylov(chord=0))
    b = jv.simulate(scene, jv.eG(1), t1=2.0, dt0=0.1)
    assert a.status == b.status == "done"
    assert int(np.sum(a.chord_iterations)) == 0 and int(np.sum(b.chord_iterations)) > 0
    assert int(np.sum(b.newton_iterations)) < int(np.sum(a.newton_iterations))
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-8)
    np.testing.assert_allclose(b.energy, a.energy, rtol=1e-10)
    H, D = np.asarray(b.energy), np.diff(np.asarray(b.dissipated))
    assert np.max(np.abs(np.diff(H) + D)) <= 1e-9 * H[0]


def test_a_tangent_of_a_nearby_step_size_serves_adaptive_steps():
    """`reuse_band`: an adaptive run whose controller changes h often forms fewer
    tangents when a stored one serves steps of an h within 25 % of its own (chord
    iterations on it, a fresh tangent where they do not finish the step). The run takes
    as many steps, each within 1e-5 of the other run's size (the controller sees
    estimates that differ at the Newton tolerance: measured 3.4e-6 at most, positions
    2.3e-6 apart against rtol = 1e-4), energy balance intact. Measured: Newton
    iterations 116 -> 27, chord iterations 675 -> 1880. Since #62 the default controller
    keeps a step while its error allows (`PIDController.change_cost`) and forms a tangent
    for a size it keeps; the case of the band is a controller that takes every longer
    step it proposes (change_cost 0, keep_band 1): 244 steps of 132 sizes, Newton
    iterations 272 -> 89, the same sizes."""
    scene = jv.scenes.lshape(dim=2, refinement=1)
    ctrl = jv.PIDController(1e-4, 1e-4, change_cost=0.0, keep_band=1.0)
    a, b = (jv.simulate(scene, jv.eG(1), t1=3.0, stepsize_controller=ctrl, solver=jv.NewtonKrylov(reuse_band=band))
            for band in (0.0, 0.25))
    assert a.status == b.status == "done" and int(a.n_steps) == int(b.n_steps)
    np.testing.assert_allclose(b.step_h, a.step_h, rtol=1e-5)
    assert len(np.unique(np.asarray(a.step_h))) >= 10  # h changes often: the case the band is for
    assert int(np.sum(b.newton_iterations)) < int(np.sum(a.newton_iterations)) // 2, (
        int(np.sum(b.newton_iterations)), int(np.sum(a.newton_iterations)))
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-5)
    H, D = np.asarray(b.energy), np.diff(np.asarray(b.dissipated))
    assert np.max(np.abs(np.diff(H) + D)) <= 1e-9 * H[0]


@pytest.mark.parametrize("kwargs, match", [(dict(chord=-1), "chord must be an integer"),
                                           (dict(chord=True), "chord must be an integer"),
                                           (dict(chord_contraction=1.0), "chord_contraction must lie"),
                                           (dict(stall_limit=-1), "stall_limit must be an integer >= 0"),
                                           (dict(stall_limit=1.5), "stall_limit must be an integer >= 0"),
                                           (dict(reuse_band=1.0), "reuse_band must be a number in"),
                                           (dict(reuse_band=-0.1), "reuse_band must be a number in"),
                                           (dict(reuse_band="0.2"), "reuse_band must be a number in")])
def test_bad_chord_options_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jv.NewtonKrylov(**kwargs)


@pytest.mark.timeout(600)
def test_a_stalled_newton_gives_the_step_up_early():
    """eG(2)'s first step at h = 1 on the paper scene has no solution near its predictor
    (the branch folds: `benchmarks/eg2_arclength.py`): Newton creeps with 4-8 line-search
    halvings per iteration. With `stall_limit=2` the solve stops, unconverged, once two
    iterations in a row needed 3 or more halvings; with 0 it runs to `max_iterations`.
    At h = 0.1 (no stall) both rules take the same iterations to the same solution."""
    from jaxvisco._solver._newton import solve_step
    from jaxvisco._solver._tangent import empty_tangent
    from jaxvisco._time_element._step import make_context, predictor

    scene, scheme = jv.scenes.lshape(), jv.eG(2)
    state = scene.initial_state()

    @eqx.filter_jit
    def solve(solver, h):
        ctx = make_context(scene, state, jnp.asarray(0.0), h)
        U0 = predictor(scheme, scene, ctx, scene.velocity(state.p))
        return solve_step(solver, scheme, scene, ctx, U0, empty_tangent(scheme, scene))

    stall, creep = (solve(jv.NewtonKrylov(stall_limit=n, chord=0), jnp.asarray(1.0)) for n in (2, 0))
    assert not bool(stall.converged) and not bool(creep.converged)
    assert int(creep.iterations) == 20, int(creep.iterations)  # max_iterations
    assert int(stall.iterations) <= 4, int(stall.iterations)
    small = [solve(jv.NewtonKrylov(stall_limit=n, chord=0), jnp.asarray(0.1)) for n in (2, 0)]
    assert all(bool(r.converged) for r in small)
    assert int(small[0].iterations) == int(small[1].iterations)
    np.testing.assert_array_equal(np.asarray(small[0].U.x), np.asarray(small[1].U.x))


def test_unknown_krylov_method_is_rejected():
    with pytest.raises(ValueError, match="krylov must be one of"), pytest.warns(DeprecationWarning):
        jv.NewtonKrylov(krylov="cg")
    with pytest.raises(ValueError, match=r"GMRES: backend must be one of \('jaxvisco', 'lineax'\), got 'cg'"):
        jv.GMRES(backend="cg")


def test_linear_solvers_are_objects_and_the_strings_of_0_1_still_work():
    """NewtonKrylov(linear_solver=GMRES(...) | Direct()); "krylov"/"direct" name the same
    objects (so the same compiled programs); the keywords krylov, krylov_max_steps and
    refresh_after are deprecated aliases of GMRES's fields."""
    assert jv.NewtonKrylov().linear_solver == jv.GMRES(max_steps=60, refresh_after=5, backend="jaxvisco")
    assert jv.NewtonKrylov(linear_solver="krylov") == jv.NewtonKrylov()
    assert jv.NewtonKrylov(linear_solver="direct") == jv.NewtonKrylov(linear_solver=jv.Direct())
    assert hash(jv.NewtonKrylov(linear_solver="direct")) == hash(jv.NewtonKrylov(linear_solver=jv.Direct()))
    with pytest.warns(DeprecationWarning, match=r"write NewtonKrylov\(linear_solver=GMRES"):
        old = jv.NewtonKrylov(krylov="lineax", krylov_max_steps=30, refresh_after=2)
    assert old.linear_solver == jv.GMRES(max_steps=30, refresh_after=2, backend="lineax")
    with pytest.raises(TypeError, match="refresh_after set.* GMRES, but linear_solver is Direct"), \
            pytest.warns(DeprecationWarning):
        jv.NewtonKrylov(linear_solver=jv.Direct(), refresh_after=3)
    for bad in ("lu", 3, jv.GMRES):
        with pytest.raises(ValueError, match=r"linear_solver must be GMRES\(...\), Direct\(\) or one of"):
            jv.NewtonKrylov(linear_solver=bad)
    for kwargs, match in [(dict(max_steps=0), "max_steps must be an integer >= 1"),
                          (dict(refresh_after=-1), "refresh_after must be an integer >= 0")]:
        with pytest.raises(ValueError, match=match):
            jv.GMRES(**kwargs)


def test_compiler_options_follow_the_environment(monkeypatch):
    """jaxvisco's programs get the CPU option where XLA knows it, none when turned off."""
    from jaxvisco import _config

    try:
        _config.compiler_options.cache_clear()
        monkeypatch.setenv("JAXVISCO_XLA_OPTIONS", "off")
        assert _config.compiler_options() == {}
        _config.compiler_options.cache_clear()
        monkeypatch.delenv("JAXVISCO_XLA_OPTIONS")
        assert _config.compiler_options() == _config._CPU_OPTIONS
    finally:
        _config.compiler_options.cache_clear()


def test_simulate_inside_a_trace_compiles_without_options():
    """Compile options belong to top-level programs only: `simulate` under `jax.jit`
    (after a top-level call has fixed the options) runs as a nested program."""
    import jax

    scene = jv.scenes.lshape(dim=2, refinement=1)
    a = jv.simulate(scene, jv.eG(1), t1=0.2, dt0=0.1, max_steps=24)  # the program of the tests above
    b = jax.jit(lambda s: jv.simulate(s, jv.eG(1), t1=0.2, dt0=0.1).x)(scene)
    np.testing.assert_allclose(np.asarray(b)[:3], np.asarray(a.x), rtol=0, atol=1e-10)
