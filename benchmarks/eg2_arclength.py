"""Does eG(2)'s first step at h = 1 on the paper scene have a solution on the branch of the
uncorrected element? Pseudo-arclength continuation in the algorithmic correction: counts only.

    python benchmarks/eg2_arclength.py [--max-points 80]

`eg2_large_step.py` continued eG(2)'s algorithmic correction beta -> s beta from s = 0 (the
assumed-strain element without correction) by exact Newton at fixed s: every s up to 0.98
converged, from s = 0.99 on none did. Natural continuation in s cannot pass a fold (where
the branch turns back in s) nor tell one from a hard stretch of the branch. Here the
branch (u(sigma), s(sigma)) is followed by its arclength sigma: at each point the tangent
t = (z, 1) / |(z, 1)| with J_u z = -dG/ds, a predictor step along t and Newton on
[G(u, s) = 0; t . (y - y_prev) = dsigma] with the bordered dense Jacobian (the step has
2096 unknowns at r1: a diagnostic like the tests' finite-difference checks, not a solver
path). dsigma halves when the corrector needs more than 8 iterations and grows 1.5x
after one that needs at most 3. Recorded per point: s, the tangent's s-component t_s (it
changes sign at a fold), the sign of det J_u (it changes sign where J_u is singular: a
fold or a bifurcation), J_u's smallest singular value, and the largest |beta| over the
points with its Gauss-quadrature strain-rate norm (beta's denominator).

The arclength norm is the plain Euclidean one of (u, s), u the step's unknowns (positions
at the step's time nodes and the internal variables), as in `eg2_large_step.newton`.

Writes benchmarks/results/eg2_arclength.json.
"""

import argparse
import time

from common import jv, machine, write_json  # noqa: I001
from eg2_large_step import _Scaled, newton, worst_point  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

from jaxvisco._solver._newton import _norm, _scale  # noqa: E402
from jaxvisco._time_element._step import make_context, predictor, residual  # noqa: E402

RTOL = 1e-10  # on the scaled max norm of the residual, as `eg2_large_step.newton`


def tangent_of(Gu, Gq, u, q, prev=None):
    """The branch's unit tangent (z, 1) / |(z, 1)|, J_u z = -dG/dq, oriented along `prev`."""
    z = np.linalg.solve(np.asarray(Gu(u, q)), -np.asarray(Gq(u, q)))
    t = np.concatenate([z, [1.0]])
    t /= np.linalg.norm(t)
    if prev is not None and t @ prev < 0:
        t = -t
    return t


def follow(G, Gu, Gq, converged, describe, u, q, rows, name, q_end, dsigma, max_points):
    """Pseudo-arclength continuation of G(u, q) = 0 in the parameter q (called `name` in
    the rows) from the converged point (u, q) whose row is rows[-1]: predictor along the
    tangent, Newton on the bordered dense Jacobian [G = 0; t . (y - y_prev) = dsigma]
    (`converged(r)`: the residual r is small enough); dsigma halves after a corrector of
    more than 8 iterations and grows 1.5x after one of at most 3. Stops at `max_points`
    rows, at q >= `q_end`, or once q has fallen 0.05 below a fold (where the tangent's
    q-component changes sign). Returns (u, q, index of the row that reached q_end or
    None, fold or None); appends a `describe(u, q, t, iterations, dsigma)` row per point."""
    t = tangent_of(Gu, Gq, u, q)
    dsig, reached, fold = dsigma, None, None
    while len(rows) < max_points and dsig > 1e-9:
        y = np.concatenate([u, [q]])
        yp = y + dsig * t
        ok, its = False, 0
        for its in range(1, 9):
            uu, qq = yp[:-1], yp[-1]
            r = np.asarray(G(uu, qq))
            if converged(r) and its > 1:
                ok = True
                break
            A = np.zeros((len(yp), len(yp)))
            A[:-1, :-1] = np.asarray(Gu(uu, qq))
            A[:-1, -1] = np.asarray(Gq(uu, qq))
            A[-1] = t
            rhs = -np.concatenate([r, [t @ (yp - y) - dsig]])
            yp = yp + np.linalg.solve(A, rhs)
            if not np.all(np.isfinite(yp)):
                break
        if not ok:
            dsig *= 0.5
            continue
        u, q = yp[:-1], float(yp[-1])
        t_new = tangent_of(Gu, Gq, u, q, t)
        rows.append(describe(u, q, t_new, its - 1, dsig))
        print({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
        if fold is None and t_new[-1] * t[-1] < 0:
            fold = {f"{name}_max": max(r[name] for r in rows), "point": len(rows) - 1}
        t = t_new
        if q >= q_end and reached is None:
            reached = len(rows) - 1
            break
        if fold is not None and q < rows[fold["point"]][name] - 0.05:
            break  # the branch has turned back well below its fold
        if its - 1 <= 3:
            dsig *= 1.5
    return u, q, reached, fold


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-points", type=int, default=80)
    ap.add_argument("--dsigma", type=float, default=0.05, help="first arclength step")
    a = ap.parse_args()
    scene = jv.scenes.lshape()
    state = scene.initial_state()
    ctx = make_context(scene, state, 0.0, 1.0)
    U0 = predictor(jv.eG(2), scene, ctx, scene.velocity(state.p))
    u0, unravel = ravel_pytree(U0)
    sx = _scale(ctx, scene, residual(jv.eG(2), scene, ctx, U0))

    def G(u, s):
        return ravel_pytree(residual(_Scaled(2, s), scene, ctx, unravel(u)))[0]

    G = jax.jit(G)
    Gu = jax.jit(jax.jacfwd(G, argnums=0))
    Gs = jax.jit(jax.jacfwd(G, argnums=1))

    def norm(u, s):
        return float(_norm(unravel(G(u, s)), sx))

    leaves = jax.tree_util.tree_leaves_with_path(U0)
    bounds = np.cumsum([0] + [leaf.size for _, leaf in leaves])

    def localize(v):
        """Where J_u's null vector lives: its largest component, named (field, index),
        and the share of |v|^2 in that component's spatial point (all its time nodes
        and components)."""
        i = int(np.argmax(np.abs(v)))
        j = int(np.searchsorted(bounds, i, side="right") - 1)
        path, leaf = leaves[j]
        idx = np.unravel_index(i - bounds[j], leaf.shape)
        block = np.zeros(leaf.shape)
        block[(slice(None),) + tuple(idx[1:-1])] = 1.0  # every time node and component of that point
        share = float(np.sum(v[bounds[j]:bounds[j + 1]] ** 2 * block.ravel()) / np.sum(v**2))
        return dict(field=jax.tree_util.keystr(path), index=[int(x) for x in idx], point_share=share)

    def describe(u, s, t, its, dsig):
        J = np.asarray(Gu(u, s))
        sign, _ = np.linalg.slogdet(J)
        sv = np.linalg.svd(J, compute_uv=False)
        smin = float(sv[-1])
        extra = {}
        if smin < 0.01:  # near the fold: where is J_u singular?
            extra = dict(null_vector=localize(np.linalg.svd(J)[2][-1]))
        return dict(s=float(s), t_s=float(t[-1]), det_sign=int(sign), smallest_singular_value=smin, **extra,
                    corrector_iterations=its, dsigma=dsig, residual=norm(u, s),
                    u_change_from_s0=float(np.linalg.norm(u - u_start)),
                    **worst_point(scene, ctx, _Scaled(2, s), unravel(u)))

    t0 = time.perf_counter()
    u, n, _ = newton(scene, ctx, _Scaled(2, 0.0), u0, unravel)  # s = 0 from the predictor
    u = np.asarray(u)
    u_start = u.copy()
    s = 0.0
    rows = [describe(u, s, tangent_of(Gu, Gs, u, s), len(n) - 1, 0.0)]
    print({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    u, s, reached, fold = follow(G, Gu, Gs, lambda r: _norm(unravel(r), sx) <= RTOL, describe, u, s, rows, "s", 1.0,
                                 a.dsigma, a.max_points)
    at_1 = None
    if reached is not None:  # eG(2) itself (s = 1), by exact Newton from the branch's point past s = 1
        u1, n, smin = newton(scene, ctx, jv.eG(2), u, unravel)
        at_1 = dict(iterations=len(n) - 1, residuals=n, smallest_singular_value=smin,
                    distance_from_predictor=float(np.linalg.norm(np.asarray(u1) - np.asarray(u0))),
                    distance_from_s0_solution=float(np.linalg.norm(np.asarray(u1) - u_start)))
        print("eG(2) from the branch:", at_1)
    out = dict(machine=machine(), unknowns=int(u0.size), wall_s=time.perf_counter() - t0,
               settings=dict(scene="jv.scenes.lshape() (2D r1, consistent mass)", h=1.0, step="first step (t = 0 -> 1)",
                             continuation="pseudo-arclength in (u, s), dense bordered Jacobian, Euclidean norm",
                             rtol=RTOL, first_dsigma=a.dsigma),
               reached_s_1_at_point=reached, eG2_from_branch=at_1, fold=fold, points=rows)
    write_json("eg2_arclength.json", out)
    print("fold:", fold, "reached s = 1 at point:", reached)


if __name__ == "__main__":
    main()
