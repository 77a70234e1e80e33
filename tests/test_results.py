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
from jaxvisco import ResultsWriter, read_results
from jaxvisco._io import write_xdmf


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


# ------------------------------------------------------------------ crash consistency

_H5_OPS = [("Dataset", "__setitem__"), ("Dataset", "resize"), ("AttributeManager", "__setitem__"),
           ("Group", "create_dataset"), ("Group", "__delitem__"), ("File", "flush")]


@pytest.fixture(autouse=False)
def _fork_ok():
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        yield


def _killed_at(n, work):
    """Run `work()` in a forked child that SIGKILLs itself just before its n-th h5py
    write operation (dataset writes and resizes, attribute writes, creations, deletions,
    flushes). Returns True if the kill happened, False if `work` finished first."""
    import signal

    import h5py

    pid = os.fork()
    if pid == 0:  # child: no JAX here, h5py and numpy only
        try:
            count = [0]
            for cls_name, meth in _H5_OPS:
                cls = getattr(h5py, cls_name)
                orig = getattr(cls, meth)

                def patched(self, *a, _orig=orig, **k):
                    count[0] += 1
                    if count[0] == n:
                        os.kill(os.getpid(), signal.SIGKILL)
                    return _orig(self, *a, **k)

                setattr(cls, meth, patched)
            work()
        finally:
            os._exit(0)
    _, status = os.waitpid(pid, 0)
    return os.WIFSIGNALED(status)


def _commits(mesh, path, n_chunks=3):
    """The appends of a 3-chunk run (frames 0..4, 4..7, 7..10)."""
    sols = [fake_solution(5, 0.0, mesh)] + [fake_solution(4, 0.4 + 0.3 * i, mesh) for i in range(n_chunks - 1)]
    for s in sols:
        s.end_velocity = s.p[-1] * 0.5
    return sols


def test_kill_at_every_write_of_an_append(tmp_path, mesh, _fork_ok):
    """A SIGKILL before any single HDF5 operation of an append leaves a file whose committed
    state is the one before or after the append, whose restart state is its last frame, and
    which a restart continues to the same file as an uninterrupted writer."""
    chunks = _commits(mesh, None)
    ref = tmp_path / "ref.h5"
    with ResultsWriter(ref, mesh) as w:
        for i, s in enumerate(chunks):
            w.append(s, skip_first=i > 0, gamma=True)
    full = read_results(ref)
    base = tmp_path / "base.h5"
    with ResultsWriter(base, mesh) as w:
        w.append(chunks[0], gamma=True)
        w.append(chunks[1], skip_first=True, gamma=True)
    before = read_results(base)

    def append_third(path):
        w = ResultsWriter(path, append=True)
        w.append(chunks[2], skip_first=True, gamma=True)
        w.close(status="done")

    outcomes = set()
    for n in range(1, 200):
        path = tmp_path / f"k{n}.h5"
        shutil.copy(base, path)
        killed = _killed_at(n, lambda: append_third(path))
        r = read_results(path)
        k = len(r["t"])
        assert k in (len(before["t"]), len(full["t"])), (n, k)
        for key in ("t", "x", "p", "gamma", "energy", "dissipated", "step_t"):
            np.testing.assert_array_equal(r[key], full[key][:len(r[key])], err_msg=f"{key} after kill {n}")
        rs = jv.read_restart(path)  # verified: the restart state is the last committed frame
        assert rs.t == r["t"][-1] and rs.n_frames == k
        np.testing.assert_array_equal(rs.state.x, r["x"][-1])
        if k == len(before["t"]):  # continue: the same file as the uninterrupted writer
            append_third(path)
        again = read_results(path)
        for key in ("t", "x", "p", "gamma", "energy", "dissipated", "step_t", "newton_iterations"):
            np.testing.assert_array_equal(again[key], full[key], err_msg=f"{key} resumed after kill {n}")
        np.testing.assert_array_equal(jv.read_restart(path).velocity, jv.read_restart(ref).velocity)
        outcomes.add((killed, k))
        if not killed:
            break
    assert not killed, "the append did not finish within 200 operations"
    assert n > 20 and (True, len(before["t"])) in outcomes  # kills hit many operations, before the commit too


def test_kill_while_creating_leaves_no_file_or_frame_zero(tmp_path, mesh, _fork_ok):
    """A new file appears under its name only with a committed frame; an old file replaced
    with overwrite stays intact until then."""
    sol = fake_solution(3, 0.0, mesh)
    path = tmp_path / "new.h5"
    old = tmp_path / "old.h5"
    with ResultsWriter(old, mesh) as w:
        w.append(fake_solution(2, 5.0, mesh))
    old_t = read_results(old)["t"]
    seen = set()
    for n in range(1, 200):
        for p in (path, old):
            if p == path and p.exists():
                p.unlink()
        replaced = tmp_path / f"rep{n}.h5"
        shutil.copy(old, replaced)

        def create():
            for target, overwrite in ((path, False), (replaced, True)):
                w = ResultsWriter(target, mesh, overwrite=overwrite)
                w.append(sol)
                w.close(status="done")

        killed = _killed_at(n, create)
        if path.exists():
            r = read_results(path)
            assert len(r["t"]) == 3 and jv.read_restart(path).t == r["t"][-1]
        rt = read_results(replaced)["t"]
        assert np.array_equal(rt, old_t) or np.array_equal(rt, sol.t), n
        seen.add((path.exists(), np.array_equal(rt, old_t)))
        if not killed:
            break
    assert not killed and (False, True) in seen and (True, False) in seen


def test_inconsistent_restart_refused(tmp_path, mesh, capsys):
    path = tmp_path / "r.h5"
    with ResultsWriter(path, mesh) as w:
        w.append(fake_solution(4, 0.0, mesh), gamma=True)
    with h5py.File(path, "r+") as f:
        slot = "restart/slot%d" % ((f.attrs["committed"][2] - 1) % 2)
        f[slot + "/x"][0, 0] += 0.5
    with pytest.raises(ValueError, match=r"inconsistent: its restart state disagrees with its last committed frame "
                                         r"\(max \|restart.x - x\[3\]\| = 0.5\)"):
        jv.read_restart(path)
    with pytest.raises(ValueError, match="inconsistent"):
        ResultsWriter(path, append=True)
    from jaxvisco.cli import main

    assert main(["run", "--resume", str(path), "--t-end", "1"]) == 2
    err = capsys.readouterr().err
    assert "is inconsistent" in err and "max |restart.x - x[3]| = 0.5" in err and "Traceback" not in err
    with h5py.File(path, "r+") as f:
        f[slot + "/x"][0, 0] -= 0.5
        f[slot].attrs["t"] = 0.4
    with pytest.raises(ValueError, match=r"restart t = 0.4, last frame t = 0.3"):
        jv.read_restart(path)


def test_format1_file_read_and_migrated(tmp_path, mesh):
    """A file written before the two-phase commit (counters as attributes, one restart group)
    is read, verified and continued."""
    path = tmp_path / "v1.h5"
    with ResultsWriter(path, mesh) as w:
        w.append(fake_solution(4, 0.0, mesh), gamma=True)
    with h5py.File(path, "r+") as f:  # rewrite as format 1
        n_frames, n_steps, n_commits = (int(v) for v in f.attrs["committed"])
        f.copy(f"restart/slot{(n_commits - 1) % 2}", "old")
        del f["restart"]
        f.move("old", "restart")
        del f.attrs["committed"], f.attrs["format"]
        f.attrs["n_frames"], f.attrs["n_steps"] = n_frames, n_steps
    assert jv.read_restart(path).t == pytest.approx(0.3)
    w = ResultsWriter(path, append=True)
    w.append(fake_solution(3, 0.3, mesh), skip_first=True, gamma=True)
    w.close(status="done")
    r = read_results(path)
    assert len(r["t"]) == 6 and jv.read_restart(path).t == r["t"][-1]
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == 2 and "n_frames" not in f.attrs


def test_existing_file_not_overwritten(tmp_path, mesh):
    path = tmp_path / "r.h5"
    with ResultsWriter(path, mesh) as w:
        w.append(fake_solution(2, 0.0, mesh))
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match=r"r.h5' exists; pass overwrite=True"):
        ResultsWriter(path, mesh)
    with pytest.raises(FileExistsError, match="exists"):
        jv.save(fake_solution(3, 0.0, mesh), mesh, path)
    assert path.read_bytes() == before
    jv.save(fake_solution(3, 0.0, mesh), mesh, path, overwrite=True)
    assert len(read_results(path)["t"]) == 3


# ------------------------------------------------------------------ any scene


def _clamped_loaded_scene():
    m = jv.rectangle(4, 1, lx=4.0, ly=1.0)
    X = np.asarray(m.points)
    fixed = np.zeros(X.shape, bool)
    fixed[X[:, 0] == 0.0] = True
    load = np.zeros(X.shape)
    load[X[:, 0] == 4.0, 1] = -50.0
    nh = jv.NeoHooke(lam=3e4, mu=7.5e3)
    mat = jv.ReeseGovindjee(nh, nh, eta_dev=5e4, eta_vol=1e4)
    import jax.numpy as jnp

    return jv.Scene(m, mat, 8.93, fixed=fixed, load=load, load_time=lambda t: jnp.where(t < 0.15, 1.0, 0.0))


def _hex20_scene():
    m = jv.box(2, 1, 1, 2.0, 1.0, 1.0, cell_type="hex20")
    X = np.asarray(m.points)
    nh = jv.NeoHooke(lam=3e4, mu=7.5e3)
    mat = jv.ReeseGovindjee(nh, nh, eta_dev=5e4, eta_vol=1e4)
    return jv.Scene(m, mat, 8.93, velocities=np.stack([np.ones(len(X)), 0.5 * X[:, 0], -0.3 * X[:, 1]], -1))


@pytest.mark.parametrize("make", [_clamped_loaded_scene, _hex20_scene])
def test_save_any_scene_round_trip(tmp_path, make):
    """`save` writes a solution of a clamped, loaded 2D scene and of a free 3D hex20 scene:
    read back equal, its restart record verified, opened by meshio's XDMF reader with every
    step, plotted by `jaxvisco plot`, and continued by `resume`."""
    import meshio

    from jaxvisco.cli import main

    scene = make()
    sol = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, saveat=jv.SaveAt(gamma=True), max_steps=3)  # one compilation
    path = tmp_path / "run" / "s.h5"
    assert jv.save(sol, scene, path) == str(path)
    r = read_results(path)
    for k in ("t", "x", "p", "gamma", "energy", "dissipated", "external_work", "linear_momentum",
              "angular_momentum", "step_h", "newton_iterations"):
        np.testing.assert_array_equal(r[k], np.asarray(getattr(sol, k)), err_msg=k)
    assert r["attrs"]["status"] == "done" and r["attrs"]["dim"] == scene.dim
    assert r["attrs"]["held_components"] == (0 if scene.fixed is None else int(scene.fixed.array.sum()))
    assert bool(r["attrs"]["loaded"]) == (scene.load is not None)
    rs = jv.read_restart(path)
    np.testing.assert_array_equal(rs.state.gamma, np.asarray(sol.gamma)[-1])
    np.testing.assert_array_equal(rs.velocity, np.asarray(sol.end_velocity))
    with meshio.xdmf.TimeSeriesReader(str(path.with_suffix(".xdmf"))) as reader:
        points, cells = reader.read_points_cells()
        assert len(points) == scene.mesh.n_nodes and cells[0].data.shape == np.asarray(scene.mesh.cells).shape
        assert reader.num_steps == 4
        for k in range(reader.num_steps):
            t, point_data, _ = reader.read_data(k)
            assert t == pytest.approx(0.1 * k)
            np.testing.assert_allclose(point_data["displacement"][:, :scene.dim], r["x"][k] - r["points"])
    assert main(["plot", str(path), "--out", str(tmp_path / "s.png")]) == 0
    more = jv.resume(path, scene, jv.eG(1), t1=0.5, dt0=0.1, append=True, max_steps=3)
    assert more.status == "done"
    r2 = read_results(path)
    assert len(r2["t"]) == 6 and r2["t"][-1] == 0.5 and jv.read_restart(path).t == 0.5
    np.testing.assert_array_equal(r2["x"][:4], r["x"])
