"""Why eG(2) rejects every step at h = 1 on the paper's scene: a diagnosis, counts only.

    python benchmarks/eg2_large_step.py

`large_steps.py` shows eG(2) at h = 1 rejecting (halving) every step with 25-30
Newton iterations, while cG(2) and eG(3) converge in 4. This script asks whether the
nonlinear solver or the discrete problem is at fault, on the first step of
`jv.scenes.lshape()` (2D r1, consistent mass):

1. exact Newton with the dense Jacobian (`jax.jacfwd`; the step has 2096 unknowns at
   r1, a diagnostic like the tests' finite-difference checks, not a solver path), from
   the predictor and from cG(2)'s converged step;
2. continuation in the size of eG's algorithmic correction: beta -> s * beta in the
   stress and in the flow rule's driving force (s = 0 is the assumed-strain element
   without correction, s = 1 is eG(2)), each s solved by exact Newton from the previous
   solution. Recorded per s: iterations, final residual, the smallest singular value of
   the step's Jacobian at the last iterate, and the largest |beta| (eG(2)'s, unscaled)
   over the spatial points with that point's Gauss-quadrature strain-rate norm
   sum_l w_l |C'(alpha_l)|^2 (beta's denominator) and |C_1 - C_0|;
3. `simulate` with eG(2) and 3 or 4 time-quadrature points (its denominator then
   integrates |C'|^2 more accurately), 10 steps at h = 1. Since session 33 the flow rule
   stays collocated at the k Gauss points (D_n >= 0 for every quadrature), but with more
   points than k angular momentum is not conserved (`eG`; `large_steps.py` records
   it), so this is a diagnosis, not a remedy. (The stored counts were measured in
   session 32, when the flow rule took the same points; session 33's rule gave the same
   counts for 4 points: `large_steps.json`.)

Writes benchmarks/results/eg2_large_step.json.
"""

from common import jv, machine, write_json  # noqa: I001
from large_steps import run  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

from jaxvisco._solver._newton import _norm, _scale  # noqa: E402
from jaxvisco._time_element._step import make_context, nodal_fields, predictor, residual  # noqa: E402


class _Scaled(jv.eG):
    """eG(k) with its algorithmic correction scaled by `s` (s = 1: eG(k) itself)."""

    s: float = 1.0

    def __init__(self, k, s):
        super().__init__(k)
        self.s = s

    def _enhanced_terms(self, material, F, G):
        e = super()._enhanced_terms(material, F, G)
        beta = self.s * e["beta"]
        Y = None if G is None else e["Y"] - 4.0 * (e["beta"] - beta) * e["Gd"]
        return dict(e, beta=beta, Y=Y)


def newton(scene, ctx, scheme, u, unravel, iterations=15, rtol=1e-10):
    f = jax.jit(lambda u: ravel_pytree(residual(scheme, scene, ctx, unravel(u)))[0])
    jac = jax.jit(jax.jacfwd(f))
    R = residual(scheme, scene, ctx, unravel(u))
    sx = _scale(ctx, scene, R)
    norms = []
    for _ in range(iterations + 1):
        r = np.asarray(f(u))
        norms.append(float(_norm(unravel(r), sx)))
        if norms[-1] <= rtol or len(norms) > iterations:
            break
        u = u + np.linalg.solve(np.asarray(jac(u)), -r)
    smin = float(np.linalg.svd(np.asarray(jac(u)), compute_uv=False)[-1])
    return u, norms, smin


def worst_point(scene, ctx, scheme, U):
    _, F, G = nodal_fields(scheme, scene, ctx, U)

    def point(mat, f, g):
        e = jv.eG._enhanced_terms(scheme, mat, f, g)
        den_c = jnp.sum(e["w"] * jnp.sum(e["Cd"] ** 2, axis=(-1, -2)))
        dC = f[-1].T @ f[-1] - f[0].T @ f[0]
        return e["beta"], den_c, jnp.sqrt(jnp.sum(dC**2))

    beta, den_c, dC = (np.asarray(a).ravel() for a in scene.map_points(point, F, G))
    i = int(np.argmax(np.abs(beta)))
    return dict(beta_max_abs=float(abs(beta[i])), den_C_there=float(den_c[i]), dC_norm_there=float(dC[i]),
                den_C_median=float(np.median(den_c)))


def main():
    scene = jv.scenes.lshape()
    state = scene.initial_state()
    ctx = make_context(scene, state, 0.0, 1.0)
    U0 = predictor(jv.eG(2), scene, ctx, scene.velocity(state.p))
    u0, unravel = ravel_pytree(U0)
    out = dict(unknowns=int(u0.size))
    _, n, _ = newton(scene, ctx, jv.eG(2), u0, unravel)
    out["eG2_from_predictor"] = n
    uc, n, _ = newton(scene, ctx, jv.cG(2), u0, unravel)
    out["cG2_from_predictor"] = n
    _, n, _ = newton(scene, ctx, jv.eG(2), uc, unravel)
    out["eG2_from_cG2"] = n
    print("exact Newton, scaled residual norms:",
          {k: [f"{x:.1e}" for x in v] for k, v in out.items() if k != "unknowns"})
    rows, u = [], u0
    for s in (0.0, 0.5, 0.9, 0.95, 0.98, 0.99, 0.995, 1.0):
        scheme = _Scaled(2, s)
        u, n, smin = newton(scene, ctx, scheme, u, unravel)
        row = dict(s=s, iterations=len(n) - 1, residual=n[-1], converged=n[-1] <= 1e-10,
                   jacobian_smallest_singular_value=smin, **worst_point(scene, ctx, scheme, unravel(u)))
        rows.append(row)
        print({k: (f"{v:.3g}" if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    out["continuation"] = rows
    out["quadrature"] = []
    for nq in (2, 3, 4):
        out["quadrature"].append(dict(quadrature=nq, **run(jv.eG(2, quadrature=nq), 10.0, 1.0)))
        print(out["quadrature"][-1], flush=True)
    write_json("eg2_large_step.json", dict(machine=machine(), settings=dict(
        scene="jv.scenes.lshape() (2D r1, consistent mass)", h=1.0, step="first step (t = 0 -> 1)",
        newton="exact Newton, dense Jacobian (jax.jacfwd), full steps, rtol 1e-10 on the scaled max norm"),
        **out))


if __name__ == "__main__":
    main()
