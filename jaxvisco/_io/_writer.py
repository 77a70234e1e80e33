"""Writing results files: crash-consistent by construction (see `_layout` for the layout).

A results file is only ever changed in ways that leave the committed part alone:

1. New frames and steps are written past the committed rows of the resizable datasets,
   the next restart record into the slot the commit record does *not* name, the XDMF
   copies of the new frames under new names. Then the file is flushed and fsync'ed.
2. The commit is one attribute write, ``committed = [n_frames, n_steps, n_commits]``,
   flushed and fsync'ed again.

A SIGKILL before step 2 reaches the disk leaves the previous commit in force (readers
and restarts never look past it, and a restart cuts the uncommitted rows away); after
it, the new one. No committed byte is ever overwritten, so the restart state always
belongs to the last committed frame (`read_restart` verifies that it does). A new file
is written under ``name.h5.partial`` and renamed to ``name.h5`` at its first commit, so
``name.h5`` either does not exist (an old one, with ``overwrite``, stays intact until
then) or holds a committed first frame. The XDMF file is extended after each commit, so
it lists committed frames only. HDF5 writes each flushed block with one system call,
which a SIGKILL cannot tear; surviving a power loss also needs the disk to honour
fsync ordering.
"""

import json
import os
from typing import TYPE_CHECKING

import numpy as np

from ._layout import (
    FORMAT,
    FRAME_DATASETS,
    FRAME_KEYS,
    STEP_DATASETS,
    STEP_KEYS,
    XDMF_FIELDS,
    committed,
    frame_name,
    scene_attributes,
)
from ._read import check_restart, open_results
from ._xdmf import extend_xdmf, pad3, write_xdmf

if TYPE_CHECKING:
    from .._integrate._solution import Solution
    from .._scene import Scene


class ResultsWriter:
    """Append-as-you-go, crash-consistent writer of a results file (HDF5 + XDMF).

    Each `append` commits in two phases, so that a process killed at any instant leaves a
    file whose committed frames and restart record are intact (the user guide's page on
    results files states the guarantees and how they are tested).

    **Arguments:**

    - `path`: the ``.h5`` file; the XDMF goes beside it (``name.xdmf``).
    - `scene`: the `Scene` (its mesh and parameters are recorded, and
      `write_initial_state` can evaluate its diagnostics) or just a `Mesh`. Not needed
      with `append`.
    - `attrs`: root attributes (scalars or strings; anything else is stored as JSON).
    - `xdmf`: also keep the XDMF time series (default True).
    - `overwrite`: replace an existing file (default False: refuse). The old file stays
      intact until the new one commits its first frame.
    - `append`: continue an existing results file (a restart): its uncommitted rows are
      cut away, cumulative dissipation and external work continue from its last frame.
    - `durable`: fsync at every commit (default True), so a commit survives a power
      loss; a SIGKILL cannot undo a commit either way.

    **Raises:**

    `FileExistsError` for an existing file without `overwrite` or `append`;
    `ValueError` for a file to append to that is not a results file.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jaxvisco as jv

    scene = jv.scenes.lshape()
    with jv.ResultsWriter("pieces.h5", scene, {"note": "two parts"}, overwrite=True) as w:
        w.write_initial_state()
        part = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, saveat=jv.SaveAt(gamma=True))
        w.append(part, skip_first=True)
    ```
    """

    def __init__(self, path, scene=None, attrs=None, *, xdmf=True, overwrite=False, append=False, durable=True):
        import h5py

        self.path = os.fspath(path)
        self.xdmf_path = os.path.splitext(self.path)[0] + ".xdmf" if xdmf else None
        self.durable = bool(durable)
        self.dropped_nonfinite = False
        self._offset = dict(dissipated=0.0, external_work=0.0)
        self._t_last = -np.inf  # time of the last committed frame
        mesh = getattr(scene, "mesh", scene)
        self.scene = scene if mesh is not scene else None
        self.f = None
        if append:
            self._reopen(attrs)
            return
        if mesh is None:
            raise TypeError("ResultsWriter needs the scene (or its mesh) to start a new results file.")
        if os.path.exists(self.path) and not overwrite:
            raise FileExistsError(f"results file {self.path!r} exists; pass overwrite=True (--overwrite on the "
                                  "command line) to replace it, or continue it (jaxvisco.resume, --resume).")
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        self._partial = self.path + ".partial"
        self.f = h5py.File(self._partial, "w")
        self.points = np.asarray(mesh.points, dtype=np.float64)
        g = self.f.create_group("mesh")
        g.create_dataset("points", data=self.points)
        g.create_dataset("cells", data=np.asarray(mesh.cells)).attrs["cell_type"] = str(mesh.cell_type)
        import jax

        from .._config import __version__

        self.f.attrs["format"] = FORMAT
        self.f.attrs["jaxvisco_version"] = __version__
        self.f.attrs["jax_version"] = jax.__version__
        self.f.attrs["status"] = "running"
        for k, v in ({} if self.scene is None else scene_attributes(self.scene)).items():
            self.set_attr(k, v)
        for k, v in (attrs or {}).items():
            self.set_attr(k, v)
        self.n_frames = self.n_steps = self.n_commits = 0
        self._commit()

    def _reopen(self, attrs):
        if not os.path.isfile(self.path):
            raise FileNotFoundError(f"results file {self.path!r} does not exist.")
        self._partial = None
        self.f = open_results(self.path, "r+")
        try:
            c = committed(self.f)
            self.points = np.asarray(self.f["mesh/points"], dtype=np.float64)
            self.n_frames, self.n_steps = c.n_frames, c.n_steps
            _truncate(self.f, c.n_frames, c.n_steps)
            record = check_restart(self.f, self.path) if c.n_frames else None  # refuse an inconsistent file
            if c.n_commits < 0:  # format 1: its verified restart group becomes slot 0
                del self.f["restart"]
                for k in ("n_frames", "n_steps"):
                    self.f.attrs.pop(k, None)
                self.f.attrs["format"] = FORMAT
                self._write_slot("restart/slot0", record)
                self.n_commits = 1
                self._commit()
            else:
                self.n_commits = c.n_commits
            if self.n_frames:
                self._t_last = float(self.f["time"][self.n_frames - 1])
            for k in self._offset:
                ds = self.f.get("diagnostics/" + k)
                if ds is not None and self.n_frames:
                    self._offset[k] = float(ds[self.n_frames - 1])
            self.f.attrs["status"] = "running"
            for k, v in (attrs or {}).items():
                self.set_attr(k, v)
            self._flush()
            if self.xdmf_path:
                write_xdmf(self.xdmf_path, self.path, self.f)
        except BaseException:
            self.f.close()
            raise

    # ------------------------------------------------------------------ low level
    def set_attr(self, key, value):
        if isinstance(value, (str, bool, int, float, np.integer, np.floating)):
            self.f.attrs[key] = value
        else:
            self.f.attrs[key] = json.dumps(value)

    def _write_rows(self, name, start, data):
        """Write `data` as rows start.. of the resizable dataset `name` (created if new)."""
        data = np.asarray(data)
        if data.dtype == bool:
            data = data.astype(np.int8)
        if name not in self.f:
            chunks = (max(1, min(64, len(data))),) + data.shape[1:] if data.ndim else None
            self.f.create_dataset(name, shape=(start,) + data.shape[1:], dtype=data.dtype,
                                  maxshape=(None,) + data.shape[1:], chunks=chunks)
        ds = self.f[name]
        ds.resize(start + len(data), axis=0)
        ds[start:] = data

    def _append(self, name, data):
        """Grow dataset `name` by the rows `data` (not committed until `_commit`)."""
        self._write_rows(name, self.f[name].shape[0] if name in self.f else 0, data)

    def _put(self, name, data):
        """Create or overwrite a fixed-shape dataset (never one a commit names)."""
        data = np.asarray(data)
        if name in self.f and self.f[name].shape == data.shape and self.f[name].dtype == data.dtype:
            self.f[name][...] = data
        else:
            if name in self.f:
                del self.f[name]
            self.f.create_dataset(name, data=data)

    def _write_slot(self, slot, record):
        """Write a restart record (arrays x, p, gamma, velocity, None where absent; t,
        n_frames, n_steps) into `slot`, which no commit may name at the time."""
        for name in ("x", "p", "gamma", "velocity"):
            if record[name] is not None:
                self._put(f"{slot}/{name}", record[name])
            elif f"{slot}/{name}" in self.f:
                del self.f[f"{slot}/{name}"]
        for name in ("t", "n_frames", "n_steps"):
            self.f[slot].attrs[name] = record[name]

    def _flush(self):
        self.f.flush()
        if self.durable:
            try:
                os.fsync(self.f.id.get_vfd_handle())
            except (OSError, ValueError, TypeError):  # a driver without a file descriptor
                pass

    def _commit(self):
        """Phase 2: make everything written so far the committed state (one attribute)."""
        self._flush()
        self.f.attrs["committed"] = np.array([self.n_frames, self.n_steps, self.n_commits], dtype=np.int64)
        self._flush()
        if self._partial is not None and self.n_frames:
            os.replace(self._partial, self.path)
            self._partial = None
            if self.xdmf_path:
                write_xdmf(self.xdmf_path, self.path, self.f)
            return True
        return False

    # ------------------------------------------------------------------ appending
    def write_initial_state(self, t0=0.0, state=None, velocity=None):
        """Commit frame 0: the scene's initial state (or `state`) at `t0`, as the restart
        point. Call it before the first (compiling) `simulate` call, so that a run killed
        while it compiles can be resumed from `t0`. `velocity`: the first step's
        predictor velocity, if not the velocity of the momenta."""
        if self.scene is None:
            raise TypeError("write_initial_state needs the Scene: give it to ResultsWriter, not just its mesh.")
        from .._integrate._solution import initial_solution

        self.append(initial_solution(self.scene, state, t0, velocity))

    def append(self, sol, skip_first=False, gamma=False):
        """Append a `Solution`'s frames and steps, and commit them.

        `skip_first` drops the first frame (a continuation repeats the previous part's
        last frame). Cumulative `dissipated` and `external_work` (which start at 0 in
        every `simulate` call) are offset to stay cumulative over the file. `gamma=True`
        also stores `/qp/gamma`. The last frame (with the full internal variable when
        the solution has it, and `sol.end_velocity` when the solution completed)
        becomes the restart state. Frames from the first one that is not finite on are
        dropped and the file is marked ``status = "failed"``.
        """
        s = 1 if skip_first else 0
        t = np.asarray(sol.t, dtype=np.float64)[s:]
        x = np.asarray(sol.x)[s:]
        p = np.asarray(sol.p)[s:]
        g = None if getattr(sol, "gamma", None) is None else np.asarray(sol.gamma)[s:]
        r = None if getattr(sol, "reaction", None) is None else np.asarray(sol.reaction)[s:]
        rm = None if getattr(sol, "reaction_mean", None) is None else np.asarray(sol.reaction_mean)[s:]
        diag = {}
        for k in FRAME_KEYS:
            v = np.asarray(getattr(sol, k), dtype=np.float64)
            diag[k] = (v + self._offset[k] if k in self._offset else v)[s:]
        finite = np.isfinite(t) & _all_finite(x) & _all_finite(p)
        for v in list(diag.values()) + [a for a in (g, r, rm) if a is not None]:
            finite &= _all_finite(v)
        n_ok = len(t) if finite.all() else int(np.argmin(finite))
        steps = {k: np.asarray(getattr(sol, k)) for k in STEP_KEYS if getattr(sol, k, None) is not None}
        # Statistics a solution does not carry (e.g. chord iterations of an older object) are 0.
        steps = {k: steps.get(k, np.zeros(len(steps["step_t"]), int)) for k in STEP_KEYS}
        if n_ok < len(t):
            self.dropped_nonfinite = True
            self.f.attrs["status"] = "failed"
            t, x, p = t[:n_ok], x[:n_ok], p[:n_ok]
            g, r, rm = (None if a is None else a[:n_ok] for a in (g, r, rm))
            diag = {k: v[:n_ok] for k, v in diag.items()}
        # The statistics of the steps up to the last frame written: later steps (of a run
        # that failed between saved frames) left no state to restart from.
        keep = steps["step_t"] <= (t[-1] if n_ok else self._t_last)
        steps = {k: v[keep] for k, v in steps.items()}
        n0, m0 = self.n_frames, self.n_steps
        if n_ok == 0 and len(steps["step_t"]) == 0:
            self._flush()
            return
        # phase 1: everything past the committed state
        for name, data in zip(FRAME_DATASETS, (t, x, p, g, r, rm) + tuple(diag[k] for k in FRAME_KEYS)):
            if n_ok and data is not None and (name != "qp/gamma" or gamma):
                self._write_rows(name, n0, data)
        for name, k in zip(STEP_DATASETS, STEP_KEYS):
            self._write_rows(name, m0, steps[k])
        n_steps = m0 + len(steps["step_t"])
        if n_ok:
            complete = n_ok == len(np.asarray(sol.t)[s:]) and getattr(sol, "status", "done") != "failed"
            v_end = getattr(sol, "end_velocity", None) if complete else None
            self._write_slot(f"restart/slot{self.n_commits % 2}", dict(
                x=x[-1], p=p[-1], gamma=None if g is None else g[-1],
                velocity=None if v_end is None else np.asarray(v_end, dtype=np.float64),
                t=float(t[-1]), n_frames=n0 + n_ok, n_steps=n_steps))
            for k in self._offset:
                self._offset[k] = float(diag[k][-1])
            self._t_last = float(t[-1])
            if self.xdmf_path:
                for j in range(n_ok):
                    for field, value in zip(XDMF_FIELDS, (x[j], x[j] - self.points, p[j])):
                        self._put(f"xdmf/{field}/{frame_name(n0 + j)}", pad3(value))
            self.n_commits += 1
        # phase 2: the commit
        self.n_frames, self.n_steps = n0 + n_ok, n_steps
        renamed = self._commit()
        if self.xdmf_path and n_ok and not renamed and self._partial is None:
            extend_xdmf(self.xdmf_path, self.path, self.f, n0, self.n_frames)

    def close(self, status: str | None = None) -> None:
        """Set the final `status` (if given), flush and close. A new file that never
        committed a frame is removed (an existing file it was to replace stays)."""
        if self.f:
            if status is not None:
                self.f.attrs["status"] = "failed" if (self.dropped_nonfinite and status == "done") else status
            self._flush()
            self.f.close()
            self.f = None
            if self._partial is not None:
                os.remove(self._partial)
                self._partial = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def save(solution: "Solution", scene: "Scene", path: str | os.PathLike, *, gamma: bool | None = None, attrs: dict | None = None, overwrite: bool = False,
         xdmf: bool = True) -> str:
    """Write a `Solution` of any scene to a results file (HDF5, with an XDMF file beside
    it), which ParaView, `jaxvisco plot` and `read_results` open.

    The restart record holds the last frame (with its full internal variable if the
    solution has it), so `resume` can continue the run. The file's status is the
    solution's.

    **Arguments:**

    - `solution`: the `Solution`.
    - `scene`: the `Scene` it ran (its mesh and parameters are recorded).
    - `path`: the `.h5` file.
    - `gamma`: also store the internal variable of every frame (default: when the
      solution has it).
    - `attrs`: root attributes to add (scalars or strings; anything else as JSON).
    - `overwrite`: replace an existing file (default: refuse).
    - `xdmf`: also write the XDMF time series for ParaView (default True).

    **Returns:**

    The path of the results file.

    **Raises:**

    `FileExistsError` for an existing file without `overwrite`; `ValueError` for a
    `Solution` without its diagnostics (`SaveAt(diagnostics=False)`: a results file holds
    them).

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jaxvisco as jv

    scene = jv.scenes.lshape()
    sol = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, saveat=jv.SaveAt(gamma=True))
    jv.save(sol, scene, "run.h5", overwrite=True)   # with Γ, so that resume can continue it
    r = jv.read_results("run.h5")
    ```
    """
    if getattr(solution, "energy", 0) is None:
        raise ValueError("save: this Solution holds no diagnostics (it was run with SaveAt(diagnostics=False)); "
                         "a results file keeps the energies and momenta of every frame: run with diagnostics=True.")
    if gamma is None:
        gamma = getattr(solution, "gamma", None) is not None
    attrs = dict(attrs or {})
    attrs.setdefault("integrator", getattr(solution, "integrator", "") or "")
    w = ResultsWriter(path, scene, attrs, xdmf=xdmf, overwrite=overwrite)
    try:
        w.append(solution, gamma=bool(gamma))
    finally:
        w.close(status=getattr(solution, "status", "done"))
    return w.path


def _all_finite(a):
    """Per leading entry (frame or step): all values finite. Empty when `a` has no entries
    (a chunk whose first step failed appends nothing)."""
    a = np.asarray(a)
    return np.isfinite(a).all(axis=tuple(range(1, a.ndim)))


def _truncate(f, n_frames, n_steps):
    """Cut resizable datasets back to the committed counts (after a kill mid-append)."""
    for names, n in ((FRAME_DATASETS, n_frames), (STEP_DATASETS, n_steps)):
        for name in names:
            if name in f and f[name].shape[0] > n:
                f[name].resize(n, axis=0)
    for field in XDMF_FIELDS:
        g = f.get("xdmf/" + field)
        if g is not None:
            for name in [k for k in g if int(k) >= n_frames]:
                del g[name]
