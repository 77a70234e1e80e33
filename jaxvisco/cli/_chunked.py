"""Running in chunks: a simulation advanced in calls of one compiled program each
(`run_chunked` for fixed steps, `run_adaptive_chunked` for error-controlled ones), every
chunk committed to the results writer as it returns and progress printed, and
`chunk_size`, the chunk length that lets all chunks of all runs share one program.
"""

import sys
import time

import numpy as np


def chunk_size(lengths, target=50, save_every=1):
    """The chunk length (in steps): `target` as a multiple of `save_every` (at least
    `save_every`), at most the longest run's length. Every chunk is one call of the same
    program, whose capacity is this length (`simulate`'s `max_steps`) whatever number of
    steps the chunk has, so the chunks of all runs share it.

    (It was the largest divisor of every run length up to `target`, from before
    capacities: `jaxvisco paper --quick` then ran its 204 + 24 steps in chunks of 12, each
    a `simulate` call and a durable commit; in chunks of 50 the four runs took 5.75 s
    instead of 7.25-7.52 s, one after the other with every program cached.)"""
    c = max(save_every, (target // save_every) * save_every)
    return min(c, max(lengths))


def run_chunked(scene, integrator, steps, chunk=50, commit_every=5.0, save_every=1, solver=None, writer=None,
                save_gamma=False, label="", quiet=False, stream=None, initial_state=None, initial_velocity=None,
                should_stop=None, max_halvings=6):
    """Integrate over the steps of `steps` (a `StepTo`) in chunks, committing each one.

    A new `writer` first commits frame 0 (before anything compiles), so a run killed at
    any moment can be resumed. Every chunk is one call of one compiled program (capacity
    `chunk` steps) that continues from the previous chunk's last state and predictor
    velocity, and is committed to `writer` when it returns. With `commit_every` > 0
    (seconds) the chunks are sized from the measured time per step so that a commit
    follows at least about every `commit_every` seconds: the first chunk of a process is
    `save_every` steps (it also compiles), later ones as many as fit, at most `chunk`.
    With `commit_every` = 0 every chunk has `chunk` steps, so a run split at a chunk
    boundary repeats the uninterrupted one exactly (the reused tangent that
    preconditions the Krylov solver starts afresh at every chunk, so other splits agree
    to the Newton tolerance). `initial_state`/`initial_velocity` continue a saved run.
    `should_stop()` is asked after every chunk; when true the run ends "interrupted".

    Returns a dict: `status`, `steps` (taken), `newton` (total iterations), `wall`,
    `state` (last state), `t_last`.
    """
    import jaxvisco as jv

    stream = stream or sys.stderr
    solver = solver or jv.NewtonKrylov()
    ts = np.asarray(steps.ts)
    n = len(ts) - 1
    state, v = initial_state, initial_velocity
    start = time.perf_counter()
    if writer is not None and writer.n_frames == 0:
        writer.write_initial_state(float(ts[0]), state, v)
    status, i, newton, per_step = "done", 0, 0, None
    if not quiet:
        print(f"{label}: {n} steps; frame 0 written, the first chunk compiles (~10-60 s)", file=stream, flush=True)
    while i < n:
        m = chunk
        if commit_every > 0:
            m = save_every if per_step is None else int(commit_every / max(per_step, 1e-9))
            m = max(save_every, min(chunk, m) // save_every * save_every)
        m = min(m, n - i)
        t_call = time.perf_counter()
        sol = jv.simulate(scene, integrator, stepsize_controller=jv.StepTo(ts[i:i + m + 1], max_halvings=max_halvings),
                          saveat=jv.SaveAt(every=save_every, gamma=True), root_finder=solver, initial_state=state,
                          throw=False, initial_velocity=v, max_steps=chunk)
        per_step = (time.perf_counter() - t_call) / m  # the first call also compiles: an overestimate
        ns, its = _commit(writer, sol, save_gamma)
        i += ns
        newton += int(its.sum())
        state, v = sol.state(-1), sol.end_velocity
        H = float(np.asarray(sol.energy)[-1])
        if not quiet:
            print(f"{label}: t = {float(np.asarray(sol.t)[-1]):9.4f}  step {i:6d}/{n}  newton/step "
                  f"{its.mean() if ns else 0:4.1f}  H = {H:.8g}", file=stream, flush=True)
        if sol.status in ("failed", "equilibrium"):
            status = sol.status
            break
        if should_stop is not None and should_stop() and i < n:
            status = "interrupted"
            break
    return dict(status=status, steps=i, newton=newton, wall=time.perf_counter() - start, state=_on_host(state),
                t_last=float(ts[i]) if status != "failed" else float(np.asarray(sol.t)[-1]))


def run_adaptive_chunked(scene, integrator, controller, t0, t_end, dt0=None, chunk=50, save_every=1, solver=None,
                         writer=None, save_gamma=False, label="", quiet=False, stream=None, initial_state=None,
                         initial_velocity=None, should_stop=None):
    """`run_chunked` for error-controlled steps (`controller`, a `PIDController`): calls
    of at most `chunk` accepted steps (one compiled program), each committed to
    `writer`, each continuing from the previous one's state, predictor velocity and last
    accepted step. Returns the dict of `run_chunked`, with `h_last`."""
    import jaxvisco as jv

    stream = stream or sys.stderr
    solver = solver or jv.NewtonKrylov()
    state, v, t, h = initial_state, initial_velocity, float(t0), dt0
    controller = controller.for_run(t0, t_end)  # the tolerance is the whole run's, not a chunk's
    start = time.perf_counter()
    if writer is not None and writer.n_frames == 0:
        writer.write_initial_state(t, state, v)
    status, n, newton, rejected = "done", 0, 0, 0
    if not quiet:
        print(f"{label}: adaptive steps (rtol = {float(controller.rtol):g}, atol = {float(controller.atol):g}) to "
              f"t = {t_end:g}; frame 0 written, the first chunk compiles (~10-60 s)", file=stream, flush=True)
    while True:
        sol = jv.simulate(scene, integrator, t, t_end, h, saveat=jv.SaveAt(every=save_every, gamma=True), root_finder=solver,
                          initial_state=state, throw=False, initial_velocity=v, max_steps=chunk,
                          stepsize_controller=controller)
        ns, its = _commit(writer, sol, save_gamma)
        n += ns
        newton += int(its.sum())
        rejected += int(np.asarray(sol.rejections).sum())
        if ns:
            state, v, t, h = sol.state(-1), sol.end_velocity, float(np.asarray(sol.step_t)[-1]), \
                float(np.asarray(sol.step_h)[-1])
            # the next chunk measures atol on the internal variable in the same strain
            controller = controller.continued(sol.strain_scale)
        if not quiet:
            print(f"{label}: t = {t:9.4f}  steps {n:6d} ({rejected} rejected)  h = {h if h else float('nan'):.4g}  "
                  f"newton/step {its.mean() if ns else 0:4.1f}  H = {float(np.asarray(sol.energy)[-1]):.8g}",
                  file=stream, flush=True)
        if sol.status != "max_steps":
            status = sol.status
            break
        if should_stop is not None and should_stop():
            status = "interrupted"
            break
    return dict(status=status, steps=n, newton=newton, wall=time.perf_counter() - start, state=_on_host(state), t_last=t,
                h_last=h)


def _commit(writer, sol, save_gamma):
    """Append a chunk's frames after its first (the previous chunk's last) to `writer`
    (if any). Returns the chunk's number of steps and its Newton iterations per step."""
    if writer is not None:
        writer.append(sol, skip_first=True, gamma=save_gamma)
    return int(len(np.asarray(sol.step_t))), np.asarray(sol.newton_iterations)


def _on_host(state):
    """A `State` of numpy arrays."""
    import jaxvisco as jv

    return jv.State(np.asarray(state.x), np.asarray(state.p), None if state.gamma is None else np.asarray(state.gamma))


def run_into(writer, go):
    """`go()` (a chunked run writing to `writer`) and its result; `writer` is closed with
    the run's status, also when `go` fails ("failed") or is interrupted ("interrupted")."""
    status = "failed"
    try:
        r = go()
        status = r["status"]
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    finally:
        writer.close(status=status)
    return r
