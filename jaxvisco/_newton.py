"""The jitted Newton–Krylov loop that solves one time element.

Per iteration: one `jax.linearize` of the step residual; GMRES (`_krylov.gmres`) on its JVP,
preconditioned by the exact block solve with a condensed tangent (`_tangent`); forcing
terms after Eisenstat–Walker; a backtracking line search on the scaled residual norm.
The tangent is formed when none fits (first step, new step size) and re-formed when the
Krylov solver needed many iterations, so one factorization serves many iterations and
steps. `linear_solver="direct"` instead forms the tangent at every iteration and takes
the exact Newton step with it (no Krylov): the robust choice for stiff regimes.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx

from ._krylov import gmres
from ._step import residual
from ._tangent import Tangent, form_tangent, schur_solve

_LINEAR_SOLVERS = ("krylov", "direct")
_KRYLOV = ("gmres", "lineax")


class NewtonKrylov(eqx.Module):
    """Settings of the nonlinear solver of each time element.

    **Arguments:**
    - `rtol`: convergence when the momentum residual (relative to the momentum scale of
      the step) and the evolution residual are below it (max norm). Default 1e-10. A
      residual below 1000 rtol that an iteration no longer halves is accepted too: that
      is the rounding floor of the residual, which Newton cannot go below. Energy balance
      and momenta hold to this tolerance: the paper's L-shape drifts ~3e-10 in angular
      momentum over its first 1000 steps at 1e-10 and ~1e-13 at 1e-12 (about 25 % more
      iterations), the setting for long runs.
    - `max_iterations`: Newton iterations before the step counts as failed (20).
    - `linear_solver`: `"krylov"` (GMRES with the condensed-tangent preconditioner,
      default) or `"direct"` (exact Newton steps with a fresh sparse factorization).
    - `krylov`: `"gmres"` (default: jaxvisco's right-preconditioned GMRES, which checks
      the residual after every Arnoldi step) or `"lineax"` (lineax's `GMRES`, restarted
      every 5 vectors; it checks convergence once per restart cycle and needs two
      cycles, so it costs more Krylov vectors: see `_krylov`).
    - `krylov_max_steps`: GMRES iterations per Newton iteration (60).
    - `refresh_after`: re-form the tangent once GMRES needed more iterations than this (8).
    - `line_search`: backtracking halvings allowed per iteration (8; 0 disables it).
    - `reuse_limit`: keep the tangent for the next step only if this step needed at most
      this many Newton iterations (3).
    """

    rtol: float = eqx.field(static=True, default=1e-10)
    max_iterations: int = eqx.field(static=True, default=20)
    linear_solver: str = eqx.field(static=True, default="krylov")
    krylov: str = eqx.field(static=True, default="gmres")
    krylov_max_steps: int = eqx.field(static=True, default=60)
    refresh_after: int = eqx.field(static=True, default=8)
    line_search: int = eqx.field(static=True, default=8)
    reuse_limit: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        if self.linear_solver not in _LINEAR_SOLVERS:
            raise ValueError(f"linear_solver must be one of {_LINEAR_SOLVERS}, got {self.linear_solver!r}.")
        if self.krylov not in _KRYLOV:
            raise ValueError(f"krylov must be one of {_KRYLOV}, got {self.krylov!r}.")
        if not (0.0 < self.rtol < 1.0):
            raise ValueError(f"rtol must lie in (0, 1), got {self.rtol!r}.")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations!r}.")


class NewtonResult(eqx.Module):
    U: eqx.Module
    converged: jax.Array
    iterations: jax.Array
    krylov_iterations: jax.Array
    residual: jax.Array
    tangent: Tangent


def _scale(ctx, scene, R0):
    """Momentum scale of a step: |p_0|, the step's force impulse, and a floor tied to the
    positions so that a body at rest still has a meaningful relative tolerance."""
    p = jnp.max(jnp.abs(ctx.state.p))
    f = jnp.max(jnp.abs(R0.x))
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
    res = lambda U: residual(scheme, scene, ctx, U)  # noqa: E731
    R0 = res(U0)
    sx = _scale(ctx, scene, R0)
    direct = solver.linear_solver == "direct"
    stale = direct | tangent.stale | (tangent.h != ctx.h)

    def scaled(R):
        return eqx.tree_at(lambda r: r.x, R, R.x / sx)

    def unscale(R):
        return eqx.tree_at(lambda r: r.x, R, R.x * sx)

    def done(norm, prev):
        return (norm <= solver.rtol) | ((norm <= 1e3 * solver.rtol) & (norm > 0.5 * prev))

    def cond(c):
        U, R, norm, it, kits, tan, refresh, prev = c
        return ~done(norm, prev) & (it < solver.max_iterations) & jnp.isfinite(norm)

    def body(c):
        U, R, norm, it, kits, tan, refresh, prev = c
        tan = jax.lax.cond(refresh, lambda: form_tangent(scheme, scene, ctx, U), lambda: tan)
        precond = lambda r: schur_solve(scheme, scene, ctx, tan, unscale(r))  # noqa: E731
        rhs = scaled(jax.tree_util.tree_map(jnp.negative, R))
        if direct:
            dU_s, n_lin = precond(rhs), jnp.asarray(0)
        else:
            _, jvp = jax.linearize(lambda u: scaled(res(u)), U)
            # Eisenstat–Walker (choice 2) forcing, kept in [1e-12, 1e-2].
            eta = jnp.clip(0.9 * (norm / jnp.minimum(prev, 1.0)) ** 2, 1e-12, 1e-2)
            if solver.krylov == "lineax":
                dU_s, n_lin = _lineax_gmres(jvp, precond, rhs, eta, solver.krylov_max_steps)
            else:
                dU_s, n_lin, _ = gmres(jvp, precond, rhs, eta, solver.krylov_max_steps)
        dU = dU_s
        phi0 = _merit(R, sx)

        # Backtracking as a do-while loop: the full step is tried in the loop body too,
        # so the program holds one copy of the residual for the line search, not two.
        def ls_cond(s):
            a, Rn, n = s
            return (n == 0) | ((_merit(Rn, sx) > (1.0 - 1e-4 * a) * phi0) & (n <= solver.line_search))

        def ls_body(s):
            a, _, n = s
            a = jnp.where(n == 0, 1.0, 0.5 * a)
            return a, res(_axpy(a, dU, U)), n + 1

        a, Rn, n_ls = jax.lax.while_loop(ls_cond, ls_body, (jnp.asarray(1.0), R, 0))
        n_ls = n_ls - 1  # halvings
        U = _axpy(a, dU, U)
        new_norm = _norm(Rn, sx)
        refresh = direct | (n_lin > solver.refresh_after) | (n_ls > 0)
        return U, Rn, new_norm, it + 1, kits + n_lin, tan, refresh, norm

    init = (U0, R0, _norm(R0, sx), jnp.asarray(0), jnp.asarray(0), tangent, stale, jnp.asarray(jnp.inf))
    U, R, norm, it, kits, tan, _, prev = jax.lax.while_loop(cond, body, init)
    converged = done(norm, prev)
    tan = eqx.tree_at(lambda t: t.stale, tan, (~converged) | (it > solver.reuse_limit))
    return NewtonResult(U, converged, it, kits, norm, tan)
