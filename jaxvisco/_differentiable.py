"""The time loop for derivatives: fixed steps, implicit step derivatives, checkpointing.

`simulate(..., differentiable=True)` runs this loop instead of the adaptive one. JAX
cannot reverse-differentiate a `while_loop`, and step halving makes the number of
steps data dependent, so here the steps are the schedule's, exactly, in nested
`lax.scan`s:

    segments (each under `jax.checkpoint`) → frames (save_every steps each) → steps.

Each step is `solve_step_implicit` (its derivative is one linear solve with the
converged tangent, `_implicit`). In reverse mode only the state at segment boundaries
is stored during the forward pass; the backward pass re-runs one segment at a time
(Newton included) and keeps that segment's step residuals. With `checkpoint_every`
= m frames per segment and n frames in all, the stored states number n/m + m per
trajectory: O(sqrt n) for the default m = ceil(sqrt n), at the price of running the
forward pass twice. Forward mode (`jax.jvp`) needs no storage at all.

A step that fails (Newton not converged, non-finite values) stops the run: later
steps are skipped, the last good state is kept, and `status` reports "failed".
"""

import math

import jax
import jax.numpy as jnp

from ._config import jit
from ._implicit import solve_step_implicit
from ._solution import DONE, FAILED, RUNNING, Solution
from ._step import make_context, predictor, step_outcome
from ._tangent import empty_tangent


def layout(n_steps, save_every, checkpoint_every=None):
    """Frames per segment, number of segments, padded frame count."""
    n_frames = -(-n_steps // save_every)
    m = math.ceil(math.sqrt(n_frames)) if checkpoint_every is None else int(checkpoint_every)
    m = max(1, min(m, n_frames))
    n_seg = -(-n_frames // m)
    return m, n_seg


@jit
def run_scan(scene, scheme, solver, state0, t0, hs, te, n_active, save_every, save_gamma, m, n_seg, v0, use_v0, n_keep):
    """hs, te: (n_seg * m * save_every,) step sizes and end times, padded; steps >= n_active are skipped.
    n_keep (static): the schedule's step count; the padding is cut from the outputs so a
    traced Solution has exactly the schedule's frames and steps."""
    diag0 = scene.diagnostics(state0)
    hs = hs.reshape(n_seg, m, save_every)
    te = te.reshape(hs.shape)
    idx = jnp.arange(hs.size).reshape(hs.shape)
    fresh_tangent = empty_tangent(scheme, scene)

    def step(c, inp):
        h, t_next, i = inp
        active = (i < n_active) & (c["status"] == RUNNING)

        def attempt(c):
            ctx = make_context(scene, c["state"], c["t"], h)
            U0 = predictor(scheme, scene, ctx, c["v"])
            r = solve_step_implicit(solver, scheme, scene, ctx, U0, c["tan"])
            new, D, W, v_end, ok = step_outcome(scheme, scene, ctx, r)
            keep = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(ok, x, y), a, b)  # noqa: E731
            out = dict(state=keep(new, c["state"]), t=jnp.where(ok, t_next, c["t"]),
                       v=keep(v_end, c["v"]), tan=r.tangent,
                       dissipated=c["dissipated"] + jnp.where(ok, D, 0.0),
                       work=c["work"] + jnp.where(ok, W, 0.0),
                       status=jnp.where(ok, c["status"], FAILED), n_done=c["n_done"] + ok.astype(int))
            stats = (r.iterations, r.krylov_iterations, r.chord_iterations, jnp.where(ok, r.residual, jnp.inf))
            return out, stats

        def skip(c):
            return c, (jnp.asarray(0), jnp.asarray(0), jnp.asarray(0), jnp.asarray(0.0))

        c, (its, kits, chord, res) = jax.lax.cond(active, attempt, skip, c)
        return c, dict(step_t=c["t"], step_h=h, newton_iterations=its, krylov_iterations=kits,
                       chord_iterations=chord, residual=res,
                       rejections=jnp.asarray(0))

    def frame(c, inp):
        # A fresh tangent at every frame start. Newton's preconditioner is otherwise kept
        # across steps, and the converged steps depend on it within the Newton tolerance
        # (~1e-10 relative); segments are whole frames, so resetting per frame makes the
        # trajectory (and its gradient) independent of `checkpoint_every`, and the
        # recomputation in the backward pass repeats the forward pass exactly and never
        # needs an old factorization.
        c = dict(c, tan=fresh_tangent)
        started = (inp[2][0] < n_active) & (c["status"] == RUNNING)
        c, steps = jax.lax.scan(step, c, inp)
        st = c["state"]
        out = dict(t=c["t"], x=st.x, p=st.p, dissipated=c["dissipated"], external_work=c["work"],
                   started=started, **scene.diagnostics(st))
        if save_gamma and st.gamma is not None:
            out["gamma"] = st.gamma
        return c, (out, steps)

    @jax.checkpoint
    def segment(c, inp):
        return jax.lax.scan(frame, c, inp)

    init = dict(state=state0, t=t0, v=jnp.where(use_v0, v0, scene.velocity(state0.p)), tan=fresh_tangent,
                dissipated=jnp.asarray(0.0), work=jnp.asarray(0.0), status=jnp.asarray(RUNNING),
                n_done=jnp.asarray(0))
    c, (frames, steps) = jax.lax.scan(segment, init, (hs, te, idx))
    n_frames = -(-n_keep // save_every)
    frames = jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:])[:n_frames], frames)
    steps = jax.tree_util.tree_map(lambda a: a.reshape(-1)[:n_keep], steps)
    first = dict(t=t0, x=state0.x, p=state0.p, dissipated=jnp.asarray(0.0), external_work=jnp.asarray(0.0),
                 started=jnp.asarray(True), **diag0)
    if "gamma" in frames:
        first["gamma"] = state0.gamma
    frames = {k: jnp.concatenate([jnp.asarray(first[k])[None], v]) for k, v in frames.items()}
    status = jnp.where(c["status"] == RUNNING, DONE, c["status"])
    return Solution(
        t=frames["t"], x=frames["x"], p=frames["p"], gamma=frames.get("gamma"), energy=frames["energy"],
        kinetic=frames["kinetic"], free_energy=frames["free_energy"], dissipated=frames["dissipated"],
        dissipation_rate=frames["dissipation_rate"], external_work=frames["external_work"],
        linear_momentum=frames["linear_momentum"], angular_momentum=frames["angular_momentum"],
        n_saved=jnp.sum(frames["started"]).astype(int), n_steps=c["n_done"], status_code=status,
        integrator=scheme.describe(), **steps)
