"""The whole time loop as one compiled program.

`simulate` parses the schedule on the host, then runs one `lax.while_loop` over all
steps (compile time does not depend on their number). Each nominal step is advanced by
an inner loop that halves the step after a failed Newton solve and grows back after
successes; a step that cannot be recovered ends the run with the last good state.
The loop is differentiable (`jax.grad`, `jax.jvp`) through a replay of its accepted
sub-steps (`_differentiable`).
"""

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import _top_level, jit
from .._scene import Scene, State
from .._solver._implicit import materialize_zeros
from .._solver._newton import NewtonKrylov, solve_step
from .._solver._tangent import empty_tangent, position_pattern
from .._time_element._step import make_context, predictor, step_outcome
from .._time_element._time_element import AbstractTimeElement
from .._validation import check_finite
from ._adaptive import run_adaptive
from ._differentiable import (
    check_replay,
    empty_record,
    frame_tangents,
    record_frame,
    record_size,
    record_substep,
    replay,
    segment_length,
)
from ._frames import at_equilibrium, frame_buffers, frame_fields, write_frame
from ._schedule import StepTo, step_times
from ._solution import DONE, EQUILIBRIUM, FAILED, RUNNING, Solution, SolverError
from ._stepsize import PIDController, SaveAt


def simulate(scene: Scene, integrator: AbstractTimeElement, t_end, dt, t0=None, save_every=1,
             solver: NewtonKrylov = NewtonKrylov(), save_gamma=False, stop_at_equilibrium=None,
             max_halvings=6, initial_state: Optional[State] = None, max_steps=None,
             throw=True, initial_velocity=None, differentiable=False, checkpoint_every=None,
             stepsize_controller: Optional[PIDController] = None, saveat: Optional[SaveAt] = None) -> Solution:
    """Integrate a scene in time.

    **Arguments:**
    - `scene`, `integrator` (`cG(k)`, `eG(k)`, `Midpoint()`, `Newmark()`).
    - `t_end`, `t0` (default 0); `dt`: a step, a schedule `[(t_until, dt), ...]` in
      absolute times (piecewise constant, e.g. `[(20.0, 0.1), (40.0, 0.5)]`; it must
      reach `t_end`, or end with `t_until = inf`), or `StepTo(ts)` (steps ending at the
      times `ts`; then `t0` and `t_end` may be None). Step end times are exact: a
      piece's steps end at `start + m * h`, never at an accumulated sum.
    - `save_every`: keep every n-th step (the last step is always kept).
    - `solver`: `NewtonKrylov(...)` settings.
    - `save_gamma`: also keep the internal variable at the saved frames.
    - `stop_at_equilibrium`: a tolerance `tol`; the run ends once the kinetic energy
      relative to the rigid-body motion and the step's dissipated energy both fall
      below `tol * H_0`.
    - `max_halvings`: how often a failed step may be halved before the run stops: the
      smallest step tried is `h / 2**max_halvings` (after successes the sub-steps grow
      back dyadically to `h`).
    - `initial_state`: start from this `State` instead of the scene's (restarts).
    - `initial_velocity`: the predictor's velocity for the first step (default: the
      velocity of the initial momenta). A restart that passes the previous run's
      `Solution.end_velocity` repeats the uninterrupted run exactly.
    - `max_steps`: capacity of the compiled loop (default: the number of steps rounded up
      to the next of 8, 12, 16, 24, 32, 48, ...: runs of 100 and 120 steps share one
      program, in memory and in the persistent cache, at most 1.5x the saved frames
      until they are trimmed; called under a JAX transformation, the number of steps).
      Runs with the same capacity share one compilation.
    - `throw`: raise `SolverError` on failure (else return with `status == "failed"`).
    - `differentiable`: kept for compatibility; with constant steps or a schedule every
      run is differentiable and the flag changes nothing. `jax.grad`, `jax.jvp` and
      `jax.vmap` of a plain call work, with respect to anything the scene holds (material
      parameters, density, initial velocities and positions, loads), `initial_state`
      and `initial_velocity`; step halving and `stop_at_equilibrium` stay on. The
      derivative follows the run's accepted sub-steps (step sizes are constants of the
      derivative), each step differentiated implicitly (one linear solve with the
      converged tangent; Newton is never differentiated). See `_differentiable`.
    - `checkpoint_every`: frames per checkpointed segment when the run is differentiated
      in reverse mode (default: ceil(sqrt(sub-steps)) sub-steps; reverse-mode memory
      grows like the square root of the number of steps).

    - `stepsize_controller`: `PIDController(rtol, atol, ...)` for error-controlled steps
      (see `_stepsize`, `_estimate`): `dt` is then the first step tried (a number, or
      None: a hundredth of the run), `max_steps` the capacity of accepted steps (default
      4096; frames: every `save_every`-th accepted step, so memory grows with it), and
      a run that needs more ends with `status == "max_steps"` (`SolverError` with
      `throw`). `max_halvings` does not apply (the controller retries smaller steps
      down to its `dtmin`). With `differentiable=True` the run is first made without
      derivatives to find its accepted steps, then differentiated along them (steps
      are constants of the derivative, as in diffrax; not under `jax.jit`/`jax.vmap`).
    - `saveat`: `SaveAt(ts)`: frames at the times `ts` (adaptive runs only), each from
      the time polynomial of the step that covers it.

    **Returns:** a `Solution` (trimmed to the saved frames when called outside `jit`).
    """
    if not isinstance(integrator, AbstractTimeElement):
        raise TypeError(f"integrator must be cG(k), eG(k), Midpoint() or Newmark(), got {integrator!r}.")
    if isinstance(save_every, bool) or not isinstance(save_every, (int, np.integer)) or save_every < 1:
        raise ValueError(f"save_every must be an integer >= 1, got {save_every!r}.")
    if stop_at_equilibrium is not None and not (float(stop_at_equilibrium) > 0):
        raise ValueError(f"stop_at_equilibrium must be a positive tolerance or None, got {stop_at_equilibrium!r}.")
    if not isinstance(max_halvings, (int, np.integer)) or not 0 <= max_halvings <= 30:
        raise ValueError(f"max_halvings must be an integer in [0, 30], got {max_halvings!r}.")
    state0 = scene.initial_state() if initial_state is None else initial_state
    if initial_state is not None:
        ref = dict(x=scene.x0, p=scene.x0, gamma=scene.gamma0)
        for name in ("x", "p", "gamma"):
            a, b = getattr(initial_state, name), ref[name]
            if (a is None) != (b is None) or (a is not None and jnp.shape(a) != jnp.shape(b)):
                raise ValueError(f"initial_state.{name} must have shape {None if b is None else jnp.shape(b)} "
                                 f"for this scene, got {None if a is None else jnp.shape(a)}.")
            if a is not None:
                check_finite(f"initial_state.{name}", a)
    if initial_velocity is None:
        v0, use_v0 = jnp.zeros_like(state0.p), jnp.asarray(False)
    else:
        v0, use_v0 = jnp.asarray(initial_velocity, dtype=state0.p.dtype), jnp.asarray(True)
        if v0.shape != state0.p.shape:
            raise ValueError(f"initial_velocity must have shape {state0.p.shape}, got {v0.shape}.")
        check_finite("initial_velocity", v0)
    if saveat is not None and not isinstance(saveat, SaveAt):
        raise TypeError(f"saveat must be a SaveAt(ts=...), got {saveat!r}.")
    if stepsize_controller is not None:
        return _adaptive(scene, integrator, stepsize_controller, t_end, dt, t0, save_every, solver, save_gamma,
                         stop_at_equilibrium, state0, max_steps, throw, v0, use_v0, differentiable, checkpoint_every,
                         saveat)
    if saveat is not None:
        raise ValueError("saveat=SaveAt(ts=...) (dense output) needs error-controlled steps "
                         "(stepsize_controller=PIDController(...)); with constant steps use save_every.")
    hs, ts = step_times(t0, t_end, dt)
    t0, te = ts[0], ts[1:]
    n_active = len(hs)
    if max_steps is not None:
        if int(max_steps) < n_active:
            raise ValueError(f"max_steps = {max_steps} is less than the {n_active} steps of the schedule.")
        hs, te = _padded(hs, te, int(max_steps))
    elif _top_level():  # traced callers keep arrays of the run's length
        hs, te = _padded(hs, te, capacity(n_active))
    if checkpoint_every is not None and (isinstance(checkpoint_every, bool) or int(checkpoint_every) < 1):
        raise ValueError(f"checkpoint_every must be a positive number of frames or None, got {checkpoint_every!r}.")
    segment = segment_length(record_size(len(hs)), int(save_every), checkpoint_every)
    if not _top_level():
        # Under a transformation the run may be differentiated: a backward sweep needs
        # the factorizations of a whole segment at once (one per sub-step for the
        # derivative, a few more for Newton when the segment is re-run).
        position_pattern(scene.disc.cells, integrator.k, scene.disc.n_nodes, scene.dim, scene.fixed).reserve(
            64 + 8 * segment)
    sol = _run(scene, integrator, solver, state0, jnp.asarray(float(t0)), jnp.asarray(hs), jnp.asarray(te),
               jnp.asarray(n_active), int(save_every), bool(save_gamma),
               None if stop_at_equilibrium is None else jnp.asarray(float(stop_at_equilibrium)),
               int(max_halvings), v0, use_v0, segment)
    return _finish(sol, integrator, int(max_halvings), throw)


def _adaptive(scene, integrator, ctrl, t_end, dt, t0, save_every, solver, save_gamma, stop_at_equilibrium, state0,
              max_steps, throw, v0, use_v0, differentiable, checkpoint_every, saveat):
    """`simulate` with error-controlled steps (`run_adaptive`)."""
    if not isinstance(ctrl, PIDController):
        raise TypeError(f"stepsize_controller must be a PIDController(rtol=..., atol=...), got {ctrl!r}.")
    t0 = 0.0 if t0 is None else float(t0)
    if t_end is None or not (np.isfinite(float(t_end)) and np.isfinite(t0) and float(t_end) > t0):
        raise ValueError(f"an adaptive run needs finite t0 < t_end, got t0 = {t0!r}, t_end = {t_end!r}.")
    t_end = float(t_end)
    if dt is None:
        h0 = 0.01 * (t_end - t0)
    elif isinstance(dt, (int, float, np.integer, np.floating)) and not isinstance(dt, bool) and 0 < float(dt) < np.inf:
        h0 = float(dt)
    else:
        raise ValueError(f"with a stepsize_controller, dt is the first step to try (a positive number) or None "
                         f"(a hundredth of the run), got {dt!r}; schedules and StepTo fix the steps themselves.")
    cap = 4096 if max_steps is None else int(max_steps)
    if cap < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps!r}.")
    if saveat is not None:
        saveat.check(t0, t_end)
    if saveat is not None and differentiable:
        raise ValueError("saveat=SaveAt(ts=...) is not available with differentiable=True; the differentiable "
                         "run saves at its steps (save_every).")
    if differentiable:
        # Step sizes are constants of the derivative (as in diffrax): find the accepted
        # steps without derivatives, then differentiate the run along them.
        no_grad = lambda tree: jax.tree_util.tree_map(  # noqa: E731
            lambda a: jax.lax.stop_gradient(a) if eqx.is_array(a) else a, tree)
        probe = _adaptive(no_grad(scene), integrator, ctrl, t_end, dt, t0, save_every, solver, False,
                          None, no_grad(state0), max_steps, throw, no_grad(v0), use_v0, False, None, None)
        if isinstance(probe.step_t, jax.core.Tracer):
            raise ValueError("differentiable=True with a stepsize_controller needs the accepted steps as numbers: "
                             "call it outside jax.jit/jax.vmap (jax.grad and jax.jvp are fine), or run the adaptive "
                             "run first and differentiate simulate(..., dt=StepTo(...)) along its steps.")
        if probe.status != "done":
            return probe
        ts = np.concatenate([[t0], np.asarray(probe.step_t)])
        return simulate(scene, integrator, None, StepTo(ts), save_every=save_every, solver=solver,
                        save_gamma=save_gamma, initial_state=state0, throw=throw,
                        initial_velocity=jnp.where(use_v0, v0, scene.velocity(state0.p)),
                        checkpoint_every=checkpoint_every)
    sol, _ = run_adaptive(scene, integrator, solver, ctrl, state0, jnp.asarray(t0), jnp.asarray(t_end),
                          jnp.asarray(h0), cap, int(save_every), bool(save_gamma),
                          None if saveat is None else jnp.asarray(saveat.ts),
                          None if stop_at_equilibrium is None else jnp.asarray(float(stop_at_equilibrium)), v0, use_v0)
    if isinstance(sol.n_saved, jax.core.Tracer):
        return sol
    sol = sol.trimmed()
    if sol.status == "max_steps" and throw:
        t = float(sol.step_t[-1]) if len(sol.step_t) else t0
        raise SolverError(f"{integrator.name}: the adaptive run reached max_steps = {cap} accepted steps at t = {t:.6g} "
                          f"before t_end = {t_end:g}; raise max_steps or loosen the tolerances (the state there is "
                          "attached).", t, sol.state(-1), sol)
    if sol.status == "failed" and throw:
        t = float(sol.step_t[-1]) if len(sol.step_t) else t0
        raise SolverError(f"{integrator.name}: the adaptive step after t = {t:.6g} did not converge at the smallest "
                          f"step allowed (dtmin = {float(ctrl.dtmin):g}); the last good state is attached.",
                          t, sol.state(-1), sol)
    return sol


def capacity(n):
    """The compiled loop's default number of step slots for `n` steps: the next of 8, 12,
    16, 24, 32, 48, 64, ... (powers of two and 1.5 times them), so that runs of nearby
    lengths (another `t_end`, another `dt`) reuse one compiled program."""
    c = 8
    while c < n:
        c = c * 3 // 2 if c & (c - 1) == 0 else c // 3 * 4
    return c


def _padded(hs, te, n):
    """Step sizes and end times extended to `n` entries by unit steps that the compiled
    loops skip (they only fix the shapes, so runs of different lengths share a program)."""
    extra = n - len(hs)
    return np.concatenate([hs, np.ones(extra)]), np.concatenate([te, te[-1] + np.arange(1, extra + 1)])


def _finish(sol, integrator, max_halvings, throw):
    if isinstance(sol.n_saved, jax.core.Tracer):
        return sol
    sol = sol.trimmed()
    if sol.status == "failed" and throw:
        t = float(sol.t[-1])
        raise SolverError(
            f"{integrator.name}: the step after t = {t:.6g} did not converge even after "
            f"{max_halvings} halvings; the last good state is attached (SolverError.state).",
            t, sol.state(-1), sol)
    return sol


@jit(export=True)
def _run(scene, scheme, solver, state0, t0, hs, te, n_steps, save_every, save_gamma, eq_tol, max_halvings, v0, use_v0,
         segment):
    """The time loop (`_loop`), compiled. `segment`: sub-steps per checkpointed segment
    of its derivative (`_differentiable`)."""
    return _loop(scene, state0, v0, scheme=scheme, solver=solver, t0=t0, hs=hs, te=te, n_steps=n_steps,
                 save_every=save_every, save_gamma=save_gamma, eq_tol=eq_tol, max_halvings=max_halvings,
                 use_v0=use_v0, segment=segment)


@eqx.filter_custom_jvp
def _loop(scene, state0, v0, **kw):
    """The loop's `Solution`; differentiable in the scene, the initial state and the
    predictor's initial velocity through the replay of its sub-steps (`_loop_jvp`)."""
    kw.pop("segment")
    return _probe(scene, state0, v0, **kw)[0]


@_loop.def_jvp
def _loop_jvp(primals, tangents, *, segment, **kw):
    scene, state0, v0 = primals
    sol, rec = _probe(scene, state0, v0, **kw)

    def fn(scene, state0, v0):
        return replay(kw["scheme"], kw["solver"], scene, state0, v0, kw["use_v0"], rec, kw["save_gamma"], segment)

    out, d_out = eqx.filter_jvp(fn, primals, tangents)
    d_first, d_ys, d_v = materialize_zeros(d_out[:3], out[:3])
    # The checks sit on the primal output, which every derivative evaluates.
    sol = check_replay(rec, out[3], sol)
    frames = frame_tangents(rec, sol.n_saved, d_first, d_ys)
    t_sol = jax.tree_util.tree_map(lambda _: None, sol)
    names = [k for k in frames if getattr(sol, k) is not None]
    t_sol = eqx.tree_at(lambda s: [getattr(s, k) for k in names] + [s.end_velocity], t_sol,
                        [frames[k] for k in names] + [d_v], is_leaf=lambda x: x is None)
    return sol, t_sol


def _probe(scene, state0, v0, *, scheme, solver, t0, hs, te, n_steps, save_every, save_gamma, eq_tol, max_halvings,
           use_v0):
    """The loop itself: a `Solution` and the `Record` of its accepted sub-steps."""
    n_frames = 1 + -(-hs.shape[0] // save_every)
    diag0 = scene.diagnostics(state0)
    H0 = diag0["energy"]
    full = 2**max_halvings

    def advance(state, t, h, t_next, v, tan, rec):
        """One nominal step from t to t_next = t + h, halved on failure (dyadic sub-steps;
        the sub-steps end at t + (pos / full) h, the last at t_next exactly)."""

        def cond(c):
            return (c["pos"] < full) & ~c["failed"]

        def body(c):
            hs_ = h / (2.0 ** c["level"])
            ctx = make_context(scene, c["state"], c["t"], hs_)
            r = solve_step(solver, scheme, scene, ctx, predictor(scheme, scene, ctx, c["v"]), c["tan"])
            new, D, W, v_end, ok = step_outcome(scheme, scene, ctx, r)
            pick = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(ok, x, y), a, b)  # noqa: E731
            pos = c["pos"] + jnp.where(ok, jnp.right_shift(full, c["level"]), 0)
            # Grow back once the position is aligned with the coarser grid.
            coarser = jnp.right_shift(full, jnp.maximum(c["level"] - 1, 0))
            level = jnp.where(ok, jnp.where((c["level"] > 0) & (pos % coarser == 0), c["level"] - 1, c["level"]),
                              c["level"] + 1)
            return dict(
                state=pick(new, c["state"]), t=jnp.where(pos == full, t_next, t + pos * (h / full)),
                v=pick(v_end, c["v"]), tan=r.tangent, level=level, pos=pos,
                its=c["its"] + r.iterations, kits=c["kits"] + r.krylov_iterations, chord=c["chord"] + r.chord_iterations,
                rej=c["rej"] + jnp.where(ok, 0, 1), D=c["D"] + jnp.where(ok, D, 0.0),
                W=c["W"] + jnp.where(ok, W, 0.0), res=jnp.maximum(c["res"], jnp.where(ok, r.residual, 0.0)),
                failed=level > max_halvings, rec=record_substep(c["rec"], c["t"], hs_, ok),
            )

        init = dict(state=state, t=t, v=v, tan=tan, level=jnp.asarray(0), pos=jnp.asarray(0), rec=rec,
                    its=jnp.asarray(0), kits=jnp.asarray(0), chord=jnp.asarray(0), rej=jnp.asarray(0), D=jnp.asarray(0.0),
                    W=jnp.asarray(0.0), res=jnp.asarray(0.0), failed=jnp.asarray(False))
        return jax.lax.while_loop(cond, body, init)

    def cond(c):
        return (c["i"] < n_steps) & (c["status"] == RUNNING)

    def body(c):
        i = c["i"]
        a = advance(c["state"], c["t"], hs[i], te[i], c["v"], c["tan"], c["rec"])
        failed = a["failed"]
        dissipated, work = c["dissipated"] + a["D"], c["work"] + a["W"]
        status = jnp.where(failed, FAILED, RUNNING)
        if eq_tol is not None:
            at_rest = at_equilibrium(scene, a["state"], a["D"], eq_tol, H0)
            status = jnp.where((status == RUNNING) & at_rest, EQUILIBRIUM, status)
        status = jnp.where((status == RUNNING) & (i == n_steps - 1), DONE, status)
        save = ((i + 1) % save_every == 0) | (status != RUNNING)
        save = save & ~failed

        def do_save(frames):
            return write_frame(frames, c["n_saved"], a["t"], a["state"], scene.diagnostics(a["state"]), dissipated, work)

        frames = jax.lax.cond(save, do_save, lambda f: f, c["frames"])
        steps = c["steps"]
        steps = dict(step_t=steps["step_t"].at[i].set(a["t"]), step_h=steps["step_h"].at[i].set(hs[i]),
                     newton_iterations=steps["newton_iterations"].at[i].set(a["its"]),
                     krylov_iterations=steps["krylov_iterations"].at[i].set(a["kits"]),
                     chord_iterations=steps["chord_iterations"].at[i].set(a["chord"]),
                     residual=steps["residual"].at[i].set(a["res"]),
                     rejections=steps["rejections"].at[i].set(a["rej"]))
        rec = record_frame(a["rec"], c["n_saved"], save)
        return dict(i=i + 1, state=a["state"], t=a["t"], v=a["v"], tan=a["tan"], frames=frames, steps=steps, rec=rec,
                    n_saved=c["n_saved"] + save.astype(int), dissipated=dissipated, work=work, status=status,
                    n_done=c["n_done"] + (~failed).astype(int))

    frames = write_frame(frame_buffers(n_frames, t0, state0, diag0, save_gamma), 0, t0, state0, diag0,
                         jnp.asarray(0.0), jnp.asarray(0.0))
    zeros_f, zeros_i = jnp.zeros(hs.shape[0]), jnp.zeros(hs.shape[0], dtype=int)
    steps = dict(step_t=zeros_f, step_h=zeros_f, newton_iterations=zeros_i, krylov_iterations=zeros_i, chord_iterations=zeros_i,
                 residual=zeros_f, rejections=zeros_i)
    v_init = jnp.where(use_v0, v0, scene.velocity(state0.p))
    init = dict(i=jnp.asarray(0), state=state0, t=t0, v=v_init, tan=empty_tangent(scheme, scene),
                frames=frames, steps=steps, rec=empty_record(hs.shape[0], n_frames, t0.dtype),
                n_saved=jnp.asarray(1), dissipated=jnp.asarray(0.0),
                work=jnp.asarray(0.0), status=jnp.asarray(RUNNING), n_done=jnp.asarray(0))
    c = jax.lax.while_loop(cond, body, init)
    sol = Solution(
        **frame_fields(c["frames"]), n_saved=c["n_saved"], n_steps=c["n_done"],
        status_code=c["status"], integrator=scheme.describe(), end_velocity=c["v"], **c["steps"])
    return sol, c["rec"]
