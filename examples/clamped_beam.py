"""A clamped beam from a scene file: a tip load switched off at t = 1, then damped vibration.

    python examples/clamped_beam.py [--quick] [--plot FILE.png]

Reads examples/scenes/beam2d.toml (a Gmsh mesh with physical groups, a clamp on the group
"left", a traction on "right" scaled by a step in time) with jaxvisco.read_scene_file and
runs it with simulate, as `jaxvisco run examples/scenes/beam2d.toml` would. Prints the tip
deflection and the energy balance (the loads' work W = H - H0 + dissipated); --plot draws
them (the gallery's picture). --quick: the first 10 steps (to t = 0.5) instead of t = 6.
"""

import argparse
import os

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxvisco as jv  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--plot", default=None, help="optional figure (.png)")
    args = ap.parse_args(argv)
    sf = jv.read_scene_file(os.path.join(HERE, "scenes", "beam2d.toml"))
    steps = jv.StepTo(sf.steps.ts[:11]) if args.quick else sf.steps
    sol = jv.simulate(sf.scene, sf.integrator, stepsize_controller=steps, saveat=sf.saveat,
                      root_finder=sf.root_finder)
    mesh, groups = jv.read_mesh(os.path.join(HERE, "scenes", "beam2d.msh"))
    tip = groups.node_group("right")
    x0 = np.asarray(sf.scene.x0)
    deflection = (np.asarray(sol.x)[:, tip, 1] - x0[tip, 1]).mean(axis=1)
    H, D, W = (np.asarray(a) for a in (sol.energy, sol.dissipated, sol.external_work))
    balance = np.max(np.abs(H - H[0] + D - W)) / max(np.max(np.abs(W)), 1e-300)
    print(f"{sf.integrator.name}: {len(sol.step_t)} steps to t = {float(sol.t[-1]):g}, status {sol.status}; "
          f"tip deflection at the end {deflection[-1]:.4g} (largest {deflection.min():.4g}); "
          f"energy balance error {balance:.1e} of the loads' work")
    if args.plot:
        plot(np.asarray(sol.t), deflection, H, D, W, args.plot)
    return sol, deflection


def plot(t, deflection, H, D, W, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.5))
    a.plot(t, deflection)
    a.axvline(1.0, color="gray", ls=":")
    a.set_xlabel("t")
    a.set_title("mean vertical tip displacement")
    b.plot(t, H, label="H")
    b.plot(t, D, label="dissipated")
    b.plot(t, W, "--", label="work of the load")
    b.axvline(1.0, color="gray", ls=":")
    b.set_xlabel("t")
    b.legend()
    b.set_title("energy balance: H + dissipated = H0 + work")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
