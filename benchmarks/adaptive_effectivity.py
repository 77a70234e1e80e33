"""Effectivity of the adaptive step's error estimate: estimated over true local error.

    python benchmarks/adaptive_effectivity.py [--quick]

The paper's 2D L-shape (refinement 1), eG(1), eG(2), eG(3). Along an adaptive run
(rtol = atol = 1e-3 and 1e-5, to t = 10), at every few accepted steps, the step is taken
again from its start state and its time polynomial is compared at the estimator's check
points with a reference started from the same state (cG(3), 16 sub-steps between
consecutive check points: local error ~1e-15). Per group (positions, internal variable):
effectivity = estimated / true, root mean square over the body, maximal over the check
points. Writes benchmarks/results/adaptive_effectivity.json.
"""

import argparse

from common import RESULTS, jv, machine, write_json  # noqa: I001

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxvisco._fem._tensor import sym_to_vec  # noqa: E402
from jaxvisco._solver._newton import NewtonKrylov, solve_step  # noqa: E402
from jaxvisco._solver._tangent import empty_tangent  # noqa: E402
from jaxvisco._time_element._estimate import defect_matrices, defects, dense_state  # noqa: E402
from jaxvisco._time_element._step import make_context, predictor, step_outcome  # noqa: E402


@eqx.filter_jit
def _step(scene, scheme, state, t, h):
    """The step's estimated defects and its polynomial at the check points."""
    ctx = make_context(scene, state, t, h)
    r = solve_step(NewtonKrylov(), scheme, scene, ctx, predictor(scheme, scene, ctx, scene.velocity(state.p)),
                   empty_tangent(scheme, scene))
    _, _, _, _, ok = step_outcome(scheme, scene, ctx, r)
    e_x, e_g = defects(scheme, scene, ctx, r.U)
    sigma = jnp.asarray(defect_matrices(scheme.k)[0])
    states = jax.vmap(lambda s: dense_state(scheme, scene, ctx, r.U, s))(sigma)
    return ok, e_x, e_g, states


def _rms(a):
    a = np.asarray(a).reshape(a.shape[0], -1)
    return np.sqrt(np.mean(a * a, axis=1))


def effectivity(scene, scheme, state, t, h, substeps=16):
    ok, e_x, e_g, states = _step(scene, scheme, state, jnp.asarray(float(t)), jnp.asarray(float(h)))
    sigma = defect_matrices(scheme.k)[0]
    knots = np.concatenate([[0.0], sigma])
    ts = np.concatenate([t + h * (knots[i] + (knots[i + 1] - knots[i]) * np.arange(substeps) / substeps)
                         for i in range(len(sigma))] + [[t + h * sigma[-1]]])
    ref = jv.simulate(scene, jv.cG(3), stepsize_controller=jv.StepTo(ts), initial_state=state, saveat=jv.SaveAt(gamma=True),
                      initial_velocity=scene.velocity(state.p))
    idx = substeps * np.arange(1, len(sigma) + 1)
    true_x = np.asarray(states.x) - np.asarray(ref.x)[idx]
    out = dict(t=float(t), h=float(h), ok=bool(ok),
               est_x=_rms(e_x).tolist(), true_x=_rms(true_x).tolist())
    out["effectivity_x"] = float(np.max(_rms(e_x)) / np.max(_rms(true_x)))
    if e_g is not None:
        true_g = np.asarray(sym_to_vec(states.gamma)) - np.asarray(sym_to_vec(ref.gamma))[idx]
        out.update(est_g=_rms(e_g).tolist(), true_g=_rms(true_g).tolist(),
                   effectivity_g=float(np.max(_rms(e_g)) / np.max(_rms(true_g))))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    scene = jv.scenes.lshape(2, 1)
    rows = []
    for k in (1, 2, 3):
        for rtol in (1e-3, 1e-5):
            sol = jv.simulate(scene, jv.eG(k), 0.0, 10.0, None, saveat=jv.SaveAt(gamma=True),
                              stepsize_controller=jv.PIDController(rtol=rtol, atol=rtol))
            n = int(sol.n_steps)
            picks = np.unique(np.linspace(0, n - 1, 4 if args.quick else 10).astype(int))
            ts = np.concatenate([[0.0], np.asarray(sol.step_t)])
            for i in picks:
                r = effectivity(scene, jv.eG(k), sol.state(int(i)), ts[i], float(sol.step_h[i]))
                r.update(scheme=f"eG({k})", rtol=rtol, step=int(i))
                rows.append(r)
                print(f"eG({k}) rtol {rtol:g} step {i:4d} t {r['t']:7.3f} h {r['h']:.4f} "
                      f"eff_x {r['effectivity_x']:.2f} eff_g {r.get('effectivity_g', float('nan')):.2f}", flush=True)
    summary = {}
    for key in ("effectivity_x", "effectivity_g"):
        for k in (1, 2, 3):
            v = [r[key] for r in rows if r["scheme"] == f"eG({k})" and key in r]
            summary[f"eG({k}) {key}"] = dict(min=min(v), median=float(np.median(v)), max=max(v))
    for name, s in summary.items():
        print(f"{name}: min {s['min']:.2f} median {s['median']:.2f} max {s['max']:.2f}")
    write_json(RESULTS / "adaptive_effectivity.json", dict(machine=machine(), summary=summary, rows=rows))


if __name__ == "__main__":
    main()
