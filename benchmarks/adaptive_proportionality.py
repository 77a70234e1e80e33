"""Tolerance proportionality of the error-controlled eG(k) steps (#18).

    python benchmarks/adaptive_proportionality.py [--t-end 2] [--orders 1,2,3]

The paper's 2D L-shape (refinement 1) to t = 2, adaptive eG(k) at rtol = atol = 1e-3 ...
1e-6 against eG(3) at h = 0.005 (checked against h = 0.01). Errors at the end: the root
mean square of the position error over the body's size, and the relative error of the
dissipated energy. Slopes: least-squares fits of log10(error) on log10(tol). Deterministic
(step counts and errors, no timing). Writes benchmarks/results/adaptive_proportionality.json.
"""

import argparse

from common import RESULTS, jv, machine, write_json  # noqa: I001

import numpy as np  # noqa: E402

TOLS = (1e-3, 1e-4, 1e-5, 1e-6)
TIGHT = jv.NewtonKrylov(rtol=1e-12)


def reference(scene, t_end, h):
    sol = jv.simulate(scene, jv.eG(3), t1=t_end, dt0=h, solver=TIGHT, max_steps=int(round(t_end / h)) + 1)
    return np.asarray(sol.x[-1]), float(sol.dissipated[-1])


def errors(x, d, x_ref, d_ref):
    """Position error (root mean square over the body's size) and relative error of the
    dissipated energy."""
    size = np.sqrt(np.mean((x_ref - x_ref.mean(axis=0)) ** 2))
    return float(np.sqrt(np.mean((x - x_ref) ** 2)) / size), abs(d - d_ref) / d_ref


def slope(tols, errs):
    return float(np.polyfit(np.log10(tols), np.log10(errs), 1)[0])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--t-end", type=float, default=2.0)
    ap.add_argument("--orders", default="1,2,3")
    args = ap.parse_args()
    scene = jv.scenes.lshape(dim=2, refinement=1)
    x_ref, d_ref = reference(scene, args.t_end, 0.005)
    x_chk, d_chk = errors(*reference(scene, args.t_end, 0.01), x_ref, d_ref)
    print(f"reference eG(3) h = 0.005 against h = 0.01: x {x_chk:.2e}, D {d_chk:.2e}")
    out = dict(machine=machine(), t_end=args.t_end, reference=dict(scheme="eG(3)", h=0.005, check_x=x_chk,
                                                                    check_D=d_chk), runs={})
    for k in (int(k) for k in args.orders.split(",")):
        rows = []
        for tol in TOLS:
            sol = jv.simulate(scene, jv.eG(k), t1=args.t_end, dt0=None, solver=TIGHT, max_steps=20000,
                              stepsize_controller=jv.PIDController(rtol=tol, atol=tol))
            e_x, e_d = errors(np.asarray(sol.x[-1]), float(sol.dissipated[-1]), x_ref, d_ref)
            rows.append(dict(tol=tol, steps=int(sol.n_steps), rejected=int(np.sum(np.asarray(sol.rejections))),
                             error_x=e_x, error_D=e_d))
            print(f"eG({k}) tol {tol:.0e}: {rows[-1]['steps']:5d} steps ({rows[-1]['rejected']} rejected), "
                  f"x {e_x:.2e} ({e_x / tol:.2f} tol), D {e_d:.2e} ({e_d / tol:.2f} tol)", flush=True)
        s_x = slope(TOLS, [r["error_x"] for r in rows])
        s_d = slope(TOLS, [r["error_D"] for r in rows])
        print(f"eG({k}) slopes: x {s_x:.3f}, D {s_d:.3f}")
        out["runs"][f"eG({k})"] = dict(rows=rows, slope_x=s_x, slope_D=s_d)
    write_json(RESULTS / "adaptive_proportionality.json", out)


if __name__ == "__main__":
    main()
