"""One time element over the whole mesh: unknowns, residual, dissipation, predictor.

Unknowns of a step are the position increments $x_I - x_n$ at the k new time nodes and,
where the material has a viscous branch, the internal variable at the k new nodes and every spatial
quadrature point (6 Voigt components). The nodal momenta are eliminated exactly (they
follow linearly from the weak form of $M\\dot x = p$; see `time_element_matrices`), so
the momentum equations become a system in positions, like Newmark's in displacements.
"""

import functools
import operator
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._export import register_type
from .._fem._quadrature import gauss_legendre
from .._fem._tensor import small_solve, sym_to_vec, vec_to_sym
from .._scene import Scene, State


@register_type  # a stored derivative program returns one (`_export.inline`)
class Unknowns(eqx.Module):
    x: jax.Array  # (k, n_nodes, dim): increments x_I - x_n (see `nodal_fields`)
    g: Optional[jax.Array]  # (k, n_cells, nq, 6) or None


def unknowns_like(scheme, scene, state):
    """The shapes and dtypes of a step's `Unknowns` (`jax.ShapeDtypeStruct` leaves)."""
    k, disc = scheme.k, scene.disc
    x = jax.ShapeDtypeStruct((k,) + state.x.shape, state.x.dtype)
    g = None if state.gamma is None else jax.ShapeDtypeStruct((k, disc.n_cells, disc.n_qp, 6), state.x.dtype)
    return Unknowns(x, g)


class StepContext(eqx.Module):
    """What is known when a step starts."""

    state: State
    t0: jax.Array
    h: jax.Array
    F0: jax.Array  # deformation gradient at the start (n_cells, nq, 3, 3)


def make_context(scene: Scene, state: State, t0, h) -> StepContext:
    return StepContext(state, jnp.asarray(t0, float), jnp.asarray(h, float),
                       scene.disc.deformation_gradient(state.x))


def increments(ctx, U):
    """Position increments $X_I - x_n$ at all k+1 time nodes (zero at the first)."""
    return jnp.concatenate([jnp.zeros_like(ctx.state.x)[None], U.x], axis=0)


def nodal_fields(scheme, scene, ctx, U, node_major=False):
    """Position increments $X_I - x_n$ (k+1, n, d; zero at the first node), deformation
    gradients and internal variables at the time nodes of every spatial quadrature point
    (n_cells, nq, k+1, 3, 3; `node_major`: (k+1, n_cells, nq, 3, 3), for
    `Scene.map_point_histories`).

    The unknowns are increments, not positions: a body that has flown far from the origin
    (|x| ~ 600 at t = 100 on the paper's L-shape, moving 0.6 per step) can resolve a
    position only to ulp(600) ~ 1e-13, i.e. its step to ~2e-13 relative, and the momenta
    $\\propto M(X_I - x_n)/h$ carried that noise into an angular-momentum drift. The
    operators acting on positions in time annihilate constants, so they act on the
    increments unchanged, and F = F_n + grad(increment) is translation-free.
    """
    dX = increments(ctx, U)
    F = jnp.concatenate([ctx.F0[None], ctx.F0[None] + scene.disc.gradient(U.x)], axis=0)
    G = None if U.g is None else jnp.concatenate([ctx.state.gamma[None], vec_to_sym(U.g)], axis=0)
    if node_major:
        return dX, F, G
    return dX, jnp.moveaxis(F, 0, 2), None if G is None else jnp.moveaxis(G, 0, 2)




def momenta(scheme, scene, ctx, X):
    """Nodal momenta at the k new time nodes, from the weak form of $M\\dot x = p$, given
    the position increments X (k+1, n, d) of `nodal_fields`."""
    m, _ = scheme.matrices()
    MX = scene.disc.mass_matvec(X, scene.density)
    return (jnp.einsum("JI,Ind->Jnd", jnp.asarray(m["Pm"]), MX) / ctx.h
            + jnp.asarray(m["Pp"])[:, None, None] * ctx.state.p[None])


def force_term(scheme, scene, ctx, P):
    """$h \\sum_l W_{Jl} f_{int}(P_l)$ for stresses P (n_cells, nq, nq_t, 3, 3)."""
    m, _ = scheme.matrices()
    f = scene.disc.force(jnp.moveaxis(P, 2, 0))  # (nq_t, n, d)
    return ctx.h * jnp.einsum("Jl,lnd->Jnd", jnp.asarray(m["W"]), f)


def external_term(scheme, scene, ctx):
    m, _ = scheme.matrices()
    if scene.loads is None:
        return None
    ts = ctx.t0 + ctx.h * jnp.asarray(m["points"])
    fext = jax.vmap(scene.external_force)(ts)
    return ctx.h * jnp.einsum("Jl,lnd->Jnd", jnp.asarray(m["W"]), fext)


def residual(scheme, scene: Scene, ctx: StepContext, U: Unknowns) -> Unknowns:
    """Weak residual of the time element: momentum equations (k, n, d) in units of
    momentum, evolution law (k, n_cells, nq, 6) dimensionless."""
    return _constrained(scheme, scene, ctx, U, *_unconstrained_residual(scheme, scene, ctx, U))


def carries_dissipation(scheme, scene):
    """Whether `residual_and_dissipation` yields the step's dissipation (eG with an
    internal variable: its point kernel has the dissipation at hand)."""
    return scheme.enhanced and scene.has_internal_variable


def residual_and_dissipation(scheme, scene: Scene, ctx: StepContext, U: Unknowns):
    """`residual` and the step's dissipation $D_n$ at U from the same point evaluations
    (`carries_dissipation`; else None), as Newton's loop evaluates it."""
    if not carries_dissipation(scheme, scene):
        return residual(scheme, scene, ctx, U), None
    R_x, R_G, d = _unconstrained_residual(scheme, scene, ctx, U, with_dissipation=True)
    return _constrained(scheme, scene, ctx, U, R_x, R_G), scene.disc.integrate(d)


def _constrained(scheme, scene, ctx, U, R_x, R_G):
    """The step residual from the unconstrained one (`_unconstrained_residual`)."""
    if scene.fixed is not None:
        # Held components: the momentum equation is replaced by the constraint, scaled
        # to momentum units like the rows it replaces.
        mask = jnp.asarray(scene.fixed.array)[None]
        gap = ctx.state.x[None] + U.x - held_targets(scheme, scene, ctx)
        R_x = jnp.where(mask, gap * constraint_scale(scene, ctx.h), R_x)
    return Unknowns(R_x, R_G)


def held_targets(scheme, scene, ctx):
    """Positions of the held components at the k new time nodes (k, n, d)."""
    m, _ = scheme.matrices()
    if scene.prescribed is None:
        return scene.x0[None]
    ts = ctx.t0 + ctx.h * jnp.asarray(m["nodes"][1:])
    return jax.vmap(scene.held_positions)(ts)


def _unconstrained_residual(scheme, scene, ctx, U, with_dissipation=False):
    """The residual with every momentum equation kept (held rows too: there it is the
    reaction's share, `reaction_work`); `with_dissipation`: and the dissipation of every
    spatial point (`residual_and_dissipation`)."""
    m, _ = scheme.matrices()
    X, F, G = nodal_fields(scheme, scene, ctx, U, node_major=True)
    if with_dissipation:
        P, R_G, d = scene.map_point_histories(lambda mat, f, g: scheme.point_kernel_and_dissipation(mat, f, g, ctx.h),
                                              F, G)
    else:
        P, R_G = scene.map_point_histories(lambda mat, f, g: scheme.point_kernel(mat, f, g, ctx.h), F, G)
    MX = scene.disc.mass_matvec(X, scene.density)
    R_x = (jnp.einsum("JI,Ind->Jnd", jnp.asarray(m["A"]), MX) / ctx.h
           + jnp.asarray(m["b"])[:, None, None] * ctx.state.p[None]
           + force_term(scheme, scene, ctx, P))
    ext = external_term(scheme, scene, ctx)
    if ext is not None:
        R_x = R_x - ext
    R_G = None if R_G is None else jnp.moveaxis(R_G, 2, 0)
    return (R_x, R_G, d) if with_dissipation else (R_x, R_G)


def constraint_scale(scene, h):
    """Mass per node over the step: the scale of a constraint row (Dirichlet)."""
    return scene.mass() / scene.disc.n_nodes / h


def step_dissipation(scheme, scene, ctx, U):
    """The scheme's dissipated energy over the step, $D_n$."""
    _, F, G = nodal_fields(scheme, scene, ctx, U)
    if G is None:
        return jnp.zeros((), dtype=ctx.h.dtype)
    d = scene.map_points(lambda mat, f, g: scheme.point_dissipation(mat, f, g, ctx.h), F, G)
    return scene.disc.integrate(d)


def external_work(scheme, scene, ctx, U):
    """Work of the dead loads over the step, $\\int x_h' \\cdot f_{ext} d\\alpha$, plus
    that of the reactions where held components move (`reaction_work`)."""
    work = jnp.zeros((), dtype=ctx.h.dtype)
    if scene.prescribed is not None:
        work = work + reaction_work(scheme, scene, ctx, U)
    if scene.loads is None:
        return work
    m, _ = scheme.matrices()
    Xd = jnp.einsum("lI,Ind->lnd", jnp.asarray(m["D"]), increments(ctx, U))
    ts = ctx.t0 + ctx.h * jnp.asarray(m["points"])
    fext = jax.vmap(scene.external_force)(ts)
    return work + jnp.sum(jnp.asarray(m["weights"])[:, None, None] * Xd * fext)


def reaction_coefficients(scheme, scene, ctx, U):
    r"""The force the supports exert on the held components over the step, as the time
    element's own Lagrange multiplier: the polynomial $r(t)$ of degree k-1 (the test
    space) whose moments are the held rows of the momentum equations without the
    constraint, $h\int_0^1 r\,T_J\,ds = R_J$. On the test functions' nodes (the k Gauss
    points, where $\int_0^1 T_I T_J\,ds = w_J \delta_{IJ}$) its values are
    $R_J / (h\,w_J)$ (k, n, d; zero on the free components). Summed over the held
    components it is the rate of the body's linear momentum minus the loads at every
    time of the step (the internal forces sum to zero), its mean over the step is the
    impulse over h, and its work where the held components move at a constant velocity
    is `reaction_work`'s. For eG(1) it is constant within a step."""
    R_x, _ = _unconstrained_residual(scheme, scene, ctx, U)
    w = jnp.asarray(gauss_legendre(scheme.k)[1], R_x.dtype)
    return jnp.where(jnp.asarray(scene.fixed.array)[None], R_x / (ctx.h * w[:, None, None]), 0.0)


def reaction_at(scheme, coefficients, sigma):
    """`reaction_coefficients`' polynomial at the fraction `sigma` of the step."""
    nodes = gauss_legendre(scheme.k)[0]
    basis = [functools.reduce(operator.mul, [(sigma - b) / (a - b) for b in nodes if b != a], 1.0)
             for a in nodes]
    return sum(T * c for T, c in zip(basis, coefficients))


def mean_reaction(coefficients, scheme):
    """`reaction_coefficients`' mean over the step (the impulse over h)."""
    w = jnp.asarray(gauss_legendre(scheme.k)[1], coefficients.dtype)
    return jnp.einsum("J,Jnd->nd", w, coefficients)


def static_reaction(scene, state, t, momentum_rate=None):
    """The force the supports exert on the held components of a body in `state` at time
    `t` (n, d; zero on the free components): the rate of the momenta (`momentum_rate`,
    default zero: a body at rest) plus the internal minus the external force there."""
    f = scene.internal_force(state.x, state.gamma)
    if scene.loads is not None:
        f = f - scene.external_force(t)
    if momentum_rate is not None:
        f = f + momentum_rate
    return jnp.where(jnp.asarray(scene.fixed.array), f, 0.0)


def reaction_work(scheme, scene, ctx, U):
    r"""Work of the reactions on the held components over the step.

    The reactions $r$ close the momentum equations of the held rows:
    $R_J = h \sum_l W_{Jl} r_l$ ($R$ without the constraint). Their work
    $\sum_l w_l x_h'(\alpha_l) \cdot r_l$ is, because $x_h'$ is a polynomial of the test
    space, $\sum_J x_h'(\beta_J) \cdot R_J / h$ with $\beta_J$ the test nodes
    (`time_element_matrices`' `D_test`): the same identity that makes the work of the
    loads exact, so the energy balance of eG stays exact with moving supports."""
    m, _ = scheme.matrices()
    R_x, _ = _unconstrained_residual(scheme, scene, ctx, U)
    Xd = jnp.einsum("JI,Ind->Jnd", jnp.asarray(m["D_test"]), increments(ctx, U))
    held = jnp.asarray(scene.fixed.array)[None]
    return jnp.sum(jnp.where(held, Xd * R_x, 0.0)) / ctx.h


def end_state(scheme, scene, ctx, U) -> State:
    p_new = momenta(scheme, scene, ctx, increments(ctx, U))
    gamma = None if U.g is None else vec_to_sym(U.g[-1])
    return State(ctx.state.x + U.x[-1], p_new[-1], gamma)


def end_velocity(scheme, ctx, U):
    """$x_h'(1)/h$: the position polynomial's velocity at the step's end."""
    m, _ = scheme.matrices()
    return jnp.einsum("I,Ind->nd", jnp.asarray(m["D_end"]), increments(ctx, U)) / ctx.h


def next_velocity(scheme, scene, ctx, U, new, velocity=None):
    r"""The velocity the next step's predictor moves the body with (`Solution.end_velocity`).

    Where nodes are held, the position polynomial's end velocity (`end_velocity`). A
    free body: the velocity of its momenta, $v = M^{-1}p_{n+1}$, whose rigid part
    (`_rigid_fit`) the predictor follows at the scheme's own rotation angle, and whose
    deformation velocity u is scaled by the share of its speed that this step's motion
    kept: $s = \min(|\bar u| / |u|, 1)$, $\bar u$ the deformation part of the step's mean
    velocity $(x_{n+1} - x_n)/h$ (what is left after its rigid fit at the step's mid
    configuration). A vibration much slower than the step keeps its velocity (s ~ 1);
    one far stiffer than the step, which the scheme turns over within it, contributes
    little (s ~ 0), where moving the nodes along it for a whole step would push them away
    from the solution. (The projection $\langle \bar u, u\rangle / |u|^2$ clipped to
    [0, 1] took the same large steps but is noisy at small ones: on the 2D r4 L-shape at
    h = 0.1 it swung between -0.96 and 1.22 from step to step, and the step after the
    -0.96 (clipped to 0) stalled its chord iterations, eG(2), 4 Newton iterations.)

    Measured on the paper's L-shape (2D r1, eG(1); max over nodes, median over steps):
    the predictor missed the converged next positions at h = 1 by 1.0 when it followed
    the polynomial's end velocity (the step's secant) with the exact angle, by 0.15 with
    M^{-1}p and the exact angle, by 0.11 with the scheme's angle, and by 0.037 with this
    velocity (0.030 with no deformation velocity at all); at h = 0.1 by 1.3e-2 (end
    velocity) and 4.5e-3 (this one). At h = 0.003 the deformation velocity in full saved
    20 % of the chord iterations against none; the share keeps both regimes.

    `velocity`: $M^{-1}p_{n+1}$ where the caller has solved for it already."""
    if scene.fixed is not None:
        return end_velocity(scheme, ctx, U)
    v = scene.velocity(new.p, rtol=1e-10) if velocity is None else velocity
    rigid = _rigid_fit(new.x, v)[3]
    u = v - rigid
    mean = (new.x - ctx.state.x) / ctx.h
    u_mean = mean - _rigid_fit(0.5 * (new.x + ctx.state.x), mean)[3]
    uu = jnp.vdot(u, u)
    # clipped away from 0 before the root: a finite derivative also for a rigid motion
    share = jnp.sqrt(jnp.clip(jnp.vdot(u_mean, u_mean) / jnp.where(uu > 0, uu, 1.0), 1e-30, 1.0))
    return rigid + jnp.where(uu > 0, share, 1.0) * u


def _rotate(a, r):
    """Rotate the points `r` (n, d) by the rotation `a`: an angle (2D) or a rotation
    vector (3D, Rodrigues' formula with series where the angle is tiny)."""
    if r.shape[-1] == 2:
        c, s = jnp.cos(a), jnp.sin(a)
        return jnp.stack([c * r[:, 0] - s * r[:, 1], s * r[:, 0] + c * r[:, 1]], -1)
    phi2 = jnp.dot(a, a)
    small = phi2 < 1e-12
    phi = jnp.sqrt(jnp.where(small, 1.0, phi2))
    s1 = jnp.where(small, 1.0 - phi2 / 6.0, jnp.sin(phi) / phi)
    s2 = jnp.where(small, 0.5 - phi2 / 24.0, (1.0 - jnp.cos(phi)) / jnp.where(small, 1.0, phi2))
    ar = jnp.cross(a, r)
    return r + s1 * ar + s2 * jnp.cross(a, ar)


def _rigid_fit(x, v):
    """Best-fitting rigid motion of the nodal velocities `v` at `x` (least squares over the
    nodes): centroid c, its velocity vc, angular velocity w (a scalar in 2D), the rigid
    velocity field, and its angular speed |w|."""
    c, vc = jnp.mean(x, axis=0), jnp.mean(v, axis=0)
    r, dv = x - c, v - vc
    if x.shape[-1] == 2:
        w = jnp.sum(r[:, 0] * dv[:, 1] - r[:, 1] * dv[:, 0]) / jnp.sum(r * r)
        spin = w * jnp.stack([-r[:, 1], r[:, 0]], -1)
        speed = jnp.abs(w)
    else:
        inertia = jnp.sum(r * r) * jnp.eye(3) - r.T @ r
        w = small_solve(inertia, jnp.sum(jnp.cross(r, dv), axis=0))
        spin = jnp.cross(w, r)
        speed = jnp.sqrt(jnp.sum(w * w))
    return c, vc, w, vc + spin, speed


def rigid_motion_increments(x, v, taus, angles=None):
    """Position increments at the times `taus` (k,) after the current one for a body at
    `x` (n, d) moving with the nodal velocities `v`: the best-fitting rigid motion
    (centroid velocity and angular velocity, least squares over the nodes) is followed
    exactly, the rest of the velocity is carried along with the body's rotation. A free
    body that turns 0.6 rad per step is predicted turned, not stretched along its
    tangents as uniform motion would (|x + h v - c| grows by sqrt(1 + 0.36) there).
    `angles`: the angles (k,) the body turns through by the times `taus` at angular speed
    `s` (a scalar, >= 0), `angles(s)`; default `s * taus` (the exact rotation; a time
    element's own are `rotation_angles`)."""
    c, vc, w, rigid, speed = _rigid_fit(x, v)
    r, u = x - c, v - rigid  # u: the deformation velocity
    if angles is None:
        turn = taus
    else:  # angle per unit angular speed (the times themselves as the speed goes to 0)
        tiny = speed <= 1e-12 / jnp.maximum(jnp.max(jnp.abs(taus)), 1e-300)
        turn = jnp.where(tiny, taus, angles(jnp.where(tiny, 1.0, speed)) / jnp.where(tiny, 1.0, speed))

    def at(tau, a):
        return c + tau * vc + _rotate(w * a, r + tau * u) - x

    return jax.vmap(at)(taus, turn)


def rotation_angles(scheme, z):
    r"""The angles (k,) at the new time nodes through which the time element turns a body
    that spins at a constant rate: the phase of its nodal solution of $y' = i\omega y$,
    $y(0) = 1$, with $z = \omega h$ (traced). The trial and test functions and the momentum
    rule are the scheme's; cG(1)/eG(1) (and midpoint, Newmark) turn by the Cayley angle
    $2\arctan(z/2)$, not $z$: at the paper's h = 1 (z = 0.6) 0.583 rad, which the converged
    eG(1) steps of the L-shape reproduce to 2e-3 rad, while the exact 0.600 mispredicts
    the body's far corner by ~0.15. Degree k >= 2 turns by z to O(z^{2k+1}). Each phase is
    taken on the branch nearest the exact angle $\alpha_I z$."""
    num_re, num_im, den_re, den_im = (jnp.asarray(c) for c in _response_polynomials(scheme))
    zp = z ** jnp.arange(den_re.shape[-1])
    phase = jnp.arctan2(num_im @ zp, num_re @ zp) - jnp.arctan2(den_im @ zp, den_re @ zp)
    exact = jnp.asarray(scheme.matrices()[0]["nodes"][1:]) * z
    return exact + jnp.remainder(phase - exact + jnp.pi, 2.0 * jnp.pi) - jnp.pi


@functools.lru_cache(maxsize=None)
def _response_polynomials(scheme):
    """The time element's nodal solution of y' = lambda y, y(0) = 1 on one step as
    y_I = N_I(h lambda) / D(h lambda), at h lambda = i z: the real and imaginary parts of
    N_I(i z) and D(i z) as polynomials in z, coefficients (k, k+1), (k, k+1), (k+1,),
    (k+1,), lowest degree first. Cramer's rule on the k x k weak form
    (Q - h lambda E) y = 0 with the scheme's trial and test functions and momentum rule;
    the determinants have degree <= k, so k + 1 samples determine them. Numbers at trace
    time: no linear solve in the compiled loop (a 2k x 2k real solve there added ~300
    instructions to it)."""
    m, _ = scheme.matrices()
    Q, E = m["Q"], m["W"] @ m["V"]  # (k, k+1)
    k = Q.shape[0]
    lam = np.cos(np.pi * (np.arange(k + 1) + 0.5) / (k + 1))  # Chebyshev samples
    dets = []
    for x in lam:
        A, rhs = Q[:, 1:] - x * E[:, 1:], -(Q[:, 0] - x * E[:, 0])
        row = [np.linalg.det(A)]
        for i in range(k):
            Ai = A.copy()
            Ai[:, i] = rhs
            row.append(np.linalg.det(Ai))
        dets.append(row)
    coef = np.linalg.solve(np.vander(lam, k + 1, increasing=True), np.asarray(dets))  # (k+1, 1+k) in lambda
    coef = coef * (1j ** np.arange(k + 1))[:, None]  # in z, at lambda = i z
    num, den = coef[:, 1:].T, coef[:, 0]
    return num.real.copy(), num.imag.copy(), den.real.copy(), den.imag.copy()


def predictor(scheme, scene, ctx, velocity) -> Unknowns:
    """Position increments from the body's current motion (its best-fitting rigid motion
    followed at the scheme's own rotation angle, `rigid_motion_increments` and
    `rotation_angles`; uniform motion where nodes are held), frozen internal variable.
    `velocity`: the last step's `next_velocity` (M^-1 p at the start of a run)."""
    m, _ = scheme.matrices()
    alpha = jnp.asarray(m["nodes"][1:])
    if scene.fixed is None:
        x = rigid_motion_increments(ctx.state.x, velocity, alpha * ctx.h,
                                    lambda speed: rotation_angles(scheme, speed * ctx.h))
    else:
        x = alpha[:, None, None] * ctx.h * velocity[None]
        x = jnp.where(jnp.asarray(scene.fixed.array)[None], held_targets(scheme, scene, ctx) - ctx.state.x[None], x)
    g = None
    if ctx.state.gamma is not None:
        g = jnp.broadcast_to(sym_to_vec(ctx.state.gamma)[None], (len(alpha),) + ctx.state.gamma.shape[:-2] + (6,))
    return Unknowns(x, g)


def step_outcome(scheme, scene, ctx, r, dissipation_of_solve=False, velocity=None, new=None):
    """What a solved step yields: end state, dissipation, external work, end velocity,
    and whether it is acceptable (Newton converged and every value finite).
    `dissipation_of_solve`: take the dissipation that the solve evaluated with its last
    residual (`NewtonResult.dissipation`, where there is one) instead of evaluating it
    again; not differentiable (the loops whose derivative replays their steps).
    `velocity`: $M^{-1}p_{n+1}$ where the caller has it (`next_velocity`); `new`: the
    end state (`end_state`) where the caller has formed it."""
    new = end_state(scheme, scene, ctx, r.U) if new is None else new
    if dissipation_of_solve and r.dissipation is not None:
        D = r.dissipation
    else:
        D = step_dissipation(scheme, scene, ctx, r.U)
    W = external_work(scheme, scene, ctx, r.U)
    finite = jnp.all(jnp.isfinite(new.x)) & jnp.all(jnp.isfinite(new.p)) & jnp.isfinite(D)
    if new.gamma is not None:
        finite = finite & jnp.all(jnp.isfinite(new.gamma))
    return new, D, W, next_velocity(scheme, scene, ctx, r.U, new, velocity), r.converged & finite
