"""Derivatives of the time loop: the run's accepted sub-steps, replayed.

Every `simulate` run is one `lax.while_loop` (`_simulate`): nominal steps, each halved
after a failed solve, and an early stop at equilibrium. JAX cannot reverse-differentiate
a `while_loop` whose trip count depends on the data, so the loop is a `custom_jvp`
(`_simulate._loop`): evaluated plainly (also under `jax.vmap`) it is just the loop;
differentiated, its rule

1. runs the loop, which also writes a `Record`: the start time and size of every
   accepted sub-step, and the sub-step whose end state each saved frame holds;
2. replays those sub-steps (`replay`) in nested `lax.scan`s, segments under
   `jax.checkpoint` -> sub-steps, each step differentiated implicitly
   (`solve_step_implicit`: one linear solve with the converged tangent; Newton is never
   differentiated), and returns the replay's tangents at the frames' sub-steps (dense
   output, `SaveAt(ts)`: of the sub-steps' time polynomials where the frames lie).

Step sizes are constants of the derivative (as in diffrax). The replay's primal equals
the loop's to the Newton tolerance; it starts every sub-step from a fresh tangent, so
its result does not depend on the segment length. Reverse mode stores the state at
segment boundaries (L = ceil(sqrt(K)) sub-steps per segment by default, K the record's
size: O(sqrt K) states) plus the replay's per-sub-step frame values (K of them), and
re-runs one segment at a time in the backward pass; forward mode (`jax.jvp`) stores
nothing but those values. A derivative costs the loop plus the replay twice (forward
and, in reverse mode, its recomputation) plus one transposed solve per sub-step.

The record holds `record_size(n)` sub-steps for a loop of n nominal slots; a run that
halves more often than that, or a sub-step that does not converge again when replayed,
raises an error at run time instead of returning a wrong derivative.
"""

import dataclasses
import math
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp

from .._fem._update import put_or_drop
from .._solver._implicit import materialize_zeros, solve_step_implicit
from .._solver._tangent import empty_tangent
from .._time_element._estimate import polynomial_state, step_polynomial
from .._time_element._step import make_context, predictor, step_outcome
from ._frames import frame_values


class Record(eqx.Module):
    """What the loop writes for its derivative: start time `t` and size `h` of each of
    its `n` accepted sub-steps, and per saved frame the index of the sub-step whose end
    state it holds (`frame_slot`, -1 for the initial state and unused frames). Dense
    output (`SaveAt(ts)`): `frame_s`, where in its sub-step each frame lies (a fraction
    of the sub-step, a constant of the derivative like the step sizes); None: at its end."""

    t: jax.Array
    h: jax.Array
    n: jax.Array
    frame_slot: jax.Array
    frame_s: Optional[jax.Array] = None


def record_size(n_slots):
    """Sub-steps a loop of `n_slots` nominal step slots records: room for a quarter more
    (at least 16) sub-steps from halvings."""
    return n_slots + max(16, n_slots // 4)


def empty_record(size, n_frames, dtype, dense=False):
    """A `Record` with room for `size` accepted sub-steps and `n_frames` frames (inside
    sub-steps if `dense`)."""
    return Record(t=jnp.zeros(size, dtype), h=jnp.ones(size, dtype), n=jnp.asarray(0),
                  frame_slot=jnp.full(n_frames, -1), frame_s=jnp.zeros(n_frames, dtype) if dense else None)


def record_substep(rec, t, h, ok):
    """`rec` with the sub-step from `t` of size `h` written at slot `rec.n`, which it
    takes if it was accepted (`ok`); a rejected attempt is overwritten by the next."""
    return Record(t=put_or_drop(rec.t, rec.n, t), h=put_or_drop(rec.h, rec.n, h),
                  n=rec.n + ok.astype(int), frame_slot=rec.frame_slot, frame_s=rec.frame_s)


def record_frame(rec, frame, save):
    """`rec` noting that frame `frame` holds the last accepted sub-step (when `save`)."""
    slot = jnp.where(save, rec.n - 1, rec.frame_slot[jnp.minimum(frame, rec.frame_slot.shape[0] - 1)])
    return eqx.tree_at(lambda r: r.frame_slot, rec, put_or_drop(rec.frame_slot, frame, slot))


def record_dense_frame(rec, frame, slot, s):
    """`rec` noting that frame `frame` lies at the fraction `s` of the sub-step `slot`."""
    return eqx.tree_at(lambda r: (r.frame_slot, r.frame_s), rec,
                       (put_or_drop(rec.frame_slot, frame, slot), put_or_drop(rec.frame_s, frame, s)))


def segment_length(n_slots, save_every=1, checkpoint_every=None):
    """Sub-steps per checkpointed segment of the replay: ceil(sqrt(n_slots)), or
    `checkpoint_every` frames' worth of sub-steps."""
    if checkpoint_every is None:
        return max(1, math.ceil(math.sqrt(n_slots)))
    return max(1, min(int(checkpoint_every) * int(save_every), n_slots))


def replay(scheme, solver, scene, state0, v0, use_v0, rec, save_gamma, segment):
    """Re-run the recorded sub-steps; differentiable in `scene`, `state0` and `v0`.

    Returns the initial frame's values, every frame's values (leading axis: the record's
    frames; the sub-step end `rec.frame_slot` holds, or with `rec.frame_s` the sub-step's
    time polynomial there), the end velocity and whether a replayed sub-step failed."""
    size = rec.t.shape[0]
    dense = rec.frame_s is not None
    seg = min(segment, size)
    # A backward sweep needs the factorizations of a whole segment at once (one per
    # sub-step for the derivative, a few more for Newton when the segment is re-run).
    solver = dataclasses.replace(solver, retain=max(solver.retain, 64 + 8 * seg))
    n_seg = -(-size // seg)
    pad = n_seg * seg - size
    ts = jnp.pad(rec.t, (0, pad)).reshape(n_seg, seg)
    hs = jnp.pad(rec.h, (0, pad), constant_values=1.0).reshape(n_seg, seg)
    idx = jnp.arange(n_seg * seg).reshape(n_seg, seg)
    fresh = empty_tangent(scheme, scene, solver)
    dtype = state0.p.dtype

    def attempt(c, t, h):
        ctx = make_context(scene, c["state"], t, h)
        r = solve_step_implicit(solver, scheme, scene, ctx, predictor(scheme, scene, ctx, c["v"]), fresh)
        new, D, W, v_end, ok = step_outcome(scheme, scene, ctx, r)
        out = dict(state=new, v=v_end, D=c["D"] + D, W=c["W"] + W, failed=c["failed"] | ~ok)
        # Dense output: the sub-step's polynomial and its energies, to be evaluated inside.
        poly = dict(poly=step_polynomial(scheme, scene, ctx, r.U), D0=c["D"], W0=c["W"], D=D, W=W) if dense else None
        return out, poly

    def substep(c, inp):
        t, h, k = inp

        def skip(c):
            if not dense:
                return c, None
            return c, jax.tree_util.tree_map(jnp.zeros_like, jax.eval_shape(lambda: attempt(c, t, h)[1]))

        c, poly = jax.lax.cond(k < rec.n, lambda c: attempt(c, t, h), skip, c)
        if dense:
            return c, poly
        return c, frame_values(c["state"], scene.diagnostics(c["state"]), c["D"], c["W"], save_gamma)

    @jax.checkpoint
    def run_segment(c, inp):
        return jax.lax.scan(substep, c, inp)

    v_state0 = scene.velocity(state0.p)
    v_init = jnp.where(use_v0, v0, v_state0)
    init = dict(state=state0, v=v_init, D=jnp.zeros((), dtype), W=jnp.zeros((), dtype), failed=jnp.asarray(False))
    c, ys = jax.lax.scan(run_segment, init, (ts, hs, idx))
    ys = jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:])[:size], ys)
    zero = jnp.zeros((), dtype)
    first = frame_values(state0, scene.diagnostics(state0, v_state0), zero, zero, save_gamma)
    slot = jnp.clip(rec.frame_slot, 0, size - 1)
    if dense:
        def at(k, s):
            y = jax.tree_util.tree_map(lambda a: a[k], ys)
            st = polynomial_state(scheme, y["poly"], s)
            return frame_values(st, scene.diagnostics(st), y["D0"] + s * y["D"], y["W0"] + s * y["W"], save_gamma)

        frames = jax.vmap(at)(slot, rec.frame_s)
    else:
        frames = jax.tree_util.tree_map(lambda y: y[slot], ys)
    return first, frames, c["v"], c["failed"]


def frame_tangents(rec, n_saved, first, frames):
    """The frames' tangents from the replay's: the initial state's for frames before the
    first sub-step (`rec.frame_slot` -1), zero for unused frames."""
    j = jnp.arange(rec.frame_slot.shape[0])

    def pick(f0, g):
        shape = (-1,) + (1,) * (g.ndim - 1)
        g = jnp.where((rec.frame_slot < 0).reshape(shape), f0[None], g)
        return jnp.where((j < n_saved).reshape(shape), g, 0.0)

    return {k: pick(first[k], frames[k]) for k in frames}


def check_replay(rec, failed, value):
    """`value`, or a run-time error where the derivative would be wrong."""
    value = eqx.error_if(value, rec.n > rec.t.shape[0],
                         "jaxvisco: the run halved its steps into more sub-steps than its derivative records; "
                         "pass a larger max_steps (the record holds max_steps + max(16, max_steps // 4) sub-steps).")
    return eqx.error_if(value, failed,
                        "jaxvisco: a sub-step that converged in the run did not converge when it was replayed for "
                        "the derivative; tighten or loosen NewtonKrylov's tolerances, or use smaller steps.")


def differentiate(sol, rec, primals, tangents, *, scheme, solver, use_v0, save_gamma, segment):
    """The tangent of a loop's `Solution` `sol` (the rule of a `custom_jvp` around a time
    loop that wrote `rec`): the replay's tangents at the frames and the end velocity;
    `primals`/`tangents`: the scene, the initial state and the predictor's initial
    velocity. Returns `sol` with the replay's run-time checks attached, and its tangent."""

    def fn(scene, state0, v0):
        return replay(scheme, solver, scene, state0, v0, use_v0, rec, save_gamma, segment)

    out, d_out = eqx.filter_jvp(fn, primals, tangents)
    d_first, d_frames, d_v = materialize_zeros(d_out[:3], out[:3])
    # The checks sit on the primal output, which every derivative evaluates.
    sol = check_replay(rec, out[3], sol)
    frames = frame_tangents(rec, sol.n_saved, d_first, d_frames)
    t_sol = jax.tree_util.tree_map(lambda _: None, sol)
    names = [k for k in frames if getattr(sol, k) is not None]
    t_sol = eqx.tree_at(lambda s: [getattr(s, k) for k in names] + [s.end_velocity], t_sol,
                        [frames[k] for k in names] + [d_v], is_leaf=lambda x: x is None)
    return sol, t_sol
