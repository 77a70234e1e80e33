"""Read a mesh file and run the paper's set-up on it.

    python examples/read_mesh.py [--mesh FILE] [--steps N]

Reads examples/data/lshape2d.msh (Gmsh 2.2; any format meshio reads works), gives it the
paper's material (Neo-Hooke equilibrium and non-equilibrium branches, eta_dev = 5e4,
eta_vol = 1e4, density 8.93) and the rigid initial velocity v0 = v_T + omega x X, and
runs eG(1) with h = 0.1.
"""

import argparse
import os

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxvisco as jv  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=os.path.join(HERE, "data", "lshape2d.msh"))
    ap.add_argument("--steps", type=int, default=3)
    args = ap.parse_args(argv)
    mesh = jv.Mesh.read(args.mesh)
    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=50000.0, eta_vol=10000.0)
    X = jnp.asarray(mesh.points)
    v0 = jnp.asarray([6.0, 0.0]) + 0.6 * jnp.stack([-X[:, 1], X[:, 0]], axis=-1)  # v_T + omega e_z x X
    scene = jv.Scene(mesh, material, density=8.93, velocities=v0)
    sol = jv.simulate(scene, jv.eG(1), t1=0.1 * args.steps, dt0=0.1)
    print(f"{args.mesh}: {mesh.n_cells} {mesh.cell_type} cells, {mesh.n_nodes} nodes")
    for t, H in zip(np.asarray(sol.t), np.asarray(sol.energy)):
        print(f"t = {t:5.2f}  H = {H:.10g}")
    return sol


if __name__ == "__main__":
    main()
