"""`simulate`'s diffrax-shaped signature: option objects, their checks, and the
deprecated keywords of jaxvisco 0.1 (same runs, one warning, clear conflicts)."""

import warnings

import jax
import numpy as np
import pytest

import jaxvisco as jv

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def scene():
    return jv.scenes.lshape(dim=2, refinement=1)


def test_option_objects_refuse_bad_values():
    for make, needle in [
        (lambda: jv.SaveAt(every=0), "every must be an integer >= 1, got 0"),
        (lambda: jv.SaveAt(every=2.0), "every must be an integer >= 1, got 2.0"),
        (lambda: jv.SaveAt([0.1, 0.2], every=2), "give ts or every, not both"),
        (lambda: jv.SaveAt(gamma="yes"), "gamma must be True or False"),
        (lambda: jv.Equilibrium(-1e-3), "tol must be positive and finite, got -0.001"),
        (lambda: jv.Equilibrium("x"), "tol must be a positive number, got 'x'"),
        (lambda: jv.ConstantStepSize(max_halvings=31), r"max_halvings must be an integer in \[0, 30\], got 31"),
        (lambda: jv.StepTo([0.0, 0.1], max_halvings=-1), r"max_halvings must be an integer in \[0, 30\], got -1"),
        (lambda: jv.Schedule([(1.0, 0.0)]), "dt must be positive and finite, got dt = 0.0 in schedule piece 0"),
        (lambda: jv.RecursiveCheckpointAdjoint(checkpoint_every=0), "checkpoint_every must be a positive number"),
    ]:
        with pytest.raises(ValueError, match=needle):
            make()


def test_simulate_refuses_bad_options_before_compiling(scene):
    eG1 = jv.eG(1)
    for kwargs, err, needle in [
        (dict(t1=1.0, dt0=0.1, saveat=5), TypeError, r"saveat must be SaveAt\(every=n, gamma=...\) or SaveAt\(ts\)"),
        (dict(t1=1.0, dt0=0.1, stepsize_controller="pid"), TypeError, "stepsize_controller must be ConstantStepSize()"),
        (dict(t1=1.0, dt0=0.1, event=1e-3), TypeError, r"event must be Equilibrium\(tol\) or None"),
        (dict(t1=1.0, dt0=0.1, adjoint="direct"), TypeError, "adjoint must be RecursiveCheckpointAdjoint"),
        (dict(t1=1.0, dt0=0.1, solver="newton"), TypeError, r"solver must be NewtonKrylov\(...\)"),
        (dict(t1=1.0, dt0=[(1.0, 0.1)]), ValueError, r"for piecewise-constant steps pass stepsize_controller=Schedule"),
        (dict(t1=1.0, dt0=0.1, stepsize_controller=jv.Schedule([(1.0, 0.1)])), ValueError,
         "dt0 = 0.1 conflicts with a Schedule"),
        (dict(dt0=0.1, stepsize_controller=jv.StepTo([0.0, 0.1])), ValueError, "dt0 = 0.1 conflicts with StepTo"),
        (dict(t0=0.5, stepsize_controller=jv.StepTo([0.0, 0.1])), ValueError,
         "t0 = 0.5 disagrees with the StepTo times"),
        # fixed steps take SaveAt(ts) too since #60 (frames at the data's own times)
        (dict(t1=1.0, dt0=0.1, saveat=jv.SaveAt([0.5, 1.5])), ValueError, r"ts must lie within \[t0, t1\]"),
        (dict(t1=1.0, dt0=[(1.0, 0.1)], stepsize_controller=jv.PIDController(1e-3, 1e-3)), ValueError,
         "dt0 is the first step to try"),
        (dict(t1=1.0, saveat=jv.SaveAt([0.5, 2.0]), stepsize_controller=jv.PIDController(1e-3, 1e-3)), ValueError,
         r"ts must lie within \[t0, t1\] = \[0, 1\]"),
    ]:
        with pytest.raises(err, match=needle):
            jv.simulate(scene, eG1, **kwargs)
    # The arguments of jaxvisco 0.1 in their old places, (t_end, dt): a clear error.
    with pytest.raises(ValueError, match=r"t1 = 0.1 must be greater than t0 = 1.0. simulate's arguments are \(scene, "
                                         r"integrator, t0, t1, dt0\)"):
        jv.simulate(scene, eG1, 1.0, 0.1)


def test_old_keywords_are_deprecated_aliases_of_the_same_run(scene):
    """Each 0.1 keyword maps onto its option object: the same run, one DeprecationWarning
    naming the replacements; an old keyword with its replacement is refused."""
    new = jv.simulate(scene, jv.eG(1), t1=0.4,
                      stepsize_controller=jv.Schedule([(0.2, 0.1), (0.4, 0.2)], max_halvings=3), saveat=jv.SaveAt(every=2, gamma=True), event=jv.Equilibrium(1e-12),
                      adjoint=jv.RecursiveCheckpointAdjoint(checkpoints=2), max_steps=8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = jv.simulate(scene, jv.eG(1), t_end=0.4, dt=[(0.2, 0.1), (0.4, 0.2)], max_halvings=3, save_every=2,
                          save_gamma=True, stop_at_equilibrium=1e-12, checkpoint_every=2, differentiable=True,
                          max_steps=8)
    msgs = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(msgs) == 1
    for name, replacement in [("t_end", "t1="), ("dt", "Schedule"), ("save_every", "SaveAt(every=n)"),
                              ("stop_at_equilibrium", "Equilibrium(tol)"), ("checkpoint_every", "RecursiveCheckpointAdjoint(checkpoints=n)")]:
        assert f"{name}= is deprecated, use" in msgs[0] and replacement in msgs[0]
    np.testing.assert_array_equal(np.asarray(new.t), [0.0, 0.2, 0.4])
    for field in ("t", "x", "p", "gamma", "energy", "dissipated", "step_h"):
        np.testing.assert_array_equal(np.asarray(getattr(old, field)), np.asarray(getattr(new, field)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        with pytest.raises(TypeError, match="give t1 or the deprecated t_end, not both"):
            jv.simulate(scene, jv.eG(1), t1=0.4, t_end=0.4, dt0=0.1)
        with pytest.raises(TypeError, match="give event or the deprecated stop_at_equilibrium, not both"):
            jv.simulate(scene, jv.eG(1), t1=0.4, dt0=0.1, event=jv.Equilibrium(1e-3), stop_at_equilibrium=1e-3)
    with pytest.raises(TypeError, match=r"unexpected keyword argument\(s\) \['tend'\]"):
        jv.simulate(scene, jv.eG(1), t1=0.4, dt0=0.1, tend=1.0)
