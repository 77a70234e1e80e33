"""jaxvisco: finite-strain viscoelastodynamics with Galerkin time elements in JAX.

jaxvisco computes in float64 and never switches precision behind your back: call
``jax.config.update("jax_enable_x64", True)`` (or set ``JAX_ENABLE_X64=1``) first.
"""

from . import scenes as scenes
from ._config import require_x64 as require_x64
from ._drive import drive as drive
from ._elements import ElementType as ElementType, element_type as element_type
from ._generators import box as box, lshape_mesh as lshape_mesh, rectangle as rectangle
from ._materials import NeoHooke as NeoHooke, ReeseGovindjee as ReeseGovindjee, paper_material as paper_material
from ._mesh import Mesh as Mesh
from ._newton import NewtonKrylov as NewtonKrylov
from ._ode import SemiDiscrete as SemiDiscrete, semidiscrete as semidiscrete
from ._results import read_restart as read_restart, read_results as read_results, resume as resume
from ._scene import Scene as Scene, State as State
from ._simulate import Solution as Solution, SolverError as SolverError, simulate as simulate
from ._time_element import (
    AbstractTimeElement as AbstractTimeElement,
    Midpoint as Midpoint,
    Newmark as Newmark,
    cG as cG,
    eG as eG,
)

__version__ = "0.1.0"
