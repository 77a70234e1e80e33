"""Material-point probes: markers, extensometers and DIC grids.

A `Probe` reads the motion at chosen material points, given by their reference
coordinates anywhere in the body (not only at nodes), through the shape functions of the
element holding each point: positions, displacements, deformation gradients and Green
strains, for one frame or a stack of frames, differentiably.

The points are located once, on the host, in NumPy:

1. each element's bounding box is that of the Bernstein control net of its isoparametric
   map, which contains the element (convex-hull property), curved quadratic elements
   included;
2. boxes and points are hashed into a uniform grid of about one element per bin, and each
   point meets only the elements whose boxes share its bin and contain it;
3. every (point, candidate element) pair is inverted at once by Newton's method on the
   isoparametric map, from the reference centroid;
4. each point keeps the candidate whose reference coordinates lie inside (or least outside)
   the reference cell; a point no element holds within `tol` is outside the body.

Shape functions on the host are the library's own (`ElementType.shape_functions`),
written once per element type in the monomial basis of degree <= 2 per coordinate (which
holds every element here) so that NumPy evaluates them for all pairs at once.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import device_array
from ._elements import element_type
from ._mesh import Mesh

_NEWTON_ITERATIONS = 30
_CHUNK = 1 << 16  # (point, element) pairs inverted at once: bounds the host memory


class Probe(eqx.Module):
    """Material points of a mesh (markers, extensometers, DIC grids), located once on the
    host, read differentiably in every frame: positions, displacements, deformation
    gradients and Green strains, through the shape functions of the element holding each
    point (curved quadratic elements included).

    **Attributes:**

    - `points`: the reference coordinates asked for, `(m, dim)`.
    - `element`: index of the element holding each point, `(m,)`.
    - `xi`: each point's coordinates in its element's reference cell, `(m, dim)`.
    - `cells`: node indices of that element, `(m, n_en)`.
    - `N`: shape-function values at the points, `(m, n_en)`.
    - `dN_dX`: shape-function gradients with respect to the reference coordinates at
      the points, `(m, n_en, dim)`.
    - `X_nodes`: reference coordinates of those nodes, `(m, n_en, dim)`.

    On an element boundary the gradients (`deformation_gradient`, `green_strain`) are
    those of the element the point was assigned to: finite element strains jump there.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import jaxvisco as jv

    mesh = jv.box(4, 2, 2, lx=2.0)
    probe = jv.Probe(mesh, [[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]])
    x = 1.1 * mesh.points[None]                     # a frame stretched by 10 %
    gauge = probe.positions(x)                      # (1, 2, 3)
    print(jnp.linalg.norm(gauge[:, 1] - gauge[:, 0], axis=-1) - 1.0)   # 0.1
    ```
    """

    points: jax.Array
    element: jax.Array
    xi: jax.Array
    cells: jax.Array
    N: jax.Array
    dN_dX: jax.Array
    X_nodes: jax.Array
    n_nodes: int = eqx.field(static=True)
    dim: int = eqx.field(static=True)

    def __init__(self, mesh: Mesh, points, tol: float = 1e-8):
        """**Arguments:**

        - `mesh`: the `Mesh` (reference configuration).
        - `points`: reference coordinates of the material points, `(m, dim)` (or one
          point, `(dim,)`).
        - `tol`: how far outside its element's reference cell a point may lie and still
          count as inside, in reference coordinates (the cells span 1 or 2): points on
          the surface given with rounding errors are accepted.

        **Raises:**

        `ValueError` if `points` has the wrong shape or non-finite entries, `tol` is not
        a small non-negative number, or some points lie outside the body (the message
        gives how many, the first ones and `tol`).
        """
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh must be a jaxvisco Mesh, got {type(mesh).__name__}.")
        if isinstance(points, jax.core.Tracer) or isinstance(mesh.points, jax.core.Tracer):
            raise ValueError("a Probe is located on the host: build it outside jit/vmap/grad, from "
                             "concrete points and mesh.")
        P = np.asarray(points, dtype=np.float64)
        if P.ndim == 1:
            P = P[None]
        if P.ndim != 2 or P.shape[1] != mesh.dim or P.shape[0] == 0:
            raise ValueError(
                f"points must have shape (m, {mesh.dim}) with m >= 1 for this "
                f"{mesh.dim}D mesh, got shape {np.shape(points)}."
            )
        bad = np.flatnonzero(~np.all(np.isfinite(P), axis=1))
        if bad.size:
            raise ValueError(f"point {bad[0]} has non-finite coordinates {P[bad[0]]}.")
        if not (np.isscalar(tol) and 0.0 <= float(tol) < 0.5):
            raise ValueError(f"tol must be a number in [0, 0.5), got {tol!r}.")
        X = np.asarray(mesh.points, dtype=np.float64)
        cells = np.asarray(mesh.cells, dtype=np.int64)
        element, xi = locate(mesh.cell_type, X, cells, P, float(tol))
        poly = _polynomial(mesh.cell_type)
        N, dN = poly.evaluate(xi)
        Xe = X[cells[element]]
        J = np.einsum("mai,maj->mij", Xe, dN)  # dX/dxi
        dN_dX = np.einsum("maj,mji->mai", dN, np.linalg.inv(J))
        self.points = device_array(P)
        self.element = device_array(element, np.int32)
        self.xi = device_array(xi)
        self.cells = device_array(cells[element], np.int32)
        self.N = device_array(N)
        self.dN_dX = device_array(dN_dX)
        self.X_nodes = device_array(Xe)
        self.n_nodes = mesh.n_nodes
        self.dim = mesh.dim

    @property
    def n_points(self) -> int:
        """Number of points `m`."""
        return self.points.shape[0]

    def _nodes(self, x):
        x = jnp.asarray(x)
        if x.ndim < 2 or x.shape[-2:] != (self.n_nodes, self.dim):
            raise ValueError(
                f"x must hold node positions of shape (n_nodes, dim) = "
                f"({self.n_nodes}, {self.dim}), or a stack (..., {self.n_nodes}, "
                f"{self.dim}), got shape {x.shape}."
            )
        return x[..., self.cells, :]  # (..., m, n_en, dim)

    def positions(self, x) -> jax.Array:
        """Current positions of the points.

        **Arguments:**

        - `x`: node positions, `(n_nodes, dim)`, or a stack of frames
          `(..., n_nodes, dim)`.

        **Returns:**

        `(..., m, dim)`: $x(X_p) = \\sum_a N_a(X_p)\\, x_a$.
        """
        return jnp.einsum("...mai,ma->...mi", self._nodes(x), self.N)

    def displacements(self, x) -> jax.Array:
        """Displacements of the points, $\\sum_a N_a(X_p)(x_a - X_a)$ (zero for `x` equal
        to the reference node positions).

        **Arguments:**

        - `x`: node positions, `(n_nodes, dim)` or `(..., n_nodes, dim)`.

        **Returns:**

        `(..., m, dim)`.
        """
        return jnp.einsum("...mai,ma->...mi", self._nodes(x) - self.X_nodes, self.N)

    def deformation_gradient(self, x) -> jax.Array:
        """Deformation gradients at the points, $F = \\sum_a x_a \\otimes \\nabla_X N_a$.

        **Arguments:**

        - `x`: node positions, `(n_nodes, dim)` or `(..., n_nodes, dim)`.

        **Returns:**

        `(..., m, dim, dim)` (2x2 on plane meshes).
        """
        return jnp.einsum("...mai,maj->...mij", self._nodes(x), self.dN_dX)

    def green_strain(self, x) -> jax.Array:
        """Green–Lagrange strains at the points, $E = (F^T F - I)/2$.

        **Arguments:**

        - `x`: node positions, `(n_nodes, dim)` or `(..., n_nodes, dim)`.

        **Returns:**

        `(..., m, dim, dim)`, symmetric.
        """
        F = self.deformation_gradient(x)
        C = jnp.einsum("...ki,...kj->...ij", F, F)
        return 0.5 * (C - jnp.eye(self.dim, dtype=F.dtype))


# --------------------------------------------------------------------------- location


def locate(cell_type: str, X, cells, P, tol: float = 1e-8):
    """Find the element holding each point and the point's reference coordinates there.

    **Arguments:**

    - `cell_type`: element name.
    - `X`: node coordinates, `(n_nodes, dim)`.
    - `cells`: connectivity, `(n_cells, n_en)`.
    - `P`: points, `(m, dim)`.
    - `tol`: accepted distance outside the reference cell, in reference coordinates.

    **Returns:**

    `(element, xi)`: NumPy arrays `(m,)` and `(m, dim)`.

    **Raises:**

    `ValueError` naming how many points lie outside the body, the first ones and `tol`.
    """
    poly = _polynomial(cell_type)
    Xe_all = X[cells]  # (n_cells, n_en, dim)
    control = np.einsum("ka,cad->ckd", poly.control, Xe_all)
    lo, hi = control.min(axis=1), control.max(axis=1)
    size = np.max(hi - lo, axis=1)
    # `tol` in reference coordinates is at most `dim * tol * size` in length.
    pad = (X.shape[1] * tol + 1e-12) * size[:, None]
    lo, hi = lo - pad, hi + pad
    p_idx, e_idx = _candidates(lo, hi, P)

    m, dim = P.shape
    best = np.full(m, np.inf)
    element = np.full(m, -1, dtype=np.int64)
    xi = np.zeros((m, dim))
    for start in range(0, p_idx.size, _CHUNK):  # chunks of pairs, not of elements
        pi, ei = p_idx[start : start + _CHUNK], e_idx[start : start + _CHUNK]
        z, outside = _invert(poly, Xe_all[ei], P[pi], size[ei])
        # The best candidate of each point: sort by (point, outside), keep the first.
        order = np.lexsort((ei, outside, pi))
        pi, ei, z, outside = pi[order], ei[order], z[order], outside[order]
        first = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
        pi, ei, z, outside = pi[first], ei[first], z[first], outside[first]
        better = outside < best[pi]
        best[pi[better]] = outside[better]
        element[pi[better]] = ei[better]
        xi[pi[better]] = z[better]
    out = np.flatnonzero(~(best <= tol))
    if out.size:
        shown = "; ".join(
            f"point {i} at ({', '.join(f'{v:.10g}' for v in P[i])})"
            for i in out[:3]
        )
        raise ValueError(
            f"{out.size} of {m} points lie outside the body (no element holds them "
            f"within tol={tol:g} in reference coordinates): {shown}"
            + (" ..." if out.size > 3 else ".")
        )
    return element, xi


def _candidates(lo, hi, P):
    """(point, element) pairs whose (padded) element box holds the point.

    Boxes and points are hashed into a uniform grid (bins about one typical element
    wide); a point meets the elements registered in its bin, which a sort and a
    `searchsorted` join find for all points at once."""
    n_cells, dim = lo.shape
    g_lo, g_hi = lo.min(axis=0), hi.max(axis=0)
    h = np.median(np.max(hi - lo, axis=1))
    span = np.maximum(g_hi - g_lo, h)
    counts = np.maximum(np.ceil(span / h).astype(np.int64), 1)
    while np.prod(counts) > 8 * n_cells + 64:  # a few bins per element at most
        h *= 1.5
        counts = np.maximum(np.ceil(span / h).astype(np.int64), 1)

    def bin_of(y):
        return np.clip(np.floor((y - g_lo) / h).astype(np.int64), 0, counts - 1)

    b_lo, b_hi = bin_of(lo), bin_of(hi)
    extent = b_hi - b_lo + 1  # (n_cells, dim) bins per direction
    per_cell = np.prod(extent, axis=1)
    owner = np.repeat(np.arange(n_cells), per_cell)
    local = np.arange(owner.size) - np.repeat(np.cumsum(per_cell) - per_cell, per_cell)
    key = np.zeros(owner.size, dtype=np.int64)
    for d in range(dim):  # mixed-radix decode of `local` into bin offsets per direction
        ext = extent[owner, d]
        key = key * counts[d] + b_lo[owner, d] + local % ext
        local = local // ext
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]

    inside_grid = np.all((P >= g_lo) & (P <= g_hi), axis=1)
    pb = bin_of(P)
    p_key = np.zeros(len(P), dtype=np.int64)
    for d in range(dim):
        p_key = p_key * counts[d] + pb[:, d]
    first = np.searchsorted(key, p_key, side="left")
    last = np.searchsorted(key, p_key, side="right")
    n = np.where(inside_grid, last - first, 0)
    p_idx = np.repeat(np.arange(len(P)), n)
    e_idx = owner[np.repeat(first, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)]
    keep = np.all((P[p_idx] >= lo[e_idx]) & (P[p_idx] <= hi[e_idx]), axis=1)
    return p_idx[keep], e_idx[keep]


def _invert(poly, Xe, P, size):
    """Newton's method on `x(xi) = P` for a batch of (element, point) pairs.

    **Returns:** `(xi, outside)`: reference coordinates, and how far they lie outside the
    reference cell (`inf` where Newton did not converge to the point)."""
    n, dim = P.shape
    xi = np.broadcast_to(poly.centroid, (n, dim)).copy()
    active = np.arange(n)  # pairs still iterating
    clipped = np.zeros(n, dtype=bool)
    for _ in range(_NEWTON_ITERATIONS):
        N, dN = poly.evaluate(xi[active])
        Xa = Xe[active]
        r = np.einsum("na,nai->ni", N, Xa) - P[active]
        J = np.einsum("nai,naj->nij", Xa, dN)
        ok = np.abs(np.linalg.det(J)) > 1e-14 * size[active] ** dim
        step = np.zeros((active.size, dim))
        step[ok] = -np.linalg.solve(J[ok], r[ok][..., None])[..., 0]
        # Stay in a bounded region around the cell, where the map is still well defined;
        # a pair pushed against that region's edge twice holds the point far outside.
        new = xi[active] + step
        hit = np.any((new < poly.low - 1.0) | (new > poly.high + 1.0), axis=1)
        xi[active] = np.clip(new, poly.low - 1.0, poly.high + 1.0)
        done = ~ok | (hit & clipped[active]) | np.all(np.abs(step) <= 1e-12, axis=1)
        clipped[active] = hit
        active = active[~done]
        if active.size == 0:
            break
    N, _ = poly.evaluate(xi)
    r = np.einsum("na,nai->ni", N, Xe) - P
    converged = np.linalg.norm(r, axis=1) <= 1e-10 * size
    return xi, np.where(converged, poly.outside(xi), np.inf)


# ------------------------------------------------------- shape functions on the host


class _Polynomial:
    """An element's shape functions in the monomial basis of degree <= 2 per coordinate.

    `coefficients` `(n_mono, n_en)`: $N_a(\\xi) = \\sum_k c_{ka} \\xi^{e_k}$;
    `control` `(n_ctrl, n_en)`: the tensor Bernstein control net of the isoparametric
    map on the reference cell's bounding box is `control @ X_e`."""

    def __init__(self, name):
        e = element_type(name)
        dim = e.dim
        self.simplex = e.is_simplex
        self.low, self.high = (0.0, 1.0) if e.is_simplex else (-1.0, 1.0)
        self.centroid = np.full(dim, 1.0 / (dim + 1) if e.is_simplex else 0.0)
        # The 3^dim points {0, 1/2, 1}^dim of the cell's bounding box (as t in [0, 1]^dim)
        # are unisolvent for both bases; the shape functions there fix both expansions.
        t = np.stack(np.meshgrid(*[[0.0, 0.5, 1.0]] * dim, indexing="ij"), -1)
        t = t.reshape(-1, dim)
        exponents = np.rint(2 * t).astype(np.int64)  # {0, 1, 2}^dim
        xi = self.low + (self.high - self.low) * t
        values = np.asarray(jax.vmap(e.shape_functions)(jnp.asarray(xi)))
        monomials = np.prod(xi[:, None, :] ** exponents[None], axis=2)
        coefficients = np.linalg.solve(monomials, values)
        used = np.any(np.abs(coefficients) > 1e-12, axis=1)  # e.g. tet4: 1, x, y, z
        self.exponents, self.coefficients = exponents[used], coefficients[used]
        if e.is_simplex:
            # Quadratic Bernstein polynomials of the barycentric coordinates (the P2
            # nodes are unisolvent): the net hugs the simplex.
            xi = element_type("tri6" if dim == 2 else "tet10").reference_nodes()
            lam = np.concatenate([1.0 - xi.sum(axis=1, keepdims=True), xi], axis=1)
            i, j = np.triu_indices(dim + 1)
            bernstein = np.where(i == j, 1.0, 2.0) * lam[:, i] * lam[:, j]
            values = np.asarray(jax.vmap(e.shape_functions)(jnp.asarray(xi)))
        else:
            # Quadratic Bernstein polynomials of t per coordinate, and their products.
            bern = np.stack([(1 - t) ** 2, 2 * t * (1 - t), t**2], -1)  # (3^dim, dim, 3)
            bernstein = np.prod(bern[:, np.arange(dim), exponents], axis=2)
        self.control = np.linalg.solve(bernstein, values)

    def evaluate(self, xi):
        """Shape functions `(n, n_en)` and reference gradients `(n, n_en, dim)`."""
        n, dim = xi.shape
        ones = np.ones_like(xi)
        powers = np.stack([ones, xi, xi * xi], axis=1)  # (n, 3, dim): xi^0, xi^1, xi^2
        slopes = np.stack([0.0 * xi, ones, 2.0 * xi], axis=1)  # their derivatives
        axes = np.arange(dim)
        factors = powers[:, self.exponents, axes]  # (n, n_mono, dim)
        mono = np.prod(factors, axis=2)
        dmono = np.empty((n, dim, len(self.exponents)))
        for d in range(dim):  # the derivative along d replaces the d-th factor
            rest = np.prod(factors[:, :, axes != d], axis=2)
            dmono[:, d] = slopes[:, self.exponents[:, d], d] * rest
        N = mono @ self.coefficients
        dN = np.swapaxes(dmono @ self.coefficients, 1, 2)
        return N, dN

    def outside(self, xi):
        """How far `xi` lies outside the reference cell (<= 0 inside)."""
        if self.simplex:
            return np.maximum(np.max(-xi, axis=1), np.sum(xi, axis=1) - 1.0)
        return np.max(np.abs(xi), axis=1) - 1.0


@functools.cache
def _polynomial(name: str) -> _Polynomial:
    return _Polynomial(name)
