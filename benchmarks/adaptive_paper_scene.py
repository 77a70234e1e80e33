"""Error-controlled steps against the constant step on the paper's scene to t = 40 (#18).

    python benchmarks/adaptive_paper_scene.py [--t-end 40] [--orders 1,2] [--tols 1e-3,1e-4]

#18's target: an adaptive run reaches a given accuracy with at least 2x fewer steps than
the constant step of the same accuracy, on the paper's L-shape (2D r1) to t = 40. Here
the accuracy of a run is its largest error over all its step ends (positions: root mean
square over the nodes, over the body's size; dissipated energy: over the reference's D
at the end), against eG(3) with h = 0.0025 between whose steps the reference is
interpolated (`adaptive_proportionality.Reference`; its difference from h = 0.005 is
reported). For each adaptive run (`PIDController(tol, tol)`), the fewest constant steps
h = T / N whose errors are at most the adaptive run's: in the positions, in D, and in
both; and the ratios N / (adaptive steps). N from 40 (h = 1) by doubling, then bisection;
a run that fails to converge counts as inaccurate. The errors of the constant step need
not fall monotonically with N (a phase error can pass through zero; the dissipated
energy's largest error wiggles by ~1.5 % from one N to the next), so the bisection's answer
is then lowered to the least N meeting the errors among the `--window` N below it
(`constant_steps`; the bisection's own answer is `bisection_steps`).

`--position-only`: the same adaptive runs with the estimate of the positions alone (the
internal variable's defect set to zero; an experiment, not an option of the library),
against the constant step of the same count in positions: on the free body, whose
rotation drifts at a constant rate, how much a step that follows the positions' error
gains over the constant one.
`adaptive_relaxation.py --scene paper` measures the same scene at sample times with the
internal variable too (there the constant step is h = 0.25 / m). Deterministic (counts and errors). Writes
benchmarks/results/adaptive_paper_scene.json.
"""

import argparse

from adaptive_proportionality import TIGHT, Reference  # noqa: I001
from adaptive_relaxation import fewest
from common import RESULTS, jv, machine, write_json

import numpy as np  # noqa: E402


def run_errors(ref, sol):
    e_x, e_d = ref.errors(sol)
    n = int(sol.n_saved)
    return dict(x=float(e_x[:n].max()), D=float(e_d[:n].max()))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--t-end", type=float, default=40.0)
    ap.add_argument("--orders", default="1,2")
    ap.add_argument("--tols", default="1e-3,1e-4")
    ap.add_argument("--window", type=int, default=40)
    ap.add_argument("--position-only", action="store_true")
    args = ap.parse_args()
    T = args.t_end
    scene = jv.scenes.lshape(dim=2, refinement=1)
    ref = Reference(scene, T, 0.0025)
    ref_check = run_errors(ref, jv.simulate(scene, jv.eG(3), t1=T, dt0=0.005, root_finder=TIGHT,
                                            max_steps=int(round(T / 0.005)) + 1))
    print(f"reference eG(3) h = 0.0025; h = 0.005 differs by x {ref_check['x']:.1e}, D {ref_check['D']:.1e}",
          flush=True)
    out = dict(machine=machine(), t_end=T, reference=dict(scheme="eG(3)", h=0.0025, difference_from_h_0_005=ref_check),
               runs=[])
    for k in (int(k) for k in args.orders.split(",")):
        cache = {}

        def constant(n):
            if n not in cache:
                sol = jv.simulate(scene, jv.eG(k), t1=T, dt0=T / n, throw=False)  # capacities bucketed: few programs
                # a step too large to converge is not accurate
                cache[n] = run_errors(ref, sol) if sol.status == "done" else dict(x=np.inf, D=np.inf)
            return cache[n]

        for tol in (float(t) for t in args.tols.split(",")):
            sol = jv.simulate(scene, jv.eG(k), t1=T, stepsize_controller=jv.PIDController(tol, tol), max_steps=40000)
            steps = int(sol.n_steps)
            e = run_errors(ref, sol)
            need, bisection = {}, {}
            for name, qs in (("x", ("x",)), ("D", ("D",)), ("both", ("x", "D"))):
                ok = lambda n, qs=qs: all(constant(n)[q] <= e[q] for q in qs)  # noqa: E731
                bisection[name] = fewest(ok, start=40)
                need[name] = next(n for n in range(max(1, bisection[name] - args.window), bisection[name] + 1) if ok(n))
            row = dict(scheme=f"eG({k})", tol=tol, steps=steps, error_x=e["x"], error_D=e["D"],
                       constant_steps=need, bisection_steps=bisection, ratio={q: need[q] / steps for q in need},
                       constant_errors_at_same_steps=constant(steps),
                       constant_errors_at_twice_the_steps=constant(2 * steps))
            out["runs"].append(row)
            print(f"eG({k}) tol {tol:.0e}: {steps} steps, x {e['x']:.2e}, D {e['D']:.2e}; constant steps for the "
                  "same accuracy: " + ", ".join(f"{q} {need[q]} ({need[q] / steps:.2f}x)" for q in need)
                  + f"; at N = {steps}: x {row['constant_errors_at_same_steps']['x']:.2e}, "
                  f"D {row['constant_errors_at_same_steps']['D']:.2e}", flush=True)
    if args.position_only:
        out["position_only"] = position_only(scene, ref, T, args)
    write_json(RESULTS / "adaptive_paper_scene.json", out)


def position_only(scene, ref, T, args):
    """Adaptive runs whose estimate sees the positions only, against the constant step of
    the same count (both: largest position error over the step ends)."""
    import jaxvisco._time_element._estimate as estimate

    full = estimate.defects

    def positions_only(*a, **kw):
        e_x, e_g = full(*a, **kw)
        return e_x, None if e_g is None else 0.0 * e_g

    import jax

    estimate.defects = positions_only
    jax.clear_caches()  # trace the adaptive program again, with the patched estimate
    rows = []
    try:
        for k in (int(k) for k in args.orders.split(",")):
            for tol in (float(t) for t in args.tols.split(",")):
                sol = jv.simulate(scene, jv.eG(k), t1=T, stepsize_controller=jv.PIDController(tol, tol),
                                  max_steps=40000)
                steps = int(sol.n_steps)
                c = jv.simulate(scene, jv.eG(k), t1=T, dt0=T / steps, throw=False)
                rows.append(dict(scheme=f"eG({k})", tol=tol, steps=steps, error_x=run_errors(ref, sol)["x"],
                                 constant_error_x=run_errors(ref, c)["x"] if c.status == "done" else None))
                print(f"positions only: eG({k}) tol {tol:.0e}: {steps} steps, x {rows[-1]['error_x']:.3e}; constant "
                      f"steps, as many: x {rows[-1]['constant_error_x']:.3e}", flush=True)
    finally:
        estimate.defects = full
        jax.clear_caches()
    return rows


if __name__ == "__main__":
    main()
