"""What the command line's values build: the step schedule of ``--schedule``
(`parse_schedule`), the integrator of ``--integrator``/``--order`` (`make_integrator`)
and the built-in L-shape or a mesh file's scene with any material parameter overridden
(`make_scene`); each rejects a bad value with a `ValueError` naming the option.
"""

import math


def parse_schedule(text):
    """``"20:0.1,40:1.0"`` -> ``[(20.0, 0.1), (40.0, 1.0)]``."""
    pieces = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            a, b = part.split(":")
            pieces.append((float(a), float(b)))
        except ValueError:
            raise ValueError(f"bad --schedule entry {part!r}: expected T_UNTIL:DT, e.g. '20:0.1,40:1.0'.") from None
    if not pieces:
        raise ValueError(f"empty --schedule {text!r}: expected T_UNTIL:DT pairs, e.g. '20:0.1,40:1.0'.")
    return pieces


def make_integrator(name, order=1):
    import jaxvisco as jv

    key = str(name).strip().lower()
    if key in ("cg", "eg"):
        if not isinstance(order, int) or order < 1:
            raise ValueError(f"--order must be an integer >= 1, got {order!r}.")
        return jv.cG(order) if key == "cg" else jv.eG(order)
    if key == "newmark":
        return jv.Newmark()
    if key == "midpoint":
        return jv.Midpoint()
    raise ValueError(f"unknown integrator {name!r}; choose cG, eG, Newmark or Midpoint.")


def make_scene(dim=2, refinement=1, element=None, mesh=None, lam=None, mu=None, density=None, eta_dev=None,
               eta_vol=None):
    """The paper's L-shape (or a mesh file with the paper's material and rigid initial
    velocity v0 = v_T + omega x X), with any parameter overridden."""
    import jax.numpy as jnp

    import jaxvisco as jv

    p = dict(jv.scenes.PAPER)
    for k, v in dict(lam=lam, mu=mu, density=density, eta_dev=eta_dev, eta_vol=eta_vol).items():
        if v is not None:
            if not (v > 0 and math.isfinite(v)) and not (k.startswith("eta") and v == math.inf):
                raise ValueError(f"--{k.replace('_', '-')} must be positive, got {v!r}.")
            p[k] = v
    if mesh is None:
        if dim not in (2, 3):
            raise ValueError(f"--dim must be 2 or 3, got {dim!r}.")
        if not isinstance(refinement, int) or refinement < 1:
            raise ValueError(f"--refinement must be an integer >= 1, got {refinement!r}.")
        return jv.scenes.lshape(dim=dim, refinement=refinement, element=element, lam=p["lam"], mu=p["mu"],
                                density=p["density"], eta_dev=p["eta_dev"], eta_vol=p["eta_vol"])
    m = jv.Mesh.read(mesh)
    nh = jv.NeoHooke(lam=p["lam"], mu=p["mu"])
    material = jv.ReeseGovindjee(nh, nh, eta_dev=p["eta_dev"], eta_vol=p["eta_vol"])
    X = jnp.asarray(m.points)
    vT = jnp.asarray(p["v_translation"], dtype=float)
    w = jnp.asarray(p["omega"], dtype=float)
    if m.dim == 2:
        v0 = vT[:2] + w[2] * jnp.stack([-X[:, 1], X[:, 0]], axis=-1)
    else:
        v0 = vT + jnp.cross(w, X)
    return jv.Scene(m, material, p["density"], velocities=v0)
