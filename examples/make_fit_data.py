"""Write the synthetic measurements of examples/fit/: the tensile specimen's relaxation,
cyclic and creep tests (scene files beside them) run with the scene files' material, with
1 % Gaussian noise (relative to each column's RMS) on every measured column.

    python examples/make_fit_data.py [--noise 0.01] [--seed 0] [--out examples/fit]

Columns: ``time``, then relaxation ``force`` (the grip's load cell, N) and ``marker`` (the
lateral displacement of the point (20, 10, 5), mm); cyclic ``force``; creep
``elongation`` (an extensometer between (10, 10, 5) and (30, 10, 5), mm). Sampled every
0.05 s. `jaxvisco identify examples/fit/fit.toml` fits them.
"""

import argparse
import os

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxvisco as jv  # noqa: E402

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fit")


def observables(scene, nodes, test):
    if test == "relaxation":
        return {"force": jv.ReactionForce(nodes("grip"), "x"),
                "marker": jv.Displacement(scene.mesh, [[20.0, 10.0, 5.0]], "y")}
    if test == "cyclic":
        return {"force": jv.ReactionForce(nodes("grip"), "x")}
    return {"elongation": jv.Extensometer(scene.mesh, [10.0, 10.0, 5.0], [30.0, 10.0, 5.0])}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=HERE)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    os.makedirs(args.out, exist_ok=True)
    for test in ("relaxation", "cyclic", "creep"):
        sf = jv.read_scene_file(os.path.join(HERE, f"{test}.toml"))
        obs = observables(sf.scene, sf.nodes, test)
        times = np.linspace(0.0, sf.t1, int(round(sf.t1 / 0.05)) + 1)
        e = jv.Experiment(sf.scene, sf.integrator, times, np.zeros((len(times), len(obs))), list(obs.values()),
                          dt0=sf.dt0, name=test)
        clean = np.asarray(jax.jit(lambda s: e.model(e.run(s)))(sf.scene))
        noisy = clean + args.noise * np.sqrt(np.mean(clean**2, axis=0)) * rng.standard_normal(clean.shape)
        path = os.path.join(args.out, f"{test}.csv")
        np.savetxt(path, np.column_stack([times, noisy]), delimiter=",", header=",".join(["time", *obs]),
                   comments="", fmt="%.10g")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
