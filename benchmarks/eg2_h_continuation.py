"""Does eG(2)'s first step on the paper scene have a solution at h = 1 on the branch of its
smaller steps? Pseudo-arclength continuation in the step size: counts only.

    python benchmarks/eg2_h_continuation.py [--h-start 0.25] [--max-points 80]

`eg2_arclength.py` followed the branch of the step's solutions from the element without
algorithmic correction (s = 0) at h = 1 and found it folding at s = 0.98: no solution of
eG(2) at h = 1 on that branch. An eG(2) solution at h = 1 could still lie on another
branch; the one a homotopy in the step size would follow is the branch of eG(2)'s own
solutions at smaller h. Here that branch (u(sigma), h(sigma)), from the converged step at
`--h-start` (exact Newton from the predictor), is followed by its arclength as in
`eg2_arclength.py`: tangent t = (z, 1) / |(z, 1)| with J_u z = -dG/dh, predictor along t,
Newton on the bordered dense Jacobian, dsigma halved after a corrector of more than 8
iterations and grown 1.5x after one of at most 3. The unknowns are the step's position
increments and internal variables, so the branch is continuous in h. Recorded per point:
h, the tangent's h-component t_h (it changes sign at a fold), the sign of det J_u, J_u's
smallest singular value and the largest |beta|. If the branch reaches h = 1, eG(2) is
solved there by exact Newton from it, and the solution's distance from the step's
predictor is recorded.

Writes benchmarks/results/eg2_h_continuation.json.
"""

import argparse
import time

from common import jv, machine, write_json  # noqa: I001
from eg2_arclength import RTOL, follow, tangent_of  # noqa: E402
from eg2_large_step import newton, worst_point  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

from jaxvisco._solver._newton import _norm, _scale  # noqa: E402
from jaxvisco._time_element._step import make_context, predictor, residual  # noqa: E402

def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h-start", type=float, default=0.25)
    ap.add_argument("--h-end", type=float, default=1.0)
    ap.add_argument("--max-points", type=int, default=80)
    ap.add_argument("--dsigma", type=float, default=0.05, help="first arclength step")
    a = ap.parse_args()
    scene = jv.scenes.lshape()
    scheme = jv.eG(2)
    state = scene.initial_state()
    v0 = scene.velocity(state.p)

    def ctx_of(h):
        return make_context(scene, state, 0.0, h)

    U_pred = predictor(scheme, scene, ctx_of(a.h_end), v0)  # what the time loop starts the h_end step from
    u_pred, unravel = ravel_pytree(U_pred)
    sx = _scale(ctx_of(a.h_end), scene, residual(scheme, scene, ctx_of(a.h_end), U_pred))

    def G(u, h):
        return ravel_pytree(residual(scheme, scene, ctx_of(h), unravel(u)))[0]

    G = jax.jit(G)
    Gu = jax.jit(jax.jacfwd(G, argnums=0))
    Gh = jax.jit(jax.jacfwd(G, argnums=1))

    def norm(u, h):
        return float(_norm(unravel(G(u, h)), sx))

    def describe(u, h, t, its, dsig):
        J = np.asarray(Gu(u, h))
        sign, _ = np.linalg.slogdet(J)
        smin = float(np.linalg.svd(J, compute_uv=False)[-1])
        return dict(h=float(h), t_h=float(t[-1]), det_sign=int(sign), smallest_singular_value=smin,
                    corrector_iterations=its, dsigma=dsig, residual=norm(u, h),
                    **worst_point(scene, ctx_of(h), scheme, unravel(u)))

    t0 = time.perf_counter()
    u0 = ravel_pytree(predictor(scheme, scene, ctx_of(a.h_start), v0))[0]
    u, n, _ = newton(scene, ctx_of(a.h_start), scheme, u0, unravel)
    u, h = np.asarray(u), a.h_start
    start = dict(h=h, newton_residuals=n)
    print("start:", start, flush=True)
    rows = [describe(u, h, tangent_of(Gu, Gh, u, h), len(n) - 1, 0.0)]
    print({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    u, h, reached, fold = follow(G, Gu, Gh, lambda r: _norm(unravel(r), sx) <= RTOL, describe, u, h, rows, "h",
                                 a.h_end, a.dsigma, a.max_points)
    at_end = None
    if reached is not None:  # eG(2) at h_end itself, by exact Newton from the branch's point past it
        u1, n, smin = newton(scene, ctx_of(a.h_end), scheme, u, unravel)
        at_end = dict(iterations=len(n) - 1, residuals=n, smallest_singular_value=smin,
                      distance_from_predictor=float(np.linalg.norm(np.asarray(u1) - np.asarray(u_pred))),
                      predictor_norm=float(np.linalg.norm(np.asarray(u_pred))),
                      **worst_point(scene, ctx_of(a.h_end), scheme, unravel(np.asarray(u1))))
        print("eG(2) at h_end from the branch:", at_end)
    out = dict(machine=machine(), unknowns=int(u_pred.size), wall_s=time.perf_counter() - t0,
               settings=dict(scene="jv.scenes.lshape() (2D r1, consistent mass)", scheme="eG(2)",
                             step="first step (from t = 0)", h_start=a.h_start, h_end=a.h_end,
                             continuation="pseudo-arclength in (u, h), dense bordered Jacobian, Euclidean norm",
                             rtol=RTOL, first_dsigma=a.dsigma),
               start=start, reached_h_end_at_point=reached, eG2_at_h_end=at_end, fold=fold, points=rows)
    write_json("eg2_h_continuation.json", out)
    print("fold:", fold, "reached h_end at point:", reached)


if __name__ == "__main__":
    main()
