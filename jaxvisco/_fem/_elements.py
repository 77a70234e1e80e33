"""Isoparametric Lagrange and serendipity elements.

Node ordering follows meshio/VTK, which for the linear cells and for the 20-node
hexahedron is also the Abaqus (C3D8, C3D20) ordering:

- `quad4`/`hex8`: counter-clockwise corners, bottom face (z = -1) then top face.
- `tri6`: corners, then mid-edges 0-1, 1-2, 2-0.
- `tet10`: corners, then mid-edges 0-1, 1-2, 2-0, 0-3, 1-3, 2-3.
- `quad8`/`quad9`: corners, mid-edges 0-1, 1-2, 2-3, 3-0 (then the centre).
- `hex20`: corners, mid-edges 0-1, 1-2, 2-3, 3-0, 4-5, 5-6, 6-7, 7-4, 0-4, 1-5, 2-6,
  3-7.
- `hex27`: as `hex20`, then face centres x = -1, x = +1, y = -1, y = +1, z = -1,
  z = +1 (VTK's triquadratic hexahedron), then the centre.
- `line2`/`line3` (facets of 2D cells, used for boundary loads): the two ends, then
  the middle.

Reference domains: [-1, 1]^d for lines, quadrilaterals and hexahedra, the unit simplex for
triangles and tetrahedra.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ._quadrature import quadrature as _quadrature

_QUAD4 = [[-1, -1], [1, -1], [1, 1], [-1, 1]]
_HEX8 = [[x, y, z] for z in (-1, 1) for (x, y) in _QUAD4]
_HEX_EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4),
              (0, 4), (1, 5), (2, 6), (3, 7)]  # fmt: skip
_QUAD_EDGES = [(0, 1), (1, 2), (2, 3), (3, 0)]
_TRI_EDGES = [(0, 1), (1, 2), (2, 0)]
_TET_EDGES = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]
_HEX_FACES = [[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]]


def _with_midpoints(corners, edges):
    c = np.asarray(corners, dtype=np.float64)
    mids = [(c[a] + c[b]) / 2 for a, b in edges]
    return np.concatenate([c, np.asarray(mids)], axis=0)


_TRI3 = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
_TET4 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])

_REFERENCE_NODES = {
    "line2": np.array([[-1.0], [1.0]]),
    "line3": np.array([[-1.0], [1.0], [0.0]]),
    "tri3": _TRI3,
    "tri6": _with_midpoints(_TRI3, _TRI_EDGES),
    "tet4": _TET4,
    "tet10": _with_midpoints(_TET4, _TET_EDGES),
    "quad4": np.array(_QUAD4, dtype=np.float64),
    "quad8": _with_midpoints(_QUAD4, _QUAD_EDGES),
    "quad9": np.concatenate([_with_midpoints(_QUAD4, _QUAD_EDGES), [[0.0, 0.0]]]),
    "hex8": np.array(_HEX8, dtype=np.float64),
    "hex20": _with_midpoints(_HEX8, _HEX_EDGES),
    "hex27": np.concatenate(
        [_with_midpoints(_HEX8, _HEX_EDGES), _HEX_FACES, [[0.0, 0.0, 0.0]]]
    ).astype(np.float64),
}

# name: (dim, n_nodes, degree, meshio name, family)
_TABLE = {
    "tri3": (2, 3, 1, "triangle", "simplex"),
    "quad4": (2, 4, 1, "quad", "lagrange"),
    "tet4": (3, 4, 1, "tetra", "simplex"),
    "hex8": (3, 8, 1, "hexahedron", "lagrange"),
    "tri6": (2, 6, 2, "triangle6", "simplex"),
    "quad8": (2, 8, 2, "quad8", "serendipity"),
    "quad9": (2, 9, 2, "quad9", "lagrange"),
    "tet10": (3, 10, 2, "tetra10", "simplex"),
    "hex20": (3, 20, 2, "hexahedron20", "serendipity"),
    "hex27": (3, 27, 2, "hexahedron27", "lagrange"),
    # Facet elements (boundary loads on 2D meshes); no Mesh is made of them.
    "line2": (1, 2, 1, "line", "lagrange"),
    "line3": (1, 3, 2, "line3", "lagrange"),
}
_MESHIO_TO_NAME = {row[3]: name for name, row in _TABLE.items()}
_EDGES = {"tri6": _TRI_EDGES, "tet10": _TET_EDGES}


@dataclasses.dataclass(frozen=True)
class ElementType:
    """A reference finite element: node layout, shape functions and quadrature.

    **Fields:**

    - `name`: one of `"tri3"`, `"quad4"`, `"tet4"`, `"hex8"`, `"tri6"`, `"quad8"`,
      `"quad9"`, `"tet10"`, `"hex20"`, `"hex27"`, or the facet elements `"line2"`,
      `"line3"` (edges of 2D cells; meshes are never made of them).
    - `dim`: dimension of the reference cell (2 or 3; 1 for `line2`/`line3`).
    - `n_nodes`: number of nodes.
    - `degree`: polynomial degree (1 or 2).
    - `meshio_name`: the meshio cell type.
    - `default_order`: quadrature order `2 * degree`, i.e. full integration of the
      stiffness and mass of an affine element (2x2(x2) Gauss for `quad4`/`hex8`, 3x3(x3)
      for the quadratic quadrilaterals and hexahedra).
    """

    name: str
    dim: int
    n_nodes: int
    degree: int
    meshio_name: str
    default_order: int

    @property
    def is_simplex(self) -> bool:
        """Whether the reference cell is the unit triangle/tetrahedron."""
        return _TABLE[self.name][4] == "simplex"

    @property
    def reference_volume(self) -> float:
        """Volume of the reference cell (1/2, 1/6, 2, 4 or 8)."""
        if self.is_simplex:
            return 0.5 if self.dim == 2 else 1.0 / 6.0
        return float(2**self.dim)

    def reference_nodes(self) -> np.ndarray:
        """Node coordinates in the reference cell, shape `(n_nodes, dim)`, float64."""
        return _REFERENCE_NODES[self.name].copy()

    def shape_functions(self, xi) -> jax.Array:
        """Shape functions at one reference point.

        **Arguments:**

        - `xi`: reference coordinates, shape `(dim,)`.

        **Returns:**

        The `n_nodes` shape-function values, shape `(n_nodes,)`. Pure `jnp`: can be
        jitted, vmapped and differentiated.
        """
        xi = jnp.asarray(xi, dtype=jnp.float64)
        family = _TABLE[self.name][4]
        r = jnp.asarray(_REFERENCE_NODES[self.name])
        if family == "simplex":
            lam = jnp.concatenate([jnp.reshape(1.0 - jnp.sum(xi), (1,)), xi])
            if self.degree == 1:
                return lam
            edges = np.asarray(_EDGES[self.name])
            corners = lam * (2.0 * lam - 1.0)
            mids = 4.0 * lam[edges[:, 0]] * lam[edges[:, 1]]
            return jnp.concatenate([corners, mids])
        if family == "lagrange":
            if self.degree == 1:
                return jnp.prod(0.5 * (1.0 + xi * r), axis=1)
            factors = jnp.where(r == 0, 1.0 - xi**2, 0.5 * xi * r * (1.0 + xi * r))
            return jnp.prod(factors, axis=1)
        # Serendipity (quad8, hex20).
        corner = np.all(_REFERENCE_NODES[self.name] != 0, axis=1)
        factors = jnp.where(r == 0, 1.0 - xi**2, 1.0 + xi * r)
        extra = jnp.where(corner, jnp.sum(xi * r, axis=1) - (self.dim - 1), 1.0)
        scale = jnp.asarray(np.where(corner, 0.5**self.dim, 0.5 ** (self.dim - 1)))
        return scale * extra * jnp.prod(factors, axis=1)

    def shape_gradients(self, xi) -> jax.Array:
        """Reference gradients of the shape functions at one point.

        **Arguments:**

        - `xi`: reference coordinates, shape `(dim,)`.

        **Returns:**

        `dN/dxi`, shape `(n_nodes, dim)`.
        """
        return jax.jacfwd(self.shape_functions)(jnp.asarray(xi, dtype=jnp.float64))

    def quadrature(self, order: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Quadrature rule on the reference cell.

        **Arguments:**

        - `order`: polynomial degree integrated exactly; `default_order` if `None`.

        **Returns:**

        `(points, weights)`, numpy float64 arrays of shapes `(nq, dim)` and `(nq,)`.
        """
        return _quadrature(self.name, self.default_order if order is None else order)


_ELEMENTS = {
    name: ElementType(name, dim, n, deg, mname, 2 * deg)
    for name, (dim, n, deg, mname, _) in _TABLE.items()
}


def element_type(name: str) -> ElementType:
    """Look up an element by its jaxvisco name (`"hex8"`) or meshio name (`"hexahedron"`).

    **Arguments:**

    - `name`: element name, or an `ElementType` (returned unchanged).

    **Returns:**

    The `ElementType`.
    """
    if isinstance(name, ElementType):
        return name
    if isinstance(name, str):
        key = _MESHIO_TO_NAME.get(name, name)
        if key in _ELEMENTS:
            return _ELEMENTS[key]
    raise ValueError(
        f"Unknown cell type {name!r}; accepted: {list(_ELEMENTS)} or their meshio "
        f"names {list(_MESHIO_TO_NAME)}."
    )
