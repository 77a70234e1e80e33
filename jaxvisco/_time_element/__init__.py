"""Galerkin time elements: time bases, time-element schemes, the step residual and the error estimate."""
