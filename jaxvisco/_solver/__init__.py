"""Nonlinear solver: sparse host LU (with its FFI extension), the condensed tangent, Newton-Krylov and implicit step derivatives."""
