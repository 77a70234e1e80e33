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
