"""The paper's free-flying L-shaped body (Simo & Tarnow's L-block, as in Groß & Betsch 2005)."""

import warnings
from typing import Optional, Sequence

from .._fem._generators import lshape_mesh
from .._fem._rigid import rigid_velocity
from .._materials import NeoHooke, ReeseGovindjee
from .._scene import Scene

PAPER = dict(lam=30000.0, mu=7500.0, density=8.93, eta_dev=50000.0, eta_vol=10000.0,
             v_translation=(6.0, 0.0, 0.0), omega=(0.0, 0.0, 0.6))


def lshape(dim: int = 2, refinement: int = 1, cell_type: Optional[str] = None, lam: float = PAPER["lam"],
           mu: float = PAPER["mu"], density: float = PAPER["density"], eta_dev: float = PAPER["eta_dev"],
           eta_vol: float = PAPER["eta_vol"],
           v_translation: Sequence[float] = PAPER["v_translation"], omega: Sequence[float] = PAPER["omega"],
           viscous: bool = True, quadrature_order: Optional[int] = None, *, element: Optional[str] = None) -> Scene:
    r"""The paper's example: Simo & Tarnow's L-block set free with
    $v_0(X) = v_T + \omega \times X$.

    Plane strain in 2D ($[0,6]\times[0,3] \cup [0,3]\times[0,10]$), extruded over
    $z \in [0,3]$ in 3D; squares (cubes) of edge 1/`refinement`. Both branches are
    Neo-Hookean with the paper's data by default; its initial energy is
    $H_0 = 3111.93$ at refinement 1 in 2D.

    **Arguments:**

    - `dim`: 2 or 3.
    - `refinement`: lattice cells per unit length.
    - `cell_type`: the element (`lshape_mesh`'s; default quad4 / hex8).
    - `lam`, `mu`: the Lamé constants of both Neo-Hooke branches (30000, 7500).
    - `density`: 8.93.
    - `eta_dev`, `eta_vol`: the viscosities (50000, 10000).
    - `v_translation`, `omega`: the rigid initial motion, 3-vectors ((6, 0, 0) and
      (0, 0, 0.6); in 2D the first two and the third components are used).
    - `viscous`: False drops the viscous branch (an elastic scene, no internal variable).
    - `quadrature_order`: the spatial quadrature (default: the element's full rule).
    - `element`: deprecated name of `cell_type`.

    **Returns:**

    A `Scene`.

    **Example:**

    ```python
    import jaxvisco as jv

    scene = jv.scenes.lshape(dim=2, refinement=1)
    ```
    """
    if element is not None:
        if cell_type is not None:
            raise TypeError("lshape(): give cell_type or the deprecated element, not both.")
        warnings.warn("lshape(): element= is deprecated, use cell_type=.", DeprecationWarning, stacklevel=2)
        cell_type = element
    mesh = lshape_mesh(dim=dim, refinement=refinement, cell_type=cell_type)
    nh = NeoHooke(lam=lam, mu=mu)
    material = ReeseGovindjee(nh, nh if viscous else None, eta_dev=eta_dev, eta_vol=eta_vol)
    w = omega[2] if dim == 2 else omega  # numpy where the data are concrete (`rigid_velocity`)
    v0 = rigid_velocity(mesh, velocity=v_translation[:dim], angular_velocity=w)
    return Scene(mesh, material, density, velocities=v0, quadrature_order=quadrature_order)
