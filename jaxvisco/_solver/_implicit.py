"""Derivatives of a time step by the implicit function theorem.

A converged step solves $R(U;\\,\\theta) = 0$, where $\\theta$ is everything the step
depends on (scene parameters: material, density, loads; the start state; the time).
Its derivative is $dU = -R_U^{-1} R_\\theta\\,d\\theta$, so Newton's iterations are never
differentiated: `solve_step_implicit` is a `custom_jvp` whose rule forms the condensed
tangent at the converged $U$ and solves the one linear system with the exact block
solve (`schur_solve`) plus iterative refinement. Every piece of that rule is linear
in the tangents and transposable (the sparse LU solve is a primitive with a transpose
rule), so reverse mode works through JAX's transposition of the rule: one transposed
solve per step with the transposed factors, the pattern of optimistix's implicit differentiation.

On the multigrid path (`GMRES(preconditioner="amg")`) the block solve is not exact (a
few W-cycles), so a fixed number of refinement sweeps would leave an error that depends
on the mesh: there the system is solved by GMRES to `KRYLOV_RTOL` inside
`jax.lax.custom_linear_solve`, whose transpose (reverse mode) is GMRES on the
transposed JVP right-preconditioned by the transposed W-cycles (`jax.linear_transpose`:
the multigrid solve is a fixed linear map of its right-hand side). That is lineax's
pattern: a linear solve as a primitive that knows its own transpose.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._fem._krylov import gmres
from .._time_element._step import residual
from ._newton import _scale, solve_step
from ._tangent import form_tangent, schur_solve

_SWEEPS = 2
# Relative residual of the multigrid path's implicit solve (and its transpose), and its
# Krylov vectors at most.
KRYLOV_RTOL = 1e-12
KRYLOV_MAX_STEPS = 80


def refined_solve(matvec, precond, b, sweeps=_SWEEPS):
    r"""$y = S b$ improved by `sweeps` steps of iterative refinement $y += S(b - A y)$.

    With S the exact block solve at the converged step, $\|I - AS\| \approx 10^{-11}$
    (measured), so two sweeps reach rounding. The map is linear in `b` with a fixed
    number of operations, so JAX transposes it exactly (reverse mode) without any
    tolerance that would depend on the size of the tangent.
    """
    add = lambda u, v: jax.tree_util.tree_map(jnp.add, u, v)  # noqa: E731
    sub = lambda u, v: jax.tree_util.tree_map(jnp.subtract, u, v)  # noqa: E731
    y = precond(b)
    for _ in range(sweeps):
        y = add(y, precond(sub(b, matvec(y))))
    return y


def krylov_solve(matvec, precond, b, rtol=KRYLOV_RTOL, max_steps=KRYLOV_MAX_STEPS):
    r"""$y = A^{-1} b$ by right-preconditioned GMRES (`precond` $\approx A^{-1}$, linear),
    as a `jax.lax.custom_linear_solve`: differentiable and transposable in `b`, the
    transpose solved by GMRES on $A^T$ with the preconditioner's transpose."""

    def solve(A, r):
        return gmres(A, precond, r, rtol, max_steps, recompute=True)[0]

    def transpose_solve(AT, r):
        precond_t = jax.linear_transpose(precond, r)
        return gmres(AT, lambda v: precond_t(v)[0], r, rtol, max_steps, recompute=True)[0]

    return jax.lax.custom_linear_solve(matvec, b, solve, transpose_solve)


def materialize_zeros(tangents, primals):
    """`tangents` with each symbolic zero (`None`, an output that does not depend on what
    is differentiated) replaced by zeros shaped like its primal."""
    return jax.tree_util.tree_map(lambda t, p: jnp.zeros_like(p) if t is None else t, tangents, primals,
                                  is_leaf=lambda t: t is None)


@eqx.filter_custom_jvp
def _solve(scene, ctx, U0, tangent, *, solver, scheme):
    return solve_step(solver, scheme, scene, ctx, U0, tangent)


@_solve.def_jvp
def _solve_jvp(primals, tangents, *, solver, scheme):
    scene, ctx, U0, tangent = primals
    d_scene, d_ctx, _, _ = tangents
    out = solve_step(solver, scheme, scene, ctx, U0, tangent)
    U = out.U
    res = lambda s, c: residual(scheme, s, c, U)  # noqa: E731
    R, dR = eqx.filter_jvp(res, (scene, ctx), (d_scene, d_ctx))
    dR = materialize_zeros(dR, R)
    sx = jnp.maximum(_scale(ctx, scene, R), 1e-300)  # R: the residual at U, from the JVP above

    def scaled(R):
        return eqx.tree_at(lambda r: r.x, R, R.x / sx)

    def unscale(R):
        return eqx.tree_at(lambda r: r.x, R, R.x * sx)

    _, jvp = jax.linearize(lambda u: scaled(residual(scheme, scene, ctx, u)), U)
    block = solver.linear_solver.block_solver(scene)
    # float64 multigrid whatever `multigrid_precision`: `krylov_solve` forms its solution
    # as M^{-1}(V y) (`gmres(recompute=True)`), exact for a linear M only, and float32
    # W-cycles are linear to float32 rounding only. 3D hex8 r1 with held nodes, 4 steps of
    # eG(1), gradient of a loss against fourth-order finite differences
    # (`test_gradient_on_the_multigrid_path_matches_finite_differences`): relative errors
    # 2e-7 to 1.1e-6 with float32 cycles, depending on how XLA rounded the forward
    # arithmetic; 1e-12 to 3e-10 with float64 ones.
    tan = form_tangent(scheme, scene, ctx, U, retain=solver.retain, preconditioner=block, block_dtype=np.float64)
    linear = refined_solve if block == "lu" else krylov_solve
    dU = linear(jvp, lambda r: schur_solve(scheme, scene, ctx, tan, unscale(r)),
                scaled(jax.tree_util.tree_map(jnp.negative, dR)))
    t_out = jax.tree_util.tree_map(lambda _: None, out)
    t_out = eqx.tree_at(lambda o: o.U, t_out, dU, is_leaf=lambda x: x is None)
    return out, t_out


def solve_step_implicit(solver, scheme, scene, ctx, U0, tangent):
    """`solve_step` whose solution is differentiable (forward and reverse) with respect
    to the scene and the step context, by the implicit function theorem."""
    U0 = jax.lax.stop_gradient(U0)
    tangent = jax.lax.stop_gradient(tangent)
    return _solve(scene, ctx, U0, tangent, solver=solver, scheme=scheme)
