"""Identification of (eta_dev, eta_vol) from synthetic observations (examples/identify_viscosity.py)."""

import importlib.util
import os

import numpy as np
import pytest

import jaxvisco as jv

EXAMPLES = os.path.join(os.path.dirname(__file__), os.pardir, "examples")


def _example():
    spec = importlib.util.spec_from_file_location("identify_viscosity", os.path.join(EXAMPLES, "identify_viscosity.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_identify_recovers_viscosities(tmp_path):
    """Markers on the flying L-shape, starts off by factors 4 and 3: exact data -> within
    1e-6, 1 % noise -> within 5 % and inside the 95 % intervals."""
    results = _example().main(["--quick", "--out", str(tmp_path)])
    (clean, e_clean), (noisy, e_noisy) = results.values()
    assert clean.converged, clean.message
    assert max(abs(v) for v in e_clean.values()) <= 1e-6, e_clean
    assert max(abs(v) for v in e_noisy.values()) <= 0.05, e_noisy
    assert all(noisy.identifiable.values())
    assert (tmp_path / "identify_fit.png").stat().st_size > 10_000  # the gallery's picture


def test_identify_rejects_bad_input():
    """The deprecated form keeps its checks; the new one names a bad parameter, bounds that
    exclude the start, data of the wrong shape and a missing data column."""
    scene = jv.scenes.lshape(dim=2, refinement=1)
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="unknown parameter 'eta'"):
        jv.identify(scene, jv.eG(1), lambda s: s.energy, np.ones(3), t1=0.2, dt0=0.1, initial={"eta": 1.0})
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="positive and finite"):
        jv.identify(scene, jv.eG(1), lambda s: s.energy, np.ones(3), t1=0.2, dt0=0.1, initial={"eta_dev": -1.0})
    exp = jv.Experiment(scene, jv.eG(1), [0.0, 0.1, 0.2], np.ones((3, 1)), jv.Quantity("dissipated"), dt0=0.1)
    with pytest.raises(ValueError, match="unknown parameter 'eta'"):
        jv.identify(exp, {"eta": 1.0})
    with pytest.raises(ValueError, match="must lie strictly inside its bounds"):
        jv.identify(exp, {"eta_dev": jv.Parameter(1e4, lower=2e4, upper=1e5)})
    with pytest.raises(ValueError, match=r"data must have shape \(len\(times\), columns of observe\) = \(3, 1\)"):
        jv.Experiment(scene, jv.eG(1), [0.0, 0.1, 0.2], np.ones((3, 2)), jv.Quantity("dissipated"), dt0=0.1)
    with pytest.raises(ValueError, match="field must be one of"):
        jv.Quantity("energies")


def _marker_test(name, column):
    """The example's test (markers on the flying L-shape, T = 1, h = 0.1) with a name for
    the test and for its first column."""
    iv = _example()
    scene = jv.scenes.lshape(dim=2, refinement=1)
    times = np.linspace(0.0, 1.0, 11)
    markers = [jv.Extensometer(scene.mesh, iv.MARKERS[a], iv.MARKERS[b], name=f"{column} {a}-{b}")
               for a, b in iv.PAIRS]
    return jv.Experiment(scene, jv.eG(1), times, np.zeros((11, len(markers))), markers, dt0=0.1, name=name)


def test_sensitivities_are_the_runs_model_and_its_derivatives():
    """`Experiment.sensitivities`: the model equals `model(run())` at the same values, to
    rounding; each derivative matches central differences of runs (step 1e-3 of the value,
    so truncation ~1e-6 relative)."""
    e = _marker_test("markers", "gauge")
    values = {"eta_dev": 50000.0, "eta_vol": 10000.0}
    model, derivatives = e.sensitivities(values)

    def run(v):
        return np.asarray(e.model(e.run(jv.with_parameters(e.scene, v))))

    ref = run(values)
    assert model.shape == ref.shape == (11, 3)
    np.testing.assert_allclose(model, ref, rtol=0, atol=1e-12 * np.max(np.abs(ref)))
    assert sorted(derivatives) == sorted(values)
    for k, v in values.items():
        h = 1e-3 * v
        fd = (run({**values, k: v + h}) - run({**values, k: v - h})) / (2 * h)
        assert np.max(np.abs(fd)) > 0
        np.testing.assert_allclose(derivatives[k], fd, rtol=0, atol=1e-5 * np.max(np.abs(fd)))
    with pytest.raises(ValueError, match="Experiment.sensitivities: unknown parameter 'eta'"):
        e.sensitivities({"eta": 1.0})


def test_fit_reuses_the_sensitivities_program_whatever_the_names():
    """A fit evaluates by the program `sensitivities` compiled for the same layout, also
    where the test and its columns are named otherwise (names only label reports): no
    residual + Jacobian program is compiled during the fit."""
    import jax

    values = {"eta_dev": 50000.0, "eta_vol": 10000.0}
    data, _ = _marker_test("truth", "gauge").sensitivities(values)
    renamed = _marker_test("renamed", "marker")
    renamed = jv.Experiment(renamed.scene, renamed.integrator, np.asarray(renamed.times), data, renamed.observe,
                            dt0=0.1, name="renamed")
    compiled = []

    def listen(event, duration, fun_name=None, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(fun_name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        fit = jv.identify(renamed, {"eta_dev": 40000.0, "eta_vol": 12000.0}, max_iterations=3)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert fit.names == ("eta_dev", "eta_vol") and renamed.labels[0].startswith("marker")
    assert "jit(_block)" not in compiled, compiled
    assert not any("_run" in str(f) or "_iteration" in str(f) for f in compiled), compiled


def test_a_new_process_loads_the_fits_traced_program(tmp_path):
    """With the persistent cache on, an experiment's evaluation program (the run and its
    tangents) is stored traced (`jax.export`): a new process (here: this one, its memory
    of loaded programs cleared) loads it, for `sensitivities` and for the blocks of a
    joint fit (prepared one at a time ahead of their first calls), and gives the same
    numbers. Checked through the cache's counts, not by time."""
    import jax

    from jaxvisco import _export

    def test(name, t1):
        spec = jv.scenes.specimen("relaxation", elements=(2, 1, 1), t1=t1, dt0=0.1)
        times = np.linspace(0.0, t1, 3)
        return jv.Experiment(spec.scene, jv.eG(1), times, np.zeros((3, 1)), jv.ReactionForce(spec.grip, "x"),
                             dt0=0.1, name=name)

    values = {"eta_dev": 2.0}
    prev = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    _export.clear()
    try:
        before = dict(_export.stats)
        first = test("a", 0.2).sensitivities(values)
        assert _export.stats["exported"] == before["exported"] + 1
        _export.clear()
        again = test("b", 0.2).sensitivities(values)
        assert _export.stats["loaded"] == before["loaded"] + 1 and _export.stats["exported"] == before["exported"] + 1
        np.testing.assert_array_equal(again[0], first[0])
        np.testing.assert_array_equal(again[1]["eta_dev"], first[1]["eta_dev"])
        tests = [jv.Experiment(e.scene, e.integrator, np.asarray(e.times), first[0] * f, e.observe, dt0=0.1,
                               name=e.name) for e, f in ((test("c", 0.2), 1.0), (test("d", 0.2), 1.01))]
        _export.clear()
        loaded = _export.stats["loaded"]
        fit = jv.identify(tests, {"eta_dev": 3.0}, max_iterations=2)
        assert _export.stats["loaded"] == loaded + 1, _export.stats  # the blocks' one program, from disk
        assert _export.stats["exported"] == before["exported"] + 1
        assert fit.iterations >= 1
    finally:
        jax.config.update("jax_compilation_cache_dir", prev)
        _export.clear()
