"""The condensed tangent of a time element and its exact block solve.

The Jacobian of the step residual has a position block and an internal-variable block
that is block diagonal over spatial quadrature points (Γ is local). At every quadrature
point the local block is inverted in closed loops of array arithmetic and condensed into
the stress sensitivity, exactly as a consistent algorithmic tangent in a
return-mapping code:

    dP/dF|total = ∂P/∂F + ∂P/∂Γ · dΓ/dF,   dΓ/dF = -(∂R_Γ/∂Γ)^{-1} ∂R_Γ/∂F.

The position block (the Schur complement) is assembled element by element into one
sparse matrix (pattern fixed per mesh and degree) and factored on the host. `schur_solve`
then solves the full linearized system exactly at the point where the tangent was
formed; away from it, it is the preconditioner of the Krylov solver.
"""

import functools
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._export import record_pattern, register_pattern
from .._fem._passes import map_in_passes
from .._fem._tensor import mm, small_inv, sym_to_vec, vec_to_sym
from .._fem._update import pad_to_3d
from .._time_element._step import Unknowns, constraint_scale, force_term, nodal_fields
from . import _amg
from ._sparse import RETAIN, HostLU, lu_factor, lu_solve


_PATTERN_LOCK = threading.Lock()


def position_pattern(cells, k, n_nodes, dim, fixed=None):
    """Host factorization object for the (k n d)^2 position block of a mesh (element
    blocks, then one diagonal entry per held component and time node)."""
    record_pattern("position_pattern", (cells, k, n_nodes, dim, fixed))
    with _PATTERN_LOCK:  # one HostLU per pattern also when threads trace at once (it owns the key's store)
        return _position_pattern(cells, k, n_nodes, dim, fixed)


register_pattern("position_pattern", position_pattern)


@functools.lru_cache(maxsize=32)
def _position_pattern(cells, k, n_nodes, dim, fixed):
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
    dG_dF: jax.Array | None  # (n_cells, nq, 6k, k d^2): in-plane components of F in 2D
    dP_dG: jax.Array | None  # (n_cells, nq, nq_t d^2, 6k)
    mg: _amg.Multigrid | None = None  # the multigrid of the position block (in place of `token`)


def empty_tangent(scheme, scene, solver=None):
    """A tangent that is stale: the start of a loop's carry, shaped as `form_tangent`'s
    output for `solver` (a `NewtonKrylov`; its linear solver decides the block solve)."""
    k, d, dd = scheme.k, scene.dim, scene.dim**2
    nq_t = len(scheme.matrices()[0]["points"])
    head = (jnp.asarray(-1, jnp.int64), jnp.asarray(jnp.nan), jnp.asarray(True), jnp.eye(d))
    mg = None
    if solver is not None and solver.linear_solver.block_solver(scene) == "amg":
        disc = scene.disc
        hier = _amg.of_scene(k, scene)
        dtype = solver.linear_solver.block_dtype()
        shapes = jax.eval_shape(lambda A, x: _amg.build(hier, A, x, dtype),
                                jax.ShapeDtypeStruct((hier.levels[0].nnzb, k * d, k * d), float),
                                jax.ShapeDtypeStruct((disc.n_nodes, d), float))
        mg = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    if not scene.has_internal_variable:
        return Tangent(*head, None, None, None, mg)
    ne, nq = scene.disc.n_cells, scene.disc.n_qp
    z = functools.partial(jnp.zeros, dtype=float)
    return Tangent(*head, z((ne, nq, 6 * k, 6 * k)), z((ne, nq, 6 * k, dd * k)), z((ne, nq, nq_t * dd, 6 * k)), mg)


# JVPs unrolled per iteration of `jacobian_by_directions`' scan (see there).
DIRECTIONS_PER_ITERATION = 1


def jacobian_by_directions(fun, *xs):
    """`jax.jacfwd(fun, argnums=(0, 1, ...))(*xs)` as one JVP of `fun` per input component,
    in a scan over the directions (`DIRECTIONS_PER_ITERATION` unrolled per iteration).

    Why: `jacfwd` pushes all directions through the program at once, batched over a
    direction axis whose layouts cost transposes and copies; one direction at a time
    runs like the residual's JVP. The multigrid path's element blocks
    (`_multigrid_blocks`, 15 directions per point) of the 3D L-shape hex8, eG(1), five
    interleaved rounds, medians: r6 `jacfwd` 5.78 s, this 4.73 s, unrolled by 5 4.12 s
    (r5: 3.01 / 2.68 / 2.06 s with all 15 unrolled; r4: 1.71-1.76 / 1.26 / 1.19-1.31 s).
    Unrolled JVPs share their primal (XLA merges the copies) but the time loop that
    holds them compiled 6-10 s longer at r2 (27-32 s against 17-27 s, noisy machine),
    a cost most runs would not earn back; one per iteration compiles like `jacfwd`."""
    sizes = [x.size for x in xs]
    offs = np.cumsum([0] + sizes)

    def one(e):
        ts = tuple(e[offs[i]:offs[i + 1]].reshape(x.shape) for i, x in enumerate(xs))
        return jax.jvp(fun, tuple(xs), ts)[1]

    basis = jnp.eye(int(offs[-1]), dtype=xs[0].dtype)
    cols = jax.lax.scan(lambda c, e: (c, one(e)), None, basis, unroll=DIRECTIONS_PER_ITERATION)[1]  # (n, *out)
    per_input = [jax.tree_util.tree_map(lambda c, lo=offs[i], hi=offs[i + 1], s=x.shape:
                                        jnp.moveaxis(c[lo:hi], 0, -1).reshape(c.shape[1:] + s), cols)
                 for i, x in enumerate(xs)]
    return jax.tree_util.tree_map(lambda *d: tuple(d), *per_input)


def _point_tangent(scheme, material, h, F, G, d=3, directions=False):
    """Condensed sensitivities at one spatial point (F, G at the k+1 time nodes): of the
    d x d components of P that the forces of a d-dimensional mesh use, with respect to
    the d x d components of F that its motion changes. `directions`: the forward
    Jacobian one direction at a time (`jacobian_by_directions`), else `jax.jacfwd`.

    In 2D (plane strain) the gradient of a position increment has no out-of-plane
    components, and the assembly reads only the in-plane stresses, so the forward
    Jacobian runs in 4k + 6k directions instead of 9k + 6k (eG(1): 10 instead of 15),
    and the condensed sensitivities that every block solve reads are 4/9 of the size."""
    k = scheme.k
    F0, Fu = F[0], F[1:]
    dd = d * d
    if directions:
        jac = jacobian_by_directions
    else:
        jac = lambda f, *x: jax.jacfwd(f, argnums=tuple(range(len(x))))(*x)  # noqa: E731

    inside = pad_to_3d(jnp.ones((d, d), bool))  # F's components the motion changes

    def full(fu):  # the d x d components into the point's F at the new nodes
        fu = fu.reshape(k, d, d)
        return fu if d == 3 else jnp.where(inside, pad_to_3d(fu), Fu)

    fu = Fu[:, :d, :d]

    if G is None:
        def fun(fu):
            P, _ = scheme.point_kernel(material, jnp.concatenate([F0[None], full(fu)]), None, h)
            return P[:, :d, :d]
        (dP_dF,) = jac(fun, fu)
        return dP_dF.reshape(-1, dd * k), None, None, None

    G0 = G[0]
    gu = sym_to_vec(G[1:])

    def fun(fu, gu):
        P, R = scheme.point_kernel(material, jnp.concatenate([F0[None], full(fu)]),
                                   jnp.concatenate([G0[None], vec_to_sym(gu)]), h)
        return P[:, :d, :d], R

    (dP_dF, dP_dg), (dR_dF, dR_dg) = jac(fun, fu, gu)
    nP = dP_dF.shape[0] * dd
    Ainv = small_inv(dR_dg.reshape(6 * k, 6 * k))
    dG_dF = -mm(Ainv, dR_dF.reshape(6 * k, dd * k))
    dP_dg = dP_dg.reshape(nP, 6 * k)
    dP_dF_total = dP_dF.reshape(nP, dd * k) + mm(dP_dg, dG_dF)
    return dP_dF_total, Ainv, dG_dF, dP_dg


# Spatial points whose local sensitivities (a forward-mode Jacobian in 9k + 6k
# directions) are formed in one vectorized pass. On large meshes the passes run one
# after the other (`lax.map`), so the Jacobian's intermediates of only this many points
# are alive at a time: the 3D L-shape hex8 r4 (59 904 points, eG(1), 5 steps) peaked at
# 4.9 GB RSS with all points at once and at 3.6 GB in passes of 4096, with the same
# Newton and Krylov counts (3.4 and 8.8 per step). Small meshes (the 2D L-shape up to
# refinement 4) take one pass, as before. The last pass is padded rather than left to
# `lax.map(..., batch_size=)`, which traces the remainder as a second copy of the
# Jacobian program (compile time).
_POINTS_PER_PASS = 4096


def _map_points(fn, xs):
    """`vmap(fn)` over the leading (point) axis of the pytree `xs`, in passes of at most
    `_POINTS_PER_PASS` points; the last pass is padded with copies of the first point."""
    n = jax.tree_util.tree_leaves(xs)[0].shape[0]
    if n <= _POINTS_PER_PASS:
        return jax.vmap(fn)(xs)
    return map_in_passes(jax.vmap(fn), xs, _POINTS_PER_PASS)


def _element_blocks(scheme, h, JxW, dN, dPdF, cell_mass, free):
    """Element blocks (ne, k, n_en, d, k, n_en, d) of $A \\otimes M / h + h\\,\\sum_l W K_l$
    for the elements whose arrays are given (`free`: (ne, n_en, d) mask of the components
    not held, or None)."""
    m, _ = scheme.matrices()
    k = scheme.k
    ne, nq, _, d = dN.shape
    nq_t = dPdF.shape[2] // (d * d)
    dPdF = dPdF.reshape(ne, nq, nq_t, d, d, k, d, d)
    W = jnp.asarray(m["W"])
    # K[e, J, a, i, I, b, j] = h sum_q JxW sum_l W[J,l] dN[a,A] dPdF[l,i,A,I,j,B] dN[b,B]
    K = h * jnp.einsum("eq,Jl,eqaA,eqliAIjB,eqbB->eJaiIbj", JxW, W, dN, dPdF, dN)
    A = jnp.asarray(m["A"])[:, 1:]
    Ke = K + jnp.einsum("JI,eab,ij->eJaiIbj", A, cell_mass, jnp.eye(d)) / h
    if free is None:
        return Ke
    free = jnp.broadcast_to(free[:, None], (ne, k) + free.shape[1:])
    return Ke * free[:, :, :, :, None, None, None] * free[:, None, None, None]


def _free(scene):
    """(ne, n_en, d) mask of the element components that are not held (None: none held)."""
    return None if scene.fixed is None else jnp.asarray(~scene.fixed.array[scene.disc.cells.array])


def position_blocks(scheme, scene, ctx, dPdF):
    """Element blocks (ne, k, n_en, d, k, n_en, d) of the position block
    $A \\otimes M / h + h\\,\\sum_l W K_l$ from the condensed point sensitivities, held
    rows and columns zeroed, and the diagonal value of the held components (None
    without held nodes)."""
    disc = scene.disc
    Ke = _element_blocks(scheme, ctx.h, disc.JxW, disc.dN, dPdF, disc.cell_mass(scene.density), _free(scene))
    return Ke, None if scene.fixed is None else constraint_scale(scene, ctx.h)


# Elements whose blocks the multigrid path forms at a time (`_multigrid_blocks`; at most
# `_POINTS_PER_PASS` points): the element blocks and the einsum's intermediates of the
# 3D L-shape hex8 r4 (7488 elements) held 270 MB at once.
ELEMENTS_PER_PASS = 2048


def multigrid_arguments(scheme, scene, solver):
    """The index arrays of the multigrid hierarchy that a compiled time loop takes as an
    argument (`multigrid_scope`): None unless `solver` (a `NewtonKrylov`) solves the
    position block of `scene` by multigrid. Built on the host (the hierarchy is cached)."""
    if solver.linear_solver.block_solver(scene) != "amg":
        return None
    return _amg.of_scene(scheme.k, scene).arguments()


def multigrid_scope(scheme, scene, args):
    """The context in which a loop's traced code reads the hierarchy's index arrays from
    `args` (`multigrid_arguments`, an argument of the program), not as constants."""
    return _amg.arguments(None if args is None else _amg.of_scene(scheme.k, scene), args)


def _multigrid_blocks(scheme, scene, ctx, F, G, hier, point):
    """The multigrid path's condensed tangent in one pass over the elements: per pass of
    elements, the points' sensitivities (`point`: `_point_tangent` of one point's F, G and
    material) and the pass's element blocks added into the node blocks (nnzb, k d, k d)
    on the multigrid's pattern (`_amg.Hierarchy.element_map`). Returns the node blocks and
    (Ainv, dG_dF, dP_dG) of every point (n_cells, nq, ...).

    Why fused: the position block needs dP/dF only inside its element blocks, so no pass
    keeps it for the whole mesh ((9k)^2 numbers per point: 296 MB at the 3D L-shape hex8
    r8, eG(1)). Each pass reads its elements in place and writes its points'
    sensitivities in place (the scan's carry); the last one overlaps the one before, and
    the overlapped elements' blocks are not added twice (their targets are dropped).
    (`_fem._passes.map_in_passes` wrote its outputs in place the same way for one
    session; inside the time loop that made the residual's passes slower: hex8 r8, 5
    steps, 11.4 against 14.4 s/step in one alternating pair, same counts; reverted there.
    This formation alone at r8, median of 5: 16.0 / 16.5 s before, 16.5 / 13.8 s after.)"""
    disc = scene.disc
    ne, nq = disc.n_cells, disc.n_qp
    nnzb = hier.levels[0].nnzb
    c = max(1, min(ELEMENTS_PER_PASS, _POINTS_PER_PASS // nq, ne))
    mats = scene.point_materials()
    dyn, static = (None, None) if mats is None else eqx.partition(mats, eqx.is_array)
    per_cell = lambda a: a.reshape((ne, nq) + a.shape[1:])  # noqa: E731
    cells = dict(F=F, G=G, JxW=disc.JxW, dN=disc.dN, mass=disc.cell_mass(scene.density), free=_free(scene),
                 target=hier.ix("element_map").reshape(ne, -1),
                 mat=None if dyn is None else jax.tree_util.tree_map(per_cell, dyn))

    def sensitivities(p):
        flat = lambda a: a.reshape((-1,) + a.shape[2:])  # noqa: E731
        mat = None if p["mat"] is None else jax.tree_util.tree_map(flat, p["mat"])
        G = None if p["G"] is None else flat(p["G"])
        one = lambda m, f, g: point(scene.material if m is None else eqx.combine(m, static), f, g)  # noqa: E731
        return jax.vmap(one)(mat, flat(p["F"]), G)

    per_cell_of = lambda v: v.reshape((c, nq) + v.shape[1:])  # noqa: E731

    def add(carry, i):
        A, out = carry
        s = jnp.minimum(i * c, ne - c)
        p = jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, s, c), cells)
        dPdF, *local = sensitivities(p)
        Ke = _element_blocks(scheme, ctx.h, p["JxW"], p["dN"], per_cell_of(dPdF), p["mass"], p["free"])
        fresh = s + jnp.arange(c) >= i * c  # the elements this pass adds for the first time
        target = jnp.where(fresh[:, None], p["target"], nnzb).reshape(-1)
        A = A.at[target].add(_amg.element_node_blocks(Ke), mode="drop")
        put = lambda o, v: jax.lax.dynamic_update_slice_in_dim(o, per_cell_of(v), s, 0)  # noqa: E731
        return (A, jax.tree_util.tree_map(put, out, tuple(local))), None

    first = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct((c,) + a.shape[1:], a.dtype), cells)
    shapes = jax.eval_shape(sensitivities, first)[1:]
    out = jax.tree_util.tree_map(lambda o: jnp.zeros((ne, nq) + o.shape[1:], o.dtype), tuple(shapes))
    b = scheme.k * scene.dim
    (A, out), _ = jax.lax.scan(add, (jnp.zeros((nnzb, b, b)), out), jnp.arange(-(-ne // c)))
    held = None if scene.fixed is None else constraint_scale(scene, ctx.h)
    return _amg.add_held(hier, A, held), out


def form_tangent(scheme, scene, ctx, U, rotation=None, retain=RETAIN, preconditioner="lu",
                 block_dtype=np.float32) -> Tangent:
    """Condensed tangent at U: local inverses, sensitivities, and the position block
    (`position_blocks`), factored on the host (``preconditioner="lu"``) or as an
    aggregation multigrid in JAX (``"amg"``, `_amg`) whose operators are stored in
    `block_dtype` (`GMRES.multigrid_precision`). `retain`: factorizations of the
    pattern the host store keeps alive (`NewtonKrylov.retain`)."""
    k, d, disc = scheme.k, scene.dim, scene.disc
    _, F, G = nodal_fields(scheme, scene, ctx, U)
    rotation = jnp.eye(d) if rotation is None else rotation
    if preconditioner == "amg":
        hier = _amg.of_scene(k, scene)
        point = lambda mat, f, g: _point_tangent(scheme, mat, ctx.h, f, g, d=d, directions=True)  # noqa: E731
        A0, (Ainv, dGdF, dPdG) = _multigrid_blocks(scheme, scene, ctx, F, G, hier, point)
        mg = _amg.build(hier, A0, ctx.state.x, block_dtype)
        return Tangent(jnp.asarray(-1, jnp.int64), ctx.h, jnp.asarray(False), rotation, Ainv, dGdF, dPdG, mg)
    ne, nq = disc.n_cells, disc.n_qp
    flat = lambda a: None if a is None else a.reshape((ne * nq,) + a.shape[2:])  # noqa: E731
    mats = scene.point_materials()
    if mats is None:
        point = functools.partial(_point_tangent, scheme, scene.material, ctx.h)
        out = _map_points(lambda fg: point(*fg, d=d), (flat(F), flat(G)))
    else:
        dyn, static = eqx.partition(mats, eqx.is_array)
        out = _map_points(lambda a: _point_tangent(scheme, eqx.combine(a[0], static), ctx.h, a[1], a[2], d=d),
                          (dyn, flat(F), flat(G)))
    dPdF, Ainv, dGdF, dPdG = (None if o is None else o.reshape((ne, nq) + o.shape[1:]) for o in out)
    Ke, held = position_blocks(scheme, scene, ctx, dPdF)
    if held is not None:
        n_held = len(_held_dofs(scene.fixed, k, disc.n_nodes, d))
        data = jnp.concatenate([Ke.reshape(-1), jnp.full(n_held, held)])
    else:
        data = Ke.reshape(-1)
    host = position_pattern(disc.cells, k, disc.n_nodes, d, scene.fixed)
    token = lu_factor(host, data, retain)
    return Tangent(token, ctx.h, jnp.asarray(False), rotation, Ainv, dGdF, dPdG)


def _matvec(A, b):
    return jnp.sum(A * b[..., None, :], axis=-1)


def schur_solve(scheme, scene, ctx, tangent: Tangent, b: Unknowns, rotation=None, block_rtol=None) -> Unknowns:
    """Solve the linearized step equations with the condensed tangent (exact where the
    tangent was formed).

    With `rotation` (the body's rotation now, `body_rotation`) the tangent is carried
    along the rigid rotation R since it was formed: if every position turns by R, the
    stresses P = F S turn with it and C, Γ do not, so the Jacobian becomes T J Tᵀ with
    T = diag(R on positions, 1 on Γ), and its inverse T J⁻¹ Tᵀ. A body that spins keeps
    a preconditioner that fits, where the unrotated one degrades within a few steps.

    `block_rtol`: on the multigrid path, cycle until the position block's residual fell
    by this factor (`_amg.solve(rtol=)`) instead of `_amg.CYCLES` fixed cycles; not a
    fixed linear map then, so only for the chord iterations, never inside GMRES. The
    host LU is exact and ignores it.
    """
    k, d, disc = scheme.k, scene.dim, scene.disc
    R = None if rotation is None else rotation @ tangent.rotation.T
    bx = b.x if R is None else b.x @ R  # R^T b per node
    if b.g is not None:
        bg = jnp.moveaxis(b.g, 0, 2).reshape(disc.n_cells, disc.n_qp, 6 * k)
        z = _matvec(tangent.Ainv, bg)
        dP = _matvec(tangent.dP_dG, z)
        dP = dP.reshape(disc.n_cells, disc.n_qp, -1, d, d)  # the in-plane components in 2D
        coupling = force_term(scheme, scene, ctx, dP)
        if scene.fixed is not None:
            coupling = jnp.where(jnp.asarray(scene.fixed.array)[None], 0.0, coupling)
        bx = bx - coupling
    if tangent.mg is None:
        host = position_pattern(disc.cells, k, disc.n_nodes, d, scene.fixed)
        dx = lu_solve(host, tangent.token, bx.reshape(-1)).reshape(bx.shape)
    else:  # multigrid cycles on the node-major layout (n, k d)
        hier = _amg.of_scene(k, scene)
        nodes = jnp.moveaxis(bx, 0, 1).reshape(disc.n_nodes, k * d)
        dx = jnp.moveaxis(_amg.solve(hier, tangent.mg, nodes, rtol=block_rtol).reshape(disc.n_nodes, k, d), 1, 0)
    turn = (lambda v: v) if R is None else (lambda v: v @ R.T)  # R v per node
    if b.g is None:
        return Unknowns(turn(dx), None)
    dF = jnp.moveaxis(disc.gradient(dx)[..., :d, :d], 0, 2)  # (e, q, k, d, d)
    dg = z + _matvec(tangent.dG_dF, dF.reshape(disc.n_cells, disc.n_qp, d * d * k))
    dg = jnp.moveaxis(dg.reshape(disc.n_cells, disc.n_qp, k, 6), 2, 0)
    return Unknowns(turn(dx), dg)
