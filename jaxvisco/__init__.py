"""jaxvisco: finite-strain viscoelastodynamics with Galerkin time elements in JAX."""

from ._config import require_x64 as require_x64
