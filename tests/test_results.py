"""Results files: append-and-flush, read back, XDMF beside the HDF5 file."""

import json
import os
import shutil
import subprocess
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


def test_xdmf_extended_in_place_equals_rewrite(tmp_path, mesh):
    path = tmp_path / "r.h5"
    with ResultsWriter(path, mesh) as w:
        w.append(fake_solution(3, 0.0, mesh))
        w.append(fake_solution(3, 0.2, mesh), skip_first=True)
    grown = (tmp_path / "r.xdmf").read_text()
    write_xdmf(str(tmp_path / "again.xdmf"), str(path))
    assert grown == (tmp_path / "again.xdmf").read_text()
    assert len(ET.fromstring(grown).findall(".//Grid[@GridType='Uniform']")) == 5


def test_nonfinite_frames_never_written(tmp_path, mesh):
    sol = fake_solution(5, 0.0, mesh)
    sol.x = sol.x.copy()
    sol.x[3, 0, 0] = np.nan
    path = tmp_path / "r.h5"
    w = ResultsWriter(path, mesh)
    w.append(sol)
    w.close(status="done")
    r = read_results(path)
    assert r["t"].shape == (3,) and np.all(np.isfinite(r["x"]))
    assert r["attrs"]["status"] == "failed"
    assert np.all(r["step_t"] <= r["t"][-1])


def test_reads_only_committed_frames(tmp_path, mesh):
    """A kill between growing the datasets and raising the counters exposes nothing."""
    path = tmp_path / "r.h5"
    with ResultsWriter(path, mesh) as w:
        w.append(fake_solution(3, 0.0, mesh))
        w._append("time", np.array([9.0]))  # half an append: datasets grown, counters not
        w._append("nodal/x", np.zeros((1,) + mesh.points.shape))
    r = read_results(path)
    assert r["t"].tolist() == pytest.approx([0.0, 0.1, 0.2]) and r["x"].shape[0] == 3
    w = ResultsWriter(path, append=True)  # a restart cuts the half-written frame away
    w.close()
    with h5py.File(path, "r") as f:
        assert f["time"].shape == (3,) and f["nodal/x"].shape[0] == 3


PVPYTHON = shutil.which("pvpython")
_PV_SCRIPT = r"""
import json, sys
from paraview import simple, servermanager
out = {}
for name in ("XDMFReader", "Xdmf3ReaderS", "Xdmf3ReaderT"):
    if name == "XDMFReader":
        r = simple.XDMFReader(FileNames=[sys.argv[1]])
    else:
        r = getattr(simple, name)(FileName=[sys.argv[1]])
    r.UpdatePipelineInformation()
    ts = list(r.TimestepValues)
    r.UpdatePipeline(ts[-1])
    d = servermanager.Fetch(r)
    if d.IsA("vtkMultiBlockDataSet"):
        d = d.GetBlock(0)
    pd = d.GetPointData()
    out[name] = dict(times=ts, points=d.GetNumberOfPoints(), cells=d.GetNumberOfCells(), bounds=list(d.GetBounds()),
                     arrays=sorted(pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())))
print("RESULT" + json.dumps(out))
"""


@pytest.mark.skipif(PVPYTHON is None, reason="ParaView's pvpython is not installed")
@pytest.mark.parametrize("dim", [2, 3])
def test_paraview_opens_xdmf(tmp_path, dim):
    """Both ParaView XDMF readers open the time series: number of steps, points, cells,
    point data, and the deformed bounds of the last frame."""
    m = jv.rectangle(3, 2, lx=2.0, ly=1.0) if dim == 2 else jv.box(2, 2, 1, 2.0, 1.0, 0.5)
    path = tmp_path / "run" / "r.h5"
    with ResultsWriter(path, m) as w:
        w.append(fake_solution(4, 0.0, m))
        w.append(fake_solution(4, 0.3, m), skip_first=True)
    x = read_results(path)["x"][-1]
    script = tmp_path / "pv.py"
    script.write_text(_PV_SCRIPT)
    p = subprocess.run([PVPYTHON, "--force-offscreen-rendering", str(script), str(path.with_suffix(".xdmf"))],
                       capture_output=True, text=True, timeout=240, cwd=tmp_path)
    line = [s for s in p.stdout.splitlines() if s.startswith("RESULT")]
    assert p.returncode == 0 and line, p.stdout[-2000:] + p.stderr[-2000:]
    res = json.loads(line[0][len("RESULT"):])
    lo = np.zeros(3)
    hi = np.zeros(3)
    lo[:dim], hi[:dim] = x.min(axis=0), x.max(axis=0)
    for name, r in res.items():
        assert len(r["times"]) == 7, name
        np.testing.assert_allclose(r["times"], 0.1 * np.arange(7), atol=1e-12, err_msg=name)
        assert r["points"] == m.n_nodes and r["cells"] == m.n_cells, name
        np.testing.assert_allclose(np.asarray(r["bounds"]).reshape(3, 2), np.stack([lo, hi], 1), atol=1e-12,
                                   err_msg=name)
        assert {"displacement", "momentum"} <= set(r["arrays"]), name
