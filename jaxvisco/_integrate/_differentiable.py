"""Derivatives of the time loop: a discrete adjoint along its accepted sub-steps.

Every `simulate` run is one `lax.while_loop` (`_simulate`, `_adaptive`): nominal steps,
each halved after a failed solve, an early stop at equilibrium, or error-controlled
steps. JAX cannot reverse-differentiate a `while_loop` whose trip count depends on the
data, so the loop is a `custom_jvp`: evaluated plainly (also under `jax.vmap`) it is just
the loop; differentiated, its rule

1. runs the loop, which also writes a `Record`: the start time and size of every
   accepted sub-step and, where the memory budget allows (`RecursiveCheckpointAdjoint`),
   its converged unknowns U and start positions and momenta (*store* plan); otherwise
   the state at the start of every L-th sub-step (*checkpoint* plan);
2. returns the tangent of its frames as one linear map of the input tangents (`_sweep`),
   whose transpose is written out by hand (`_adjoint_sweep`): JAX calls the first for
   `jax.jvp`/`jax.jacfwd` and the second for `jax.grad`/`jax.vjp` (one primitive,
   `_sweep_p`, carries the pair).

Each sub-step j is the map $(\\theta, s_j, U_j) \\mapsto (R, s_{j+1}, D_j, W_j)$
(`_step_map`: residual, end state, dissipation, external work) with the constraint
$R(U_j) = 0$. Its tangent is one linear solve $A\\,dU = -(R_\\theta d\\theta + R_s ds)$
with $A = \\partial R/\\partial U$ and its adjoint one transposed solve $A^T \\mu =
\\bar U$; neither re-solves the step (no Newton) nor differentiates Newton. Both
solves are right-preconditioned GMRES to `KRYLOV_RTOL` with a condensed tangent that
the sweep forms where the loop formed one (`Record.formed`), at least every `EPOCH`
sub-steps and where h leaves the tangent's band, carried along the body's rotation as
the loop's chord iterations carry theirs: one formation serves many sub-steps, a
sub-step costs a linearization of its map and a few Krylov vectors. The checkpoint plan
re-solves each segment's sub-steps from its stored state (Newton) into a buffer before
sweeping it: memory O(segments + L) instead of O(K), one more forward run of work.

Step sizes are constants of the derivative (as in diffrax). Second derivatives are not
supported (the sweeps are not differentiated again).
"""

import dataclasses
import math
from typing import Optional

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from .. import _export
from .._export import register_type
from .._fem._krylov import gmres
from .._fem._tensor import vec_to_sym
from .._fem._update import put, put_or_drop
from .._scene import State
from .._solver._newton import _residual as newton_residual
from .._solver._newton import force_impulse, solve_step
from .._solver._tangent import body_rotation, empty_tangent, form_tangent, schur_solve
from .._time_element._estimate import polynomial_state, step_polynomial
from .._time_element._step import (
    Unknowns,
    end_state,
    external_work,
    make_context,
    next_velocity,
    predictor,
    step_dissipation,
    step_outcome,
)
from ._frames import first_reactions, frame_diagnostics, frame_values, step_reactions
from ._solution import FRAME_FIELDS

# Relative residual of the sweeps' linear solves (2-norm of the scaled system) and their
# Krylov vectors at most (restarted every `KRYLOV_RESTART`).
KRYLOV_RTOL = 1e-12
KRYLOV_MAX_STEPS = 120
KRYLOV_RESTART = 30
# Sub-steps one formed tangent serves at most in a sweep, and the step-size band it
# serves (as `NewtonKrylov.reuse_band`).
EPOCH = 16
BAND = 0.25


@dataclasses.dataclass(frozen=True)
class Plan:
    """How a loop records itself for its derivative (static): ``store`` every sub-step's
    unknowns and start state, or the state at the start of every `segment`-th sub-step
    (``checkpoint``); whether a derivative it cannot compute raises (`throw`)."""

    store: bool
    segment: int = 0
    throw: bool = False


@register_type  # a stored derivative program returns one (`_export.inline`)
class Record(eqx.Module):
    """What the loop writes for its derivative: start time `t` and size `h` of each of
    its `n` accepted sub-steps, and per saved frame the index of the sub-step whose end
    state it holds (`frame_slot`, -1 for the initial state and unused frames). Dense
    output (`SaveAt(ts)`): `frame_s`, where in its sub-step each frame lies (a fraction
    of the sub-step, a constant of the derivative like the step sizes); None: at its end.
    A derivative's loop also writes `formed` (the sub-step formed a tangent) and, by its
    `Plan`, the unknowns `U` with the start positions `x` and momenta `p` of every
    sub-step, or the states `ck` (x, p, gamma, predictor velocity v) at segment starts."""

    t: jax.Array
    h: jax.Array
    n: jax.Array
    frame_slot: jax.Array
    frame_s: Optional[jax.Array] = None
    formed: Optional[jax.Array] = None
    U: Optional[Unknowns] = None
    x: Optional[jax.Array] = None
    p: Optional[jax.Array] = None
    ck: Optional[dict] = None
    segment: int = eqx.field(static=True, default=0)


def record_size(n_slots):
    """Sub-steps a loop of `n_slots` nominal step slots records: room for a quarter more
    (at least 16) sub-steps from halvings."""
    return n_slots + max(16, n_slots // 4)


def step_bytes(scheme, scene):
    """Bytes the store plan keeps per sub-step: the unknowns and the start x, p."""
    disc, k, d = scene.disc, scheme.k, scene.dim
    n = k * disc.n_nodes * d + 2 * disc.n_nodes * d
    if scene.has_internal_variable:
        n += k * disc.n_cells * disc.n_qp * 6
    return 8 * n


def state_bytes(scene):
    """Bytes of one checkpointed state (x, p, gamma, the predictor's velocity)."""
    disc, d = scene.disc, scene.dim
    n = 3 * disc.n_nodes * d + (9 * disc.n_cells * disc.n_qp if scene.has_internal_variable else 0)
    return 8 * n


def plan(adjoint, n_record, save_every, scheme, scene):
    """The `Plan` of a loop that records `n_record` sub-steps, by `adjoint`
    (`RecursiveCheckpointAdjoint`): every sub-step where that fits `max_bytes` (and no
    number of checkpoints is asked for); else checkpoints every L sub-steps, L chosen to
    need the least memory (a state per checkpoint and a buffer of L sub-steps:
    L = sqrt(K * state / step)); `checkpoints=c`: L = ceil(K / c)."""
    per_step, per_state = step_bytes(scheme, scene), state_bytes(scene)
    throw = bool(adjoint.throw)
    if adjoint.checkpoint_every is not None:  # jaxvisco 0.2's frames per segment
        return Plan(False, max(1, min(int(adjoint.checkpoint_every) * int(save_every), n_record)), throw)
    ck = adjoint.checkpoints
    if ck is None:
        if n_record * per_step <= adjoint.max_bytes:
            return Plan(True, 0, throw)
        seg = max(1, math.ceil(math.sqrt(n_record * per_state / per_step)))
    elif ck >= n_record:
        return Plan(True, 0, throw)
    else:
        seg = max(1, math.ceil(n_record / ck))
    return Plan(False, min(seg, n_record), throw)


def plan_bytes(p, n_record, scheme, scene):
    """Bytes a `Plan` stores for a record of `n_record` sub-steps (the step buffers or the
    checkpoints, and a segment's buffer)."""
    if p.store:
        return n_record * step_bytes(scheme, scene)
    return -(-n_record // p.segment) * state_bytes(scene) + p.segment * step_bytes(scheme, scene)


def empty_record(size, n_frames, dtype, dense=False, plan=None, state0=None, U_like=None):
    """A `Record` with room for `size` accepted sub-steps and `n_frames` frames (inside
    sub-steps if `dense`); with a `Plan`, the buffers it records into (shaped like
    `state0` and the unknowns `U_like`)."""
    rec = Record(t=jnp.zeros(size, dtype), h=jnp.ones(size, dtype), n=jnp.asarray(0),
                 frame_slot=jnp.full(n_frames, -1), frame_s=jnp.zeros(n_frames, dtype) if dense else None)
    if plan is None:
        return rec
    zeros = lambda n, a: jnp.zeros((n,) + a.shape, a.dtype)  # noqa: E731
    extra = dict(formed=jnp.zeros(size, bool))
    if plan.store:
        extra.update(U=jax.tree_util.tree_map(lambda a: zeros(size, a), U_like), x=zeros(size, state0.x),
                     p=zeros(size, state0.p))
    else:
        n_seg = -(-size // plan.segment)
        extra.update(ck=dict(x=zeros(n_seg, state0.x), p=zeros(n_seg, state0.p), v=zeros(n_seg, state0.p),
                             gamma=None if state0.gamma is None else zeros(n_seg, state0.gamma)),
                     segment=plan.segment)
    return dataclasses.replace(rec, **extra)


def record_substep(rec, t, h, ok, U=None, state=None, v=None, formed=None):
    """`rec` with the sub-step from `t` of size `h` written at slot `rec.n`, which it
    takes if it was accepted (`ok`); a rejected attempt is overwritten by the next. A
    derivative's loop passes the sub-step's unknowns `U`, start `state`, predictor
    velocity `v` and whether it `formed` a tangent."""
    slot = rec.n
    out = dict(t=put_or_drop(rec.t, slot, t), h=put_or_drop(rec.h, slot, h), n=rec.n + ok.astype(int))
    if rec.formed is not None:
        out["formed"] = put_or_drop(rec.formed, slot, formed)
    if rec.U is not None:
        out.update(U=jax.tree_util.tree_map(lambda b, u: put_or_drop(b, slot, u), rec.U, U),
                   x=put_or_drop(rec.x, slot, state.x), p=put_or_drop(rec.p, slot, state.p))
    if rec.ck is not None:
        seg = jnp.where(slot % rec.segment == 0, slot // rec.segment, -1)
        vals = dict(x=state.x, p=state.p, v=v, gamma=state.gamma)
        out["ck"] = {k: None if b is None else put_or_drop(b, seg, vals[k]) for k, b in rec.ck.items()}
    return dataclasses.replace(rec, **out)


def record_frame(rec, frame, save):
    """`rec` noting that frame `frame` holds the last accepted sub-step (when `save`)."""
    slot = jnp.where(save, rec.n - 1, rec.frame_slot[jnp.minimum(frame, rec.frame_slot.shape[0] - 1)])
    return eqx.tree_at(lambda r: r.frame_slot, rec, put_or_drop(rec.frame_slot, frame, slot))


def record_dense_frame(rec, frame, slot, s):
    """`rec` noting that frame `frame` lies at the fraction `s` of the sub-step `slot`."""
    return eqx.tree_at(lambda r: (r.frame_slot, r.frame_s), rec,
                       (put_or_drop(rec.frame_slot, frame, slot), put_or_drop(rec.frame_s, frame, s)))


# --- the sub-step as a differentiable map -------------------------------------------------
def _residual(scheme, scene, state, t, h, U):
    """(R, D_j): the sub-step's residual (its constraint: R = 0) and dissipation, eG's
    from the same evaluation of its point kernels. The residual is Newton's program
    (`_newton._residual`): traced once for the loops and both sweeps."""
    ctx = make_context(scene, state, t, h)
    R, D = newton_residual(scheme, scene, ctx, U)
    return R, step_dissipation(scheme, scene, ctx, U) if D is None else D


def _outputs(scheme, scene, state, t, h, U):
    """(s_{j+1}, W_j): the end state and the external work of the sub-step."""
    ctx = make_context(scene, state, t, h)
    return end_state(scheme, scene, ctx, U), external_work(scheme, scene, ctx, U)


def _first_frame(sw, scene, state):
    """The frame of the initial state (every frame before the first sub-step)."""
    zero = jnp.zeros((), state.p.dtype)
    reaction = first_reactions(scene, state, sw.t0) if sw.save_reactions else None
    return frame_values(state, frame_diagnostics(scene, state, sw.save_diagnostics), zero, zero, sw.save_gamma,
                        reaction)


def _frame(sw, scene, state, t, h, U, D, W, D0, W0, s):
    """A frame that sub-step j writes, as a function of (theta, s_j, U_j, D_j, W_j and the
    cumulative D, W before it): its end state (`s` None), or (dense output) its time
    polynomial at the fraction `s`, with dissipation and work linear in time within it,
    and the supports' mean force over it."""
    ctx = make_context(scene, state, t, h)
    if s is None:
        st, s = end_state(sw.scheme, scene, ctx, U), 1.0
    else:
        st = polynomial_state(sw.scheme, step_polynomial(sw.scheme, scene, ctx, U), s)
    reaction = step_reactions(sw.scheme, scene, ctx, U, s) if sw.save_reactions else None
    return frame_values(st, frame_diagnostics(scene, st, sw.save_diagnostics), D0 + s * D, W0 + s * W,
                        sw.save_gamma, reaction)


def _end_velocity(scheme, scene, state, t, h, U):
    ctx = make_context(scene, state, t, h)
    return next_velocity(scheme, scene, ctx, U, end_state(scheme, scene, ctx, U))


def _add(a, b):
    return jax.tree_util.tree_map(lambda u, v: u + v, a, b)


def _zeros(tree):
    return jax.tree_util.tree_map(jnp.zeros_like, tree)


def _scale_x(u, factor):
    """`u` (unknowns) with its momentum rows times `factor`."""
    return eqx.tree_at(lambda r: r.x, u, u.x * factor)


def _where_live(mask, tree):
    return jax.tree_util.tree_map(lambda b: jnp.where(mask.reshape((-1,) + (1,) * (b.ndim - 1)), b, 0.0), tree)


class _Split:
    """The leaves of a primal pytree that its tangent differentiates (`theta`, their
    tangents `tangent`), and the primal rebuilt from new values of them (`build`)."""

    def __init__(self, primal, tangent=None, where=None):
        leaves, self.treedef = jax.tree_util.tree_flatten(primal)
        t = [None] * len(leaves) if tangent is None else self.treedef.flatten_up_to(tangent)
        self.leaves = leaves
        self.where = [i for i, ti in enumerate(t) if ti is not None] if where is None else list(where)
        self.theta = [leaves[i] for i in self.where]
        self.tangent = [t[i] for i in self.where]

    def build(self, theta):
        leaves = list(self.leaves)
        for i, v in zip(self.where, theta):
            leaves[i] = v
        return self.treedef.unflatten(leaves)


@dataclasses.dataclass
class _Sweep:
    """What both sweeps read: the record, the primal inputs, the loop's settings."""

    rec: Record
    split: _Split
    state0: State
    v0: jax.Array
    use_v0: jax.Array
    n_saved: jax.Array
    scheme: object
    solver: object
    save_gamma: bool
    save_reactions: bool
    save_diagnostics: bool
    t0: jax.Array
    throw: bool

    @property
    def scene(self):
        return self.split.build(self.split.theta)


def _epoch_starts(rec):
    """Where a forward sweep forms a tangent: where the loop formed one, every `EPOCH`
    sub-steps, and where h leaves the `BAND` about the tangent's h."""
    def body(c, inp):
        j, formed, h = inp
        last, h_t = c
        new = (j == 0) | formed | (j - last >= EPOCH) | (jnp.abs(h / h_t - 1.0) > BAND)
        return (jnp.where(new, j, last), jnp.where(new, h, h_t)), new

    return jax.lax.scan(body, (jnp.asarray(0), rec.h[0]), (jnp.arange(rec.t.shape[0]), rec.formed, rec.h))[1]


def _buffers(sw, g):
    """The sub-steps of segment `g`: buffers of their unknowns and start x, p (the store
    plan: the record's own, one segment), the internal variable at the segment start, the
    first sub-step and whether a re-solve failed. The checkpoint plan re-solves the
    segment's sub-steps from its stored state (Newton, as the loop did)."""
    rec, scheme, solver, scene = sw.rec, sw.scheme, sw.solver, sw.scene
    if rec.U is not None:
        return dict(U=rec.U, x=rec.x, p=rec.p), sw.state0.gamma, 0, jnp.asarray(False)
    L = rec.segment
    ck = jax.tree_util.tree_map(lambda a: a[g], rec.ck)
    state = State(ck["x"], ck["p"], ck["gamma"])
    U_like = predictor(scheme, scene, make_context(scene, state, rec.t[0], rec.h[0]), ck["v"])

    def one(c, i):
        j = g * L + i

        def solve(c):
            ctx = make_context(scene, c["state"], rec.t[j], rec.h[j])
            r = solve_step(solver, scheme, scene, ctx, predictor(scheme, scene, ctx, c["v"]), c["tan"])
            new, _, _, v_end, ok = step_outcome(scheme, scene, ctx, r, dissipation_of_solve=True)
            return dict(state=new, v=v_end, tan=r.tangent, failed=c["failed"] | ~ok), r.U

        out, U = jax.lax.cond(j < rec.n, solve, lambda c: (c, U_like), c)
        return out, dict(U=U, x=c["state"].x, p=c["state"].p)

    init = dict(state=state, v=ck["v"], tan=empty_tangent(scheme, scene, solver), failed=jnp.asarray(False))
    c, bufs = jax.lax.scan(one, init, jnp.arange(L))
    return bufs, ck["gamma"], g * L, c["failed"]


def _segments(rec):
    """(segments, sub-steps each): the store plan sweeps the record as one segment."""
    size = rec.t.shape[0]
    if rec.U is not None:
        return 1, size
    return -(-size // rec.segment), rec.segment


def _state_at(bufs, j, j0, gamma0):
    """The start state and unknowns of sub-step `j` from buffers that start at `j0` (the
    internal variable from the previous sub-step's unknowns, `gamma0` at `j0`)."""
    i = j - j0
    gamma = None
    if gamma0 is not None:
        gamma = jnp.where(i == 0, gamma0, vec_to_sym(bufs["U"].g[jnp.maximum(i - 1, 0), -1]))
    return State(bufs["x"][i], bufs["p"][i], gamma), jax.tree_util.tree_map(lambda a: a[i], bufs["U"])


def _form(sw, ctx, U):
    """The condensed tangent at a converged sub-step (the multigrid in float64: GMRES
    needs a fixed linear preconditioner)."""
    lin, scene = sw.solver.linear_solver, sw.scene
    return form_tangent(sw.scheme, scene, ctx, U, body_rotation(scene, ctx.state.x), sw.solver.retain,
                        lin.block_solver(scene), np.float64)


def _momentum_scale(scene, ctx):
    """The scale of a sub-step's momentum rows in the sweeps' linear solves: Newton's
    (`_newton._scale`) without the predictor's residual, which the record does not hold
    (the start momenta, the force impulse, the floor tied to the positions)."""
    mx = jnp.max(jnp.abs(scene.disc.mass_matvec(ctx.state.x, scene.density))) / ctx.h
    return jax.lax.stop_gradient(jnp.maximum(jnp.maximum(jnp.max(jnp.abs(ctx.state.p)), force_impulse(ctx, scene)),
                                             jnp.maximum(1e-8 * mx, 1e-300)))


def _no_tangent(sw):
    """A stale tangent shaped as `_form`'s (float64 multigrid operators)."""
    f64 = lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a  # noqa: E731
    return jax.tree_util.tree_map(f64, empty_tangent(sw.scheme, sw.scene, sw.solver))


def _krylov(matvec, precond, b):
    return gmres(matvec, precond, b, KRYLOV_RTOL, KRYLOV_MAX_STEPS, restart=KRYLOV_RESTART)


_RECORD = ("jaxvisco: the run halved its steps into more sub-steps than its derivative records; pass a larger "
           "max_steps (the record holds max_steps + max(16, max_steps // 4) sub-steps).")
_KRYLOV = ("jaxvisco: a linear solve of the derivative did not converge (GMRES with the condensed tangent of a nearby "
           "sub-step); the derivative would be inaccurate. Use smaller steps or NewtonKrylov(linear_solver=Direct()).")
_RESOLVE = ("jaxvisco: a sub-step that converged in the run did not converge when it was re-solved for the derivative "
            "(checkpointed segments); use smaller steps, other NewtonKrylov tolerances, or give "
            "RecursiveCheckpointAdjoint a larger max_bytes (no re-solves).")


def _refuse(value, bad, message, throw):
    """`value`, or where `bad`: a run-time error with `message` (`throw`; the program then
    holds a host callback, which JAX's persistent cache does not store) or NaN in every
    entry of `value` (no callback)."""
    if throw:
        return eqx.error_if(value, bad, message)
    return jax.tree_util.tree_map(lambda v: jnp.where(bad, jnp.nan, v), value)


def check_record(rec, value, throw=True):
    """`value`, refused (`_refuse`) where the loop halved into more sub-steps than `rec`
    holds (its derivative would be wrong)."""
    return _refuse(value, rec.n > rec.t.shape[0], _RECORD, throw)


def check_sweep(rec, value, worst, failed, throw=True):
    """`value` (what a sweep computed), refused (`_refuse`) where the record overflowed
    (`check_record`), a linear solve did not converge (its relative residual `worst`) or
    a checkpointed sub-step did not converge again (`failed`)."""
    value = check_record(rec, value, throw)
    value = _refuse(value, worst > 1e3 * KRYLOV_RTOL, _KRYLOV, throw)
    return _refuse(value, failed, _RESOLVE, throw)


def _sweep(sw, a):
    """The tangents of the frames and of the end velocity, forward through the sub-steps
    (one linear solve each). `a`: the tangents of the differentiated scene leaves, of the
    initial state and of the predictor's initial velocity."""
    d_theta, d_state0, d_v0 = a
    rec, scheme, split = sw.rec, sw.scheme, sw.split
    theta, scene = split.theta, sw.scene
    dense = rec.frame_s is not None
    n_frames = rec.frame_slot.shape[0]
    live = jnp.arange(n_frames) < sw.n_saved
    zero = jnp.zeros((), sw.state0.p.dtype)
    ds0 = State(*(None if p is None else (jnp.zeros_like(p) if t is None else t)
                  for t, p in zip((d_state0.x, d_state0.p, d_state0.gamma), (sw.state0.x, sw.state0.p, sw.state0.gamma))))
    d_first = jax.jvp(lambda th, s: _first_frame(sw, split.build(th), s), (theta, sw.state0), (d_theta, ds0))[1]
    first = (rec.frame_slot < 0) & live
    frames = jax.tree_util.tree_map(
        lambda v: jnp.where(first.reshape((-1,) + (1,) * v.ndim), v[None], jnp.zeros((n_frames,) + v.shape, v.dtype)),
        d_first)
    dv_state0 = jax.jvp(lambda th, s: split.build(th).velocity(s.p), (theta, sw.state0), (d_theta, ds0))[1]
    dv0 = jnp.zeros_like(sw.v0) if d_v0 is None else d_v0
    starts = _epoch_starts(rec)

    def step(j, c, bufs, j0, gamma0):
        state, U = _state_at(bufs, j, j0, gamma0)
        t, h = rec.t[j], rec.h[j]
        ctx = make_context(scene, state, t, h)
        (R, _), lin_U = jax.linearize(lambda u: _residual(scheme, scene, state, t, h, u), U)
        rhs, rhs_D = jax.jvp(lambda th, s: _residual(scheme, split.build(th), s, t, h, U), (theta, state),
                             (d_theta, c["ds"]))[1]
        sx = _momentum_scale(scene, ctx)
        tan = jax.lax.cond(starts[j], lambda: _form(sw, ctx, U), lambda: c["tan"])
        rotation = body_rotation(scene, state.x)
        # (S A) dU = -S rhs, S = 1/sx on the momentum rows; right preconditioner P^{-1} S^{-1}
        dU, _, res = _krylov(lambda v: _scale_x(lin_U(v)[0], 1.0 / sx),
                             lambda r: schur_solve(scheme, scene, ctx, tan, _scale_x(r, sx), rotation),
                             jax.tree_util.tree_map(jnp.negative, _scale_x(rhs, 1.0 / sx)))
        dD = rhs_D + lin_U(dU)[1]  # D's tangent, linear in (d_theta, ds, dU)
        _, (d_new, dW) = jax.jvp(lambda th, s, u: _outputs(scheme, split.build(th), s, t, h, u),
                                        (theta, state, U), (d_theta, c["ds"], dU))
        dDc, dWc = c["dD"] + dD, c["dW"] + dW
        dv = jax.lax.cond(j == rec.n - 1,
                          lambda: jax.jvp(lambda th, s, u: _end_velocity(scheme, split.build(th), s, t, h, u),
                                          (theta, state, U), (d_theta, c["ds"], dU))[1], lambda: c["dv"])

        def cond(q):
            f = q[0]
            return (f < sw.n_saved) & (rec.frame_slot[jnp.minimum(f, n_frames - 1)] == j)

        def body(q):
            f, fb = q
            s_ = rec.frame_s[f] if dense else None
            val = jax.jvp(lambda th, st, u, d, w, dc, wc: _frame(sw, split.build(th), st, t, h, u, d, w, dc, wc, s_),
                          (theta, state, U, zero, zero, zero, zero),
                          (d_theta, c["ds"], dU, dD, dW, c["dD"], c["dW"]))[1]
            return f + 1, jax.tree_util.tree_map(lambda b_, v: put(b_, f, v), fb, val)

        f, fb = jax.lax.while_loop(cond, body, (c["f"], c["frames"]))
        return dict(c, ds=d_new, dD=dDc, dW=dWc, tan=tan, dv=dv, f=f, frames=fb, worst=jnp.maximum(c["worst"], res))

    def segment(c, g):
        bufs, gamma0, j0, failed = _buffers(sw, g)
        hi = jnp.minimum(j0 + bufs["x"].shape[0], rec.n)
        c = jax.lax.fori_loop(j0, hi, lambda j, c: step(j, c, bufs, j0, gamma0), c)
        return dict(c, failed=c["failed"] | failed), None

    init = dict(ds=ds0, dD=zero, dW=zero, tan=_no_tangent(sw),
                dv=jnp.where(sw.use_v0, dv0, dv_state0), f=jnp.sum(first), frames=frames, worst=zero,
                failed=jnp.asarray(False))
    c, _ = jax.lax.scan(segment, init, jnp.arange(_segments(rec)[0]))
    return check_sweep(rec, (_where_live(live, c["frames"]), c["dv"]), c["worst"], c["failed"], sw.throw)


def _adjoint_sweep(sw, ct):
    """The transpose of `_sweep`: the cotangents of its inputs from those of the frames and
    of the end velocity, backward through the sub-steps (one transposed solve each)."""
    ct_frames, ct_v = ct
    rec, scheme, split = sw.rec, sw.scheme, sw.split
    theta, scene = split.theta, sw.scene
    dense = rec.frame_s is not None
    n_frames = rec.frame_slot.shape[0]
    live = jnp.arange(n_frames) < sw.n_saved
    ct_frames = _where_live(live, ct_frames)
    zero = jnp.zeros((), sw.state0.p.dtype)
    # reversed, a tangent is formed at the last sub-step of each forward epoch
    starts = _epoch_starts(rec)
    ends = jnp.concatenate([starts[1:], jnp.ones(1, bool)]) | (jnp.arange(rec.t.shape[0]) == rec.n - 1)

    def step(j, c, bufs, j0, gamma0):
        state, U = _state_at(bufs, j, j0, gamma0)
        t, h = rec.t[j], rec.h[j]
        ctx = make_context(scene, state, t, h)
        (R, _), r_vjp = jax.vjp(lambda th, s, u: _residual(scheme, split.build(th), s, t, h, u), theta, state, U)
        _, o_vjp = jax.vjp(lambda th, s, u: _outputs(scheme, split.build(th), s, t, h, u), theta, state, U)
        tan = jax.lax.cond(ends[j], lambda: _form(sw, ctx, U), lambda: c["tan"])
        lam_s, lam_D, lam_W = c["lam_s"], c["lam_D"], c["lam_W"]
        acc = (_zeros(theta), _zeros(state), _zeros(U))  # cotangents of (theta, s_j, U_j) besides the step's own

        def velocity(acc):
            _, v_vjp = jax.vjp(lambda th, s, u: _end_velocity(scheme, split.build(th), s, t, h, u), theta, state, U)
            return _add(acc, v_vjp(ct_v))

        acc = jax.lax.cond(j == rec.n - 1, velocity, lambda acc: acc, acc)

        def cond(q):
            f = q[0]
            return (f >= 0) & (rec.frame_slot[jnp.maximum(f, 0)] == j)

        def body(q):  # frames: functions of (theta, s_j, U_j, D_j, W_j, D_cum_j, W_cum_j)
            f, acc, dD, dW, dDc, dWc = q
            s_ = rec.frame_s[f] if dense else None
            _, fv = jax.vjp(lambda th, st, u, d, w, dc, wc: _frame(sw, split.build(th), st, t, h, u, d, w, dc, wc, s_),
                            theta, state, U, zero, zero, zero, zero)
            g_th, g_s, g_u, g_d, g_w, g_dc, g_wc = fv(jax.tree_util.tree_map(lambda b: b[f], ct_frames))
            return f - 1, _add(acc, (g_th, g_s, g_u)), dD + g_d, dW + g_w, dDc + g_dc, dWc + g_wc

        f, acc, dD_in, dW_in, dD_at, dW_at = jax.lax.while_loop(cond, body, (c["f"], acc, zero, zero, zero, zero))
        o_th, o_s, o_u = o_vjp((lam_s, lam_W + dW_in))
        cot_D = lam_D + dD_in  # D_j feeds every later cumulative value and the dense frames inside it
        d_th, d_s, d_u = r_vjp((_zeros(R), cot_D))
        o_th, o_s = _add(o_th, d_th), _add(o_s, d_s)
        gU = _add(_add(o_u, d_u), acc[2])
        sx = _momentum_scale(scene, ctx)
        rotation = body_rotation(scene, state.x)
        solve_t = jax.linear_transpose(lambda b: schur_solve(scheme, scene, ctx, tan, b, rotation), U)
        # (S A)^T nu = gU with matvec v -> A^T (S v); right preconditioner S^{-1} P^{-T}; mu = S nu
        nu, _, res = _krylov(lambda v: r_vjp((_scale_x(v, 1.0 / sx), zero))[2], lambda v: _scale_x(solve_t(v)[0], sx),
                             gU)
        r_th, r_s, _ = r_vjp((jax.tree_util.tree_map(jnp.negative, _scale_x(nu, 1.0 / sx)), zero))
        g = _add(c["g"], _add(_add(o_th, r_th), acc[0]))
        return dict(c, lam_s=_add(_add(o_s, r_s), acc[1]), lam_D=lam_D + dD_at, lam_W=lam_W + dW_at, g=g, tan=tan,
                    f=f, worst=jnp.maximum(c["worst"], res))

    def segment(c, g):
        bufs, gamma0, j0, failed = _buffers(sw, g)
        hi = jnp.minimum(j0 + bufs["x"].shape[0], rec.n)
        c = jax.lax.fori_loop(0, jnp.maximum(hi - j0, 0), lambda i, c: step(hi - 1 - i, c, bufs, j0, gamma0), c)
        return dict(c, failed=c["failed"] | failed), None

    state0 = sw.state0
    init = dict(lam_s=_zeros(state0), lam_D=zero, lam_W=zero, g=_zeros(theta),
                tan=_no_tangent(sw), f=sw.n_saved - 1, worst=zero, failed=jnp.asarray(False))
    c, _ = jax.lax.scan(segment, init, jnp.arange(_segments(rec)[0]), reverse=True)
    # the frames of the initial state (slot -1) and, after no sub-step, the end velocity
    first = (rec.frame_slot < 0) & live
    ct0 = jax.tree_util.tree_map(lambda b: jnp.sum(_where_live(first, b), 0), ct_frames)
    _, f0 = jax.vjp(lambda th, s: _first_frame(sw, split.build(th), s), theta, state0)
    none = rec.n == 0
    _, v_vjp = jax.vjp(lambda th, s: split.build(th).velocity(s.p), theta, state0)
    g_th, g_s = _add(f0(ct0), v_vjp(jnp.where(none & ~sw.use_v0, ct_v, 0.0)))
    out = (_add(c["g"], g_th), _add(c["lam_s"], g_s), jnp.where(none & sw.use_v0, ct_v, 0.0))
    return check_sweep(rec, out, c["worst"], c["failed"], sw.throw)


def differentiate(sol, rec, primals, tangents, *, scheme, solver, use_v0, save_gamma, save_reactions,
                  save_diagnostics, t0, throw):
    """The tangent of a loop's `Solution` `sol` (the rule of a `custom_jvp` around a time
    loop that wrote `rec` with a `Plan`): the frames' and the end velocity's, as the
    linear map `_sweep` of `tangents` (of the scene, the initial state and the
    predictor's initial velocity), whose transpose is `_adjoint_sweep`. `throw`: a
    derivative it cannot compute raises (else it is NaN; `_refuse`). Returns `sol` and its
    tangent."""
    scene, state0, v0 = primals
    t_scene, t_state0, t_v0 = tangents
    split = _Split(scene, t_scene)
    t_state0 = State(None, None, None) if t_state0 is None else t_state0
    t_sol = jax.tree_util.tree_map(lambda _: None, sol)
    a = (split.tangent, t_state0, t_v0)
    if not jax.tree_util.tree_leaves(a):
        return sol, t_sol
    names = [k for k in FRAME_FIELDS if k != "t" and getattr(sol, k) is not None]  # times: constants
    spec_out = _shapes(({k: getattr(sol, k) for k in names}, sol.end_velocity))
    cfg = _SweepConfig(scheme, solver, save_gamma, save_reactions, save_diagnostics, throw, tuple(split.where),
                       _shapes(a), spec_out, False)
    dyn = dict(rec=rec, scene=scene, state0=state0, v0=v0, use_v0=use_v0, n_saved=sol.n_saved, t0=t0)
    d_frames, d_v = eqxi.filter_primitive_bind(_sweep_p, dyn, a, cfg)
    t_sol = eqx.tree_at(lambda s: [getattr(s, k) for k in names] + [s.end_velocity], t_sol,
                        [d_frames[k] for k in names] + [d_v], is_leaf=lambda x: x is None)
    return sol, t_sol


# --- the pair of sweeps as one JAX primitive ----------------------------------------------
# Why a primitive: the sweep and its transpose must be one linear map to JAX (its rules
# call the first for jvp/jacfwd, the second for grad/vjp), and `lax.custom_linear_solve`,
# which carried the pair before, traces both (and batches both, under jacfwd) as soon as
# the tangent is formed: the adjoint sweep was 40 % of tracing jacfwd of a run. A
# primitive traces the sweep it runs only, and only when its program is lowered; a batch
# of its (co)tangents (jacfwd, jacrev) is the sweep vmapped inside one primitive
# (`_sweep_batch_tree`), which the persistent cache stores as it stores the unbatched one,
# any other batch the sweep traced under vmap (jacfwd of the 3D relaxation test: trace +
# lower 13.4 s -> 9.7 s). It is built with equinox's filter-primitive helpers, on which lineax
# (a dependency) builds its `linear_solve_p`; JAX's own lazily transposed
# `custom_derivatives.linear_call` has no batching rule (jax 0.10).
@dataclasses.dataclass(frozen=True, eq=False)
class _SweepConfig:
    """The static half of a sweep primitive: the loop's settings, which scene leaves are
    differentiated (`where`), the shapes of the input tangents `spec_a` and of the frame
    tangents `spec_out`, the direction (`transpose`: the adjoint sweep) and, for a batch
    of tangents or cotangents (`_sweep_batch_tree`), its size `batch` (0: none)."""

    scheme: object
    solver: object
    save_gamma: bool
    save_reactions: bool
    save_diagnostics: bool
    throw: bool
    where: tuple
    spec_a: object
    spec_out: object
    transpose: bool
    batch: int = 0

    def flipped(self):
        return dataclasses.replace(self, transpose=not self.transpose)

    def sweep(self, dyn):
        """What both sweeps read, from the primitive's array inputs `dyn`."""
        return _Sweep(dyn["rec"], _Split(dyn["scene"], where=self.where), dyn["state0"], dyn["v0"], dyn["use_v0"],
                      dyn["n_saved"], self.scheme, self.solver, self.save_gamma, self.save_reactions,
                      self.save_diagnostics, dyn["t0"], self.throw)


def _shapes(tree):
    return jax.tree_util.tree_map(lambda v: jax.ShapeDtypeStruct(v.shape, v.dtype), tree)


def _sweep_impl(dyn, lin, cfg):
    """The forward sweep of the input tangents `lin`, or (`cfg.transpose`) the adjoint
    sweep of the frames' cotangents `lin`, shaped as the input tangents; stored with the
    persistent cache on (`_export.inline`: a later process loads the sweep's program
    instead of tracing it)."""
    return _export.inline(_sweep_run, dyn, lin, cfg)


def _sweep_run(dyn, lin, cfg):
    if cfg.batch:  # a batch of (co)tangents along their first axis, the primal unbatched
        one = dataclasses.replace(cfg, batch=0)
        return jax.vmap(lambda b: _sweep_run(dyn, b, one))(lin)
    sw = cfg.sweep(dyn)
    if not cfg.transpose:
        return _sweep(sw, lin)
    g_theta, g_state, g_v0 = _adjoint_sweep(sw, lin)
    _, t_state0, t_v0 = cfg.spec_a
    g_state = jax.tree_util.tree_map(lambda t, g: None if t is None else g, t_state0, g_state,
                                     is_leaf=lambda t: t is None)
    return list(g_theta), g_state, None if t_v0 is None else g_v0


def _sweep_abstract_eval(dyn, lin, cfg):
    del dyn, lin
    lead = (cfg.batch,) if cfg.batch else ()
    return jax.tree_util.tree_map(lambda v: jax.core.ShapedArray(lead + v.shape, v.dtype),
                                  cfg.spec_a if cfg.transpose else cfg.spec_out)


def _sweep_jvp(primals, tangents):
    """The sweeps are linear in their input tangents; their other inputs are constants
    (second derivatives of a run are not supported)."""
    dyn, lin, cfg = primals
    t_dyn, t_lin, _ = tangents
    if jax.tree_util.tree_leaves(t_dyn):
        raise NotImplementedError("jaxvisco: second derivatives of a run are not supported (its derivative is "
                                  "computed by sweeps that are not differentiated again).")
    t_lin = jax.tree_util.tree_map(eqxi.materialise_zeros, lin, t_lin, is_leaf=lambda t: t is None)
    return eqxi.filter_primitive_bind(_sweep_p, dyn, lin, cfg), eqxi.filter_primitive_bind(_sweep_p, dyn, t_lin, cfg)


def _sweep_transpose(inputs, cts):
    """The transpose of either sweep is the other one, with the same constants `dyn`."""
    dyn, _, cfg = inputs
    none = jax.tree_util.tree_map(lambda _: None, dyn)
    return none, eqxi.filter_primitive_bind(_sweep_p, dyn, cts, cfg.flipped()), None


_sweep_p = eqxi.create_vprim("jaxvisco_sweep", eqxi.filter_primitive_def(_sweep_impl),
                             eqxi.filter_primitive_def(_sweep_abstract_eval), eqxi.filter_primitive_jvp(_sweep_jvp),
                             eqxi.filter_primitive_transpose(materialise_zeros=True)(_sweep_transpose))


class _General(Exception):
    """A batch that `_sweep_batch_tree` leaves to equinox's rule."""


def _sweep_batch_tree(inputs, axes, size):
    """A batch of input tangents (`jax.jacfwd`) or of frame cotangents (`jax.jacrev`)
    for one primal run: the sweep primitive itself with the batch along the first axis
    of every (co)tangent (`_SweepConfig.batch`), so that its program is one call that the
    persistent cache stores (`_export.inline`) as the unbatched sweep's is."""
    dyn, lin, cfg = inputs
    dyn_axes, lin_axes, _ = axes
    if cfg.batch or jax.tree_util.tree_leaves(dyn_axes):
        raise _General
    first = lambda x, a: (jnp.broadcast_to(x, (size,) + x.shape) if a is None  # noqa: E731
                          else jnp.moveaxis(x, a, 0))
    lin = jax.tree_util.tree_map(lambda x, a: None if x is None else first(x, a), lin, lin_axes,
                                 is_leaf=lambda x: x is None)
    out = eqxi.filter_primitive_bind(_sweep_p, dyn, lin, dataclasses.replace(cfg, batch=size))
    return out, jax.tree_util.tree_map(lambda _: 0, out)


def _register_sweep_batch():
    """Batches of (co)tangents of one run by `_sweep_batch_tree`; any other batch (of
    primal runs, or of a batch) by equinox's rule: the sweep traced under `jax.vmap`."""
    from jax.interpreters import batching

    general = batching.fancy_primitive_batchers[_sweep_p]

    def rule(axis_data, vals, dims, **params):
        try:
            tree_rule = eqxi.filter_primitive_batching(lambda i, a: _sweep_batch_tree(i, a, axis_data.size))
            return tree_rule(vals, dims, **params)
        except _General:
            return general(axis_data, vals, dims, **params)

    batching.fancy_primitive_batchers[_sweep_p] = rule


_register_sweep_batch()
