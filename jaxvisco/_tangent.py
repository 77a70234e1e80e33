"""The condensed tangent of a time element and its exact block solve.

The Jacobian of the step residual has a position block and an internal-variable block
that is block diagonal over spatial quadrature points (Γ is local). At every quadrature
point the local block is inverted in closed loops of array arithmetic and condensed into
the stress sensitivity, exactly as a consistent algorithmic tangent in a
return-mapping code:

    dP/dF|total = ∂P/∂F + ∂P/∂Γ · dΓ/dF,   dΓ/dF = -(∂R_Γ/∂Γ)^{-1} ∂R_Γ/∂F.

The local derivatives come from the Newton iteration's own linearization of the point
kernel (`_step.linearize`), applied to the 9k + 6k unit directions one after the other
(`lax.map`): the compiled program holds one linearized material law for the Krylov JVP
and the tangent together, and only one direction's intermediates are alive at a time.
Measured against a separate `jacfwd` of the point kernel (eG(1)): the whole 2D L-shape
run compiles to 13 223 HLO instructions instead of 14 608, and the 3D L-shape (hex8
refinement 4, 26 871 DOFs) peaks at 3.5 GB RSS instead of 4.9 GB (6.4 GB with all
directions at once under `vmap`).

The position block (the Schur complement) is assembled element by element into one
sparse matrix (pattern fixed per mesh and degree) and factored on the host. `schur_solve`
then solves the full linearized system exactly at the point where the tangent was
formed; away from it, it is the preconditioner of the Krylov solver.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._sparse import HostLU, lu_factor, lu_solve
from ._step import Linearization, Unknowns, constraint_scale, force_term
from ._tensor import small_inv, vec_to_sym


@functools.lru_cache(maxsize=32)
def position_pattern(cells, k, n_nodes, dim, fixed=None):
    """Host factorization object for the (k n d)^2 position block of a mesh (element
    blocks, then one diagonal entry per held component and time node)."""
    c = cells.array
    J = np.arange(k)[:, None, None]
    i = np.arange(dim)[None, None, :]
    dofs = (J * n_nodes * dim)[None] + c[:, None, :, None] * dim + i[None]  # (e, k, n_en, d)
    dofs = dofs.reshape(c.shape[0], -1)
    rows = np.broadcast_to(dofs[:, :, None], dofs.shape + (dofs.shape[1],)).ravel()
    cols = np.broadcast_to(dofs[:, None, :], dofs.shape + (dofs.shape[1],)).ravel()
    if fixed is not None:
        held = _held_dofs(fixed, k, n_nodes, dim)
        rows, cols = np.concatenate([rows, held]), np.concatenate([cols, held])
    return HostLU(rows, cols, k * n_nodes * dim)


def _held_dofs(fixed, k, n_nodes, dim):
    flat = np.flatnonzero(fixed.array.ravel())
    return (np.arange(k)[:, None] * n_nodes * dim + flat[None]).ravel()


def body_rotation(scene, x):
    r"""Rotation Q (d, d) that best maps the initial positions onto `x` about their
    centroids (polar factor of $\sum_a (x_a - \bar x)(X_a - \bar X)^T$); the identity for a
    scene with held nodes, which cannot rotate freely."""
    d = scene.dim
    if scene.fixed is not None:
        return jnp.eye(d, dtype=x.dtype)
    X = scene.x0
    A = (x - jnp.mean(x, axis=0)).T @ (X - jnp.mean(X, axis=0))
    if d == 2:
        th = jnp.arctan2(A[1, 0] - A[0, 1], A[0, 0] + A[1, 1])
        c, s = jnp.cos(th), jnp.sin(th)
        return jnp.array([[c, -s], [s, c]])
    u, _, vt = jnp.linalg.svd(A)
    flip = jnp.sign(jnp.linalg.det(u @ vt))
    return (u * jnp.stack([1.0, 1.0, flip])) @ vt


class Tangent(eqx.Module):
    token: jax.Array  # host LU of the position block (-1: none)
    h: jax.Array  # step the tangent was formed for
    stale: jax.Array  # re-form before the next use
    rotation: jax.Array  # body rotation (d, d) where it was formed (`body_rotation`)
    Ainv: jax.Array | None  # (n_cells, nq, 6k, 6k) inverse local block
    dG_dF: jax.Array | None  # (n_cells, nq, 6k, 9k)
    dP_dG: jax.Array | None  # (n_cells, nq, nq_t*9, 6k)


def empty_tangent(scheme, scene):
    k = scheme.k
    nq_t = len(scheme.matrices()[0]["points"])
    head = (jnp.asarray(-1, jnp.int64), jnp.asarray(jnp.nan), jnp.asarray(True), jnp.eye(scene.dim))
    if not scene.has_internal_variable:
        return Tangent(*head, None, None, None)
    ne, nq = scene.disc.n_cells, scene.disc.n_qp
    z = functools.partial(jnp.zeros, dtype=float)
    return Tangent(*head, z((ne, nq, 6 * k, 6 * k)), z((ne, nq, 6 * k, 9 * k)), z((ne, nq, nq_t * 9, 6 * k)))


def _condense(dP_dF, dP_dg, dR_dF, dR_dg):
    """Eliminate Γ at one spatial point: (dP/dF total, A⁻¹, dΓ/dF, dP/dΓ)."""
    Ainv = small_inv(dR_dg)
    dG_dF = -Ainv @ dR_dF
    return dP_dF + dP_dg @ dG_dF, Ainv, dG_dF, dP_dg


def point_sensitivities(scheme, scene, lin: Linearization):
    """Derivatives of the point kernel with respect to the unknown deformation gradients
    (9k) and internal variables (6k, Voigt) at every spatial point, from the step's
    linearization: one vmap of its linear point map over the 9k + 6k unit directions
    (the same linear program the Krylov solver's JVP runs; nothing is re-linearized).

    **Returns:** `(dP/dF, dP/dg, dR/dF, dR/dg)`, shaped (n_cells, nq, rows, columns) with
    rows (time point, 3, 3) of P and (time node, 6) of R_G, columns (node, 3, 3) and (node, 6).
    """
    k, disc = scheme.k, scene.disc
    ne, nq = disc.n_cells, disc.n_qp
    nF = 9 * k
    zero_node = lambda n: jnp.zeros((n, 1, 3, 3))  # noqa: E731  (the start node is known)
    dF = jnp.concatenate([zero_node(nF), jnp.eye(nF).reshape(nF, k, 3, 3)], axis=1)
    spread = lambda d: jnp.broadcast_to(d[:, None, None], (d.shape[0], ne, nq) + d.shape[1:])  # noqa: E731
    if lin.R_G is None:
        dP, _ = jax.lax.map(lambda f: lin.point_jvp(f, None), spread(dF))
        return jnp.moveaxis(dP, 0, -1).reshape(ne, nq, -1, nF), None, None, None
    nG = 6 * k
    dG = jnp.concatenate([zero_node(nG), vec_to_sym(jnp.eye(nG).reshape(nG, k, 6))], axis=1)
    dirs_F = jnp.concatenate([dF, jnp.zeros((nG, k + 1, 3, 3))])
    dirs_G = jnp.concatenate([jnp.zeros((nF, k + 1, 3, 3)), dG])
    dP, dR = jax.lax.map(lambda fg: lin.point_jvp(*fg), (spread(dirs_F), spread(dirs_G)))
    dP = jnp.moveaxis(dP, 0, -1).reshape(ne, nq, -1, nF + nG)
    dR = jnp.moveaxis(dR, 0, -1).reshape(ne, nq, nG, nF + nG)
    return dP[..., :nF], dP[..., nF:], dR[..., :nF], dR[..., nF:]


def form_tangent(scheme, scene, ctx, lin: Linearization, rotation=None) -> Tangent:
    """Condensed tangent at the point `lin` was taken (`_step.linearize`): local
    inverses, sensitivities, and the factored position block
    $A \\otimes M / h + h\\,\\sum_l W K_l$ (exact, with Γ eliminated)."""
    m, _ = scheme.matrices()
    k, d, disc = scheme.k, scene.dim, scene.disc
    dPdF, dPdG, dRdF, dRdG = point_sensitivities(scheme, scene, lin)
    if dPdG is None:
        Ainv = dGdF = None
    else:
        dPdF, Ainv, dGdF, dPdG = jax.vmap(jax.vmap(_condense))(dPdF, dPdG, dRdF, dRdG)
    ne, nq = disc.n_cells, disc.n_qp
    nq_t = dPdF.shape[2] // 9
    dPdF = dPdF.reshape(ne, nq, nq_t, 3, 3, k, 3, 3)[:, :, :, :d, :d, :, :d, :d]
    W = jnp.asarray(m["W"])
    # K[e, J, a, i, I, b, j] = h sum_q JxW sum_l W[J,l] dN[a,A] dPdF[l,i,A,I,j,B] dN[b,B]
    K = ctx.h * jnp.einsum("eq,Jl,eqaA,eqliAIjB,eqbB->eJaiIbj", disc.JxW, W, disc.dN, dPdF, disc.dN)
    A = jnp.asarray(m["A"])[:, 1:]
    Mass = scene.density * jnp.einsum("JI,eab,ij->eJaiIbj", A, disc.mass_el, jnp.eye(d)) / ctx.h
    Ke = K + Mass
    if scene.fixed is not None:
        free = ~scene.fixed.array[disc.cells.array]  # (e, n_en, d)
        free = np.broadcast_to(free[:, None], (ne, k) + free.shape[1:])
        Ke = Ke * jnp.asarray(free)[:, :, :, :, None, None, None] * jnp.asarray(free)[:, None, None, None]
        n_held = len(_held_dofs(scene.fixed, k, disc.n_nodes, d))
        data = jnp.concatenate([Ke.reshape(-1), jnp.full(n_held, constraint_scale(scene, ctx.h))])
    else:
        data = Ke.reshape(-1)
    host = position_pattern(disc.cells, k, disc.n_nodes, d, scene.fixed)
    token = lu_factor(host, data)
    rotation = jnp.eye(d) if rotation is None else rotation
    return Tangent(token, ctx.h, jnp.asarray(False), rotation, Ainv, dGdF, dPdG)


def schur_solve(scheme, scene, ctx, tangent: Tangent, b: Unknowns, rotation=None) -> Unknowns:
    """Solve the linearized step equations with the condensed tangent (exact where the
    tangent was formed).

    With `rotation` (the body's rotation now, `body_rotation`) the tangent is carried
    along the rigid rotation R since it was formed: if every position turns by R, the
    stresses P = F S turn with it and C, Γ do not, so the Jacobian becomes T J Tᵀ with
    T = diag(R on positions, 1 on Γ), and its inverse T J⁻¹ Tᵀ. A body that spins keeps
    a preconditioner that fits, where the unrotated one degrades within a few steps.
    """
    k, d, disc = scheme.k, scene.dim, scene.disc
    host = position_pattern(disc.cells, k, disc.n_nodes, d, scene.fixed)
    R = None if rotation is None else rotation @ tangent.rotation.T
    bx = b.x if R is None else b.x @ R  # R^T b per node
    if b.g is not None:
        bg = jnp.moveaxis(b.g, 0, 2).reshape(disc.n_cells, disc.n_qp, 6 * k)
        z = jnp.einsum("eqab,eqb->eqa", tangent.Ainv, bg)
        dP = jnp.einsum("eqab,eqb->eqa", tangent.dP_dG, z)
        dP = dP.reshape(disc.n_cells, disc.n_qp, -1, 3, 3)
        coupling = force_term(scheme, scene, ctx, dP)
        if scene.fixed is not None:
            coupling = jnp.where(jnp.asarray(scene.fixed.array)[None], 0.0, coupling)
        bx = bx - coupling
    dx = lu_solve(host, tangent.token, bx.reshape(-1)).reshape(bx.shape)
    turn = (lambda v: v) if R is None else (lambda v: v @ R.T)  # R v per node
    if b.g is None:
        return Unknowns(turn(dx), None)
    dF = jnp.moveaxis(disc.gradient(dx), 0, 2)  # (e, q, k, 3, 3), zero F33 row in 2D
    dg = z + jnp.einsum("eqab,eqb->eqa", tangent.dG_dF, dF.reshape(disc.n_cells, disc.n_qp, 9 * k))
    dg = jnp.moveaxis(dg.reshape(disc.n_cells, disc.n_qp, k, 6), 2, 0)
    return Unknowns(turn(dx), dg)
