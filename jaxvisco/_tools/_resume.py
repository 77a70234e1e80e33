"""Continue a run saved in a results file."""

import os
import warnings

import numpy as np

from .._integrate._saveat import SaveAt
from .._integrate._simulate import simulate
from .._integrate._solution import Solution, SolverError
from .._integrate._stepsize import PIDController
from .._io import ResultsWriter, read_restart
from .._io._layout import committed
from .._io._read import open_results
from .._scene import Scene
from .._time_element._estimate import largest_strain
from .._time_element._time_element import AbstractTimeElement


def resume(path: str | os.PathLike, scene: Scene, integrator: AbstractTimeElement, t1: float | None = None,
           dt0: float | None = None, append: bool = False, throw: bool = True, **kwargs) -> Solution:
    """Continue the run saved in a results file up to `t1`.

    Runs `simulate(scene, integrator, t0, t1, dt0, ...)` from the file's last committed
    frame, with its verified restart state (full internal variable) and predictor
    velocity, so that a run split in two repeats the uninterrupted run (exactly with
    `NewtonKrylov(linear_solver=Direct())`; with the default GMRES to the Newton
    tolerance, because the reused tangent that preconditions it is not stored).

    **Arguments:**

    - `path`: the `.h5` results file.
    - `scene`, `integrator`: those of the saved run (the file stores their parameters,
      not the objects).
    - `t1`: the time to continue to.
    - `dt0`: as in `simulate` (a `Schedule` is in absolute times).
    - `append`: also append the new frames and steps to the file (cumulative
      dissipation and external work continue) and set its status.
    - `throw`: raise `SolverError` when a step fails (default).
    - `**kwargs`: `simulate`'s other keywords (`stepsize_controller`, `saveat`,
      `root_finder`, ...). A `PIDController` continues with the largest strain of the
      file's frames as its `strain_scale`.

    **Returns:**

    The `Solution` from the file's last frame on (its `dissipated` and `external_work`
    count from that frame; add `read_restart(path).dissipated`).

    **Raises:**

    `ValueError` for a file that does not fit the scene or ends at or after `t1`;
    `TypeError` for `t0`, `initial_state` or `initial_velocity` (the file sets them);
    `SolverError` as `simulate`.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jaxvisco as jv

    scene = jv.scenes.lshape()
    first = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, saveat=jv.SaveAt(gamma=True))
    jv.save(first, scene, "first.h5", overwrite=True)   # with the internal variable
    more = jv.resume("first.h5", scene, jv.eG(1), t1=0.6, dt0=0.1, append=True)
    ```
    """
    if "t_end" in kwargs:  # jaxvisco 0.1's name (simulate translates dt= and the others)
        warnings.warn("resume(): t_end= is deprecated, use t1=.", DeprecationWarning, stacklevel=2)
        t1 = kwargs.pop("t_end")
    if t1 is None:
        raise TypeError("resume() needs t1, the time to continue the run to.")
    r = read_restart(path)
    if r.state.x.shape != scene.x0.shape:
        raise ValueError(f"{os.fspath(path)!r} holds {r.state.x.shape[0]} nodes in {r.state.x.shape[1]}D, "
                         f"the scene {scene.x0.shape[0]} in {scene.x0.shape[1]}D.")
    if scene.has_internal_variable and r.state.gamma is None:
        raise ValueError(f"{os.fspath(path)!r} holds no internal variable to restart from (its restart record has "
                         "no gamma); it cannot be continued exactly.")
    if float(t1) <= r.t:
        raise ValueError(f"t1 must be later than the file's last time t = {r.t:.17g}, got t1 = {t1!r}.")
    for k in ("t0", "initial_state", "initial_velocity"):
        if k in kwargs:
            raise TypeError(f"resume sets {k} from the results file; do not pass it.")
    ctrl = kwargs.get("stepsize_controller")
    if isinstance(ctrl, PIDController) and scene.has_internal_variable:
        # atol on the internal variable in units of the largest strain so far, as in the
        # uninterrupted run (`PIDController.strain_scale`): from the file's frames
        kwargs["stepsize_controller"] = ctrl.continued(largest_strain_in(path, scene))
    w = None
    if append:
        # the restart record needs the full internal variable
        saveat = kwargs.get("saveat") or SaveAt()
        kwargs["saveat"] = SaveAt(saveat.ts, every=saveat.every, gamma=True)
        w = ResultsWriter(path, append=True)
    status = "interrupted"
    try:
        sol = simulate(scene, integrator, r.t, t1, dt0, initial_state=r.state, initial_velocity=r.velocity,
                       throw=False, **kwargs)
        status = sol.status
        if w is not None:
            w.append(sol, skip_first=True, gamma="qp/gamma" in w.f)
    finally:
        if w is not None:
            w.close(status=status)
    if sol.status == "failed" and throw:
        t = float(sol.t[-1])
        raise SolverError(f"{integrator.name}: the step after t = {t:.6g} did not converge; the last good state is "
                          "attached (SolverError.state).", t, sol.state(-1), sol)
    return sol


def largest_strain_in(path, scene, block=256):
    """The largest strain (`_estimate.body_strain`) of the committed frames of the results
    file `path`: the `PIDController.strain_scale` that continues its run. Reads the
    positions `block` frames at a time (the last block padded with its last frame: one
    compiled program)."""
    with open_results(path) as f:
        n = committed(f).n_frames
        xs = f["nodal/x"]
        largest = 0.0
        for i in range(0, n, block):
            x = np.asarray(xs[i:min(i + block, n)])
            x = np.concatenate([x, np.repeat(x[-1:], block - len(x), axis=0)])
            largest = max(largest, float(largest_strain(scene, x)))
    return largest


def last_step_size(path):
    """The size of the last committed step of the results file `path` (None if it has
    none): the first step a continued adaptive run tries. Reads that one entry, not the
    file's frames."""
    with open_results(path) as f:
        n = committed(f).n_steps
        return float(f["steps/step_h"][n - 1]) if n and "steps/step_h" in f else None
