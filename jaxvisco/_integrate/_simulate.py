"""The whole time loop as one compiled program.

`simulate` parses the schedule on the host, then runs one `lax.while_loop` over all
steps (compile time does not depend on their number). Each nominal step is advanced by
an inner loop that halves the step after a failed Newton solve and grows back after
successes; a step that cannot be recovered ends the run with the last good state.
The loop is differentiable (`jax.grad`, `jax.jvp`) through a replay of its accepted
sub-steps (`_differentiable`).
"""

import warnings
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _export
from .._config import _top_level, device_array, jit
from .._scene import Scene, State
from .._solver._newton import NewtonKrylov, solve_step
from .._solver._tangent import empty_tangent, multigrid_arguments, multigrid_scope
from .._time_element._step import (
    make_context,
    predictor,
    step_outcome,
    unknowns_like,
)
from .._time_element._time_element import AbstractTimeElement
from .._validation import check_finite
from ._adaptive import run_adaptive
from ._adjoint import RecursiveCheckpointAdjoint
from ._differentiable import (
    differentiate,
    empty_record,
    plan,
    record_dense_frame,
    record_frame,
    record_size,
    record_substep,
)
from ._event import AbstractEvent
from ._frames import (
    at_equilibrium,
    frame_diagnostics,
    first_reactions,
    frame_fields,
    initial_frames,
    step_reactions,
    step_buffers,
    write_dense_frames,
    write_frame,
    write_step,
)
from ._legacy import translate
from ._saveat import SaveAt
from ._schedule import AbstractStepSizeController, ConstantStepSize
from ._solution import DONE, EQUILIBRIUM, FAILED, RUNNING, Solution, SolverError
from ._stepsize import PIDController


def simulate(scene: Scene, integrator: AbstractTimeElement, t0: Optional[float] = None, t1: Optional[float] = None,
             dt0: float | None = None, *,
             saveat: Optional[SaveAt] = None, stepsize_controller: Optional[AbstractStepSizeController] = None,
             event: Optional[AbstractEvent] = None, adjoint: Optional[RecursiveCheckpointAdjoint] = None,
             root_finder: Optional[NewtonKrylov] = None, max_steps: Optional[int] = None, throw: bool = True,
             initial_state: Optional[State] = None, initial_velocity: Optional[jax.Array] = None,
             solver: Optional[NewtonKrylov] = None,
             **deprecated) -> Solution:
    """Integrate a scene in time: the counterpart of `diffrax.diffeqsolve`.

    The whole time loop is one compiled program; every call is differentiable
    (`jax.grad`, `jax.jvp`, `jax.vmap`) with respect to anything the scene holds
    (material parameters, density, initial positions and velocities, loads),
    `initial_state` and `initial_velocity`.

    **Arguments:**

    - `scene`: the `Scene` (what moves).
    - `integrator`: the time element, `cG(k)`, `eG(k)`, `Midpoint()` or `Newmark()`.
    - `t0`: the start time (default 0).
    - `t1`: the end time.
    - `dt0`: the step of `ConstantStepSize` (the default controller); with a
      `PIDController` the first step tried (None: a hundredth of the run); None with
      `Schedule` and `StepTo`, which give the steps themselves (with `StepTo`, `t0` and
      `t1` may be left out). Step end times are exact: a piece's steps end at
      `start + m * h`, never at an accumulated sum.
    - `saveat`: what to keep, `SaveAt(every=n, gamma=...)` (default: every step, no
      internal variable) or `SaveAt(ts)` (frames at given times, inside steps from their
      time polynomial); `reactions=True` adds the supports' forces.
    - `stepsize_controller`: `ConstantStepSize(max_halvings=6)` (default),
      `Schedule([(t_until, dt), ...])`, `StepTo(ts)` or `PIDController(rtol, atol)`.
      Fixed steps are halved after a failed Newton solve (at most `max_halvings` times)
      and grow back after successes; a `PIDController` retries smaller steps down to its
      `dtmin`.
    - `event`: `Equilibrium(tol)` ends the run once the body is at rest.
    - `adjoint`: how `jax.grad`/`jax.jvp` differentiate the run and what they store,
      `RecursiveCheckpointAdjoint(checkpoints=..., max_bytes=...)` (the default).
    - `root_finder`: the Newton solver of each time element, `NewtonKrylov(...)`
      (default `NewtonKrylov()`).
    - `max_steps`: the capacity of the compiled loop. Fixed steps: by default the number
      of steps rounded up to the next of 8, 12, 16, 24, 32, 48, ..., so that runs of
      nearby lengths share one compiled program. `PIDController`: accepted steps
      (default 4096); a run that needs more ends with `status == "max_steps"`. A
      derivative covers every slot of the capacity: differentiate adaptive runs with a
      `max_steps` near their need.
    - `throw`: raise `SolverError` when a step fails (default); with `False` return the
      `Solution` up to the failure with `status == "failed"`.
    - `initial_state`: start from this `State` instead of the scene's (restarts).
    - `initial_velocity`: the predictor's velocity for the first step (default: the
      velocity of the initial momenta). Passing a previous run's
      `Solution.end_velocity` with its last state repeats the uninterrupted run.
    - `solver`: deprecated name of `root_finder` (`DeprecationWarning`).

    The keywords of jaxvisco 0.1 (`t_end`, `dt`, `save_every`, `save_gamma`,
    `stop_at_equilibrium`, `max_halvings`, `differentiable`, `checkpoint_every`) are
    accepted with a `DeprecationWarning`; the changelog lists their replacements.

    **Returns:**

    A `Solution`, trimmed to the saved frames when called outside `jax.jit`.

    **Raises:**

    `SolverError` when a step fails and `throw=True`; `TypeError` for an option of the
    wrong kind; `ValueError` for inconsistent times or steps (named in the message).

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jaxvisco as jv

    sol = jv.simulate(jv.scenes.lshape(), jv.eG(1), t0=0.0, t1=0.5, dt0=0.1)
    print(sol.status, sol.energy[-1])
    ```
    """
    if deprecated:
        t1, dt0, saveat, stepsize_controller, event, adjoint = translate(
            deprecated, t1, dt0, saveat, stepsize_controller, event, adjoint)
    if not isinstance(integrator, AbstractTimeElement):
        raise TypeError(f"integrator must be cG(k), eG(k), Midpoint() or Newmark(), got {integrator!r}.")
    saveat = _option("saveat", saveat, SaveAt(), SaveAt, "SaveAt(every=n, gamma=...) or SaveAt(ts)")
    if saveat.reactions and scene.fixed is None:
        raise ValueError("SaveAt(reactions=True) needs a scene with held components (Scene(fixed=...)): the "
                         "reactions are the forces the supports exert.")
    ctrl = _option("stepsize_controller", stepsize_controller, ConstantStepSize(), AbstractStepSizeController,
                   "ConstantStepSize(), Schedule([(t_until, dt), ...]), StepTo(ts) or PIDController(rtol, atol)")
    event = _option("event", event, None, AbstractEvent, "Equilibrium(tol) or None")
    adjoint = _option("adjoint", adjoint, RecursiveCheckpointAdjoint(), RecursiveCheckpointAdjoint,
                      "RecursiveCheckpointAdjoint(checkpoints=..., max_bytes=...)")
    solver = _root_finder(root_finder, solver)
    _check_order(t0, t1)
    state0, v0, use_v0 = _initial(scene, initial_state, initial_velocity)
    eq_tol = None if event is None else device_array(float(event.tol))
    if isinstance(ctrl, PIDController):
        return _adaptive(scene, integrator, ctrl, t0, t1, dt0, saveat, event, adjoint, solver, max_steps, throw,
                         state0, v0, use_v0)
    hs, ts = ctrl.step_times(t0, t1, dt0)
    t0, te = ts[0], ts[1:]
    n_active = len(hs)
    if max_steps is not None:
        if int(max_steps) < n_active:
            raise ValueError(f"max_steps = {max_steps} is less than the {n_active} steps of the run.")
        hs, te = _padded(hs, te, int(max_steps))
    elif _top_level():  # traced callers keep arrays of the run's length
        hs, te = _padded(hs, te, capacity(n_active))
    saveat.check(float(t0), float(te[n_active - 1]))
    derivative = plan(adjoint, record_size(len(hs)), saveat.every, integrator, scene)
    sol = _run(scene, integrator, solver, state0, device_array(float(t0)), device_array(hs), device_array(te),
               device_array(n_active), saveat.every, saveat.gamma, eq_tol, ctrl.max_halvings, v0, use_v0, derivative,
               multigrid_arguments(integrator, scene, solver), save_reactions=saveat.reactions,
               ts_out=None if saveat.ts is None else device_array(saveat.ts, float),
               save_diagnostics=saveat.diagnostics)
    return _finish(sol, integrator, ctrl.max_halvings, throw)


def _root_finder(root_finder, solver):
    """The Newton solver of `simulate`'s `root_finder=` (or of its deprecated name
    `solver=`, diffrax's word for the time stepper)."""
    if solver is not None:
        if root_finder is not None:
            raise TypeError("simulate(): give root_finder or the deprecated solver, not both.")
        warnings.warn("simulate(): solver= is deprecated, use root_finder= (the Newton solver of each time element; "
                      "diffrax calls the time stepper `solver`).", DeprecationWarning, stacklevel=3)
        return _option("solver", solver, NewtonKrylov(), NewtonKrylov, "NewtonKrylov(...)")
    return _option("root_finder", root_finder, NewtonKrylov(), NewtonKrylov, "NewtonKrylov(...)")


def _option(name, value, default, cls, accepted):
    """`value` (or `default` for None), checked to be a `cls`."""
    if value is None:
        return default
    if not isinstance(value, cls):
        raise TypeError(f"{name} must be {accepted}, got {value!r}.")
    return value


def _check_order(t0, t1):
    """A clear error for ``t1 <= t0``, including calls in the old order ``(t_end, dt)``."""
    try:
        a, b = float(t0), float(t1)
    except (TypeError, ValueError):
        return  # None or a non-number: the step controller reports it
    if not b > a:
        raise ValueError(f"t1 = {t1!r} must be greater than t0 = {t0!r}. simulate's arguments are (scene, integrator, "
                         "t0, t1, dt0), as in diffrax.diffeqsolve; in jaxvisco 0.1 the third and fourth were (t_end, "
                         "dt): write simulate(scene, integrator, t1=..., dt0=...).")


def _initial(scene, initial_state, initial_velocity):
    """The initial state and the predictor's initial velocity (with a flag: given)."""
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
        return state0, device_array(np.zeros(np.shape(state0.p)), state0.p.dtype), device_array(False)
    v0 = device_array(initial_velocity, state0.p.dtype)
    if v0.shape != state0.p.shape:
        raise ValueError(f"initial_velocity must have shape {state0.p.shape}, got {v0.shape}.")
    check_finite("initial_velocity", v0)
    return state0, v0, device_array(True)


def _adaptive(scene, integrator, ctrl, t0, t1, dt0, saveat, event, adjoint, solver, max_steps, throw, state0, v0,
              use_v0):
    """`simulate` with error-controlled steps (`run_adaptive`)."""
    t0 = 0.0 if t0 is None else float(t0)
    if t1 is None or not (np.isfinite(float(t1)) and np.isfinite(t0) and float(t1) > t0):
        raise ValueError(f"an adaptive run needs finite t0 < t1, got t0 = {t0!r}, t1 = {t1!r}.")
    t1 = float(t1)
    if dt0 is None:
        h0 = 0.01 * (t1 - t0)
    elif isinstance(dt0, (int, float, np.integer, np.floating)) and not isinstance(dt0, bool) and 0 < float(dt0) < np.inf:
        h0 = float(dt0)
    else:
        raise ValueError(f"with a PIDController, dt0 is the first step to try (a positive number) or None "
                         f"(a hundredth of the run), got {dt0!r}; Schedule and StepTo fix the steps themselves.")
    cap = 4096 if max_steps is None else int(max_steps)
    if cap < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps!r}.")
    saveat.check(t0, t1)
    sol, _ = run_adaptive(scene, integrator, solver, ctrl, state0, device_array(t0), device_array(t1),
                          device_array(h0), cap, saveat.every, saveat.gamma,
                          None if saveat.ts is None else device_array(saveat.ts, float),
                          None if event is None else device_array(float(event.tol)), v0, use_v0,
                          plan(adjoint, cap, saveat.every, integrator, scene), multigrid_arguments(integrator, scene, solver),
                          save_reactions=saveat.reactions, save_diagnostics=saveat.diagnostics)
    if isinstance(sol.n_saved, jax.core.Tracer):
        return sol
    sol = sol.trimmed()
    if sol.status == "max_steps" and throw:
        t = float(sol.step_t[-1]) if len(sol.step_t) else t0
        raise SolverError(f"{integrator.name}: the adaptive run reached max_steps = {cap} accepted steps at t = {t:.6g} "
                          f"before t1 = {t1:g}; raise max_steps or loosen the tolerances (the state there is "
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
         derivative, multigrid=None, save_reactions=False, ts_out=None, save_diagnostics=True):
    """The time loop (`_loop`), compiled. `derivative`: how a derivative's loop records
    itself (`_differentiable.Plan`); `multigrid`: the hierarchy's index arrays
    (`multigrid_arguments`), arguments rather than constants of the program;
    `save_reactions`: frames with the supports' forces; `ts_out`: frames at these times
    (dense output) instead of every `save_every`-th step; `save_diagnostics`: frames with
    their energies and momenta."""
    return _loop(scene, state0, v0, scheme=scheme, solver=solver, t0=t0, hs=hs, te=te, n_steps=n_steps,
                 save_every=save_every, save_gamma=save_gamma, eq_tol=eq_tol, max_halvings=max_halvings,
                 use_v0=use_v0, derivative=derivative, multigrid=multigrid, save_reactions=save_reactions,
                 ts_out=ts_out, save_diagnostics=save_diagnostics)


@eqx.filter_custom_jvp
def _loop(scene, state0, v0, **kw):
    """The loop's `Solution`; differentiable in the scene, the initial state and the
    predictor's initial velocity along its accepted sub-steps (`_loop_jvp`)."""
    kw.pop("derivative")
    with multigrid_scope(kw["scheme"], scene, kw.pop("multigrid")):
        return _probe(scene, state0, v0, **kw)[0]


@_loop.def_jvp
def _loop_jvp(primals, tangents, *, derivative, multigrid, **kw):
    # The derivative reads the multigrid's index arrays as constants: JAX runs the rules
    # of custom derivatives inside it lazily, possibly after this rule returned, where
    # arguments passed in by a context would be stale.
    del multigrid
    sol, rec = _export.inline(_probe, *primals, plan=derivative, **kw)  # stored with the cache on
    return differentiate(sol, rec, primals, tangents, scheme=kw["scheme"], solver=kw["solver"], use_v0=kw["use_v0"],
                         save_gamma=kw["save_gamma"], save_reactions=kw["save_reactions"],
                         save_diagnostics=kw["save_diagnostics"], t0=kw["t0"], throw=derivative.throw)


def _probe(scene, state0, v0, *, scheme, solver, t0, hs, te, n_steps, save_every, save_gamma, eq_tol, max_halvings,
           use_v0, save_reactions, ts_out, save_diagnostics=True, plan=None):
    """The loop itself: a `Solution` and the `Record` of its accepted sub-steps (with a
    `Plan`: what a derivative needs of them)."""
    dense = ts_out is not None
    n_frames = ts_out.shape[0] if dense else 1 + -(-hs.shape[0] // save_every)
    v_state0 = scene.velocity(state0.p)  # one mass solve for H_0 and the predictor
    diag0 = scene.diagnostics(state0, v_state0)
    H0 = diag0["energy"]
    full = 2**max_halvings

    def advance(state, t, h, t_next, v, tan, rec, frames, n_saved, dissipated, work):
        """One nominal step from t to t_next = t + h, halved on failure (dyadic sub-steps;
        the sub-steps end at t + (pos / full) h, the last at t_next exactly). Dense output:
        the frames at requested times inside its sub-steps (`frames`, `n_saved`; the
        cumulative `dissipated` and `work` at its start)."""

        def cond(c):
            return (c["pos"] < full) & ~c["failed"]

        def body(c):
            hs_ = h / (2.0 ** c["level"])
            ctx = make_context(scene, c["state"], c["t"], hs_)
            r = solve_step(solver, scheme, scene, ctx, predictor(scheme, scene, ctx, c["v"]), c["tan"])
            new, D, W, v_end, ok = step_outcome(scheme, scene, ctx, r, dissipation_of_solve=True)
            pick = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(ok, x, y), a, b)  # noqa: E731
            pos = c["pos"] + jnp.where(ok, jnp.right_shift(full, c["level"]), 0)
            # Grow back once the position is aligned with the coarser grid.
            coarser = jnp.right_shift(full, jnp.maximum(c["level"] - 1, 0))
            level = jnp.where(ok, jnp.where((c["level"] > 0) & (pos % coarser == 0), c["level"] - 1, c["level"]),
                              c["level"] + 1)
            t_new = jnp.where(pos == full, t_next, t + pos * (h / full))
            rec = record_substep(c["rec"], c["t"], hs_, ok, U=r.U, state=c["state"], v=c["v"], formed=r.formed)
            reaction = step_reactions(scheme, scene, ctx, r.U) if save_reactions else None
            frames, n_saved = c["frames"], c["n_saved"]
            if dense:
                frames, rec, n_saved = jax.lax.cond(ok, lambda: write_dense_frames(
                    scheme, scene, frames, rec, n_saved, ts_out, ctx, r.U, t_new, dissipated + c["D"], D,
                    work + c["W"], W, lambda rec, j, s: record_dense_frame(rec, j, rec.n - 1, s), save_reactions,
                    save_diagnostics),
                    lambda: (frames, rec, n_saved))
            return dict(
                state=pick(new, c["state"]), t=t_new, frames=frames, n_saved=n_saved,
                reaction=c["reaction"] if reaction is None else pick(reaction, c["reaction"]),
                v=pick(v_end, c["v"]), tan=r.tangent, level=level, pos=pos,
                its=c["its"] + r.iterations, kits=c["kits"] + r.krylov_iterations, chord=c["chord"] + r.chord_iterations,
                rej=c["rej"] + jnp.where(ok, 0, 1), D=c["D"] + jnp.where(ok, D, 0.0),
                W=c["W"] + jnp.where(ok, W, 0.0), res=jnp.maximum(c["res"], jnp.where(ok, r.residual, 0.0)),
                failed=level > max_halvings, rec=rec,
            )

        init = dict(state=state, t=t, v=v, tan=tan, level=jnp.asarray(0), pos=jnp.asarray(0), rec=rec, frames=frames,
                    n_saved=n_saved, reaction=dict(reaction=jnp.zeros_like(state.x),
                                                   reaction_mean=jnp.zeros_like(state.x)) if save_reactions else None,
                    its=jnp.asarray(0), kits=jnp.asarray(0), chord=jnp.asarray(0), rej=jnp.asarray(0), D=jnp.asarray(0.0),
                    W=jnp.asarray(0.0), res=jnp.asarray(0.0), failed=jnp.asarray(False))
        return jax.lax.while_loop(cond, body, init)

    def cond(c):
        return (c["i"] < n_steps) & (c["status"] == RUNNING)

    def body(c):
        i = c["i"]
        a = advance(c["state"], c["t"], hs[i], te[i], c["v"], c["tan"], c["rec"], c["frames"], c["n_saved"],
                    c["dissipated"], c["work"])
        failed = a["failed"]
        dissipated, work = c["dissipated"] + a["D"], c["work"] + a["W"]
        status = jnp.where(failed, FAILED, RUNNING)
        if eq_tol is not None:
            at_rest = at_equilibrium(scene, a["state"], a["D"], eq_tol, H0, dissipated, work)
            status = jnp.where((status == RUNNING) & at_rest, EQUILIBRIUM, status)
        status = jnp.where((status == RUNNING) & (i == n_steps - 1), DONE, status)
        if dense:  # written inside the sub-steps
            save, frames, n_saved = jnp.asarray(False), a["frames"], a["n_saved"]
        else:
            save = (((i + 1) % save_every == 0) | (status != RUNNING)) & ~failed
            frames = jax.lax.cond(save, lambda f: write_frame(f, c["n_saved"], a["t"], a["state"], frame_diagnostics(
                scene, a["state"], save_diagnostics), dissipated, work, a["reaction"]), lambda f: f, a["frames"])
            n_saved = c["n_saved"] + save.astype(int)
        steps = write_step(c["steps"], i, step_t=a["t"], step_h=hs[i], newton_iterations=a["its"],
                           krylov_iterations=a["kits"], chord_iterations=a["chord"], residual=a["res"],
                           rejections=a["rej"])
        rec = a["rec"] if dense else record_frame(a["rec"], c["n_saved"], save)
        return dict(i=i + 1, state=a["state"], t=a["t"], v=a["v"], tan=a["tan"], frames=frames, steps=steps, rec=rec,
                    n_saved=n_saved, dissipated=dissipated, work=work, status=status,
                    n_done=c["n_done"] + (~failed).astype(int))

    frames, n_start = initial_frames(n_frames, t0, state0, diag0 if save_diagnostics else {}, save_gamma,
                                     first_reactions(scene, state0, t0) if save_reactions else None, ts_out)
    steps = step_buffers(hs.shape[0])
    v_init = jnp.where(use_v0, v0, v_state0)
    init = dict(i=jnp.asarray(0), state=state0, t=t0, v=v_init, tan=empty_tangent(scheme, scene, solver),
                frames=frames, steps=steps,
                rec=empty_record(record_size(hs.shape[0]), n_frames, t0.dtype, dense=dense, plan=plan, state0=state0,
                                 U_like=unknowns_like(scheme, scene, state0)),
                n_saved=n_start, dissipated=jnp.asarray(0.0),
                work=jnp.asarray(0.0), status=jnp.asarray(RUNNING), n_done=jnp.asarray(0))
    c = jax.lax.while_loop(cond, body, init)
    sol = Solution(
        **frame_fields(c["frames"]), n_saved=c["n_saved"], n_steps=c["n_done"],
        status_code=c["status"], integrator=scheme.describe(), end_velocity=c["v"], **c["steps"])
    return sol, c["rec"]
