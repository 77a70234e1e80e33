"""Results files: HDF5 (h5py) plus an XDMF time series for ParaView.

Layout of ``name.h5`` (``n`` saved frames, ``N`` nodes, ``d`` = 2 or 3, ``s`` steps):

- ``/mesh/points`` (N, d) reference coordinates; ``/mesh/cells`` (n_cells, nodes per
  cell), attribute ``cell_type`` (jaxvisco name, e.g. ``"quad4"``).
- ``/time`` (n,).
- ``/nodal/x`` positions and ``/nodal/p`` momenta (n, N, d).
- ``/qp/gamma`` (n, n_cells, n_qp, 3, 3), only when asked for (``--save-gamma``).
- ``/diagnostics/{energy, kinetic, free_energy, dissipated, dissipation_rate,
  external_work}`` (n,), ``/diagnostics/linear_momentum`` (n, d),
  ``/diagnostics/angular_momentum`` (n,) in 2D, (n, 3) in 3D. ``dissipated`` and
  ``external_work`` are cumulative from the first frame.
- ``/steps/{step_t, step_h, newton_iterations, krylov_iterations, residual,
  rejections}`` (s,): per time step (end time, size, Newton and Krylov iterations,
  largest accepted residual, rejected halvings).
- ``/restart/{x, p, gamma, velocity}``: the state after the last saved step (the full
  internal variable, whether or not ``/qp/gamma`` is kept) and the predictor velocity
  of the next step (`Solution.end_velocity`); attributes ``t``, ``n_frames``,
  ``n_steps``. Overwritten at every append; `read_restart` returns it (restarts).
- ``/xdmf/{geometry, displacement, momentum}/<i>`` (N, 3) per saved frame, zero-padded
  to 3 components in 2D: what the XDMF file points at (see below).
- Root attributes: ``integrator`` (description), ``status`` ("running", "done",
  "equilibrium", "failed", "interrupted"), ``n_frames`` and ``n_steps`` (frames and
  steps completely written), ``jaxvisco_version``, ``jax_version``, the scene and
  material parameters (``dim``, ``cell_type``, ``n_nodes``, ``n_cells``, ``density``,
  ``lam``, ``mu``, ``eta_dev``, ``eta_vol`` where known), and ``parameters`` (JSON of
  everything the caller passed).

All datasets but ``/mesh`` are chunked and resizable along axis 0; `ResultsWriter.append`
extends them, writes the restart group, then raises the ``n_frames``/``n_steps``
counters and flushes, so a run that is killed leaves a readable file with every frame
written so far; `read_results` reads up to the counters only (a kill in the middle of
an append cannot expose half-written frames). Frames that are not finite are never
written: the writer drops them and marks the file ``status = "failed"``.

Beside ``name.h5`` the writer keeps ``name.xdmf``, a temporal collection whose grids
reference the HDF5 datasets by relative path, so the pair can be moved together.
Why per-frame datasets rather than slices of ``/nodal/x``: ParaView's Xdmf3 readers
(``Xdmf3ReaderS``/``T``, ParaView 5.11) crash (SIGSEGV in CopyShape) on a HyperSlab
geometry and read no points from a ``Function`` geometry; plain datasets, one per
frame, open in the legacy ``XDMFReader`` and both Xdmf3 readers (tested in
tests/test_results.py when ``pvpython`` is installed). Plain ``XY`` geometry opens too,
but ParaView treats only 3-component point data as vectors (glyphs, warp by vector),
so geometry, displacement and momentum are all padded to 3 components in 2D. The XDMF file is extended in place by one ``write`` per
append (new grids plus the closing tags), so its cost does not grow with the run and
it always references flushed frames only. Known ParaView quirk: the Xdmf3 readers
resolve the relative HDF5 path wrongly when the XDMF file name has no directory part
(``pvpython`` with ``r.xdmf``); pass ``./r.xdmf`` or an absolute path.
"""

import json
import os
from typing import NamedTuple
from xml.sax.saxutils import escape

import numpy as np

FRAME_KEYS = ("energy", "kinetic", "free_energy", "dissipated", "dissipation_rate", "external_work",
              "linear_momentum", "angular_momentum")
STEP_KEYS = ("step_t", "step_h", "newton_iterations", "krylov_iterations", "residual", "rejections")

_XDMF_TOPOLOGY = {
    "tri3": "Triangle", "tri6": "Triangle_6", "quad4": "Quadrilateral", "quad8": "Quadrilateral_8",
    "quad9": "Quadrilateral_9", "tet4": "Tetrahedron", "tet10": "Tetrahedron_10", "hex8": "Hexahedron",
    "hex20": "Hexahedron_20", "hex27": "Hexahedron_27",
}


def _h5py():
    import h5py

    return h5py


def scene_attributes(scene) -> dict:
    """Scalar parameters of a scene worth recording (mesh size, density, material)."""
    out = dict(dim=int(scene.mesh.dim), cell_type=str(scene.mesh.cell_type), n_nodes=int(scene.mesh.n_nodes),
               n_cells=int(scene.mesh.n_cells), density=float(scene.density))
    mat = scene.material
    for name in ("eta_dev", "eta_vol"):
        v = getattr(mat, name, None)
        if v is not None:
            out[name] = float(v)
    eq = getattr(mat, "equilibrium", None)
    for name in ("lam", "mu"):
        v = getattr(eq, name, None)
        if v is not None:
            try:
                out[name] = float(v)
            except (TypeError, ValueError):
                pass
    return out


class ResultsWriter:
    """Append-as-you-go writer of a results file (see the module docstring).

    **Arguments:**
    - `path`: the ``.h5`` file (overwritten, unless `append`); the XDMF goes beside it.
    - `mesh`: the scene's `Mesh` (ignored with `append`: the file's mesh is kept).
    - `attrs`: root attributes (scalars or strings; anything else is stored as JSON).
    - `xdmf`: also keep the XDMF time series (default True).
    - `append`: continue an existing results file (a restart): datasets are cut back to
      the frames and steps completely written, and cumulative dissipation and external
      work continue from the last frame.
    """

    def __init__(self, path, mesh=None, attrs=None, xdmf=True, append=False):
        h5py = _h5py()
        self.path = os.fspath(path)
        self.xdmf_path = os.path.splitext(self.path)[0] + ".xdmf" if xdmf else None
        self._offset = dict(dissipated=0.0, external_work=0.0)
        self.dropped_nonfinite = False
        if append:
            if not os.path.isfile(self.path):
                raise FileNotFoundError(f"results file {self.path!r} does not exist.")
            try:
                self.f = h5py.File(self.path, "r+")
            except OSError as e:
                raise ValueError(f"could not open results file {self.path!r} for appending: {e}") from None
            if "mesh" not in self.f:
                self.f.close()
                raise ValueError(f"{self.path!r} is not a jaxvisco results file (no /mesh).")
            self.points = np.asarray(self.f["mesh/points"], dtype=np.float64)
            self.cells = np.asarray(self.f["mesh/cells"])
            self.cell_type = str(self.f["mesh/cells"].attrs["cell_type"])
            self.n_frames, self.n_steps = _committed(self.f)
            _truncate(self.f, self.n_frames, self.n_steps)
            for k in self._offset:
                ds = self.f.get("diagnostics/" + k)
                if ds is not None and self.n_frames:
                    self._offset[k] = float(ds[self.n_frames - 1])
            self.f.attrs["status"] = "running"
            for k, v in (attrs or {}).items():
                self.set_attr(k, v)
            self.f.flush()
            if self.xdmf_path:
                write_xdmf(self.xdmf_path, self.path, self.f)
            return
        d = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(d, exist_ok=True)
        self.f = h5py.File(self.path, "w")
        self.points = np.asarray(mesh.points, dtype=np.float64)
        self.cells = np.asarray(mesh.cells)
        self.cell_type = str(mesh.cell_type)
        g = self.f.create_group("mesh")
        g.create_dataset("points", data=self.points)
        g.create_dataset("cells", data=self.cells).attrs["cell_type"] = self.cell_type
        import jax

        from . import __version__

        self.f.attrs["jaxvisco_version"] = __version__
        self.f.attrs["jax_version"] = jax.__version__
        self.f.attrs["status"] = "running"
        for k, v in (attrs or {}).items():
            self.set_attr(k, v)
        self.n_frames = 0
        self.n_steps = 0
        self.f.attrs["n_frames"] = 0
        self.f.attrs["n_steps"] = 0
        self.f.flush()
        if self.xdmf_path:
            write_xdmf(self.xdmf_path, self.path, self.f)

    def set_attr(self, key, value):
        if isinstance(value, (str, bool, int, float, np.integer, np.floating)):
            self.f.attrs[key] = value
        else:
            self.f.attrs[key] = json.dumps(value)

    def _append(self, name, data):
        data = np.asarray(data)
        if data.dtype == bool:
            data = data.astype(np.int8)
        if name not in self.f:
            chunks = (max(1, min(64, len(data))),) + data.shape[1:] if data.ndim else None
            self.f.create_dataset(name, data=data, maxshape=(None,) + data.shape[1:], chunks=chunks)
        else:
            ds = self.f[name]
            n = ds.shape[0]
            ds.resize(n + len(data), axis=0)
            ds[n:] = data

    def _put(self, name, data):
        """Create or overwrite a fixed-shape dataset."""
        data = np.asarray(data)
        if name in self.f and self.f[name].shape == data.shape and self.f[name].dtype == data.dtype:
            self.f[name][...] = data
        else:
            if name in self.f:
                del self.f[name]
            self.f.create_dataset(name, data=data)

    def append(self, sol, skip_first=False, gamma=False):
        """Append a `Solution`'s frames and steps, then flush.

        `skip_first` drops the first frame (a restarted chunk repeats the previous
        chunk's last frame). The chunk's cumulative `dissipated` and `external_work`
        (which restart at 0 in every `simulate` call) are offset so they stay
        cumulative over the whole file. `gamma=True` also stores `/qp/gamma`. The last
        frame (with the full internal variable when the solution has it, and
        `sol.end_velocity`) becomes the restart state. Frames from the first one that
        is not finite on are dropped and the file is marked ``status = "failed"``.
        """
        s = 1 if skip_first else 0
        t = np.asarray(sol.t)[s:]
        x = np.asarray(sol.x)[s:]
        p = np.asarray(sol.p)[s:]
        g = None if getattr(sol, "gamma", None) is None else np.asarray(sol.gamma)[s:]
        diag = {}
        for k in FRAME_KEYS:
            v = np.asarray(getattr(sol, k), dtype=np.float64)
            if k in self._offset:
                v = v + self._offset[k]
            diag[k] = v[s:]
        finite = np.isfinite(t) & _all_finite(x) & _all_finite(p)
        for v in diag.values():
            finite &= _all_finite(v)
        if g is not None:
            finite &= _all_finite(g)
        n_ok = len(t) if finite.all() else int(np.argmin(finite))
        if n_ok < len(t):
            self.dropped_nonfinite = True
            t, x, p, g = t[:n_ok], x[:n_ok], p[:n_ok], None if g is None else g[:n_ok]
            diag = {k: v[:n_ok] for k, v in diag.items()}
        n0 = self.n_frames
        if n_ok:
            self._append("time", t)
            self._append("nodal/x", x)
            self._append("nodal/p", p)
            if gamma and g is not None:
                self._append("qp/gamma", g)
            for k in FRAME_KEYS:
                self._append("diagnostics/" + k, diag[k])
            for k in self._offset:
                self._offset[k] = float(diag[k][-1])
        steps = {k: np.asarray(getattr(sol, k)) for k in STEP_KEYS}
        if n_ok < len(np.asarray(sol.t)[s:]):
            # keep the statistics of the steps that ended at or before the last finite frame
            keep = steps["step_t"] <= (t[-1] if n_ok else -np.inf)
            steps = {k: v[keep] for k, v in steps.items()}
        for k in STEP_KEYS:
            self._append("steps/" + k, steps[k])
        if n_ok:
            v_end = getattr(sol, "end_velocity", None)
            complete = n_ok == len(np.asarray(sol.t)[s:]) and getattr(sol, "status", "done") != "failed"
            self._put("restart/x", x[-1])
            self._put("restart/p", p[-1])
            if g is not None:
                self._put("restart/gamma", g[-1])
            elif "restart/gamma" in self.f:
                del self.f["restart/gamma"]
            if v_end is not None and complete:
                self._put("restart/velocity", np.asarray(v_end, dtype=np.float64))
            elif "restart/velocity" in self.f:
                del self.f["restart/velocity"]
            r = self.f["restart"]
            r.attrs["t"] = float(t[-1])
            r.attrs["n_frames"] = n0 + n_ok
            r.attrs["n_steps"] = self.n_steps + len(steps["step_t"])
        if self.xdmf_path:
            for j in range(n_ok):
                self._xdmf_frame(n0 + j, x[j], p[j])
        self.n_frames += n_ok
        self.n_steps += len(steps["step_t"])
        if self.dropped_nonfinite:
            self.f.attrs["status"] = "failed"
        self.f.attrs["n_frames"] = self.n_frames
        self.f.attrs["n_steps"] = self.n_steps
        self.f.flush()
        if self.xdmf_path and n_ok:
            _extend_xdmf(self.xdmf_path, self.path, self.f, n0, self.n_frames)

    def _xdmf_frame(self, i, x, p):
        def pad3(a):
            a = np.asarray(a, dtype=np.float64)
            return np.concatenate([a, np.zeros(a.shape[:-1] + (3 - a.shape[-1],))], axis=-1) if a.shape[-1] < 3 else a

        name = _frame_name(i)
        self._put("xdmf/geometry/" + name, pad3(x))
        self._put("xdmf/displacement/" + name, pad3(x - self.points))
        self._put("xdmf/momentum/" + name, pad3(p))

    def close(self, status=None):
        if self.f:
            if status is not None:
                self.f.attrs["status"] = "failed" if (self.dropped_nonfinite and status == "done") else status
            self.f.flush()
            self.f.close()
            self.f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _all_finite(a):
    a = np.asarray(a)
    return np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1) if a.ndim > 1 else np.isfinite(a)


def _frame_name(i):
    return f"{int(i):06d}"


def _committed(f):
    """Frames and steps completely written (the counters, or for files written before
    they existed, the dataset lengths)."""
    n_frames = int(f.attrs.get("n_frames", f["time"].shape[0] if "time" in f else 0))
    n_steps = int(f.attrs.get("n_steps", f["steps/step_t"].shape[0] if "steps/step_t" in f else 0))
    return n_frames, n_steps


def _truncate(f, n_frames, n_steps):
    """Cut resizable datasets back to the committed counts (after a kill mid-append)."""
    names = ["time"] + ["nodal/" + k for k in ("x", "p")] + ["qp/gamma"] + ["diagnostics/" + k for k in FRAME_KEYS]
    for name in names:
        if name in f and f[name].shape[0] > n_frames:
            f[name].resize(n_frames, axis=0)
    for k in STEP_KEYS:
        if "steps/" + k in f and f["steps/" + k].shape[0] > n_steps:
            f["steps/" + k].resize(n_steps, axis=0)
    for field in ("geometry", "displacement", "momentum"):
        g = f.get("xdmf/" + field)
        if g is not None:
            for name in [k for k in g if int(k) >= n_frames]:
                del g[name]


_XDMF_HEAD = ('<?xml version="1.0"?>\n<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">\n'
              '  <Domain>\n  <Grid Name="TimeSeries" GridType="Collection" CollectionType="Temporal">\n')
_XDMF_TAIL = '  </Grid>\n  </Domain>\n</Xdmf>\n'


def _xdmf_grids(xdmf_path, h5_path, f, start, stop):
    """XML of the grids of frames start..stop-1 (reading times and sizes from `f`)."""
    times = np.asarray(f["time"][start:stop]) if "time" in f else np.zeros(0)
    N = f["mesh/points"].shape[0]
    cells = f["mesh/cells"]
    nc, nn = cells.shape
    ctype = str(cells.attrs["cell_type"])
    topo = _XDMF_TOPOLOGY.get(ctype)
    if topo is None:
        raise ValueError(f"no XDMF topology for cell type {ctype!r}; known: {sorted(_XDMF_TOPOLOGY)}.")
    rel = escape(os.path.relpath(os.path.abspath(h5_path), os.path.dirname(os.path.abspath(xdmf_path))))

    def item(path):
        return (f'<DataItem Dimensions="{N} 3" NumberType="Float" Precision="8" Format="HDF">'
                f'{rel}:{path}</DataItem>')

    out = []
    for j, t in enumerate(times):
        name = _frame_name(start + j)
        out.append(
            f'    <Grid Name="frame{name}" GridType="Uniform">\n'
            f'      <Time Value="{float(t):.17g}"/>\n'
            f'      <Topology TopologyType="{topo}" NumberOfElements="{nc}" NodesPerElement="{nn}">\n'
            f'        <DataItem Dimensions="{nc} {nn}" NumberType="Int" Precision="8" Format="HDF">'
            f'{rel}:/mesh/cells</DataItem>\n      </Topology>\n'
            f'      <Geometry GeometryType="XYZ">\n        {item("/xdmf/geometry/" + name)}\n      </Geometry>\n'
            f'      <Attribute Name="displacement" AttributeType="Vector" Center="Node">\n'
            f'        {item("/xdmf/displacement/" + name)}\n      </Attribute>\n'
            f'      <Attribute Name="momentum" AttributeType="Vector" Center="Node">\n'
            f'        {item("/xdmf/momentum/" + name)}\n      </Attribute>\n'
            f'    </Grid>\n')
    return "".join(out)


def _extend_xdmf(xdmf_path, h5_path, f, start, stop):
    """Add the grids of frames start..stop-1 to an XDMF file written by this module, in
    one `write` that replaces the closing tags (else rewrite the file)."""
    tail = _XDMF_TAIL.encode()
    try:
        with open(xdmf_path, "r+b") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - len(tail)))
            if fh.read() == tail:
                fh.seek(size - len(tail))
                fh.write((_xdmf_grids(xdmf_path, h5_path, f, start, stop) + _XDMF_TAIL).encode())
                return
    except FileNotFoundError:
        pass
    write_xdmf(xdmf_path, h5_path, f)


def write_xdmf(xdmf_path, h5_path, f=None):
    """Write an XDMF 3 temporal collection for the results file `h5_path`.

    The HDF5 file is referenced by its path relative to the XDMF file, so the pair can be
    moved together. `f`: an open h5py file (read from `h5_path` if None). The file is
    replaced atomically.
    """
    own = f is None
    if own:
        f = _h5py().File(h5_path, "r")
    try:
        n, _ = _committed(f)
        xml = _XDMF_HEAD + _xdmf_grids(xdmf_path, h5_path, f, 0, n) + _XDMF_TAIL
    finally:
        if own:
            f.close()
    tmp = xdmf_path + ".tmp"
    with open(tmp, "w") as fh:
        fh.write(xml)
    os.replace(tmp, xdmf_path)


def read_results(path) -> dict:
    """Read a results file into a dict of numpy arrays.

    Keys: ``points``, ``cells``, ``cell_type``, ``t``, ``x``, ``p`` (and ``gamma`` if
    stored), every diagnostic and step array under its own name, and ``attrs`` (root
    attributes). Only completely written frames and steps are read (see the module
    docstring).
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"results file {path!r} does not exist.")
    h5py = _h5py()
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"could not read results file {path!r}: {e}") from None
    with f:
        if "mesh" not in f or "time" not in f:
            raise ValueError(f"{path!r} is not a jaxvisco results file (no /mesh or /time).")
        nf, ns = _committed(f)
        out = dict(points=np.asarray(f["mesh/points"]), cells=np.asarray(f["mesh/cells"]),
                   cell_type=str(f["mesh/cells"].attrs.get("cell_type", "")), t=np.asarray(f["time"][:nf]))
        for k in ("x", "p"):
            if "nodal/" + k in f:
                out[k] = np.asarray(f["nodal/" + k][:nf])
        if "qp/gamma" in f:
            out["gamma"] = np.asarray(f["qp/gamma"][:nf])
        for k in FRAME_KEYS:
            if "diagnostics/" + k in f:
                out[k] = np.asarray(f["diagnostics/" + k][:nf])
        for k in STEP_KEYS:
            if "steps/" + k in f:
                out[k] = np.asarray(f["steps/" + k][:ns])
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return out


class Restart(NamedTuple):
    """What a results file holds to continue a run (`read_restart`).

    `t`: time of the last saved frame; `state`: the `State` there (with the full
    internal variable, or None if the file lacks it); `velocity`: the predictor
    velocity of the next step (None in files written without it: a restart then
    starts from the velocity of the momenta, which changes the following steps at the
    level of the Newton tolerance); `n_frames`, `n_steps`: frames and steps written;
    `dissipated`, `external_work`: the cumulative values at `t`; `attrs`: root
    attributes (``parameters`` decoded from JSON where it is JSON).
    """

    t: float
    state: object
    velocity: np.ndarray | None
    n_frames: int
    n_steps: int
    dissipated: float
    external_work: float
    attrs: dict


def read_restart(path) -> Restart:
    """The restart data of a results file: continue with
    ``simulate(..., t0=r.t, initial_state=r.state, initial_velocity=r.velocity)``
    (see `jaxvisco.resume`)."""
    import jax.numpy as jnp

    from ._scene import State

    r = read_results(path)
    if len(r["t"]) == 0:
        raise ValueError(f"results file {os.fspath(path)!r} holds no saved frame to restart from.")
    nf = len(r["t"])
    with _h5py().File(os.fspath(path), "r") as f:
        g = f.get("restart")
        ok = g is not None and int(g.attrs.get("n_frames", -1)) == nf
        gamma = velocity = None
        if ok:
            x, p = np.asarray(g["x"]), np.asarray(g["p"])
            gamma = np.asarray(g["gamma"]) if "gamma" in g else None
            velocity = np.asarray(g["velocity"]) if "velocity" in g else None
        else:  # an older file, or a kill between the frames and the restart group
            x, p = r["x"][-1], r["p"][-1]
            gamma = r["gamma"][-1] if "gamma" in r else None
    attrs = dict(r["attrs"])
    try:
        attrs["parameters"] = json.loads(attrs.get("parameters", ""))
    except (TypeError, ValueError):
        pass
    state = State(jnp.asarray(x), jnp.asarray(p), None if gamma is None else jnp.asarray(gamma))
    return Restart(float(r["t"][-1]), state, velocity, nf, len(r.get("step_t", ())),
                   float(r["dissipated"][-1]) if "dissipated" in r else 0.0,
                   float(r["external_work"][-1]) if "external_work" in r else 0.0, attrs)


def resume(path, scene, integrator, t_end, dt, append=False, throw=True, **kwargs):
    """Continue the run saved in the results file `path` up to `t_end`.

    Starts `simulate(scene, integrator, t_end, dt, ...)` at the file's last frame with
    its state (full internal variable) and predictor velocity, so that a run split in
    two repeats the uninterrupted run (exactly with ``NewtonKrylov(linear_solver=
    "direct")``; with the default Krylov solver to the Newton tolerance, because the
    reused tangent that preconditions it is not stored). `scene` and `integrator` must
    be those of the saved run (the file stores their parameters, not the objects); `dt`
    is a step or a schedule in absolute times, as for `simulate`. `append=True` also
    appends the new frames and steps to the file (cumulative dissipation and external
    work continue) and sets its status. Other keywords go to `simulate`.

    **Returns:** the `Solution` from the file's last frame on (its `dissipated` and
    `external_work` count from that frame; add `read_restart(path).dissipated`).
    """
    from ._simulate import SolverError, simulate

    r = read_restart(path)
    if r.state.x.shape != scene.x0.shape:
        raise ValueError(f"{os.fspath(path)!r} holds {r.state.x.shape[0]} nodes in {r.state.x.shape[1]}D, "
                         f"the scene {scene.x0.shape[0]} in {scene.x0.shape[1]}D.")
    if scene.has_internal_variable and r.state.gamma is None:
        raise ValueError(f"{os.fspath(path)!r} holds no internal variable to restart from (written without "
                         "/restart/gamma); it cannot be continued exactly.")
    if float(t_end) <= r.t:
        raise ValueError(f"t_end must be later than the file's last time t = {r.t:.17g}, got t_end = {t_end!r}.")
    for k in ("t0", "initial_state", "initial_velocity"):
        if k in kwargs:
            raise TypeError(f"resume sets {k} from the results file; do not pass it.")
    if append:
        kwargs["save_gamma"] = True  # the restart group needs the full internal variable
        keep_gamma = _has_gamma(path)
    sol = simulate(scene, integrator, t_end, dt, t0=r.t, initial_state=r.state, initial_velocity=r.velocity,
                   throw=False, **kwargs)
    if append:
        w = ResultsWriter(path, append=True)
        try:
            w.append(sol, skip_first=True, gamma=keep_gamma)
        finally:
            w.close(status=sol.status)
    if sol.status == "failed" and throw:
        t = float(sol.t[-1])
        raise SolverError(f"{integrator.name}: the step after t = {t:.6g} did not converge; the last good state is "
                          "attached (SolverError.state).", t, sol.state(-1), sol)
    return sol


def _has_gamma(path):
    with _h5py().File(os.fspath(path), "r") as f:
        return "qp/gamma" in f
