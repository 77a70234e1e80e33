"""Results files: append-and-flush, read back, XDMF beside the HDF5 file."""

import os
import shutil
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

import jaxvisco as jv
from jaxvisco._results import ResultsWriter, read_results, write_xdmf


def fake_solution(n_frames, t0, mesh, D0=0.0):
    N, d = mesh.points.shape
    t = t0 + 0.1 * np.arange(n_frames)
    x = np.asarray(mesh.points)[None] + 0.01 * np.arange(n_frames)[:, None, None]
    s = n_frames - 1
    return SimpleNamespace(
        t=t, x=x, p=np.ones((n_frames, N, d)), gamma=np.ones((n_frames, 2, 1, 3, 3)),
        energy=10.0 - np.arange(n_frames), kinetic=np.ones(n_frames), free_energy=np.ones(n_frames),
        dissipated=np.arange(n_frames, dtype=float), dissipation_rate=np.ones(n_frames),
        external_work=np.zeros(n_frames), linear_momentum=np.ones((n_frames, d)), angular_momentum=np.ones(n_frames),
        step_t=t[1:], step_h=np.full(s, 0.1), newton_iterations=np.full(s, 3), krylov_iterations=np.zeros(s, int),
        residual=np.zeros(s), rejections=np.zeros(s, int))


@pytest.fixture
def mesh():
    return jv.rectangle(2, 1, lx=2.0, ly=1.0)


def test_append_two_chunks_and_flush(tmp_path, mesh):
    path = tmp_path / "r.h5"
    w = ResultsWriter(path, mesh, dict(integrator="test", parameters=dict(a=1)))
    w.append(fake_solution(4, 0.0, mesh), gamma=True)
    # What is on disk after an append is a valid file (a killed run leaves it so).
    shutil.copy(path, tmp_path / "snapshot.h5")
    with h5py.File(tmp_path / "snapshot.h5", "r") as f:
        assert f["time"].shape == (4,) and f["nodal/x"].shape[0] == 4
    w.append(fake_solution(4, 0.3, mesh), skip_first=True, gamma=True)
    w.close(status="done")
    r = read_results(path)
    assert r["t"].shape == (7,)
    assert r["x"].shape == (7,) + mesh.points.shape
    assert r["gamma"].shape[0] == 7
    assert r["newton_iterations"].shape == (6,)
    # cumulative dissipation continues across chunks
    np.testing.assert_allclose(r["dissipated"], [0, 1, 2, 3, 4, 5, 6])
    assert r["attrs"]["status"] == "done" and r["attrs"]["integrator"] == "test"
    for name in ("/diagnostics/energy", "/steps/residual", "/nodal/p", "/mesh/cells"):
        with h5py.File(path, "r") as f:
            assert name in f
    with h5py.File(path, "r") as f:
        assert f["nodal/x"].maxshape[0] is None


def test_xdmf_relative_and_parses(tmp_path, mesh, monkeypatch):
    path = tmp_path / "sub" / "r.h5"
    with ResultsWriter(path, mesh) as w:
        w.append(fake_solution(3, 0.0, mesh))
    xdmf = tmp_path / "sub" / "r.xdmf"
    monkeypatch.chdir(tmp_path)  # references resolve relative to the xdmf, not the CWD
    root = ET.parse(xdmf).getroot()
    grids = root.findall(".//Grid[@GridType='Uniform']")
    assert len(grids) == 3
    refs = {e.text.strip().split(":")[0] for e in root.iter("DataItem") if e.get("Format") == "HDF"}
    assert refs == {"r.h5"}
    assert all(os.path.isfile(os.path.join(xdmf.parent, r)) for r in refs)
    write_xdmf(str(tmp_path / "copy.xdmf"), str(path))
    root = ET.parse(tmp_path / "copy.xdmf").getroot()
    assert {e.text.strip().split(":")[0] for e in root.iter("DataItem") if e.get("Format") == "HDF"} == {"sub/r.h5"}


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        read_results(tmp_path / "nope.h5")
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    with pytest.raises(ValueError, match="bad.h5"):
        read_results(bad)
