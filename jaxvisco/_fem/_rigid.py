"""Rigid motion of the nodes: `rigid_velocity`, the velocity field of a rigid motion (what a scene
file's ``[initial]`` table gives with ``velocity``, ``angular_velocity`` and ``center``)."""

from typing import Optional, Sequence, Union

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike


def rigid_velocity(points: ArrayLike, velocity: Optional[Sequence[float]] = None,
                   angular_velocity: Union[float, Sequence[float], None] = None,
                   center: Optional[Sequence[float]] = None) -> np.ndarray | jax.Array:
    r"""The nodal velocities of a rigid motion, $v(X) = v_T + \omega \times (X - c)$.

    **Arguments:**

    - `points`: the nodal coordinates `(n_nodes, dim)`, or a `Mesh` (its points).
    - `velocity`: the translation $v_T$, `dim` numbers (default zero).
    - `angular_velocity`: $\omega$, one number in 2D (a rotation in the plane), three in
      3D (default zero).
    - `center`: the point $c$ the body turns about (default the origin).

    **Returns:**

    An array `(n_nodes, dim)` for `Scene(velocities=...)`: a numpy array for numbers, a
    JAX array where an argument is traced (so a derivative can flow through it).

    **Raises:**

    `ValueError` for arguments of the wrong size.

    **Example:**

    ```python
    import jaxvisco as jv

    mesh = jv.lshape_mesh()
    v0 = jv.rigid_velocity(mesh, velocity=[6.0, 0.0], angular_velocity=0.6)  # the paper's
    ```
    """
    X = getattr(points, "points", points)
    traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves((X, velocity, angular_velocity,
                                                                                    center)))
    xp = jnp if traced else np
    X = xp.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[1] not in (2, 3):
        raise ValueError(f"points must have shape (n_nodes, 2) or (n_nodes, 3), got {X.shape}.")
    dim = X.shape[1]
    v = xp.zeros_like(X)
    if velocity is not None:
        vT = xp.asarray(velocity, dtype=float)
        if vT.shape != (dim,):
            raise ValueError(f"velocity must be {dim} numbers for a {dim}D body, got shape {vT.shape}.")
        v = v + vT
    if angular_velocity is not None:
        Y = X if center is None else X - _sized(xp, center, dim, "center")
        w = xp.asarray(angular_velocity, dtype=float)
        if dim == 2:
            if w.shape != ():
                raise ValueError(f"angular_velocity must be one number in 2D, got shape {w.shape}.")
            v = v + w * xp.stack([-Y[:, 1], Y[:, 0]], axis=-1)
        else:
            if w.shape != (3,):
                raise ValueError(f"angular_velocity must be 3 numbers in 3D, got shape {w.shape}.")
            v = v + xp.cross(w, Y)
    elif center is not None:
        raise ValueError("a center needs an angular_velocity.")
    return v


def _sized(xp, value, dim, name):
    a = xp.asarray(value, dtype=float)
    if a.shape != (dim,):
        raise ValueError(f"{name} must be {dim} numbers for a {dim}D body, got shape {a.shape}.")
    return a
