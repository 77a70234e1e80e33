"""Read a mesh file and run the paper's set-up on it.

    python examples/read_mesh.py [--mesh FILE] [--steps N] [--plot FILE.png]

Reads examples/data/lshape2d.msh (Gmsh 2.2; any format meshio reads works), gives it the
paper's material (Neo-Hooke equilibrium and non-equilibrium branches, eta_dev = 5e4,
eta_vol = 1e4, density 8.93) and the rigid initial velocity v0 = v_T + omega x X, and
runs eG(1) with h = 0.1; --plot draws the mesh at the start and at the end (the
gallery's picture).
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
    ap.add_argument("--mesh", default=os.path.join(HERE, "data", "lshape2d.msh"))
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--plot", default=None, help="optional figure (.png)")
    args = ap.parse_args(argv)
    mesh = jv.Mesh.read(args.mesh)
    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=50000.0, eta_vol=10000.0)
    v0 = jv.rigid_velocity(mesh, velocity=[6.0, 0.0], angular_velocity=0.6)  # v_T + omega e_z x X
    scene = jv.Scene(mesh, material, density=8.93, velocities=v0)
    sol = jv.simulate(scene, jv.eG(1), t1=0.1 * args.steps, dt0=0.1)
    print(f"{args.mesh}: {mesh.n_cells} {mesh.cell_type} cells, {mesh.n_nodes} nodes")
    for t, H in zip(np.asarray(sol.t), np.asarray(sol.energy)):
        print(f"t = {t:5.2f}  H = {H:.10g}")
    if args.plot:
        plot(mesh, sol, args.plot)
    return sol


def plot(mesh, sol, path):
    """The mesh at the start and at a few saved frames (the body flies and turns)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    cells = np.asarray(mesh.cells)[:, :4]  # the corner nodes, in order
    x = np.asarray(sol.x)
    fig, ax = plt.subplots(figsize=(7, 4))
    picks = np.unique(np.linspace(0, len(x) - 1, 4).astype(int))
    for i, color in zip(picks, ("0.6", "C0", "C1", "C2")):
        ax.add_collection(PolyCollection(x[i][cells], facecolors="none", edgecolors=color, linewidths=0.7))
        ax.annotate(f"t = {float(sol.t[i]):.1f}", x[i].max(axis=0), color=color)
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_title(f"{mesh.n_cells} {mesh.cell_type} cells read from a Gmsh file, eG(1)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
