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


def make_scene(dim=2, refinement=1, cell_type=None, mesh=None, lam=None, mu=None, density=None, eta_dev=None,
               eta_vol=None, velocity=None, angular_velocity=None):
    """The paper's L-shape (its material and rigid initial velocity, any parameter
    overridden), or the body of a mesh file: its material must be given (`lam`, `mu`,
    `density`; without `eta_dev`/`eta_vol` it is elastic) and it starts at rest unless
    `velocity` (``"VX,VY[,VZ]"``) or `angular_velocity` (``"W"`` in 2D, ``"WX,WY,WZ"``
    in 3D, about the origin) set it moving."""
    import numpy as np

    import jaxvisco as jv

    given = dict(lam=lam, mu=mu, density=density, eta_dev=eta_dev, eta_vol=eta_vol)
    for k, v in given.items():
        if v is not None and not (v > 0 and math.isfinite(v)) and not (k.startswith("eta") and v == math.inf):
            raise ValueError(f"--{k.replace('_', '-')} must be positive, got {v!r}.")
    if mesh is None:
        if velocity is not None or angular_velocity is not None:
            raise ValueError("--velocity and --angular-velocity set the initial motion of a --mesh body; the built-in "
                             "L-shape moves as in the paper (use a scene file for another motion).")
        if dim not in (2, 3):
            raise ValueError(f"--dim must be 2 or 3, got {dim!r}.")
        if not isinstance(refinement, int) or refinement < 1:
            raise ValueError(f"--refinement must be an integer >= 1, got {refinement!r}.")
        p = dict(jv.scenes.PAPER)
        p.update({k: v for k, v in given.items() if v is not None})
        return jv.scenes.lshape(dim=dim, refinement=refinement, cell_type=cell_type, lam=p["lam"], mu=p["mu"],
                                density=p["density"], eta_dev=p["eta_dev"], eta_vol=p["eta_vol"])
    m = jv.Mesh.read(mesh)
    missing = [f"--{k}" for k in ("lam", "mu", "density") if given[k] is None]
    if missing:
        raise ValueError(f"--mesh {mesh}: give the body's material: {', '.join(missing)} (and --eta-dev/--eta-vol "
                         "for a viscous body; without them it is elastic), or describe the run in a scene file "
                         "(jaxvisco scene-template).")
    nh = jv.NeoHooke(lam=lam, mu=mu)
    viscous = any(v is not None and math.isfinite(v) for v in (eta_dev, eta_vol))
    inf = math.inf
    material = jv.ReeseGovindjee(nh, nh if viscous else None, eta_dev=inf if eta_dev is None else eta_dev,
                                 eta_vol=inf if eta_vol is None else eta_vol)
    v0 = jv.rigid_velocity(m.points, velocity=_vector(velocity, "--velocity", m.dim),
                           angular_velocity=_vector(angular_velocity, "--angular-velocity", 1 if m.dim == 2 else 3))
    return jv.Scene(m, material, density, velocities=np.asarray(v0))


def _vector(text, name, n):
    """`text` (``"1.0,2.0"``) as `n` floats (one float for n = 1), or None."""
    if text is None:
        return None
    try:
        v = [float(a) for a in str(text).split(",")]
    except ValueError:
        v = []
    if len(v) != n or not all(math.isfinite(a) for a in v):
        raise ValueError(f"{name} must be {n} finite number{'s' if n > 1 else ''} separated by commas, got {text!r}.")
    return v[0] if n == 1 else v
