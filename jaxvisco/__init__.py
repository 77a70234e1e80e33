"""jaxvisco: finite-strain viscoelastodynamics with Galerkin time elements in JAX.

jaxvisco computes in float64 and never switches precision behind your back: call
``jax.config.update("jax_enable_x64", True)`` (or set ``JAX_ENABLE_X64=1``) first.
"""

from . import scenes as scenes
from . import time_functions as time_functions
from ._config import __version__ as __version__
from ._config import compiler_options as compiler_options
from ._config import enable_compilation_cache as enable_compilation_cache
from ._config import require_x64 as require_x64
from ._export import CacheWarning as CacheWarning
from ._fem._boundary import boundary_facets as boundary_facets
from ._fem._boundary import facet_area as facet_area
from ._fem._boundary import facet_type as facet_type
from ._fem._boundary import facets_from_nodes as facets_from_nodes
from ._fem._boundary import local_facets as local_facets
from ._fem._boundary import nodes_where as nodes_where
from ._fem._boundary import pressure_load as pressure_load
from ._fem._boundary import traction_load as traction_load
from ._fem._elements import ElementType as ElementType
from ._fem._elements import element_type as element_type
from ._fem._generators import box as box
from ._fem._generators import lshape_mesh as lshape_mesh
from ._fem._generators import rectangle as rectangle
from ._fem._groups import MeshGroups as MeshGroups
from ._fem._groups import read_mesh as read_mesh
from ._fem._mesh import Mesh as Mesh
from ._fem._rigid import rigid_velocity as rigid_velocity
from ._fem._select import clamp as clamp
from ._fem._select import nodes_in as nodes_in
from ._fem._probe import Probe as Probe
from ._integrate._adjoint import AbstractAdjoint as AbstractAdjoint
from ._integrate._adjoint import (
    RecursiveCheckpointAdjoint as RecursiveCheckpointAdjoint,
)
from ._integrate._event import AbstractEvent as AbstractEvent
from ._integrate._event import Equilibrium as Equilibrium
from ._integrate._saveat import SaveAt as SaveAt
from ._integrate._schedule import (
    AbstractStepSizeController as AbstractStepSizeController,
)
from ._integrate._schedule import ConstantStepSize as ConstantStepSize
from ._integrate._schedule import Schedule as Schedule
from ._integrate._schedule import StepTo as StepTo
from ._integrate._simulate import simulate as simulate
from ._integrate._solution import Solution as Solution
from ._integrate._solution import SolverError as SolverError
from ._integrate._stepsize import PIDController as PIDController
from ._io import Restart as Restart
from ._io import ResultsWriter as ResultsWriter
from ._io import read_restart as read_restart
from ._io import read_results as read_results
from ._io import save as save
from ._materials import NeoHooke as NeoHooke
from ._materials import ReeseGovindjee as ReeseGovindjee
from ._materials import paper_material as paper_material
from ._scene import Scene as Scene
from ._scene import State as State
from ._scenefile._scenefile import SceneFile as SceneFile
from ._scenefile._scenefile import read_scene_file as read_scene_file
from ._solver._linear import GMRES as GMRES
from ._solver._linear import AbstractLinearSolver as AbstractLinearSolver
from ._solver._linear import Direct as Direct
from ._solver._newton import NewtonKrylov as NewtonKrylov
from ._time_element._time_element import (
    AbstractTimeElement as AbstractTimeElement,
)
from ._time_element._time_element import (
    Midpoint as Midpoint,
)
from ._time_element._time_element import (
    Newmark as Newmark,
)
from ._time_element._time_element import (
    cG as cG,
)
from ._time_element._time_element import (
    eG as eG,
)
from ._tools._batch import sharded_map as sharded_map
from ._tools._drive import drive as drive
from ._tools._experiment import Experiment as Experiment
from ._tools._experiment import read_csv as read_csv
from ._tools._identify import PARAMETERS as PARAMETERS
from ._tools._identify import Fit as Fit
from ._tools._identify import Identification as Identification
from ._tools._identify import Parameter as Parameter
from ._tools._identify import identify as identify
from ._tools._identify import identify_batch as identify_batch
from ._tools._observe import AbstractObservable as AbstractObservable
from ._tools._observe import Custom as Custom
from ._tools._observe import Displacement as Displacement
from ._tools._observe import Extensometer as Extensometer
from ._tools._observe import Quantity as Quantity
from ._tools._observe import ReactionForce as ReactionForce
from ._tools._identify import with_parameters as with_parameters
from ._tools._least_squares import LeastSquaresResult as LeastSquaresResult
from ._tools._least_squares import least_squares as least_squares
from ._tools._ode import SemiDiscrete as SemiDiscrete
from ._tools._ode import semidiscrete as semidiscrete
from ._tools._resume import resume as resume
