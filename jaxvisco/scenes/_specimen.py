"""A 3D tensile specimen in the tests a viscoelastic material is identified from.

Units: mm, s, N, MPa (tonne / mm^3 for the density). The specimen is a bar of 40 x 10 x
10 mm (hex8, 8 x 2 x 2 elements), its face x = 0 clamped; the face x = 40 is the grip.
"""

from typing import NamedTuple

import numpy as np

from .._fem._boundary import facets_from_nodes, nodes_where, traction_load
from .._fem._generators import box
from .._materials import NeoHooke, ReeseGovindjee
from .._scene import Scene
from .._time_functions import Ramp, Sine

# A soft polymer (Poisson's ratio 0.45 at equilibrium): relaxation times of about a
# second in shear (eta_dev / mu_neq) and in bulk.
POLYMER = dict(lam=9.0, mu=1.0, lam_neq=4.0, mu_neq=2.0, eta_dev=2.0, eta_vol=5.0, density=1.2e-9)
LENGTH, WIDTH = 40.0, 10.0
TESTS = ("relaxation", "cyclic", "creep")


class Specimen(NamedTuple):
    """A specimen test, what `specimen` returns.

    **Attributes:**

    - `scene`: the `Scene`.
    - `clamp`, `grip`: the node indices of the clamped face (x = 0) and of the grip face
      (x = 40 mm).
    - `t1`, `dt0`: the end time and the step the test is meant to be run with.
    """

    scene: Scene
    clamp: np.ndarray
    grip: np.ndarray
    t1: float
    dt0: float


def specimen(test="relaxation", *, strain=0.1, ramp=0.5, t1=None, frequency=1.0, cycles=2.0, stress=0.1,
             dt0=None, elements=(8, 2, 2), **material) -> Specimen:
    """The tensile specimen in one of three tests: a bar of 40 x 10 x 10 mm (units mm, s,
    N, MPa; density in tonne / mm^3) of a soft polymer (`POLYMER`), clamped at x = 0 and
    loaded on its grip face x = 40.

    **Arguments:**

    - `test`: ``"relaxation"`` (the grip pulled to `strain` at a constant speed over
      `ramp` seconds, then held; default to t1 = 5 s), ``"cyclic"`` (the grip moved as
      ``strain * L * sin(2 pi frequency t)`` for `cycles` periods) or ``"creep"`` (a
      nominal `stress` in MPa on the free grip face, ramped up over `ramp` seconds, then
      held; default t1 = 5 s).
    - `strain`, `ramp`, `frequency`, `cycles`, `stress`: the loading (above).
    - `t1`: the end time (default above).
    - `elements`: hex8 elements along the length, width and height (default (8, 2, 2)).
    - `dt0`: the time step the test is meant for (default: 0.05 s, a twentieth of a
      cycle where that is shorter).
    - material parameters (``lam``, ``mu``, ``lam_neq``, ``mu_neq``, ``eta_dev``,
      ``eta_vol``, ``density``): override `POLYMER`'s.

    **Returns:**

    A `Specimen`: the scene, the clamp and grip nodes, `t1` and `dt0`.

    **Raises:**

    `ValueError` for an unknown test or material parameter.

    **Example:**

    ```python
    import jaxvisco as jv

    test = jv.scenes.specimen("cyclic", frequency=2.0, elements=(4, 1, 1))
    print(test.t1, test.dt0, len(test.grip))       # 1.0 0.025 4
    ```
    """
    if test not in TESTS:
        raise ValueError(f"specimen: test must be one of {TESTS}, got {test!r}.")
    unknown = sorted(set(material) - set(POLYMER))
    if unknown:
        raise ValueError(f"specimen: unknown material parameter(s) {unknown}; accepted: {sorted(POLYMER)}.")
    p = dict(POLYMER, **material)
    mesh = box(*elements, LENGTH, WIDTH, WIDTH)
    clamp = nodes_where(mesh, lambda X: np.isclose(X[:, 0], 0.0))
    grip = nodes_where(mesh, lambda X: np.isclose(X[:, 0], LENGTH))
    mat = ReeseGovindjee(NeoHooke(p["lam"], p["mu"]), NeoHooke(p["lam_neq"], p["mu_neq"]), eta_dev=p["eta_dev"],
                         eta_vol=p["eta_vol"])
    fixed = np.zeros((mesh.n_nodes, 3), bool)
    fixed[clamp] = True
    kw = {}
    if test == "creep":
        force = traction_load(mesh, facets_from_nodes(mesh, grip), [stress, 0.0, 0.0])
        kw["loads"] = [(np.asarray(force), Ramp(0.0, ramp))]
        t_end = 5.0 if t1 is None else t1
        step = 0.05
    else:
        fixed[grip] = True
        motion = np.zeros((mesh.n_nodes, 3))
        motion[grip, 0] = strain * LENGTH
        if test == "relaxation":
            kw["prescribed"] = [(motion, Ramp(0.0, ramp))]
            t_end = 5.0 if t1 is None else t1
            step = 0.05
        else:
            kw["prescribed"] = [(motion, Sine(1.0 / frequency))]
            t_end = cycles / frequency if t1 is None else t1
            step = min(0.05, 0.05 / frequency)
    scene = Scene(mesh, mat, p["density"], fixed=fixed, **kw)
    return Specimen(scene, clamp, grip, float(t_end), float(step if dt0 is None else dt0))
