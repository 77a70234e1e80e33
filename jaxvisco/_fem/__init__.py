"""Finite elements: tensors, quadrature, element types, meshes and generators, the discrete space, boundaries, mesh groups, Krylov kernels."""
