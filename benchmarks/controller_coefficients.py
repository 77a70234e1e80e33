"""The PID coefficients of `PIDController`: wall time, rejections and accuracy.

    python benchmarks/controller_coefficients.py [--t-end 10] [--rounds 3]

The paper's 2D L-shape (refinement 1, consistent mass) to t = 10, adaptive eG(1..3) at
rtol = atol = 1e-3 and 1e-5 with (pcoeff, icoeff) = (0, 1) (diffrax's integral
controller), (0.2, 0.4) and (0.3, 0.3). All coefficients are array leaves, so one compiled
program per scheme serves every configuration; the configurations alternate within each
round (medians of the rounds). Errors at the end against eG(3) at h = 0.005: root mean
square position error over the body's size, relative error of the dissipated energy.
Writes benchmarks/results/controller_coefficients.json.
"""

import argparse
import time

from common import RESULTS, jv, machine, write_json  # noqa: I001
from adaptive_proportionality import Reference  # noqa: I001

import jax  # noqa: E402
import numpy as np  # noqa: E402

CONFIGS = {"(0, 1)": dict(pcoeff=0.0, icoeff=1.0), "(0.2, 0.4)": dict(pcoeff=0.2, icoeff=0.4),
           "(0.3, 0.3)": dict(pcoeff=0.3, icoeff=0.3)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--t-end", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    T = args.t_end
    scene = jv.scenes.lshape(dim=2, refinement=1)
    ref = Reference(scene, T, 0.005)
    rows = []
    for k in (1, 2, 3):
        def run(coeffs, tol):
            sol = jv.simulate(scene, jv.eG(k), t1=T, max_steps=8192,
                              stepsize_controller=jv.PIDController(tol, tol, **coeffs))
            jax.block_until_ready(sol.x)
            return sol

        run(CONFIGS["(0, 1)"], 1e-3)  # compiles the scheme's program
        for tol in (1e-3, 1e-5):
            walls, last = {name: [] for name in CONFIGS}, {}
            for _ in range(args.rounds):
                for name, coeffs in CONFIGS.items():
                    t0 = time.perf_counter()
                    last[name] = run(coeffs, tol)
                    walls[name].append(time.perf_counter() - t0)
            for name in CONFIGS:
                sol = last[name]  # the runs are deterministic: the last timed one carries the counts
                e_x, e_d = (float(e[-1]) for e in ref.errors(sol))  # at the end
                row = dict(scheme=f"eG({k})", tol=tol, coefficients=name, wall_s=float(np.median(walls[name])),
                           walls_s=walls[name], steps=int(sol.n_steps), rejected=int(np.sum(sol.rejections)),
                           newton=int(np.sum(sol.newton_iterations)), chord=int(np.sum(sol.chord_iterations)),
                           error_x=e_x, error_D=e_d)
                rows.append(row)
                print(f"eG({k}) tol {tol:g} {name:10s}: {row['wall_s']:.3f} s, {row['steps']} steps, "
                      f"{row['rejected']} rejected, Newton {row['newton']}, chord {row['chord']}, "
                      f"x {row['error_x']:.2e}, D {row['error_D']:.2e}", flush=True)
    write_json(RESULTS / "controller_coefficients.json", dict(machine=machine(), t_end=T, rows=rows))


if __name__ == "__main__":
    main()
