"""What a results file holds and which part of it is committed.

Layout of ``name.h5`` (format 2; ``n`` committed frames, ``N`` nodes, ``d`` = 2 or 3,
``s`` committed steps):

- ``/mesh/points`` (N, d), ``/mesh/cells`` (n_cells, nodes per cell), attribute
  ``cell_type`` (jaxvisco name, e.g. ``"quad4"``).
- ``/time`` (n,); ``/nodal/x``, ``/nodal/p`` (n, N, d); ``/qp/gamma`` (n, n_cells,
  n_qp, 3, 3) only when asked for; ``/nodal/reaction``, ``/nodal/reaction_mean`` (n, N,
  d), the supports' forces, only when the run saved them (``SaveAt(reactions=True)``).
- ``/diagnostics/{energy, kinetic, free_energy, dissipated, dissipation_rate,
  external_work}`` (n,), ``linear_momentum`` (n, d), ``angular_momentum`` (n,) in 2D,
  (n, 3) in 3D; ``dissipated`` and ``external_work`` cumulative from frame 0.
- ``/steps/{step_t, step_h, newton_iterations, krylov_iterations, chord_iterations,
  residual, rejections}`` (s,). Files written before ``chord_iterations`` existed lack
  it; appending to them creates it with zeros for the earlier steps.
- ``/restart/slot0``, ``/restart/slot1``: two restart records, each ``x``, ``p``,
  ``gamma`` (the full internal variable, if the solution had it), ``velocity`` (the
  next step's predictor velocity, if known) and attributes ``t``, ``n_frames``,
  ``n_steps``. The committed record names the valid one; the other is the one the
  next commit writes.
- ``/xdmf/{geometry, displacement, momentum}/<frame>`` (N, 3): per-frame copies the
  XDMF file points at (3 components in 2D too).
- Root attribute ``committed`` = ``[n_frames, n_steps, n_commits]`` (int64): the one
  commit record. Frames ``< n_frames`` and steps ``< n_steps`` are committed; the
  restart record is ``/restart/slot{(n_commits - 1) % 2}``. Other root attributes:
  ``format`` (2), ``integrator``, ``status`` ("running", "done", "equilibrium",
  "failed", "interrupted"), ``jaxvisco_version``, ``jax_version``, scene and material
  parameters, ``parameters`` (JSON of the caller's options).

Format 1 (jaxvisco 0.1 before the two-phase commit) kept the counters in the root
attributes ``n_frames``/``n_steps`` and one restart group ``/restart`` overwritten in
place; it is read (and verified) and migrated to format 2 when appended to.
"""

from typing import NamedTuple

import numpy as np

from .._integrate._solution import STEP_KEYS

FORMAT = 2
FRAME_KEYS = ("energy", "kinetic", "free_energy", "dissipated", "dissipation_rate", "external_work",
              "linear_momentum", "angular_momentum")
FRAME_DATASETS = (("time", "nodal/x", "nodal/p", "qp/gamma", "nodal/reaction", "nodal/reaction_mean")
                  + tuple("diagnostics/" + k for k in FRAME_KEYS))
STEP_DATASETS = tuple("steps/" + k for k in STEP_KEYS)
XDMF_FIELDS = ("geometry", "displacement", "momentum")


class Committed(NamedTuple):
    n_frames: int
    n_steps: int
    n_commits: int  # 0: no restart record (format-1 files: -1, their record is /restart)

    @property
    def slot(self):
        """Path of the committed restart record, or None."""
        if self.n_commits < 0:
            return "restart"
        return None if self.n_commits == 0 else f"restart/slot{(self.n_commits - 1) % 2}"


def committed(f) -> Committed:
    """The commit record of an open results file."""
    rec = f.attrs.get("committed")
    if rec is not None:
        n_frames, n_steps, n_commits = (int(v) for v in np.asarray(rec).ravel()[:3])
        return Committed(n_frames, n_steps, n_commits)
    # format 1: counters as attributes (or, older still, the dataset lengths)
    n_frames = int(f.attrs.get("n_frames", f["time"].shape[0] if "time" in f else 0))
    n_steps = int(f.attrs.get("n_steps", f["steps/step_t"].shape[0] if "steps/step_t" in f else 0))
    return Committed(n_frames, n_steps, -1 if "restart" in f and "x" in f["restart"] else 0)


def frame_name(i):
    return f"{int(i):06d}"


def scene_attributes(scene) -> dict:
    """Scalar parameters of a scene worth recording (mesh size, density, material,
    held components, loads); parameters given per point or element are left out."""
    out = dict(dim=int(scene.mesh.dim), cell_type=str(scene.mesh.cell_type), n_nodes=int(scene.mesh.n_nodes),
               n_cells=int(scene.mesh.n_cells))
    fixed = getattr(scene, "fixed", None)
    out["held_components"] = 0 if fixed is None else int(np.count_nonzero(fixed.array))
    out["loaded"] = getattr(scene, "loads", None) is not None
    mat = scene.material
    values = dict(density=scene.density, eta_dev=getattr(mat, "eta_dev", None),
                  eta_vol=getattr(mat, "eta_vol", None))
    eq = getattr(mat, "equilibrium", None)
    for name in ("lam", "mu"):
        values[name] = getattr(eq, name, None)
    for name, v in values.items():
        try:
            out[name] = float(v)
        except (TypeError, ValueError):  # None, an array, or a traced value
            pass
    return out
