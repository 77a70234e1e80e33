"""Results files: HDF5 (h5py) plus an XDMF time series for ParaView.

Layout of ``name.h5`` (``n`` saved frames, ``N`` nodes, ``d`` = 2 or 3, ``s`` steps):

- ``/mesh/points`` (N, d) reference coordinates; ``/mesh/cells`` (n_cells, nodes per
  cell), attribute ``cell_type`` (jaxvisco name, e.g. ``"quad4"``).
- ``/time`` (n,).
- ``/nodal/x`` positions and ``/nodal/p`` momenta (n, N, d); ``/nodal/u`` displacement
  x - X padded to 3 components (n, N, 3), for visualisation.
- ``/qp/gamma`` (n, n_cells, n_qp, 3, 3), only when asked for (``--save-gamma``).
- ``/diagnostics/{energy, kinetic, free_energy, dissipated, dissipation_rate,
  external_work}`` (n,), ``/diagnostics/linear_momentum`` (n, d),
  ``/diagnostics/angular_momentum`` (n,) in 2D, (n, 3) in 3D. ``dissipated`` and
  ``external_work`` are cumulative from the first frame.
- ``/steps/{step_t, step_h, newton_iterations, krylov_iterations, residual,
  rejections}`` (s,): per time step (end time, size, Newton and Krylov iterations,
  largest accepted residual, rejected halvings).
- Root attributes: ``integrator`` (description), ``status`` ("running", "done",
  "equilibrium", "failed"), ``jaxvisco_version``, ``jax_version``, the scene and
  material parameters (``dim``, ``cell_type``, ``n_nodes``, ``n_cells``, ``density``,
  ``lam``, ``mu``, ``eta_dev``, ``eta_vol`` where known), and ``parameters`` (JSON of
  everything the caller passed).

All datasets but ``/mesh`` are chunked and resizable along axis 0; `ResultsWriter.append`
extends them and flushes the file, so a run that is killed leaves a readable file with
every frame written so far. Beside ``name.h5`` the writer keeps ``name.xdmf``, a
temporal collection whose grids reference the HDF5 datasets by relative path (deformed
geometry from ``/nodal/x``, point data ``displacement`` and ``momentum``); open it in
ParaView with the XDMF reader.
"""

import json
import os
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
    - `path`: the ``.h5`` file (overwritten); the XDMF goes beside it.
    - `mesh`: the scene's `Mesh`.
    - `attrs`: root attributes (scalars or strings; anything else is stored as JSON).
    - `xdmf`: also keep the XDMF time series (default True).
    """

    def __init__(self, path, mesh, attrs=None, xdmf=True):
        h5py = _h5py()
        self.path = os.fspath(path)
        d = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(d, exist_ok=True)
        self.xdmf_path = os.path.splitext(self.path)[0] + ".xdmf" if xdmf else None
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
        self._offset = dict(dissipated=0.0, external_work=0.0)
        self.f.flush()

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

    def append(self, sol, skip_first=False, gamma=False):
        """Append a `Solution`'s frames and steps, then flush.

        `skip_first` drops the first frame (a restarted chunk repeats the previous
        chunk's last frame). The chunk's cumulative `dissipated` and `external_work`
        (which restart at 0 in every `simulate` call) are offset so they stay
        cumulative over the whole file. `gamma=True` also stores `/qp/gamma`.
        """
        s = 1 if skip_first else 0
        t = np.asarray(sol.t)[s:]
        x = np.asarray(sol.x)[s:]
        self._append("time", t)
        self._append("nodal/x", x)
        self._append("nodal/p", np.asarray(sol.p)[s:])
        u = x - self.points[None]
        if u.shape[-1] == 2:
            u = np.concatenate([u, np.zeros(u.shape[:-1] + (1,))], axis=-1)
        self._append("nodal/u", u)
        if gamma and sol.gamma is not None:
            self._append("qp/gamma", np.asarray(sol.gamma)[s:])
        for k in FRAME_KEYS:
            v = np.asarray(getattr(sol, k))
            if k in self._offset:
                v = v + self._offset[k]
            self._append("diagnostics/" + k, v[s:])
        for k in self._offset:
            self._offset[k] = float(np.asarray(getattr(sol, k))[-1]) + self._offset[k]
        for k in STEP_KEYS:
            self._append("steps/" + k, np.asarray(getattr(sol, k)))
        self.n_frames += len(t)
        self.n_steps += len(np.asarray(sol.step_t))
        self.f.flush()
        if self.xdmf_path:
            write_xdmf(self.xdmf_path, self.path, self.f)

    def close(self, status=None):
        if self.f:
            if status is not None:
                self.f.attrs["status"] = status
            self.f.flush()
            self.f.close()
            self.f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_xdmf(xdmf_path, h5_path, f=None):
    """Write an XDMF 3 temporal collection for the results file `h5_path`.

    The HDF5 file is referenced by its path relative to the XDMF file, so the pair can be
    moved together. `f`: an open h5py file (read from `h5_path` if None).
    """
    own = f is None
    if own:
        f = _h5py().File(h5_path, "r")
    try:
        times = np.asarray(f["time"]) if "time" in f else np.zeros(0)
        n = len(times)
        N, d = f["mesh/points"].shape
        cells = f["mesh/cells"]
        nc, nn = cells.shape
        ctype = str(cells.attrs["cell_type"])
        has_p = "nodal/p" in f
    finally:
        if own:
            f.close()
    rel = escape(os.path.relpath(os.path.abspath(h5_path), os.path.dirname(os.path.abspath(xdmf_path))))
    topo = _XDMF_TOPOLOGY.get(ctype, "Mixed")
    geom = "XY" if d == 2 else "XYZ"

    def slab(name, comps):
        return (f'<DataItem ItemType="HyperSlab" Dimensions="{N} {comps}" Type="HyperSlab">\n'
                f'          <DataItem Dimensions="3 3" Format="XML">{{i}} 0 0 1 1 1 1 {N} {comps}</DataItem>\n'
                f'          <DataItem Dimensions="{n} {N} {comps}" NumberType="Float" Precision="8" '
                f'Format="HDF">{rel}:/nodal/{name}</DataItem>\n        </DataItem>')

    gx, gu, gp = slab("x", d), slab("u", 3), slab("p", d)
    grids = []
    for i, t in enumerate(times):
        attrs = (f'      <Attribute Name="displacement" AttributeType="Vector" Center="Node">\n'
                 f'        {gu.format(i=i)}\n      </Attribute>\n')
        if has_p and d == 3:
            attrs += (f'      <Attribute Name="momentum" AttributeType="Vector" Center="Node">\n'
                      f'        {gp.format(i=i)}\n      </Attribute>\n')
        grids.append(
            f'    <Grid Name="step{i}" GridType="Uniform">\n'
            f'      <Time Value="{float(t):.17g}"/>\n'
            f'      <Topology TopologyType="{topo}" NumberOfElements="{nc}" NodesPerElement="{nn}">\n'
            f'        <DataItem Dimensions="{nc} {nn}" NumberType="Int" Precision="8" Format="HDF">'
            f'{rel}:/mesh/cells</DataItem>\n      </Topology>\n'
            f'      <Geometry GeometryType="{geom}">\n        {gx.format(i=i)}\n      </Geometry>\n'
            f'{attrs}    </Grid>\n')
    xml = ('<?xml version="1.0"?>\n<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">\n'
           '  <Domain>\n  <Grid Name="TimeSeries" GridType="Collection" CollectionType="Temporal">\n'
           + "".join(grids) + '  </Grid>\n  </Domain>\n</Xdmf>\n')
    tmp = xdmf_path + ".tmp"
    with open(tmp, "w") as fh:
        fh.write(xml)
    os.replace(tmp, xdmf_path)


def read_results(path) -> dict:
    """Read a results file into a dict of numpy arrays.

    Keys: ``points``, ``cells``, ``cell_type``, ``t``, ``x``, ``p`` (and ``gamma`` if
    stored), every diagnostic and step array under its own name, and ``attrs`` (root
    attributes).
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
        out = dict(points=np.asarray(f["mesh/points"]), cells=np.asarray(f["mesh/cells"]),
                   cell_type=str(f["mesh/cells"].attrs.get("cell_type", "")), t=np.asarray(f["time"]))
        for k in ("x", "p"):
            if "nodal/" + k in f:
                out[k] = np.asarray(f["nodal/" + k])
        if "qp/gamma" in f:
            out["gamma"] = np.asarray(f["qp/gamma"])
        for k in FRAME_KEYS:
            if "diagnostics/" + k in f:
                out[k] = np.asarray(f["diagnostics/" + k])
        for k in STEP_KEYS:
            if "steps/" + k in f:
                out[k] = np.asarray(f["steps/" + k])
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return out
