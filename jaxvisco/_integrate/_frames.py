"""What the compiled time loops share: the saved-frame buffers and the equilibrium test."""

import equinox as eqx
import jax
import jax.numpy as jnp

from .._fem._tensor import small_solve
from .._fem._update import put
from .._scene import Scene
from ._solution import FRAME_FIELDS


# The diagnostics of a frame as a program of its own: the loops write frames with it and
# the derivative sweeps differentiate it, so JAX traces it once for all of them.
diagnostics = eqx.filter_jit(Scene.diagnostics)


def frame_diagnostics(scene, state, on=True):
    """What a frame holds of the state's diagnostics: all of them (`diagnostics`), or
    none (`SaveAt(diagnostics=False)`)."""
    return diagnostics(scene, state) if on else {}


def relative_kinetic_energy(scene: Scene, x, p):
    """Kinetic energy relative to the best-fitting rigid motion (mass-weighted); for a
    body with held components, which cannot move rigidly, the whole kinetic energy."""
    v = scene.velocity(p)
    T = 0.5 * jnp.vdot(p, v)
    if scene.fixed is not None:
        return T
    c = jnp.mean(x, axis=0)
    r = x - c
    d = x.shape[-1]
    modes = [jnp.broadcast_to(jnp.eye(d, dtype=x.dtype)[i], x.shape) for i in range(d)]
    if d == 2:
        modes.append(jnp.stack([-r[:, 1], r[:, 0]], -1))
    else:
        for axis in range(3):
            e = jnp.eye(3)[axis]
            modes.append(jnp.cross(e, r))
    R = jnp.stack(modes)  # (m, n, d)
    MR = jax.vmap(lambda u: scene.disc.mass_matvec(u, scene.density))(R)
    G = jnp.einsum("and,bnd->ab", R, MR)
    b = jnp.einsum("and,nd->a", R, p)
    return T - 0.5 * jnp.dot(b, small_solve(G, b))


def at_equilibrium(scene, state, D, eq_tol, H0, dissipated, work):
    """The early-stop test (`Equilibrium`): the kinetic energy relative to the rigid
    motion and the step's dissipated energy `D` both at most `eq_tol` times the run's
    energy scale, the largest of the initial energy `H0`, the external work done so far
    (`work`, cumulative) and the energy dissipated so far (`dissipated`). A free body's
    scale is H0 (its work is zero, its dissipation at most H0); a body loaded from rest
    (H0 = 0) is measured against the work of its loads."""
    scale = jnp.maximum(jnp.maximum(H0, jnp.abs(work)), dissipated)
    return (relative_kinetic_energy(scene, state.x, state.p) <= eq_tol * scale) & (D <= eq_tol * scale)


def frame_buffers(n_frames, t0, state0, diag0, save_gamma, reactions=False):
    """Zeroed buffers of `n_frames` saved frames shaped like the initial ones
    (`reactions`: and the supports' forces, shaped like the positions)."""
    def buf(v):
        v = jnp.asarray(v)
        return jnp.zeros((n_frames,) + v.shape, v.dtype)
    out = dict(t=buf(t0), x=buf(state0.x), p=buf(state0.p),
               gamma=buf(state0.gamma) if (save_gamma and state0.gamma is not None) else None,
               dissipated=buf(0.0), external_work=buf(0.0), reaction=buf(state0.x) if reactions else None,
               reaction_mean=buf(state0.x) if reactions else None)
    out.update({k: buf(v) for k, v in diag0.items()})
    return out


def initial_frames(n_frames, t0, state0, diag0, save_gamma, reaction0=None, ts_out=None):
    """The frame buffers with the initial state written: as frame 0, or (dense output at
    the times `ts_out`) as every frame at a time <= t0. `reaction0`: the supports' force
    there, where the run saves reactions. Returns (frames, the number written)."""
    frames = frame_buffers(n_frames, t0, state0, diag0, save_gamma, reactions=reaction0 is not None)
    zero = jnp.zeros((), jnp.result_type(float))
    if ts_out is None:
        return write_frame(frames, 0, t0, state0, diag0, zero, zero, reaction0), jnp.asarray(1)
    n_start = jnp.sum(ts_out <= t0)
    return jax.lax.fori_loop(0, n_start, lambda j, f: write_frame(f, j, ts_out[j], state0, diag0, zero, zero,
                                                                   reaction0), frames), n_start


def frame_values(state, diag, dissipated, work, with_gamma, reaction=None):
    """What a saved frame holds besides its time (`gamma` only `with_gamma`; `reaction`:
    the supports' forces, `step_reactions`, where the run saves them)."""
    out = dict(x=state.x, p=state.p, dissipated=dissipated, external_work=work, **diag)
    if with_gamma and state.gamma is not None:
        out["gamma"] = state.gamma
    if reaction is not None:
        out.update(reaction)
    return out


def step_reactions(scheme, scene, ctx, U, sigma=1.0):
    """The supports' forces a frame at the fraction `sigma` of a step holds: ``reaction``,
    the force at that time (the time element's multiplier, a polynomial of degree k-1
    in time: `_step.reaction_coefficients`), and ``reaction_mean``, its mean over the
    step (whose work is the energy balance's)."""
    from .._time_element._step import mean_reaction, reaction_at, reaction_coefficients

    c = reaction_coefficients(scheme, scene, ctx, U)
    return dict(reaction=reaction_at(scheme, c, jnp.asarray(sigma, ctx.h.dtype)),
                reaction_mean=mean_reaction(c, scheme))


def first_reactions(scene, state, t):
    """`step_reactions` of an initial frame (no step before it: a body at rest)."""
    from .._time_element._step import static_reaction

    r = static_reaction(scene, state, t)
    return dict(reaction=r, reaction_mean=r)


def step_buffers(capacity):
    """A time loop's per-step records (`Solution.step_t`, `step_h`, the iteration counts,
    the residual and the rejections), zero for `capacity` steps."""
    zf, zi = jnp.zeros(capacity), jnp.zeros(capacity, dtype=int)
    return dict(step_t=zf, step_h=zf, newton_iterations=zi, krylov_iterations=zi, chord_iterations=zi,
                residual=zf, rejections=zi)


def write_step(steps, i, **values):
    """`steps` (`step_buffers`) with step `i`'s record set: a value for every key."""
    return {k: put(b, i, values[k]) for k, b in steps.items()}


def write_frame(frames, idx, t, state, diag, dissipated, work, reaction=None):
    """`frames` with frame `idx` set (`reaction`: where the buffers hold the supports' forces)."""
    vals = dict(t=t, **frame_values(state, diag, dissipated, work, frames["gamma"] is not None, reaction))
    return {k: (None if b is None else put(b, idx, vals[k])) for k, b in frames.items()}


def frame_fields(frames):
    """The `Solution` fields of the frame buffers."""
    return {k: frames.get(k) for k in FRAME_FIELDS}  # diagnostics: absent without them (None)


def write_dense_frames(scheme, scene, frames, rec, ptr, ts_out, ctx, U, t_next, D_before, D, W_before, W, note,
                       reactions=False, with_diagnostics=True):
    """`frames` with the frames at the requested times `ts_out[ptr:]` up to `t_next` (the
    end of an accepted step from `ctx` with unknowns `U`) written from the step's time
    polynomial (dense output), each noted for the derivative by `note(rec, frame, s)` (s:
    where in the step it lies), with the supports' forces there if `reactions` and the
    state's diagnostics if `with_diagnostics`. `D_before`, `W_before`: the cumulative dissipation and
    work at the step's start; `D`, `W`: the step's own (linear in time within the step).
    Returns (frames, rec, the next frame index)."""
    from .._time_element._estimate import dense_state

    n_frames = ts_out.shape[0]

    def cond(c):
        return (c[2] < n_frames) & (ts_out[jnp.minimum(c[2], n_frames - 1)] <= t_next)

    def body(c):
        f, rec, j = c
        s = jnp.clip((ts_out[j] - ctx.t0) / ctx.h, 0.0, 1.0)
        st = dense_state(scheme, scene, ctx, U, s)
        f = write_frame(f, j, ts_out[j], st, frame_diagnostics(scene, st, with_diagnostics), D_before + s * D,
                        W_before + s * W,
                        step_reactions(scheme, scene, ctx, U, s) if reactions else None)
        return f, note(rec, j, s), j + 1

    return jax.lax.while_loop(cond, body, (frames, rec, ptr))

