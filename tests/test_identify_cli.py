"""``jaxvisco identify FIT.toml`` (issue #60): a fit file of scene files and CSV data, and
one line for each bad input."""

import json

import jax
import numpy as np
import pytest

import jaxvisco as jv
from jaxvisco.cli import main

SCENE = """
[mesh]
generator = "box"
nx = 2
ny = 1
nz = 1
lx = 40.0
ly = 10.0
lz = 10.0

[groups.clamp]
x = 0.0

[groups.grip]
x = 40.0

[material]
density = 1.2e-9
eta_dev = 2.0
eta_vol = 5.0

[material.equilibrium]
lam = 9.0
mu = 1.0

[material.nonequilibrium]
lam = 4.0
mu = 2.0

[[dirichlet]]
nodes = "clamp"
components = "all"

[[dirichlet]]
nodes = "grip"
components = "all"
displacement = [4.0, 0.0, 0.0]
time = { type = "ramp", t0 = 0.0, t1 = 0.5 }

[integrator]
name = "eG"
order = 1

[time]
t1 = 1.5
dt0 = 0.1
"""

FIT = """
[parameters]
eta_dev = {start}

[[experiment]]
name = "relaxation"
scene = "relaxation.toml"
data = "relaxation.csv"

[[experiment.observe]]
column = "{column}"
reaction = "grip"
component = "x"
"""


def _files(tmp_path, start="6.0", column="force", exact=False):
    """A relaxation test of a coarse specimen: its scene file, its grip force as CSV
    (`exact`: the run's with eta_dev = 2, else zeros) and a fit file."""
    (tmp_path / "relaxation.toml").write_text(SCENE)
    from jaxvisco._scenefile._scenefile import read_scene_file

    sf = read_scene_file(tmp_path / "relaxation.toml")
    times = np.linspace(0.0, 1.5, 16)
    force = np.zeros((16, 1))
    if exact:
        e = jv.Experiment(sf.scene, sf.integrator, times, force, jv.ReactionForce(sf.nodes("grip"), "x"), dt0=0.1)
        force = np.asarray(jax.jit(lambda s: e.model(e.run(s)))(sf.scene))
    np.savetxt(tmp_path / "relaxation.csv", np.column_stack([times, force]), delimiter=",", header="time,force",
               comments="")
    (tmp_path / "fit.toml").write_text(FIT.format(start=start, column=column))
    return tmp_path / "fit.toml"


@pytest.mark.timeout(900)
def test_identify_fits_a_fit_file(tmp_path, capsys):
    fit = _files(tmp_path, exact=True)
    assert main(["identify", str(fit), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "eta_dev = 2 " in out and "95 % interval [" in out, out
    report = json.loads((tmp_path / "fit.json").read_text())
    p = report["parameters"]["eta_dev"]
    assert abs(p["value"] / 2.0 - 1.0) <= 1e-6 and p["interval"][0] <= p["value"] <= p["interval"][1]
    assert (tmp_path / "fit.png").stat().st_size > 0


@pytest.mark.parametrize("edit, message", [
    (dict(column="forse"), "column 'forse' is not in relaxation.csv; its columns: ['force']"),
    (dict(start="{ start = 6.0, lower = 0.1, upper = 5.0 }"), "start = 6 must lie strictly inside its bounds"),
    (dict(start="-1.0"), "a start value alone makes the parameter positive"),
])
def test_bad_fit_files_stop_with_one_line(tmp_path, capsys, edit, message):
    fit = _files(tmp_path, **edit)
    assert main(["identify", str(fit)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxvisco: error:") and message in err[0], err


def test_unknown_parameter_and_group(tmp_path, capsys):
    fit = _files(tmp_path)
    fit.write_text(fit.read_text().replace("eta_dev = 6.0", "eta = 6.0"))
    assert main(["identify", str(fit)]) == 2
    assert "[parameters] eta: unknown parameter; accepted:" in capsys.readouterr().err
    fit.write_text(fit.read_text().replace("eta = 6.0", "eta_dev = 6.0").replace('reaction = "grip"',
                                                                                 'reaction = "gripp"'))
    assert main(["identify", str(fit)]) == 2
    assert "no node group 'gripp'; the scene file has: clamp, grip" in capsys.readouterr().err
