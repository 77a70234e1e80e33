"""The error-controlled time loop: one compiled `lax.while_loop` over step attempts.

Each attempt solves one time element of the proposed size, estimates its error from the
integral defect of its time polynomial (`_estimate`), and is accepted (the state, the
energies, the step statistics and any requested output times inside the step are
written) or rejected (the step is retried smaller). The next size comes from the
controller (`PIDController`). Accepted steps are exactly the steps of the scheme: the
energy balance, D_n >= 0 and the momenta hold at every one as at a constant step.

The capacity (`max_steps`) fixes the shapes of the compiled program: a run that needs
more accepted steps ends with ``status == "max_steps"`` and everything up to there.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _export
from .._config import jit
from .._solver._newton import solve_step
from .._solver._tangent import empty_tangent, multigrid_scope
from .._time_element._estimate import body_strain, scaled_error, uses_end_velocities
from .._time_element._step import (
    end_state,
    make_context,
    predictor,
    step_outcome,
    unknowns_like,
)
from ._differentiable import (
    differentiate,
    empty_record,
    record_dense_frame,
    record_frame,
    record_substep,
)
from ._frames import (
    at_equilibrium,
    frame_diagnostics,
    first_reactions,
    initial_frames,
    step_reactions,
    frame_fields,
    step_buffers,
    write_dense_frames,
    write_frame,
    write_step,
)
from ._solution import DONE, EQUILIBRIUM, FAILED, MAX_STEPS, RUNNING, Solution


@jit(export=True)
def run_adaptive(scene, scheme, solver, ctrl, state0, t0, t1, h0, capacity, save_every, save_gamma, ts_out,
                 eq_tol, v0, use_v0, derivative, multigrid=None, save_reactions=False, save_diagnostics=True):
    """Integrate from `t0` to `t1` with error-controlled steps; at most `capacity`
    accepted steps. Frames: every `save_every`-th accepted step (and the last), or, if
    `ts_out` is an array, at those times (dense output); `save_reactions`: with the
    supports' forces; `save_diagnostics`: with their energies and momenta. Returns the `Solution` and the
    next step size the controller proposes. `derivative`: how a derivative's loop
    records itself (`_differentiable.Plan`); `multigrid`: the hierarchy's index arrays
    (`multigrid_arguments`), arguments rather than constants of the program."""
    return _loop(scene, state0, v0, scheme=scheme, solver=solver, ctrl=ctrl, t0=t0, t1=t1, h0=h0, capacity=capacity,
                 save_every=save_every, save_gamma=save_gamma, ts_out=ts_out, eq_tol=eq_tol, use_v0=use_v0,
                 derivative=derivative, multigrid=multigrid, save_reactions=save_reactions,
                 save_diagnostics=save_diagnostics)


@eqx.filter_custom_jvp
def _loop(scene, state0, v0, **kw):
    """The adaptive loop; differentiable in the scene, the initial state and the
    predictor's initial velocity along its accepted steps (their sizes are constants of
    the derivative), through the replay of `_differentiable`."""
    kw.pop("derivative")
    with multigrid_scope(kw["scheme"], scene, kw.pop("multigrid")):
        return _probe(scene, state0, v0, **kw)[:2]


@_loop.def_jvp
def _loop_jvp(primals, tangents, *, derivative, multigrid, **kw):
    del multigrid  # the derivative reads the hierarchy as constants (`_simulate._loop_jvp`)
    sol, h, rec = _export.inline(_probe, *primals, plan=derivative, **kw)  # stored with the cache on
    sol, t_sol = differentiate(sol, rec, primals, tangents, scheme=kw["scheme"], solver=kw["solver"],
                               use_v0=kw["use_v0"], save_gamma=kw["save_gamma"],
                               save_reactions=kw["save_reactions"], save_diagnostics=kw["save_diagnostics"],
                               t0=kw["t0"], throw=derivative.throw)
    return (sol, h), (t_sol, jnp.zeros_like(h))


def _probe(scene, state0, v0, *, scheme, solver, ctrl, t0, t1, h0, capacity, save_every, save_gamma, ts_out, eq_tol,
           use_v0, save_reactions, save_diagnostics=True, plan=None):
    """The loop itself: the `Solution`, the next step size and the `Record` of its
    accepted steps (with a `Plan`: what a derivative needs of them)."""
    order = ctrl.order(scheme.k)
    span = jnp.where(ctrl.span > 0, ctrl.span, t1 - t0)  # the run the tolerance is for
    v_state0 = scene.velocity(state0.p)  # one mass solve for H_0 and the predictor
    rates = uses_end_velocities(scheme, scene, state0)
    diag0 = scene.diagnostics(state0, v_state0)
    H0 = diag0["energy"]
    by_energy = ctrl.internal_variable == "energy" and state0.gamma is not None
    # the body's energy: the internal variable's tolerance and the run's horizon
    with_energy = state0.gamma is not None and (by_energy or ctrl.scope == "run")
    total_mass = scene.mass() if with_energy else None
    dense = ts_out is not None
    n_frames = ts_out.shape[0] if dense else 1 + -(-capacity // save_every)
    frames, n_start = initial_frames(n_frames, t0, state0, diag0 if save_diagnostics else {}, save_gamma,
                                     first_reactions(scene, state0, t0) if save_reactions else None, ts_out)
    end_eps = 1e-12 * jnp.maximum(jnp.abs(t1), jnp.abs(t0)) + 1e-300
    max_attempts = 16 * capacity

    def cond(c):
        return (c["status"] == RUNNING) & (c["attempts"] < max_attempts)

    def body(c):
        t, h = c["t"], c["h"]
        last = t + h >= t1 - end_eps
        h_try = jnp.where(last, t1 - t, h)
        t_next = jnp.where(last, t1, t + h_try)
        ctx = make_context(scene, c["state"], t, h_try)
        r = solve_step(solver, scheme, scene, ctx, predictor(scheme, scene, ctx, c["v"]), c["tan"])
        # M^{-1}p at the step's ends for the estimate (the end's also for the predictor's
        # velocity, and carried to the next step as its start's: one mass solve a step)
        new = end_state(scheme, scene, ctx, r.U)
        vm_end = scene.velocity(new.p, rtol=1e-10) if rates else c["vm"]
        new, D, W, v_end, ok = step_outcome(scheme, scene, ctx, r, dissipation_of_solve=True,
                                            velocity=vm_end if rates else None, new=new)
        dissipated, work = c["dissipated"] + D, c["work"] + W
        energy = None
        if with_energy:  # the energy of the step's end less that of its centre of mass's flight
            P = jnp.sum(new.p, axis=0)
            energy = H0 - dissipated + work - 0.5 * jnp.vdot(P, P) / total_mass
        err, strain = scaled_error(scheme, scene, ctx, r.U, new, ctrl.rtol, ctrl.atol,
                                   (c["vm"], vm_end) if rates else None, c["strain"], energy if by_energy else None)
        horizon = ctrl.horizon(span, h_try, t_next - t0, energy, dissipated)
        err = jnp.where(ok & jnp.isfinite(err), ctrl.over_run(err, h_try, horizon), jnp.inf)
        at_min = h_try <= ctrl.dtmin * (1.0 + 1e-12)
        accept = ok & ((err <= 1.0) | at_min)
        i = c["i"]
        rec = record_substep(c["rec"], t, h_try, accept, U=r.U, state=c["state"], v=c["v"], formed=r.formed)

        # Next step size; a new size divides the rest of the run into whole steps.
        grow = ctrl.accepted_factor(order, err, c["err1"], c["err2"], (t1 - t_next) / h_try)
        shrink = jnp.where(ok, ctrl.rejected_factor(order, err), 0.5)
        factor = jnp.where(accept, grow, shrink)
        h_new = jnp.clip(h_try * factor, ctrl.dtmin, ctrl.dtmax)
        h_new = jnp.where(factor == 1.0, h_new, ctrl.whole_steps(h_new, t1 - jnp.where(accept, t_next, t)))
        failed = ~accept & at_min

        status = jnp.where(failed, FAILED, RUNNING)
        if eq_tol is not None:
            status = jnp.where(accept & at_equilibrium(scene, new, D, eq_tol, H0, dissipated, work), EQUILIBRIUM,
                               status)
        status = jnp.where(accept & (status == RUNNING) & last, DONE, status)
        status = jnp.where(accept & (status == RUNNING) & (i + 1 >= capacity), MAX_STEPS, status)
        save = ((i + 1) % save_every == 0) | (status != RUNNING)
        if not dense:
            rec = record_frame(rec, c["n_saved"], accept & save)

        def on_accept(c):
            rec = c["rec"]
            reaction = step_reactions(scheme, scene, ctx, r.U) if save_reactions else None
            if dense:
                frames, rec, n_saved = write_dense_frames(
                    scheme, scene, c["frames"], rec, c["n_saved"], ts_out, ctx, r.U, t_next, c["dissipated"], D,
                    c["work"], W, lambda rec, j, s: record_dense_frame(rec, j, rec.n - 1, s), save_reactions,
                    save_diagnostics)
            else:
                frames = jax.lax.cond(
                    save, lambda f: write_frame(f, c["n_saved"], t_next, new,
                                                frame_diagnostics(scene, new, save_diagnostics), dissipated, work,
                                                reaction),
                    lambda f: f, c["frames"])
                n_saved = c["n_saved"] + save.astype(int)
            steps = write_step(c["steps"], i, step_t=t_next, step_h=h_try, newton_iterations=c["its"] + r.iterations,
                               krylov_iterations=c["kits"] + r.krylov_iterations,
                               chord_iterations=c["chord"] + r.chord_iterations, residual=r.residual,
                               rejections=c["rej"])
            return dict(i=i + 1, state=new, t=t_next, v=v_end, vm=vm_end, frames=frames, steps=steps, n_saved=n_saved,
                        dissipated=dissipated, work=work, err1=err, err2=c["err1"],
                        strain=jnp.maximum(c["strain"], strain), its=jnp.asarray(0), kits=jnp.asarray(0),
                        chord=jnp.asarray(0), rej=jnp.asarray(0), rec=rec)

        def on_reject(c):
            return dict(i=i, state=c["state"], t=t, v=c["v"], vm=c["vm"], frames=c["frames"], steps=c["steps"],
                        n_saved=c["n_saved"], dissipated=c["dissipated"], work=c["work"], err1=c["err1"],
                        err2=c["err2"], strain=c["strain"], its=c["its"] + r.iterations,
                        kits=c["kits"] + r.krylov_iterations, chord=c["chord"] + r.chord_iterations, rej=c["rej"] + 1,
                        rec=c["rec"])

        keys = ("i", "state", "t", "v", "vm", "frames", "steps", "n_saved", "dissipated", "work", "err1", "err2",
                "strain", "its", "kits", "chord", "rej")
        out = jax.lax.cond(accept, on_accept, on_reject, dict({k: c[k] for k in keys}, rec=rec))
        # A size kept after a step that a tangent of another size served (`reuse_band`):
        # the next step forms its own, which then serves the steps after it exactly.
        tan = r.tangent
        tan = eqx.tree_at(lambda a: a.stale, tan, tan.stale | (accept & (h_new == h_try) & (tan.h != h_try)))
        out.update(h=h_new, tan=tan, status=status, attempts=c["attempts"] + 1)
        return out

    # the largest strain of the run so far: the unit of atol on the internal variable
    strain0 = jnp.maximum(ctrl.strain_scale, body_strain(scene, state0.x) if state0.gamma is not None else 0.0)
    steps = step_buffers(capacity)
    one, zero = jnp.asarray(1.0), jnp.asarray(0)
    init = dict(i=zero, state=state0, t=jnp.asarray(t0, float), h=jnp.clip(h0, ctrl.dtmin, ctrl.dtmax),
                v=jnp.where(use_v0, v0, v_state0), vm=v_state0, tan=empty_tangent(scheme, scene, solver), frames=frames,
                steps=steps, n_saved=jnp.asarray(n_start), dissipated=jnp.asarray(0.0), work=jnp.asarray(0.0),
                status=jnp.asarray(RUNNING), err1=one, err2=one, strain=strain0, its=zero, kits=zero, chord=zero,
                rej=zero, attempts=zero, rec=empty_record(capacity, n_frames, jnp.result_type(float), dense=dense, plan=plan,
                                                 state0=state0, U_like=unknowns_like(scheme, scene, state0)))
    c = jax.lax.while_loop(cond, body, init)
    status = jnp.where(c["status"] == RUNNING, FAILED, c["status"])  # attempts exhausted
    return Solution(**frame_fields(c["frames"]), n_saved=c["n_saved"], n_steps=c["i"], status_code=status,
                    integrator=scheme.describe(), end_velocity=c["v"], strain_scale=c["strain"], **c["steps"]), \
        c["h"], c["rec"]
