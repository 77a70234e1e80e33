"""Reading results files: committed data only, and a restart state that is verified."""

import json
import os
from typing import NamedTuple

import numpy as np

from ._layout import FRAME_KEYS, STEP_KEYS, committed


def open_results(path, mode="r"):
    """Open a jaxvisco results file with h5py, or raise a clear error."""
    import h5py

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"results file {path!r} does not exist.")
    try:
        f = h5py.File(path, mode)
    except OSError as e:
        raise ValueError(f"could not open results file {path!r}: {e}") from None
    if "mesh" not in f or "mesh/points" not in f or "mesh/cells" not in f:
        f.close()
        raise ValueError(f"{path!r} is not a jaxvisco results file (no /mesh).")
    return f


def _frames(f, path, last_only=False):
    """Committed frames and steps of an open file (a dict of arrays); with `last_only`,
    the last committed frame alone (arrays with one row) and no steps."""
    c = committed(f)
    out = dict(points=np.asarray(f["mesh/points"]), cells=np.asarray(f["mesh/cells"]),
               cell_type=str(f["mesh/cells"].attrs.get("cell_type", "")))
    keys = [("t", "time"), ("x", "nodal/x"), ("p", "nodal/p"), ("gamma", "qp/gamma"), ("reaction", "nodal/reaction"),
            ("reaction_mean", "nodal/reaction_mean")]
    keys += [(k, "diagnostics/" + k) for k in FRAME_KEYS]
    for key, name in keys + ([] if last_only else [(k, "steps/" + k) for k in STEP_KEYS]):
        n = c.n_steps if name.startswith("steps/") else c.n_frames
        if name not in f:
            if n and key in ("t", "x", "p"):
                raise ValueError(f"{path!r} is damaged: it commits {n} frames but has no /{name}.")
            if key == "t":
                out[key] = np.zeros(0)
            continue
        if f[name].shape[0] < n:
            raise ValueError(f"{path!r} is damaged: it commits {n} rows but /{name} holds {f[name].shape[0]}.")
        out[key] = np.asarray(f[name][max(n - 1, 0) if last_only else 0:n])
    return out


def read_results(path: str | os.PathLike) -> dict:
    """Read the committed part of a results file into a dict of numpy arrays.

    Rows written after the last commit (a run killed in the middle of an append) are
    never returned.

    **Arguments:**

    - `path`: the `.h5` results file.

    **Returns:**

    A dict with `points`, `cells`, `cell_type`, `t`, `x`, `p` (and `gamma`, `reaction`
    and `reaction_mean` if stored), every diagnostic and step array under its `Solution`
    name, and `attrs` (the root attributes).

    **Raises:**

    `FileNotFoundError` for a missing file; `ValueError` for a file that is not a
    jaxvisco results file.
    """
    with open_results(path) as f:
        out = _frames(f, os.fspath(path))
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return out


def check_restart(f, path, frames=None):
    """The committed restart record of an open file, verified against its last
    committed frame: the same time, frame and step counts, and bit-for-bit the same
    positions, momenta (and internal variable, where frames store it).

    **Returns:** a dict ``x, p, gamma, velocity`` (arrays, None where absent), ``t``,
    ``n_frames``, ``n_steps``. **Raises** `ValueError` naming each mismatch.
    """
    frames = _frames(f, path, last_only=True) if frames is None else frames
    c = committed(f)
    if c.n_frames == 0:
        raise ValueError(f"results file {path!r} holds no committed frame to restart from (the run stopped "
                         "before its first frame was written); start it again.")
    if c.slot is None or c.slot not in f or "x" not in f[c.slot] or "p" not in f[c.slot]:
        raise ValueError(f"results file {path!r} holds no restart record for its {c.n_frames} committed frames; "
                         "it cannot be continued.")
    g = f[c.slot]
    rec = {k: (np.asarray(g[k]) if k in g else None) for k in ("x", "p", "gamma", "velocity")}
    rec.update(t=float(g.attrs.get("t", np.nan)), n_frames=int(g.attrs.get("n_frames", -1)),
               n_steps=int(g.attrs.get("n_steps", -1)))
    last = c.n_frames - 1
    bad = []
    if rec["n_frames"] != c.n_frames:
        bad.append(f"the restart record is of frame {rec['n_frames'] - 1}, the last committed frame is {last}")
    if rec["n_steps"] != c.n_steps:
        bad.append(f"the restart record follows {rec['n_steps']} steps, the file commits {c.n_steps}")
    if rec["t"] != float(frames["t"][-1]):
        bad.append(f"restart t = {rec['t']!r}, last frame t = {float(frames['t'][-1])!r}")
    for name, key in (("x", "x"), ("p", "p"), ("gamma", "gamma")):
        a, b = rec[name], frames.get(key)
        if a is None or b is None:
            continue
        b = b[-1]
        if a.shape != b.shape:
            bad.append(f"restart {name} has shape {a.shape}, frame {last} {b.shape}")
        elif not np.array_equal(a, b):
            bad.append(f"max |restart.{name} - {name}[{last}]| = {float(np.max(np.abs(a - b))):.3g}")
    if bad:
        raise ValueError(f"{path!r} is inconsistent: its restart state disagrees with its last committed frame "
                         f"({'; '.join(bad)}); it cannot be continued from.")
    return rec


class Restart(NamedTuple):
    """What a results file holds to continue a run: what `read_restart` returns.

    **Attributes:**

    - `t`: the time of the last committed frame.
    - `state`: the `State` there (with the full internal variable; its `gamma` is None
      where the file lacks it).
    - `velocity`: the predictor velocity of the next step (None where unknown: a restart
      then starts from the velocity of the momenta, which changes the following steps at
      the level of the Newton tolerance).
    - `n_frames`, `n_steps`: the committed frames and steps.
    - `dissipated`, `external_work`: the cumulative values at `t`.
    - `attrs`: the root attributes (`parameters` decoded from JSON where it is JSON).
    """

    t: float
    state: object
    velocity: np.ndarray | None
    n_frames: int
    n_steps: int
    dissipated: float
    external_work: float
    attrs: dict


def read_restart(path: str | os.PathLike) -> Restart:
    """The verified restart data of a results file.

    Continue the run with `simulate(scene, integrator, r.t, t1, dt0,
    initial_state=r.state, initial_velocity=r.velocity)`, or with `resume`.

    **Arguments:**

    - `path`: the `.h5` results file.

    **Returns:**

    A `Restart`.

    **Raises:**

    `ValueError` for a file whose restart state disagrees with its last committed frame
    (naming the mismatch) or that is not a results file; `FileNotFoundError`.
    """
    import jax.numpy as jnp

    from .._scene import State

    path = os.fspath(path)
    with open_results(path) as f:
        frames = _frames(f, path, last_only=True)
        rec = check_restart(f, path, frames)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    try:
        attrs["parameters"] = json.loads(attrs.get("parameters", ""))
    except (TypeError, ValueError):
        pass
    state = State(jnp.asarray(rec["x"]), jnp.asarray(rec["p"]), None if rec["gamma"] is None
                  else jnp.asarray(rec["gamma"]))
    return Restart(rec["t"], state, rec["velocity"], rec["n_frames"], rec["n_steps"],
                   float(frames["dissipated"][-1]) if "dissipated" in frames else 0.0,
                   float(frames["external_work"][-1]) if "external_work" in frames else 0.0, attrs)
