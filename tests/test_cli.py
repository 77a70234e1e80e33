"""The jaxvisco command line: help, a tiny run, plot, errors."""

import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest

import jaxvisco
from jaxvisco.cli import main
from jaxvisco.cli._main import chunk_size, energy_warning, parse_schedule


@pytest.mark.parametrize("sub", [None, "paper", "run", "plot", "scene-template"])
def test_help(sub, capsys):
    argv = ["--help"] if sub is None else [sub, "--help"]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    assert "usage: jaxvisco" in capsys.readouterr().out


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxvisco {jaxvisco.__version__}"


def test_schedule_and_chunks():
    assert parse_schedule("20:0.1, 40:1.0") == [(20.0, 0.1), (40.0, 1.0)]
    with pytest.raises(ValueError, match="20-0.1"):
        parse_schedule("20-0.1")
    # the target whatever the run lengths (one program of that capacity serves every
    # chunk), a multiple of save_every, at most the longest run
    assert chunk_size([240, 60]) == 50
    assert chunk_size([104, 24]) == 50
    assert chunk_size([240], target=50, save_every=4) == 48
    assert chunk_size([3]) == 3


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "res.h5"
    # Chunks of 3 steps; the same compiled program as the examples' eG(1) 3-step runs.
    code = main(["run", "--t-end", "0.3", "--dt", "0.1", "--chunk", "3", "--out", str(out), "--quiet"])
    assert code == 0
    return out


def test_run_writes_results(run_file):
    with h5py.File(run_file, "r") as f:
        assert f["time"].shape == (4,)
        assert f["nodal/x"].shape == (4, 56, 2)
        assert f.attrs["status"] == "done"
        H = np.asarray(f["diagnostics/energy"])
        D = np.asarray(f["diagnostics/dissipated"])
    assert np.all(np.diff(H) <= 0)  # eG(1): energy never increases
    assert np.max(np.abs(H - H[0] + D)) < 1e-6 * H[0]


def test_xdmf_from_other_cwd(run_file, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    xdmf = run_file.with_suffix(".xdmf")
    root = ET.parse(xdmf).getroot()
    assert len(root.findall(".//Grid[@GridType='Uniform']")) == 4
    for e in root.iter("DataItem"):
        if e.get("Format") == "HDF":
            h5 = e.text.strip().split(":")[0]
            assert os.path.isfile(os.path.join(xdmf.parent, h5))
    assert not list(tmp_path.iterdir())  # nothing written into the CWD


def test_plot(run_file, tmp_path):
    png = tmp_path / "p.png"
    assert main(["plot", str(run_file), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_shows_momentum_drift(run_file):
    """The momentum panels plot J(t) - J(0) and L(t) - L(0), with J(0) and L(0) in the
    legend and no axis offset notation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxvisco import read_results
    from jaxvisco.cli._main import plot_figure

    r = read_results(run_file)
    fig = plot_figure(r)
    try:
        axes = {a.get_title(): a for a in fig.axes}
        for title, key, sym in (("linear momentum drift L − L(0)", "linear_momentum", "L"),
                                ("angular momentum drift J − J(0)", "angular_momentum", "J")):
            ax = axes[title]
            ref = np.asarray(r[key]).reshape(len(r["t"]), -1)
            lines = ax.get_lines()
            assert len(lines) == ref.shape[1]
            for i, line in enumerate(lines):
                np.testing.assert_array_equal(line.get_xdata(), r["t"])
                np.testing.assert_array_equal(line.get_ydata(), ref[:, i] - ref[0, i])
                assert line.get_ydata()[0] == 0.0
                assert f"{sym}_{'xyz'[i] if ref.shape[1] > 1 else 'z'}(0) = {ref[0, i]:.10g}" in line.get_label()
            assert ax.yaxis.get_major_formatter().get_useOffset() is False
    finally:
        plt.close(fig)


def test_energy_warning_on_synthetic_runs():
    t = np.linspace(0.0, 24.0, 241)
    # cG-like: H grows by orders of magnitude while a little is dissipated
    H = 3.2e3 * np.exp(t / 3.0)
    msg = energy_warning(t, H, np.linspace(0.0, 10.0, t.size), np.zeros_like(t), "cG1_schedule")
    assert msg is not None and "\n" not in msg
    assert msg.startswith("cG1_schedule: H rose 2.98e+03-fold from H0 = 3200")
    assert "at t = 24" in msg and "too large for this scheme" in msg and "eG(k) is energy-stable" in msg
    # eG-like: H decays, exactly balanced by the dissipation (to round-off): no warning
    He = 3.2e3 * (0.5 + 0.5 * np.exp(-t / 5.0))
    assert energy_warning(t, He, 3.2e3 - He + 1e-9, np.zeros_like(t), "eG1") is None
    # a numerically dissipative scheme (H falls, nothing recorded as dissipated): no warning
    assert energy_warning(t, He, np.zeros_like(t), np.zeros_like(t), "Newmark") is None
    # energy supplied by a load is not created energy
    W = np.linspace(0.0, 500.0, t.size)
    assert energy_warning(t, 3.2e3 + W, np.zeros_like(t), W, "loaded") is None
    # the peak is reported where it happens, even if H falls again; below 5 % no warning
    bump = 3.2e3 * (1.0 + 0.2 * np.exp(-((t - 10.0) ** 2)))
    assert "to 3840 at t = 10" in energy_warning(t, bump, np.zeros_like(t), np.zeros_like(t), "bump")
    small = 3.2e3 * (1.0 + 0.04 * np.exp(-((t - 10.0) ** 2)))
    assert energy_warning(t, small, np.zeros_like(t), np.zeros_like(t), "small") is None
    # a diverged last frame (NaN) is ignored
    Hn = H.copy()
    Hn[-1] = np.nan
    assert "at t = 23.9" in energy_warning(t, Hn, np.zeros_like(t), np.zeros_like(t), "nan")


def test_bad_dt_in_process(capsys, tmp_path):
    assert main(["run", "--dt", "-1", "--out", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxvisco: error:") and "-1" in err and "Traceback" not in err


def test_missing_mesh_subprocess(tmp_path):
    p = subprocess.run([sys.executable, "-m", "jaxvisco.cli", "run", "--mesh", "missing.msh"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert "missing.msh" in p.stderr and "Traceback" not in p.stderr
    assert p.stderr.strip().splitlines()[-1].startswith("jaxvisco: error:")


def test_bad_plot_file(tmp_path, capsys):
    assert main(["plot", str(tmp_path / "none.h5")]) == 2
    assert "none.h5" in capsys.readouterr().err


@pytest.mark.timeout(600)
def test_paper_runs_its_integrators_in_threads(tmp_path, capsys):
    """`jaxvisco paper` runs cG(1) and eG(1) in two threads (their compiles and runs
    overlap): every results file is complete, and each run equals the same run alone."""
    import jaxvisco as jv
    from jaxvisco.cli import _paper

    assert _paper.PARALLEL
    out = tmp_path / "p"
    assert main(["paper", "--quick", "--t-end", "0.5", "--out", str(out), "--quiet"]) == 0
    assert sorted(f for f in os.listdir(out) if f.endswith(".h5")) == ["cG1_large.h5", "cG1_schedule.h5",
                                                                      "eG1_large.h5", "eG1_schedule.h5"]
    assert (out / "energy.png").exists()
    scene = jv.scenes.lshape(dim=2, refinement=1)
    for name, integrator in (("cG1", jv.cG(1)), ("eG1", jv.eG(1))):
        r = jv.read_results(out / f"{name}_schedule.h5")
        assert r["attrs"]["status"] == "done" and np.allclose(r["t"], np.arange(6) * 0.1)
        alone = jv.simulate(scene, integrator, t1=0.5, dt0=0.1)
        x = np.asarray(alone.x)
        np.testing.assert_allclose(r["x"], x, rtol=0, atol=1e-9 * np.abs(x).max())
        np.testing.assert_allclose(r["energy"], np.asarray(alone.energy), rtol=1e-9)
