"""Selecting nodes and holding them: `nodes_in` (nodes in coordinate ranges, as a scene
file's ``[groups.NAME]``) and `clamp` (the `Scene(fixed=...)` mask of a scene file's
``[[dirichlet]]``: some components of some nodes)."""

from typing import TYPE_CHECKING, Sequence, Union

import numpy as np
from jax.typing import ArrayLike

if TYPE_CHECKING:
    from ._mesh import Mesh

_AXES = "xyz"
Range = Union[float, Sequence[float], None]


def nodes_in(mesh: "Mesh", x: Range = None, y: Range = None, z: Range = None) -> np.ndarray:
    """The nodes whose coordinates lie in the given ranges.

    A node is selected when every coordinate given lies in its inclusive range, with a
    tolerance of 1e-9 times the mesh's bounding-box diagonal (so `x=0.0` finds the nodes
    on the plane x = 0 of a generated mesh).

    **Arguments:**

    - `mesh`: a `Mesh`.
    - `x`, `y`, `z`: a range `(lo, hi)` or one number `v` (the range `(v, v)`); None
      (default) leaves that coordinate free. `z` only for 3D meshes.

    **Returns:**

    The sorted node indices (an int array).

    **Raises:**

    `ValueError` when no range is given, a range is empty or not finite, `z` is given
    for a 2D mesh, or no node is selected (the message gives the mesh's extent).

    **Example:**

    ```python
    import jaxvisco as jv

    mesh = jv.rectangle(8, 2, lx=4.0, ly=1.0)
    left = jv.nodes_in(mesh, x=0.0)              # the 3 nodes on x = 0
    top_right = jv.nodes_in(mesh, x=(2.0, 4.0), y=1.0)
    ```
    """
    X = np.asarray(mesh.points)
    dim = X.shape[1]
    lo, hi = X.min(axis=0), X.max(axis=0)
    tol = 1e-9 * float(np.linalg.norm(hi - lo))
    ranges = dict(x=x, y=y, z=z)
    if all(r is None for r in ranges.values()):
        raise ValueError("nodes_in: give at least one coordinate range x, y or z.")
    keep = np.ones(len(X), dtype=bool)
    for axis, name in enumerate(_AXES):
        r = ranges[name]
        if r is None:
            continue
        if axis >= dim:
            raise ValueError(f"nodes_in: the mesh is {dim}D; {name} is not a coordinate of it.")
        a, b = _range(r, name)
        keep &= (X[:, axis] >= a - tol) & (X[:, axis] <= b + tol)
    if not keep.any():
        extent = ", ".join(f"{_AXES[i]} in [{lo[i]:g}, {hi[i]:g}]" for i in range(dim))
        raise ValueError(f"nodes_in: no node lies in the ranges given; the mesh spans {extent}.")
    return np.flatnonzero(keep)


def _range(r, name):
    if isinstance(r, (int, float, np.integer, np.floating)) and not isinstance(r, bool):
        a = b = float(r)
    else:
        try:
            a, b = (float(v) for v in r)
        except (TypeError, ValueError):
            raise ValueError(f"nodes_in: {name} must be a number or a range (lo, hi), got {r!r}.") from None
    if not (np.isfinite(a) and np.isfinite(b) and a <= b):
        raise ValueError(f"nodes_in: {name} must be a finite range with lo <= hi, got {r!r}.")
    return a, b


def clamp(mesh: "Mesh", nodes: ArrayLike, components: Union[str, int, Sequence[Union[str, int]]] = "all") -> np.ndarray:
    """The mask for `Scene(fixed=...)` that holds some components of some nodes.

    Masks combine with `|`: `fixed=jv.clamp(mesh, left) | jv.clamp(mesh, right, "x")`.

    **Arguments:**

    - `mesh`: a `Mesh`.
    - `nodes`: node indices (from `nodes_in`, `nodes_where` or a mesh file's groups,
      `MeshGroups.node_group`), or a boolean array with one entry per node.
    - `components`: `"all"` (default), or the held components: `"x"`, `"y"`, `"z"` or
      `0`, `1`, `2`, or a sequence of them.

    **Returns:**

    A boolean array `(n_nodes, dim)`, True where a position component is held.

    **Raises:**

    `ValueError` for node indices out of range or a component the mesh lacks.

    **Example:**

    ```python
    import jaxvisco as jv

    mesh = jv.rectangle(8, 2, lx=4.0, ly=1.0)
    fixed = jv.clamp(mesh, jv.nodes_in(mesh, x=0.0))   # a clamped left end
    ```
    """
    n, dim = np.asarray(mesh.points).shape
    idx = np.asarray(nodes)
    if idx.dtype == bool:
        if idx.shape != (n,):
            raise ValueError(f"clamp: a boolean nodes mask must have shape ({n},), got {idx.shape}.")
        idx = np.flatnonzero(idx)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) or (idx.size and (idx.min() < 0 or idx.max() >= n)):
        raise ValueError(f"clamp: nodes must be indices in [0, {n}) (or a boolean mask), got {nodes!r}.")
    mask = np.zeros((n, dim), dtype=bool)
    mask[np.ix_(idx, _components(components, dim))] = True
    return mask


def _components(components, dim):
    accepted = f"\"all\" or {', '.join(repr(a) for a in _AXES[:dim])} (or 0..{dim - 1}), or a list of them"
    if isinstance(components, str) and components == "all":
        return list(range(dim))
    items = [components] if isinstance(components, (str, int, np.integer)) else list(components)
    out = []
    for a in items:
        c = _AXES.find(a) if isinstance(a, str) and len(a) == 1 else a
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= c < dim:
            raise ValueError(f"clamp: component {a!r} of {components!r} is not one of a {dim}D mesh; "
                             f"accepted: {accepted}.")
        out.append(int(c))
    if not out:
        raise ValueError(f"clamp: no component given; accepted: {accepted}.")
    return sorted(set(out))
