"""Tolerance proportionality of the error-controlled eG(k) steps (#18).

    python benchmarks/adaptive_proportionality.py [--t-end 2] [--orders 1,2,3]

The paper's 2D L-shape (refinement 1) to t = 2, adaptive eG(k) at rtol = atol = 1e-3 ...
1e-6 against eG(3) at h = 0.0025 (checked against h = 0.005). Two measures of each
run's error, each for the positions (root mean square over the nodes, over the body's
size) and the dissipated energy (over the reference's D at the end): at the end (t = 2),
and the largest over the run's step ends (the reference there by cubic Hermite
interpolation between its steps with its velocities M^{-1}p and dissipation rates;
interpolating every other step of h = 0.005 missed the skipped ones by up to 4.0e-6 of
D and 8.9e-8 of the size, so at h = 0.0025, with the interpolation's h^4, ~2e-8 and
~4e-10). The end
value of one quantity can pass through zero between two tolerances (eG(3)'s dissipated
energy: 1.3e-7 at rtol 1e-5, 3.9e-7 at 1e-6), the largest over the run does not.
Slopes: least-squares fits of log10(error) on log10(tol). Deterministic (step counts and
errors, no timing). Writes benchmarks/results/adaptive_proportionality.json.
"""

import argparse

from common import RESULTS, jv, machine, write_json  # noqa: I001

import jax  # noqa: E402
import numpy as np  # noqa: E402

TOLS = (1e-3, 1e-4, 1e-5, 1e-6)
TIGHT = jv.NewtonKrylov(rtol=1e-12)


class Reference:
    """eG(3) with constant steps `h` to `t_end`, every step kept: positions and dissipated
    energy at any time in [0, t_end] by cubic Hermite interpolation."""

    def __init__(self, scene, t_end, h):
        sol = jv.simulate(scene, jv.eG(3), t1=t_end, dt0=h, root_finder=TIGHT, max_steps=int(round(t_end / h)) + 1)
        self.h, self.t = h, np.asarray(sol.t)
        self.x, self.d = np.asarray(sol.x), np.asarray(sol.dissipated)
        self.v = np.asarray(jax.jit(jax.vmap(scene.velocity))(sol.p))
        self.d_rate = np.asarray(sol.dissipation_rate)
        self.size = float(np.sqrt(np.mean((self.x[-1] - self.x[-1].mean(axis=0)) ** 2)))

    def _at(self, t, y, dy):
        i = np.clip(np.searchsorted(self.t, t) - 1, 0, len(self.t) - 2)
        s = ((t - self.t[i]) / self.h).reshape((-1,) + (1,) * (y.ndim - 1))
        return ((2 * s**3 - 3 * s**2 + 1) * y[i] + (s**3 - 2 * s**2 + s) * self.h * dy[i]
                + (3 * s**2 - 2 * s**3) * y[i + 1] + (s**3 - s**2) * self.h * dy[i + 1])

    def errors(self, sol):
        """Position and dissipated-energy errors of a run at each of its frames (arrays)."""
        t = np.asarray(sol.t)
        e_x = np.sqrt(np.mean((np.asarray(sol.x) - self._at(t, self.x, self.v)) ** 2, axis=(1, 2))) / self.size
        e_d = np.abs(np.asarray(sol.dissipated) - self._at(t, self.d, self.d_rate)) / self.d[-1]
        return e_x, e_d


def slope(tols, errs):
    return float(np.polyfit(np.log10(tols), np.log10(errs), 1)[0])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--t-end", type=float, default=2.0)
    ap.add_argument("--orders", default="1,2,3")
    args = ap.parse_args()
    scene = jv.scenes.lshape(dim=2, refinement=1)
    ref = Reference(scene, args.t_end, 0.0025)
    coarse = Reference(scene, args.t_end, 0.005)
    chk_x, chk_d = (float(e[-1]) for e in ref.errors(as_run(coarse)))
    print(f"reference eG(3) h = 0.0025 against h = 0.005 at the end: x {chk_x:.2e}, D {chk_d:.2e}")
    out = dict(machine=machine(), t_end=args.t_end,
               reference=dict(scheme="eG(3)", h=0.0025, check_x=chk_x, check_D=chk_d, check_h=0.005),
               measures=dict(end="errors at t_end", run="largest error over the run's step ends"), runs={})
    for k in (int(k) for k in args.orders.split(",")):
        rows = []
        for tol in TOLS:
            sol = jv.simulate(scene, jv.eG(k), t1=args.t_end, dt0=None, root_finder=TIGHT, max_steps=20000,
                              stepsize_controller=jv.PIDController(rtol=tol, atol=tol))
            e_x, e_d = ref.errors(sol)
            rows.append(dict(tol=tol, steps=int(sol.n_steps), rejected=int(np.sum(np.asarray(sol.rejections))),
                             error_x=float(e_x[-1]), error_D=float(e_d[-1]), run_error_x=float(e_x.max()),
                             run_error_D=float(e_d.max())))
            r = rows[-1]
            print(f"eG({k}) tol {tol:.0e}: {r['steps']:5d} steps ({r['rejected']} rejected); end x {r['error_x']:.2e}, "
                  f"D {r['error_D']:.2e}; run x {r['run_error_x']:.2e}, D {r['run_error_D']:.2e}", flush=True)
        fits = {f"slope_{m}": slope(TOLS, [r[m] for r in rows]) for m in ("error_x", "error_D", "run_error_x",
                                                                          "run_error_D")}
        print(f"eG({k}) slopes: end x {fits['slope_error_x']:.3f}, D {fits['slope_error_D']:.3f}; run x "
              f"{fits['slope_run_error_x']:.3f}, D {fits['slope_run_error_D']:.3f}")
        out["runs"][f"eG({k})"] = dict(rows=rows, slope_x=fits["slope_error_x"], slope_D=fits["slope_error_D"],
                                       run_slope_x=fits["slope_run_error_x"], run_slope_D=fits["slope_run_error_D"])
    write_json(RESULTS / "adaptive_proportionality.json", out)


def as_run(reference):
    """A reference's frames as a run (`t`, `x`, `dissipated`) for `Reference.errors`."""
    from types import SimpleNamespace

    return SimpleNamespace(t=reference.t, x=reference.x, dissipated=reference.d)


if __name__ == "__main__":
    main()
