"""Identify the two viscosities of the paper's L-shape from synthetic marker data.

    python examples/identify_viscosity.py [--quick] [--out DIR]

Observations: the distances between three pairs of material points (markers, as digital
image correlation would track them; their displacements are mostly the body's rigid
flight, which the viscosities do not change) of the free-flying 2D L-shape (refinement
1, eG(1)) with the paper's (eta_dev, eta_vol) = (50000, 10000), sampled every 0.1 time
units. The fit
(Levenberg–Marquardt, `jv.identify`) starts from (eta_dev, eta_vol) = (12500, 30000)
(off by factors 4 and 3), once on exact data and once on data with 1 % Gaussian noise
(relative to each column's RMS), and prints the recovered values with their 95 %
confidence intervals; the fit against the data goes to DIR/identify_fit.png.
--quick: T = 1 with h = 0.1 (default T = 4).
"""

import argparse
import os

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxvisco as jv  # noqa: E402

TRUE = {"eta_dev": 50000.0, "eta_vol": 10000.0}
START = {"eta_dev": 12500.0, "eta_vol": 30000.0}
MARKERS = [[1.0, 1.0], [5.5, 2.5], [2.5, 9.0]]
PAIRS = [(0, 1), (0, 2), (1, 2)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default="identify-out")
    ap.add_argument("--noise", type=float, default=0.01, help="relative noise level (default 0.01)")
    args = ap.parse_args(argv)
    T, h = (1.0, 0.1) if args.quick else (4.0, 0.1)
    scene = jv.scenes.lshape(dim=2, refinement=1)
    times = np.linspace(0.0, T, int(round(T / h)) + 1)
    markers = [jv.Extensometer(scene.mesh, MARKERS[a], MARKERS[b], name=f"gauge {a}-{b}") for a, b in PAIRS]
    columns = len(markers)
    run = dict(dt0=h, name="markers")
    truth = jv.Experiment(scene, jv.eG(1), times, np.zeros((len(times), columns)), markers, **run)
    # the markers' readings at the true values (by the program the fits below reuse; the
    # second result, their derivatives in the parameters, is not needed here)
    clean, _ = truth.sensitivities(TRUE)
    rng = np.random.default_rng(0)
    rms = np.sqrt(np.mean(clean**2, axis=0))
    noisy = clean + args.noise * rms * rng.standard_normal(clean.shape)
    results = {}
    for label, data in (("exact data", clean), (f"{100 * args.noise:g} % noise", noisy)):
        fit = jv.identify(jv.Experiment(scene, jv.eG(1), times, data, markers, **run), START)
        errs = {k: fit.params[k] / TRUE[k] - 1.0 for k in TRUE}
        print(f"{label}: {fit.message}")
        for k in TRUE:
            lo, hi = fit.intervals[k]
            print(f"  {k} = {fit.params[k]:.6g} ({100 * errs[k]:+.3f} %), 95 % interval [{lo:.6g}, {hi:.6g}]")
        results[label] = (fit, errs)
    os.makedirs(args.out, exist_ok=True)
    results[f"{100 * args.noise:g} % noise"][0].plot(os.path.join(args.out, "identify_fit.png"))
    return results


if __name__ == "__main__":
    main()
