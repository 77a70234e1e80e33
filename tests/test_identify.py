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
    """Start off by factors 4 and 3: exact data -> within 1 %, 1 % noise -> within 5 %."""
    results = _example().main(["--quick", "--out", str(tmp_path)])
    (clean, e_clean), (noisy, e_noisy) = results.values()
    assert clean.converged, clean.message
    assert max(abs(v) for v in e_clean.values()) <= 0.01, e_clean
    assert max(abs(v) for v in e_noisy.values()) <= 0.05, e_noisy
    assert np.all(np.isfinite(clean.history)) and clean.history[-1] < 1e-3 * clean.history[0]
    assert (tmp_path / "identify_loss.png").exists()


def test_identify_rejects_bad_input():
    scene = jv.scenes.lshape(dim=2, refinement=1)
    with pytest.raises(ValueError, match="unknown parameter 'eta'"):
        jv.identify(scene, jv.eG(1), lambda s: s.energy, np.ones(3), t1=0.2, dt0=0.1, initial={"eta": 1.0})
    with pytest.raises(ValueError, match="positive and finite"):
        jv.identify(scene, jv.eG(1), lambda s: s.energy, np.ones(3), t1=0.2, dt0=0.1, initial={"eta_dev": -1.0})
    with pytest.raises(ValueError, match="not all zero"):
        jv.identify(scene, jv.eG(1), lambda s: s.energy, np.zeros(3), t1=0.2, dt0=0.1, initial={"eta_dev": 1.0})
