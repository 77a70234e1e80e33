"""Quadrature rules on reference cells.

Reference domains: the unit interval [0, 1] for `gauss_legendre` (also used for time
elements), [-1, 1]^d for quadrilaterals and hexahedra, the unit simplex for triangles and
tetrahedra. All rules are plain numpy float64 arrays, built once, outside any jit.
"""

import functools

import numpy as np
import scipy.special

_SHAPES = {
    "line": "line",
    "interval": "line",
    "tri": "tri",
    "triangle": "tri",
    "quad": "quad",
    "quadrilateral": "quad",
    "tet": "tet",
    "tetra": "tet",
    "tetrahedron": "tet",
    "hex": "hex",
    "hexahedron": "hex",
}
# Element and meshio names map to their reference shape too.
for _name in ("line2", "line3"):
    _SHAPES[_name] = "line"
for _name in ("tri3", "tri6", "triangle6"):
    _SHAPES[_name] = "tri"
for _name in ("quad4", "quad8", "quad9"):
    _SHAPES[_name] = "quad"
for _name in ("tet4", "tet10", "tetra10"):
    _SHAPES[_name] = "tet"
for _name in ("hex8", "hex20", "hex27", "hexahedron20", "hexahedron27"):
    _SHAPES[_name] = "hex"


def _check_int(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    return int(value)


@functools.lru_cache(maxsize=None)
def _gauss_legendre_cached(n: int):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre rule with `n` points on the unit interval [0, 1].

    Exact for polynomials of degree <= 2n - 1.

    **Arguments:**

    - `n`: number of points, an integer >= 1.

    **Returns:**

    `(points, weights)`, two float64 numpy arrays of shape `(n,)`; the weights sum to 1.
    """
    n = _check_int(n, "the number of Gauss points n", 1)
    x, w = _gauss_legendre_cached(n)
    return x.copy(), w.copy()


def _n_points(order: int) -> int:
    """Gauss points per direction for exactness up to `order`."""
    return max(1, (order + 2) // 2)


def _jacobi01(n: int, alpha: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Jacobi rule for the weight (1 - u)^alpha on [0, 1]."""
    x, w = scipy.special.roots_jacobi(n, alpha, 0.0)
    return 0.5 * (x + 1.0), w / 2.0 ** (alpha + 1)


def _tensor(dim: int, order: int):
    x, w = np.polynomial.legendre.leggauss(_n_points(order))
    grids = np.meshgrid(*([x] * dim), indexing="ij")
    wgrids = np.meshgrid(*([w] * dim), indexing="ij")
    points = np.stack([g.ravel() for g in grids], axis=-1)
    weights = np.prod(np.stack([g.ravel() for g in wgrids], axis=-1), axis=-1)
    return points, weights


def _tri_symmetric(order: int):
    if order <= 1:
        return np.array([[1 / 3, 1 / 3]]), np.array([0.5])
    if order == 2:
        p = np.array([[1 / 6, 1 / 6], [2 / 3, 1 / 6], [1 / 6, 2 / 3]])
        return p, np.full(3, 1 / 6)
    # Radon's 7-point rule, degree 5, closed form.
    s = np.sqrt(15.0)
    a1, a2 = (6.0 - s) / 21.0, (6.0 + s) / 21.0
    w1, w2 = (155.0 - s) / 1200.0, (155.0 + s) / 1200.0
    pts = [[1 / 3, 1 / 3]]
    wts = [9.0 / 40.0]
    for a, w in ((a1, w1), (a2, w2)):
        b = 1.0 - 2.0 * a
        pts += [[a, a], [b, a], [a, b]]
        wts += [w] * 3
    return np.array(pts), 0.5 * np.array(wts)


def _tri_collapsed(order: int):
    n = _n_points(order)
    u, wu = _jacobi01(n, 1)  # absorbs the Duffy Jacobian (1 - u)
    v, wv = _gauss_legendre_cached(n)
    U, V = np.meshgrid(u, v, indexing="ij")
    W = np.outer(wu, wv)
    return np.stack([U.ravel(), (V * (1 - U)).ravel()], -1), W.ravel()


def _tet_symmetric(order: int):
    if order <= 1:
        return np.array([[0.25, 0.25, 0.25]]), np.array([1 / 6])
    a = (5.0 - np.sqrt(5.0)) / 20.0
    b = 1.0 - 3.0 * a
    p = np.array([[a, a, a], [b, a, a], [a, b, a], [a, a, b]])
    return p, np.full(4, 1 / 24)


def _tet_collapsed(order: int):
    n = _n_points(order)
    u, wu = _jacobi01(n, 2)  # Jacobian (1-u)^2 (1-v)
    v, wv = _jacobi01(n, 1)
    w, ww = _gauss_legendre_cached(n)
    U, V, Wc = np.meshgrid(u, v, w, indexing="ij")
    weights = (wu[:, None, None] * wv[None, :, None] * ww[None, None, :]).ravel()
    x = U
    y = V * (1 - U)
    z = Wc * (1 - U) * (1 - V)
    return np.stack([x.ravel(), y.ravel(), z.ravel()], -1), weights


def quadrature(cell_type: str, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature rule on a reference cell, exact for polynomials of degree <= `order`.

    - `"line"`: Gauss–Legendre on [-1, 1].
    - `"quad"`, `"hex"`: tensor Gauss–Legendre on [-1, 1]^d, `(order + 2) // 2` points
      per direction.
    - `"tri"`: symmetric rules (1, 3 and Radon's 7 points for orders <= 5), collapsed
      (Duffy) Gauss–Jacobi beyond.
    - `"tet"`: symmetric rules (1 and 4 points for orders <= 2), collapsed Gauss–Jacobi
      beyond (8 points for order 3, 27 for orders 4–5). All weights are positive.

    **Arguments:**

    - `cell_type`: reference shape: `"line"`, `"tri"`/`"triangle"`, `"quad"`,
      `"tet"`/`"tetra"`, `"hex"`/`"hexahedron"`, or an element name such as `"hex20"`.
    - `order`: polynomial degree to integrate exactly, an integer >= 0.

    **Returns:**

    `(points, weights)`: float64 numpy arrays of shapes `(nq, dim)` and `(nq,)`; the
    weights sum to the reference volume (2, 1/2, 4, 1/6, 8).
    """
    shape = _SHAPES.get(str(cell_type).lower()) if isinstance(cell_type, str) else None
    if shape is None:
        raise ValueError(
            f"Unknown cell type {cell_type!r} for quadrature; accepted: "
            f"{sorted(_SHAPES)}."
        )
    order = _check_int(order, "the quadrature order", 0)
    if shape == "line":
        x, w = np.polynomial.legendre.leggauss(_n_points(order))
        return x[:, None], w
    if shape == "quad":
        return _tensor(2, order)
    if shape == "hex":
        return _tensor(3, order)
    if shape == "tri":
        return _tri_symmetric(order) if order <= 5 else _tri_collapsed(order)
    return _tet_symmetric(order) if order <= 2 else _tet_collapsed(order)
