"""Error-controlled steps on a body that comes to rest, against the constant step (#18).

    python benchmarks/adaptive_relaxation.py [--scene relaxing|paper] [--t-end 40] [--orders 1,2] [--tols 1e-3,1e-4]

`relaxing_lshape()`: the paper's 2D L-shape (refinement 1) clamped at its base (y = 0),
released at rest from a shear of 5 % (x += 0.05 y), with a viscous branch ten times
faster than the paper's (eta_dev = 7500, eta_vol = 1500): it swings, and its
vibrations die out (energy 1e-9 of the initial by t = 40). The demand of the motion
decays, unlike on the paper's free body, which keeps turning.

`--scene paper`: the paper's free L-shape (`jaxvisco.scenes.lshape(2, 1)`), as #18's
target names it; it keeps turning at 0.6 rad/s after its vibrations have died out.

Accuracy of a run: the largest error over the run at the sample times t = 0.25 j
(positions: root mean square over the nodes, over the body's size; internal variable:
root mean square of Γ - I's error, over the largest |Γ - I| of the reference;
dissipated energy: |D - D_ref| over D_ref at the end), against eG(3) with rtol = atol =
1e-9. Adaptive runs: dense output at the sample times (`SaveAt(ts=...)`: the polynomial
inside a step, what the estimate controls); constant steps h = 0.25 / m: their step
ends. For each adaptive run, the fewest constant steps (m = 1, 2, 3, ...; the smallest m
whose position and internal-variable errors are both at most the adaptive run's) and the
ratio of the step counts; beside it the same for each measure alone (`ratio_by_measure`).
`--check-ratios 8,4`: instead of the search (slow where the adaptive run is accurate: the
constant step then needs tens of thousands of steps), the constant step with 8 and 4 times
the adaptive run's steps, and whether it is less accurate (the ratio is then at least that;
adaptive_relaxation_ratios.json). Deterministic (counts and errors; wall times for
orientation). Writes benchmarks/results/adaptive_relaxation.json (`--scene paper`: adaptive_paper_scene_samples.json;
benchmarks/adaptive_paper_scene.py measures that scene at every step end, with any N).
"""

import argparse
import time

from common import RESULTS, jv, machine, write_json  # noqa: I001

import numpy as np  # noqa: E402

SAMPLE = 0.25
TIGHT = jv.NewtonKrylov(rtol=1e-12)


def relaxing_lshape():
    """The clamped, sheared, fast-relaxing L-shape described above."""
    s = jv.scenes.lshape(dim=2, refinement=1, eta_dev=7500.0, eta_vol=1500.0, omega=(0.0, 0.0, 0.0),
                         v_translation=(0.0, 0.0, 0.0))
    X = np.asarray(s.mesh.points)
    fixed = np.zeros_like(X, dtype=bool)
    fixed[np.isclose(X[:, 1], 0.0)] = True
    x0 = X + np.stack([0.05 * X[:, 1], np.zeros(len(X))], axis=-1)
    return jv.Scene(s.mesh, s.material, s.density, positions=x0, fixed=fixed)


def samples(t_end):
    return SAMPLE * np.arange(int(round(t_end / SAMPLE)) + 1)


def adaptive(scene, k, tol, t_end, solver=None):
    """An adaptive run with frames at the sample times."""
    return jv.simulate(scene, jv.eG(k), t1=t_end, dt0=None, stepsize_controller=jv.PIDController(tol, tol),
                       saveat=jv.SaveAt(ts=samples(t_end), gamma=True), root_finder=solver, max_steps=40000)


def constant(scene, k, m, t_end):
    """Constant steps h = SAMPLE / m, the frames at the sample times."""
    return jv.simulate(scene, jv.eG(k), t1=t_end, dt0=SAMPLE / m, saveat=jv.SaveAt(every=m, gamma=True))


def errors(sol, ref):
    """Largest position error (over the body's size), internal-variable error (over the
    reference's largest |Γ - I|) and dissipated-energy error (over the reference's at the
    end) at the sample times."""
    x, xr = np.asarray(sol.x), np.asarray(ref.x)
    g, gr = np.asarray(sol.gamma), np.asarray(ref.gamma)
    size = np.sqrt(np.mean((xr[0] - xr[0].mean(axis=0)) ** 2))
    e_x = np.sqrt(np.mean((x - xr) ** 2, axis=(1, 2))) / size
    eye = np.eye(g.shape[-1])
    e_g = np.sqrt(np.mean((g - gr) ** 2, axis=tuple(range(1, g.ndim)))) / np.max(
        np.sqrt(np.mean((gr - eye) ** 2, axis=tuple(range(1, g.ndim)))))
    D, Dr = np.asarray(sol.dissipated), np.asarray(ref.dissipated)
    e_D = np.abs(D - Dr) / Dr[-1]
    return dict(x=float(e_x.max()), gamma=float(e_g.max()), D=float(e_D.max()))


def fewest(ok, start=1):
    """The smallest n >= `start` with ok(n), for ok monotone in n (errors fall with more
    steps): doubling n, then bisection."""
    hi = start
    while not ok(hi):
        hi *= 2
    lo = start - 1 if hi == start else hi // 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return hi


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", choices=("relaxing", "paper"), default="relaxing")
    ap.add_argument("--t-end", type=float, default=40.0)
    ap.add_argument("--orders", default="1,2")
    ap.add_argument("--tols", default="1e-3,1e-4")
    ap.add_argument("--check-ratios", default=None,
                    help="e.g. 8,4: instead of searching the fewest constant steps, run the constant step with "
                         "that many times the adaptive run's steps and record whether it is less accurate "
                         "(writes adaptive_relaxation_ratios.json)")
    args = ap.parse_args()
    scene = relaxing_lshape() if args.scene == "relaxing" else jv.scenes.lshape(dim=2, refinement=1)
    ref = adaptive(scene, 3, 1e-9, args.t_end, solver=TIGHT)
    H = np.asarray(ref.energy)
    print(f"reference eG(3) rtol 1e-9: {int(ref.n_steps)} steps; H(t_end) / H0 = {H[-1] / H[0]:.2e}", flush=True)
    out = dict(machine=machine(), scene=args.scene, t_end=args.t_end, sample=SAMPLE,
               reference=dict(scheme="eG(3)", rtol=1e-9, steps=int(ref.n_steps)), runs=[])
    cache = {}
    for k in (int(k) for k in args.orders.split(",")):
        for tol in (float(t) for t in args.tols.split(",")):
            w = time.perf_counter()
            sol = adaptive(scene, k, tol, args.t_end)
            wall = time.perf_counter() - w
            e = errors(sol, ref)
            h = np.asarray(sol.step_h)
            row = dict(scheme=f"eG({k})", tol=tol, steps=int(sol.n_steps), error_x=e["x"], error_gamma=e["gamma"],
                       error_D=e["D"], h_first=float(h[0]), h_min=float(h.min()), h_last=float(h[-1]), wall_s=wall)

            def fewest_m(measures):
                def ok(m):
                    if (k, m) not in cache:
                        cache[k, m] = errors(constant(scene, k, m, args.t_end), ref)
                    return all(cache[k, m][q] <= e[q] for q in measures)

                return fewest(ok)

            per_sample = int(round(args.t_end / SAMPLE))
            if args.check_ratios:
                row["checks"] = []
                for r in (float(v) for v in args.check_ratios.split(",")):
                    m = int(np.ceil(r * row["steps"] / per_sample))
                    c = errors(constant(scene, k, m, args.t_end), ref)
                    row["checks"].append(dict(ratio=per_sample * m / row["steps"], constant_steps=per_sample * m,
                                              constant_error_x=c["x"], constant_error_gamma=c["gamma"],
                                              constant_error_D=c["D"],
                                              less_accurate=bool(c["x"] > e["x"] and c["gamma"] > e["gamma"])))
                    print(f"eG({k}) tol {tol:.0e}: {row['steps']} steps, x {e['x']:.2e}, Γ {e['gamma']:.2e}; "
                          f"{per_sample * m} constant steps: x {c['x']:.2e}, Γ {c['gamma']:.2e} "
                          f"(less accurate: {row['checks'][-1]['less_accurate']})", flush=True)
                out["runs"].append(row)
                continue
            m = fewest_m(("x", "gamma"))
            c = cache[k, m]
            row.update(constant_h=SAMPLE / m, constant_steps=per_sample * m, constant_error_x=c["x"],
                       constant_error_gamma=c["gamma"], constant_error_D=c["D"],
                       step_ratio=per_sample * m / row["steps"],
                       ratio_by_measure={q: per_sample * fewest_m((q,)) / row["steps"] for q in ("x", "gamma", "D")})
            out["runs"].append(row)
            print(f"eG({k}) tol {tol:.0e}: {row['steps']} steps (h {h.min():.2e} ... {h[-1]:.2e}), x {e['x']:.2e}, "
                  f"Γ {e['gamma']:.2e}, D {e['D']:.2e}; constant h = {SAMPLE / m:.4g}: {per_sample * m} steps, "
                  f"x {c['x']:.2e}, Γ {c['gamma']:.2e}, D {c['D']:.2e}; ratio {row['step_ratio']:.2f}; by measure "
                  + ", ".join(f"{q} {r:.2f}" for q, r in row["ratio_by_measure"].items()), flush=True)
    name = "adaptive_relaxation.json" if args.scene == "relaxing" else "adaptive_paper_scene_samples.json"
    if args.check_ratios:
        name = name.replace(".json", "_ratios.json")
    write_json(RESULTS / name, out)


if __name__ == "__main__":
    main()
