"""The jitted Newton–Krylov loop that solves one time element.

Where the stored tangent fits the step, the step starts with chord iterations on its
factorization (`_chord`: one residual and one block solve each) and ends there when
they contract; measured on the 2D L-shape (refinement 4, lumped mass, eG(1), h = 0.1,
20 steps, same process conditions) 117.6 -> 85-89 ms per step with 8 chord and 0.2
Newton iterations per step in place of 4 Newton iterations with 2.1 Krylov vectors
each. Where they do not contract (a new step size, large steps), Newton–Krylov below
takes over from the last point that did.

Per iteration: one `jax.linearize` of the step residual (its primal is the residual that
tests convergence and the line search); GMRES (`_krylov.gmres`) on its JVP,
preconditioned by the exact block solve with a condensed tangent (`_tangent`), carried
along the body's rigid rotation; forcing terms after Eisenstat–Walker with Kelley's
safeguard; a backtracking line search on the scaled residual norm. The tangent is formed
when none fits (first step, a step size more than `reuse_band` away, failed step, or a
step of another h that the chord iterations did not finish) and re-formed when the Krylov
solver needed many iterations or the line search had to backtrack, so one factorization
serves many iterations and steps. `linear_solver=Direct()` instead forms the tangent at
every iteration and takes the exact Newton step with it (no Krylov): the robust choice
for stiff regimes.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx

from .._fem._krylov import gmres
from .._time_element._step import carries_dissipation, residual_and_dissipation
from . import _amg
from ._linear import GMRES, AbstractLinearSolver, Direct, from_legacy
from ._sparse import RETAIN
from ._tangent import Tangent, body_rotation, form_tangent, schur_solve

# The step residual as a program of its own inside the loop: the chord iterations and
# Newton's linearization call it with the same shapes, so it is traced once and the
# linearization transforms that trace (XLA inlines the call: the loop compiles to +1 % HLO).
# With eG it also yields the step's dissipation at the point it evaluates
# (`residual_and_dissipation`): the accepted iterate's is the step's `D_n`.
_residual = eqx.filter_jit(residual_and_dissipation)

# Backtracking halvings (step length 1/8 or less) that make an accepted Newton iteration
# count as stalled (`NewtonKrylov.stall_limit`). Chosen with `benchmarks/stall_limit.py`
# (2, 3, 4 halvings; 2 or 3 in a row): see `benchmarks/results/stall_limit.json` and the
# benchmarks README.
_STALL_HALVINGS = 3


class NewtonKrylov(eqx.Module):
    """The Newton solver of each time element (`simulate(..., root_finder=...)`).

    Each step starts with chord iterations on a stored factorization of the condensed
    tangent where one fits the step, and continues with Newton iterations whose linear
    systems are solved by `linear_solver` (GMRES preconditioned with the condensed
    tangent by default, or exact sparse Newton steps with `Direct()`). A backtracking
    line search guards each Newton iteration. The tangent is kept across iterations and
    steps and re-formed when it no longer serves. The benchmarks pages give the
    measurements behind each default.

    **Arguments:**

    - `rtol`: the tolerance: a step has converged when the momentum residual (relative
      to the step's momentum scale) and the evolution residual are below it (max norm).
      Default 1e-10. The energy balance and the momenta hold to this tolerance; 1e-12
      suits long runs (about 25 % more iterations). A residual below 1000 `rtol` that an
      iteration no longer halves is accepted too (the rounding floor).
    - `max_iterations`: Newton iterations before the step counts as failed (20).
    - `linear_solver`: `GMRES(...)` (default) or `Direct()`. The strings `"krylov"` and
      `"direct"` mean `GMRES()` and `Direct()`.
    - `line_search`: backtracking halvings allowed per Newton iteration (8; 0 disables
      the line search).
    - `reuse_limit`: keep the tangent for the next step only if this step needed at most
      this many Newton iterations (20: only a failed step discards it).
    - `chord`: chord iterations allowed per step before Newton (10; 0 disables them).
      A chord iteration costs one residual and one solve with the stored factorization;
      they continue while the residual contracts by `chord_contraction` per iteration
      and are counted in `Solution.chord_iterations`.
    - `chord_contraction`: the contraction a chord iteration must reach (0.5).
    - `retain`: factorizations of the condensed tangent kept alive on the host (least
      recently used go first; at most 2 GiB).
    - `stall_limit`: give a step up once this many Newton iterations in a row needed
      three or more backtracking halvings (2; 0: never). The time loop then halves the
      step (or the adaptive controller shrinks it) instead of spending the remaining
      iterations far from a solution.
    - `reuse_band`: a stored tangent also serves a step whose size differs from the one
      it was formed for by at most this fraction (0.25; 0: the same size only). Where
      its chord iterations do not finish the step, a tangent for the step's own size is
      formed at once. Only adaptive runs change the step size often.
    - `krylov`, `krylov_max_steps`, `refresh_after`: deprecated (jaxvisco 0.1) aliases of
      `GMRES(backend=..., max_steps=..., refresh_after=...)`.

    **Raises:**

    `ValueError` for a setting out of its range (named with the value).

    **Example:**

    ```python
    import jaxvisco as jv

    tight = jv.NewtonKrylov(rtol=1e-12)
    exact = jv.NewtonKrylov(linear_solver=jv.Direct())
    large_3d = jv.NewtonKrylov(linear_solver=jv.GMRES(preconditioner="amg"))
    ```
    """

    rtol: float = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    linear_solver: AbstractLinearSolver = eqx.field(static=True)
    line_search: int = eqx.field(static=True)
    reuse_limit: int = eqx.field(static=True)
    chord: int = eqx.field(static=True)
    chord_contraction: float = eqx.field(static=True)
    retain: int = eqx.field(static=True)
    stall_limit: int = eqx.field(static=True)
    reuse_band: float = eqx.field(static=True)

    def __init__(self, rtol=1e-10, max_iterations=20, linear_solver=GMRES(), line_search=8, reuse_limit=20, chord=10,
                 chord_contraction=0.5, retain=RETAIN, stall_limit=2, reuse_band=0.25, *, krylov=None,
                 krylov_max_steps=None, refresh_after=None):
        self.rtol = rtol
        self.max_iterations = max_iterations
        self.linear_solver = from_legacy(linear_solver, krylov, krylov_max_steps, refresh_after)
        self.line_search = line_search
        self.reuse_limit = reuse_limit
        self.chord = chord
        self.chord_contraction = chord_contraction
        self.retain = retain
        self.stall_limit = stall_limit
        self.reuse_band = reuse_band

    def __check_init__(self):
        if not (0.0 < self.rtol < 1.0):
            raise ValueError(f"rtol must lie in (0, 1), got {self.rtol!r}.")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations!r}.")
        if isinstance(self.chord, bool) or not isinstance(self.chord, int) or self.chord < 0:
            raise ValueError(f"chord must be an integer >= 0 (0: no chord iterations), got {self.chord!r}.")
        if not (0.0 < self.chord_contraction < 1.0):
            raise ValueError(f"chord_contraction must lie in (0, 1), got {self.chord_contraction!r}.")
        if not (isinstance(self.reuse_band, (int, float)) and not isinstance(self.reuse_band, bool)
                and 0.0 <= self.reuse_band < 1.0):
            raise ValueError(f"reuse_band must be a number in [0, 1) (0: a tangent serves its own h only), "
                             f"got {self.reuse_band!r}.")
        if isinstance(self.stall_limit, bool) or not isinstance(self.stall_limit, int) or self.stall_limit < 0:
            raise ValueError(f"stall_limit must be an integer >= 0 (0: never give a step up early), "
                             f"got {self.stall_limit!r}.")


class NewtonResult(eqx.Module):
    U: eqx.Module
    converged: jax.Array
    iterations: jax.Array
    krylov_iterations: jax.Array
    chord_iterations: jax.Array
    residual: jax.Array
    tangent: Tangent
    dissipation: jax.Array | None = None  # D_n at U, where the residual carries it
    formed: jax.Array | None = None  # whether this solve formed its tangent (derivatives re-form theirs there)


def force_impulse(ctx, scene):
    """The step's force impulse at its start: h times the largest internal force or load
    on a component, a part of the momentum scale that does not vanish where the momenta
    do (a quasi-static body, density 1e-9)."""
    f = scene.internal_force(ctx.state.x, ctx.state.gamma)
    if scene.loads is not None:
        f = jnp.maximum(jnp.abs(f), jnp.abs(scene.external_force(ctx.t0)))
    return ctx.h * jnp.max(jnp.abs(f))


def _scale(ctx, scene, R0, impulse):
    """Momentum scale of a step: |p_0|, the residual at the predictor, the step's force
    impulse (`force_impulse`), and a floor tied to the positions so that a body at rest
    still has a meaningful relative tolerance. Without the force impulse a quasi-static
    body whose predictor was good had a scale near the residual's rounding (the momenta
    and the predictor's residual small beside the forces they balance), and its steps
    converged or failed by that rounding: rejections that came and went with the
    parameters, which made a fitted model discontinuous in them (issue #60's note)."""
    p = jnp.max(jnp.abs(ctx.state.p))
    f = jnp.maximum(jnp.max(jnp.abs(R0.x)), impulse)
    mx = jnp.max(jnp.abs(scene.disc.mass_matvec(ctx.state.x, scene.density))) / ctx.h
    return jnp.maximum(jnp.maximum(p, f), 1e-8 * mx)


def _norm(R, sx):
    n = jnp.max(jnp.abs(R.x)) / sx
    if R.g is not None:
        n = jnp.maximum(n, jnp.max(jnp.abs(R.g)))
    return jnp.where(jnp.isfinite(n), n, jnp.inf)


def _merit(R, sx):
    n = jnp.sum((R.x / sx) ** 2)
    if R.g is not None:
        n = n + jnp.sum(R.g**2)
    return jnp.where(jnp.isfinite(n), n, jnp.inf)


def _scaled(R, sx):
    """Momentum rows divided by the step's momentum scale (the evolution rows are
    dimensionless already)."""
    return eqx.tree_at(lambda r: r.x, R, R.x / sx)


def _axpy(a, dU, U):
    return jax.tree_util.tree_map(lambda d, u: u + a * d, dU, U)


def _lineax_gmres(matvec, precond, rhs, eta, max_steps):
    """lineax's GMRES with the same operator, preconditioner and forcing term. Its test
    is component-wise (|r_i| <= atol + rtol |b_i|); atol = eta max|b| makes it a
    max-norm test relative to the right-hand side, like ours."""
    structure = jax.eval_shape(lambda: rhs)
    op = lx.FunctionLinearOperator(matvec, structure)
    pc = lx.FunctionLinearOperator(precond, structure)
    bmax = jnp.max(jnp.stack([jnp.max(jnp.abs(b)) for b in jax.tree_util.tree_leaves(rhs)]))
    sol = lx.linear_solve(op, rhs, lx.GMRES(rtol=eta, atol=eta * bmax, restart=5, max_steps=max_steps),
                          options={"preconditioner": pc}, throw=False)
    return sol.value, sol.stats["num_steps"]


def solve_step(solver: NewtonKrylov, scheme, scene, ctx, U0, tangent: Tangent) -> NewtonResult:
    """Newton's method on one time element.

    The loop visits trial points: each is evaluated once, by the `jax.linearize` whose
    JVP the next Krylov solve needs (the primal of a linearization costs what a residual
    does), so a full Newton step costs one linearization plus its Krylov vectors; the
    line search's backtracking trials are further passes that skip the solve.
    """
    res_D = lambda U: _residual(scheme, scene, ctx, U)  # noqa: E731  (R, D_n or None)
    impulse = force_impulse(ctx, scene)
    res = lambda U: res_D(U)[0]  # noqa: E731
    direct = isinstance(solver.linear_solver, Direct)
    lin = solver.linear_solver
    # A tangent formed for another h within `reuse_band` serves the chord iterations; where
    # they do not finish the step, Newton's first iteration forms one for this h (refresh).
    mismatch = tangent.h != ctx.h
    near = jnp.abs(ctx.h / tangent.h - 1.0) <= solver.reuse_band
    stale = direct | tangent.stale | (mismatch & ~near)
    rotation = body_rotation(scene, ctx.state.x)

    def form(U):  # the condensed tangent at U, carried along the body's rotation from here
        return form_tangent(scheme, scene, ctx, U, rotation, solver.retain, lin.block_solver(scene), lin.block_dtype())

    def done(norm, prev):
        return (norm <= solver.rtol) | ((norm <= 1e3 * solver.rtol) & (norm > 0.5 * prev))

    def body(c):
        first = c["it"] < 0
        Ut = _axpy(c["a"], c["dU"], c["U"])
        if direct:
            (Rt, Dt), jvp = res_D(Ut), None
        elif lin.memory_first(scene):
            # no linearization kept through the tangent formation and the Krylov loop
            # (hex8 r4: 103 MB of XLA buffers at the peak); each JVP re-runs the primal
            Rt, Dt = res_D(Ut)
            jvp = lambda v: jax.jvp(res, (Ut,), (v,))[1]  # noqa: E731
        else:
            Rt, jvp, Dt = jax.linearize(res_D, Ut, has_aux=True)
        sx = jnp.where(first, _scale(ctx, scene, Rt, impulse), c["sx"])
        norm_t = _norm(Rt, sx)
        decrease = _merit(Rt, sx) <= (1.0 - 1e-4 * c["a"]) * _merit(c["R"], sx)
        accept = first | decrease | (c["n_ls"] >= solver.line_search)
        prev = jnp.where(first, jnp.inf, c["norm"])
        n_newton = jnp.maximum(c["it"], 0)
        stall = jnp.where(accept & ~first, jnp.where(c["n_ls"] >= _STALL_HALVINGS, c["stall"] + 1, 0), c["stall"])
        go_on = accept & ~done(norm_t, prev) & (n_newton < solver.max_iterations) & jnp.isfinite(norm_t)
        if solver.stall_limit:
            go_on = go_on & (stall < solver.stall_limit)
        refresh = c["refresh"] | (c["n_ls"] > 0)  # a step that needed backtracking

        def newton_step(tan):
            if not form_at_start:
                tan = jax.lax.cond(refresh, lambda: form(Ut), lambda: tan)
            precond = lambda r: schur_solve(scheme, scene, ctx, tan, _scaled(r, 1.0 / sx), rotation)  # noqa: E731
            rhs = jax.tree_util.tree_map(jnp.negative, _scaled(Rt, sx))
            if direct:
                return precond(rhs), jnp.asarray(0), tan
            matvec = lambda v: _scaled(jvp(v), sx)  # noqa: E731
            # Eisenstat–Walker (choice 2) forcing, kept in [1e-12, 1e-2], and never
            # tighter than the nonlinear tolerance needs (after Kelley's safeguard): with
            # |r|_max <= |r|_2 <= eta |b|_2, eta = rtol / (10 |b|_2) lands the linear
            # model at rtol / 10, so the last iteration does not over-solve.
            bnorm = jnp.sqrt(sum(jnp.sum(b**2) for b in jax.tree_util.tree_leaves(rhs)))
            eta = jnp.maximum(0.9 * (norm_t / jnp.minimum(prev, 1.0)) ** 2, 0.1 * solver.rtol / bnorm)
            eta = jnp.clip(eta, 1e-12, 1e-2)
            if lin.backend == "lineax":
                dU_s, n_lin = _lineax_gmres(matvec, precond, rhs, eta, lin.max_steps)
            else:
                # the multigrid's 3D meshes: memory first (`gmres(recompute=True)`, restarts)
                dU_s, n_lin, _ = gmres(matvec, precond, rhs, eta, lin.max_steps,
                                       recompute=lin.memory_first(scene), restart=lin.restart_for(scene))
            return dU_s, n_lin, tan

        def skip(tan):
            return c["dU"], jnp.asarray(0), tan

        dU, n_lin, tan = jax.lax.cond(go_on, newton_step, skip, c["tan"])
        keep = lambda new, old: jax.tree_util.tree_map(lambda n, o: jnp.where(accept, n, o), new, old)  # noqa: E731
        return dict(
            U=keep(Ut, c["U"]), R=keep(Rt, c["R"]), D=keep(Dt, c["D"]), norm=jnp.where(accept, norm_t, c["norm"]),
            prev=jnp.where(accept, prev, c["prev"]), sx=sx, dU=dU,
            a=jnp.where(accept, 1.0, 0.5 * c["a"]), n_ls=jnp.where(accept, 0, c["n_ls"] + 1),
            it=c["it"] + go_on.astype(int) + first.astype(int), kits=c["kits"] + n_lin, tan=tan,
            refresh=jnp.where(accept, direct or (n_lin > lin.refresh_after), c["refresh"]),
            asked=c["asked"] | (go_on & refresh),  # a Newton step that wanted a fresh tangent
            pending=go_on | ~accept, stall=stall,
        )

    # The residual has the unknowns' structure (`residual`): no trace of it for its shape
    # (`jax.eval_shape` traced the whole residual again: ~0.4 s of a cold first call).
    zero = jax.tree_util.tree_map(jnp.zeros_like, U0)
    U_start, chord_its, chord_done = U0, jnp.asarray(0), jnp.asarray(False)
    D_none = jnp.asarray(0.0) if carries_dissipation(scheme, scene) else None  # the loops' start value
    chord_state = None
    form_at_start = lin.memory_first(scene) and not direct
    if form_at_start:
        # The multigrid path (large 3D meshes) forms a stale tangent at the predictor, the one
        # place its loop forms one: the step then starts with chord iterations, as a step with
        # a fitting tangent does, and Newton–Krylov keeps that tangent (a refresh it asks for
        # marks the tangent stale for the next step instead). There a Krylov vector (a JVP,
        # 2.7 residuals, and four W-cycles when measured: 2.2 s at hex8 r9) costs more than a
        # chord iteration (a residual and cycles to a 50-fold reduction: 1.4 s); the first
        # step used to take 3 Newton iterations with 10 Krylov vectors (hex8 r8: first step
        # 33.2 -> 21.6-26.4 s, none left); and one copy of the formation in the compiled loop
        # instead of two compiles faster (hex8 r8: 83 s with both copies, 58-59 s with this
        # one). The LU path (small meshes) keeps Newton's refresh.
        tangent = jax.lax.cond(stale | mismatch, lambda: form(U0), lambda: tangent)
        formed_at_start = stale | mismatch
        stale = mismatch = jnp.asarray(False)
    if solver.chord and not direct:
        chord_state = _chord(solver, scheme, scene, ctx, U0, tangent, rotation, stale, res_D, D_none, impulse)
        U_start, chord_its, chord_done = chord_state["U"], chord_state["it"], chord_state["done"]
    init = dict(U=U_start, R=zero, D=D_none,
                norm=jnp.asarray(jnp.inf), prev=jnp.asarray(jnp.inf), sx=jnp.asarray(1.0), dU=zero,
                a=jnp.asarray(0.0), n_ls=jnp.asarray(0), it=jnp.asarray(-1), kits=jnp.asarray(0),
                tan=tangent, refresh=stale | mismatch, asked=jnp.asarray(False), pending=~chord_done,
                stall=jnp.asarray(0))
    c = jax.lax.while_loop(lambda c: c["pending"], body, init)
    if chord_state is not None:
        c = dict(c, norm=jnp.where(chord_done, chord_state["norm"], c["norm"]),
                 prev=jnp.where(chord_done, chord_state["prev"], c["prev"]),
                 it=jnp.where(chord_done, 0, c["it"]),
                 D=jax.tree_util.tree_map(lambda a, b: jnp.where(chord_done, a, b), chord_state["D"], c["D"]))
    converged = done(c["norm"], c["prev"])
    stale_after = (~converged) | (c["it"] > solver.reuse_limit)
    if form_at_start:  # a refresh Newton asked for (it does not form here): at the next step
        stale_after = stale_after | c["asked"]
    tan = eqx.tree_at(lambda t: t.stale, c["tan"], stale_after)
    formed = formed_at_start if form_at_start else c["asked"]  # Newton forms exactly where it asks to
    return NewtonResult(c["U"], converged, c["it"], c["kits"], chord_its, c["norm"], tan, c["D"], formed)


def _chord(solver, scheme, scene, ctx, U0, tangent, rotation, stale, res_D, D_none, impulse):
    """Chord iterations on the stored factorization: U <- U - P^{-1} R(U), one residual and
    one block solve each, while the residual contracts by `chord_contraction` per
    iteration; stops at convergence (rtol, strictly) or hands the last point reached by
    a contracting iteration over to Newton–Krylov. On the multigrid path the block
    solve cycles to `_amg.CHORD_RTOL` (no Krylov method here needs it linear).

    A loop of their own, measured against passes of Newton's loop (one site of the
    residual in the compiled program, the tangent formed by an outer loop so that no
    pass copies it; same iterates, counts and end states to 1e-14): with the step's
    `jax.linearize` at that site a chord pass costs a linearization (2D L-shape r4,
    lumped, eG(1), h = 0.1, 120 steps, alternating processes: 8.5 -> 11.8 ms per step);
    with a plain residual there and `jax.jvp` in the Krylov solve, 8.2 -> 8.3 ms but the
    JVP's primal is the copy saved (compile 7.06 -> 7.08 s); the paper scene's cold first
    call 7.00 / 6.76 s -> 6.73 / 6.81 s (linearization), 6.82 / 6.85 s (jvp). Kept apart."""

    def cond(c):
        return c["go"]

    def body(c):
        R, D = res_D(c["Ut"])
        sx = jnp.where(c["it"] == 0, _scale(ctx, scene, R, impulse), c["sx"])
        norm = _norm(R, sx)
        contracting = (c["it"] == 0) | (norm <= solver.chord_contraction * c["norm"])
        better = contracting & jnp.isfinite(norm)
        U, D = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), (c["Ut"], D), (c["U"], c["D"]))
        done = better & (norm <= solver.rtol)
        go = better & ~done & (c["it"] < solver.chord)
        Ut = jax.lax.cond(
            go, lambda: _axpy(1.0, schur_solve(scheme, scene, ctx, tangent, jax.tree_util.tree_map(jnp.negative, R),
                                               rotation, _amg.CHORD_RTOL), c["Ut"]), lambda: c["Ut"])
        return dict(U=U, D=D, Ut=Ut, norm=jnp.where(better, norm, c["norm"]),
                    prev=jnp.where(better, c["norm"], c["prev"]),
                    sx=sx, it=c["it"] + 1, done=done, go=go)

    init = dict(U=U0, D=D_none, Ut=U0, norm=jnp.asarray(jnp.inf), prev=jnp.asarray(jnp.inf), sx=jnp.asarray(1.0),
                it=jnp.asarray(0), done=jnp.asarray(False), go=~stale)
    c = jax.lax.while_loop(cond, body, init)
    # it counts residual evaluations; the solves taken = it - 1 (the last one is unused)
    return dict(U=c["U"], D=c["D"], norm=c["norm"], prev=c["prev"], it=jnp.maximum(c["it"] - 1, 0), done=c["done"])
