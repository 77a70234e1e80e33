"""Continue a run saved in a results file."""

import os

from .._integrate._simulate import simulate
from .._integrate._solution import SolverError
from .._io import ResultsWriter, read_restart


def resume(path, scene, integrator, t_end, dt, append=False, throw=True, **kwargs):
    """Continue the run saved in the results file `path` up to `t_end`.

    Starts `simulate(scene, integrator, t_end, dt, ...)` at the file's last committed
    frame with its verified restart state (full internal variable) and predictor
    velocity, so that a run split in two repeats the uninterrupted run (exactly with
    ``NewtonKrylov(linear_solver="direct")``; with the default Krylov solver to the
    Newton tolerance, because the reused tangent that preconditions it is not stored).
    `scene` and `integrator` must be those of the saved run (the file stores their
    parameters, not the objects); `dt` is a step or a schedule in absolute times, as
    for `simulate`. `append=True` also appends the new frames and steps to the file
    (cumulative dissipation and external work continue) and sets its status. Other
    keywords go to `simulate`.

    **Returns:** the `Solution` from the file's last frame on (its `dissipated` and
    `external_work` count from that frame; add `read_restart(path).dissipated`).
    """
    r = read_restart(path)
    if r.state.x.shape != scene.x0.shape:
        raise ValueError(f"{os.fspath(path)!r} holds {r.state.x.shape[0]} nodes in {r.state.x.shape[1]}D, "
                         f"the scene {scene.x0.shape[0]} in {scene.x0.shape[1]}D.")
    if scene.has_internal_variable and r.state.gamma is None:
        raise ValueError(f"{os.fspath(path)!r} holds no internal variable to restart from (its restart record has "
                         "no gamma); it cannot be continued exactly.")
    if float(t_end) <= r.t:
        raise ValueError(f"t_end must be later than the file's last time t = {r.t:.17g}, got t_end = {t_end!r}.")
    for k in ("t0", "initial_state", "initial_velocity"):
        if k in kwargs:
            raise TypeError(f"resume sets {k} from the results file; do not pass it.")
    w = None
    if append:
        kwargs["save_gamma"] = True  # the restart record needs the full internal variable
        w = ResultsWriter(path, append=True)
    status = "interrupted"
    try:
        sol = simulate(scene, integrator, t_end, dt, t0=r.t, initial_state=r.state, initial_velocity=r.velocity,
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
