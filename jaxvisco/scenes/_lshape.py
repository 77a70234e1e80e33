"""The paper's free-flying L-shaped body (THEORY §4)."""

import jax
import jax.numpy as jnp
import numpy as np

from .._fem._generators import lshape_mesh
from .._materials import NeoHooke, ReeseGovindjee
from .._scene import Scene

PAPER = dict(lam=30000.0, mu=7500.0, density=8.93, eta_dev=50000.0, eta_vol=10000.0,
             v_translation=(6.0, 0.0, 0.0), omega=(0.0, 0.0, 0.6))


def lshape(dim=2, refinement=1, element=None, lam=PAPER["lam"], mu=PAPER["mu"], density=PAPER["density"],
           eta_dev=PAPER["eta_dev"], eta_vol=PAPER["eta_vol"], v_translation=PAPER["v_translation"],
           omega=PAPER["omega"], viscous=True, quadrature_order=None) -> Scene:
    """Simo & Tarnow's L-block set free with $v_0(X) = v_T + \\omega \\times X$.

    Plane strain in 2D ($[0,6]\\times[0,3] \\cup [0,3]\\times[0,10]$), extruded over
    $z \\in [0,3]$ in 3D; squares/cubes of edge 1/refinement. Both branches Neo-Hookean
    with the paper's data by default; `viscous=False` drops the viscous branch (an
    elastic scene with no internal variable).
    """
    mesh = lshape_mesh(dim=dim, refinement=refinement, element=element)
    nh = NeoHooke(lam=lam, mu=mu)
    material = ReeseGovindjee(nh, nh if viscous else None, eta_dev=eta_dev, eta_vol=eta_vol)
    # numpy where the data are concrete (each jnp operation here compiled a small program
    # of its own: 0.3 s of building the scene), jnp where they are traced
    traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves((v_translation, omega)))
    xp = jnp if traced else np
    X = xp.asarray(mesh.points)
    vT = xp.asarray(v_translation, dtype=float)
    w = xp.asarray(omega, dtype=float)
    if dim == 2:
        v0 = vT[:2] + w[2] * xp.stack([-X[:, 1], X[:, 0]], axis=-1)
    else:
        v0 = vT + xp.cross(w, X)
    return Scene(mesh, material, density, velocities=v0, quadrature_order=quadrature_order)
