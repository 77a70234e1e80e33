"""Boundary facets of a mesh and consistent nodal forces of dead surface loads.

A facet is an edge of a 2D cell (`line2`, `line3`) or a face of a 3D cell (`tri3`,
`tri6`, `quad4`, `quad8`, `quad9`), its nodes in the node order of that facet element
(meshio order: corners, then mid-edges, then the centre). Boundary facets are oriented
so that their normal points out of the body: in 2D, walking from node 0 to node 1 the
outward normal is `(dy, -dx)`; in 3D the right-hand rule over the corners gives it.
This holds for positively oriented cells (`det J > 0`, as `Mesh.validate` demands).

Topology (which facets, which nodes) is host-side numpy. Dead loads are assembled once,
so the integrals run in numpy on concrete input (no compilation) and in JAX when the
traction, pressure or coordinates are traced (e.g. differentiated).
"""

import functools
from typing import TYPE_CHECKING, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jax.typing import ArrayLike

from .._validation import _concrete
from ._elements import element_type

if TYPE_CHECKING:
    from ._mesh import Mesh

_FACET_TYPE = {
    "tri3": "line2", "quad4": "line2", "tri6": "line3", "quad8": "line3",
    "quad9": "line3", "tet4": "tri3", "tet10": "tri6", "hex8": "quad4",
    "hex20": "quad8", "hex27": "quad9",
}  # fmt: skip

# Corners of the local facets of a positively oriented cell, listed so that the facet
# normal points outward, in Abaqus face order (S1, S2, ...): Abaqus face k is local
# facet k - 1 (see `abaqus_face`).
_CORNERS = {
    "tri": [(0, 1), (1, 2), (2, 0)],
    "quad": [(0, 1), (1, 2), (2, 3), (3, 0)],
    "tet": [(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)],
    "hex": [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6),
            (3, 0, 4, 7)],
}  # fmt: skip
_SHAPE = {"tri3": "tri", "tri6": "tri", "quad4": "quad", "quad8": "quad",
          "quad9": "quad", "tet4": "tet", "tet10": "tet", "hex8": "hex",
          "hex20": "hex", "hex27": "hex"}  # fmt: skip
_N_CORNERS = {"line2": 2, "line3": 2, "tri3": 3, "tri6": 3, "quad4": 4, "quad8": 4,
              "quad9": 4}  # fmt: skip
# Quadrature orders: exact for N_a times the (polynomial) area vector of any facet of the
# type, hence for pressure always and for traction on straight/flat facets.
_ORDER = {"line2": 2, "line3": 5, "tri3": 2, "tri6": 5, "quad4": 3, "quad8": 5,
          "quad9": 5}  # fmt: skip


def facet_type(cell_type: str) -> str:
    """The facet element of a cell type.

    **Arguments:**

    - `cell_type`: element name or meshio name, e.g. `"hex20"`.

    **Returns:**

    `"line2"` (tri3, quad4), `"line3"` (tri6, quad8, quad9), `"tri3"` (tet4), `"tri6"`
    (tet10), `"quad4"` (hex8), `"quad8"` (hex20) or `"quad9"` (hex27).
    """
    name = element_type(cell_type).name
    if name not in _FACET_TYPE:
        raise ValueError(
            f"cell type {name!r} has no facet type; accepted: {sorted(_FACET_TYPE)}."
        )
    return _FACET_TYPE[name]


@functools.lru_cache(maxsize=None)
def local_facets(cell_type: str) -> np.ndarray:
    """Local node indices of the facets of a cell, `(n_local_facets, n_facet_nodes)`.

    Outward oriented for a positively oriented cell, in Abaqus face order: row `k` is
    face `S{k+1}` (tri: edges 1-2, 2-3, 3-1; quad: 1-2, 2-3, 3-4, 4-1; tet: 1-2-3,
    1-4-2, 2-4-3, 3-4-1; hex: 1-2-3-4, 5-8-7-6, 1-5-6-2, 2-6-7-3, 3-7-8-4, 4-8-5-1).
    Mid-edge and centre nodes are found from the reference coordinates.
    """
    element = element_type(cell_type)
    ftype = facet_type(element.name)
    ref = element.reference_nodes()
    n_facet = element_type(ftype).n_nodes

    def node_at(x):
        return int(np.flatnonzero(np.all(np.isclose(ref, x), axis=1))[0])

    rows = []
    for corners in _CORNERS[_SHAPE[element.name]]:
        row = list(corners)
        if n_facet > len(corners):
            pairs = [(0, 1)] if len(corners) == 2 else [
                (i, (i + 1) % len(corners)) for i in range(len(corners))
            ]
            row += [node_at(ref[[corners[i], corners[j]]].mean(0)) for i, j in pairs]
        if n_facet > len(row):  # quad9: the face centre
            row.append(node_at(ref[list(corners)].mean(0)))
        rows.append(row)
    out = np.asarray(rows, dtype=np.int64)
    out.flags.writeable = False
    return out


def _all_facets(mesh):
    """Every local facet of every cell `(n_cells * n_local, n_fn)` and its sorted corners."""
    table = local_facets(mesh.cell_type)
    facets = np.asarray(mesh.cells, dtype=np.int64)[:, table].reshape(-1, table.shape[1])
    keys = np.sort(facets[:, : _N_CORNERS[facet_type(mesh.cell_type)]], axis=1)
    return facets, keys


def _boundary(mesh):
    """`(facets, cell, local)`: boundary facets, their cell and local facet index."""
    facets, keys = _all_facets(mesh)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    on = np.flatnonzero(counts[inverse.ravel()] == 1)
    n_local = local_facets(mesh.cell_type).shape[0]
    return facets[on], on // n_local, on % n_local


def boundary_facets(mesh: "Mesh") -> np.ndarray:
    """The facets that belong to exactly one cell, oriented outward.

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.

    **Returns:**

    int64 array `(n_facets, n_facet_nodes)` in the node order of `facet_type(mesh.
    cell_type)`, ordered by cell, then local facet.
    """
    return _boundary(mesh)[0]


def match_boundary(mesh, facets) -> tuple[np.ndarray, np.ndarray]:
    """Find given facets (any orientation) among the boundary facets by their corners.

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.
    - `facets`: `(n, k)` node indices whose first columns are the facet's corners (any
      order); `k` >= the number of corners of the facet type.

    **Returns:**

    `(oriented, found)`: the outward boundary facets matched (unique, sorted by boundary
    facet index) and a bool `(n,)` mask of the rows that are boundary facets.
    """
    boundary = boundary_facets(mesh)
    nc = _N_CORNERS[facet_type(mesh.cell_type)]
    facets = np.asarray(facets, dtype=np.int64).reshape(len(facets), -1)
    if facets.shape[1] < nc:
        raise ValueError(
            f"facets need at least {nc} corner nodes for cell type {mesh.cell_type!r}, "
            f"got {facets.shape[1]} columns."
        )
    keys = np.concatenate([np.sort(boundary[:, :nc], 1), np.sort(facets[:, :nc], 1)])
    _, ids = np.unique(keys, axis=0, return_inverse=True)
    ids = ids.ravel()
    owner = np.full(ids.max() + 1 if ids.size else 0, -1, dtype=np.int64)
    owner[ids[: len(boundary)]] = np.arange(len(boundary))
    hit = owner[ids[len(boundary) :]]
    found = hit >= 0
    return boundary[np.unique(hit[found])], found


def nodes_where(mesh: "Mesh", predicate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Sorted indices of the nodes whose coordinates satisfy `predicate`.

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.
    - `predicate`: function of the numpy coordinates `(n_nodes, dim)` returning a bool
      array `(n_nodes,)`, e.g. `lambda X: np.isclose(X[:, 0], 0.0)`.

    **Returns:**

    int64 array of node indices. Raises `ValueError` if the predicate returns anything
    but a bool array of shape `(n_nodes,)`, or selects no node.
    """
    points = np.array(mesh.points)
    mask = np.asarray(predicate(points.copy()))
    if mask.shape != (len(points),) or mask.dtype != np.bool_:
        raise ValueError(
            f"predicate must return a bool array of shape ({len(points)},) (one value "
            f"per node), got dtype {mask.dtype} and shape {mask.shape}."
        )
    if not mask.any():
        lo, hi = points.min(0).tolist(), points.max(0).tolist()
        raise ValueError(
            f"predicate selects no node of the mesh ({len(points)} nodes, bounding box "
            f"{lo} to {hi}); compare coordinates with a tolerance (np.isclose)."
        )
    return np.flatnonzero(mask)


def _check_index_array(name, value, n, width=None):
    a = np.asarray(value)
    shape_ok = (a.ndim == 2 and a.shape[1] == width) if width else a.ndim == 1
    if not shape_ok or a.dtype == np.bool_ or a.dtype.kind not in "iuf" or a.size == 0:
        want = f"(n, {width})" if width else "(n,)"
        raise ValueError(
            f"{name} must be a non-empty integer array of shape {want}, got dtype "
            f"{a.dtype} and shape {a.shape}."
        )
    if a.dtype.kind == "f" and not np.all(a == np.round(a)):
        raise ValueError(f"{name} must hold integer node indices, got {a.dtype} values.")
    a = a.astype(np.int64)
    bad = (a < 0) | (a >= n)
    if bad.any():
        raise ValueError(
            f"{name} holds node index {a[bad][0]} outside [0, {n - 1}] (the mesh has {n} "
            "nodes)."
        )
    return a


def facets_from_nodes(mesh: "Mesh", nodes: ArrayLike) -> np.ndarray:
    """The boundary facets whose nodes all lie in `nodes`.

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.
    - `nodes`: node indices, `(k,)` integers.

    **Returns:**

    Outward facets `(n_facets, n_facet_nodes)` as `boundary_facets` gives them. Raises
    `ValueError` if no boundary facet lies in `nodes`.
    """
    nodes = _check_index_array("nodes", nodes, mesh.n_nodes)
    facets = boundary_facets(mesh)
    inside = np.zeros(mesh.n_nodes, dtype=bool)
    inside[nodes] = True
    out = facets[np.all(inside[facets], axis=1)]
    if not len(out):
        raise ValueError(
            f"no boundary facet has all its nodes among the {np.unique(nodes).size} "
            "nodes given (a facet needs all of its nodes, mid-side ones too)."
        )
    return out


def _check_facets(mesh, facets):
    width = element_type(facet_type(mesh.cell_type)).n_nodes
    try:
        return _check_index_array("facets", facets, mesh.n_nodes, width)
    except ValueError as e:
        raise ValueError(
            f"{e} {mesh.cell_type} meshes have {facet_type(mesh.cell_type)} facets of "
            f"{width} nodes."
        ) from None


def _check_values(name, value, n_f, dim):
    """A constant `(*trailing,)` or per-facet `(n_f, *trailing)` value, broadcast."""
    trailing = (dim,) if dim else ()
    shape = np.shape(value)
    if shape not in (trailing, (n_f, *trailing)):
        raise ValueError(
            f"{name} must have shape {trailing} (constant) or {(n_f, *trailing)} (one per "
            f"facet), got shape {shape}."
        )
    v = _concrete(value)
    if v is not None and (v.dtype.kind not in "iuf" or v.dtype == np.bool_):
        raise ValueError(f"{name} must be real numbers, got dtype {v.dtype}.")
    if v is not None and not np.all(np.isfinite(v)):
        bad = float(v[~np.isfinite(v)].ravel()[0])
        raise ValueError(f"{name} must be finite, got {bad} in {name}.")
    if v is not None:
        return np.broadcast_to(v.astype(np.float64), (n_f, *trailing))
    return jnp.broadcast_to(jnp.asarray(value, dtype=jnp.float64), (n_f, *trailing))


@functools.lru_cache(maxsize=None)
def _basis(ftype):
    """Facet shape functions `(nq, n_fn)`, gradients `(nq, n_fn, fdim)`, weights."""
    element = element_type(ftype)
    xi, w = element.quadrature(_ORDER[ftype])
    with jax.ensure_compile_time_eval():  # concrete even if first called under a trace
        N, dN = jax.jit(lambda x: (jax.vmap(element.shape_functions)(x),
                                   jax.vmap(element.shape_gradients)(x)))(jnp.asarray(xi))
    return np.asarray(N), np.asarray(dN), w


def _xp(*values):
    """numpy for concrete values (no compilation: loads are built once), jnp if traced."""
    return np if all(_concrete(v) is not None for v in values) else jnp


def _geometry(mesh, facets):
    """Shape functions `(nq, n_fn)` and weighted area vectors `n dA` `(n_f, nq, dim)`."""
    xp = _xp(mesh.points)
    N, dN, w = _basis(facet_type(mesh.cell_type))
    X = xp.asarray(mesh.points)[facets]
    T = xp.einsum("fai,qak->fqik", X, dN)
    if X.shape[-1] == 2:
        n = xp.stack([T[..., 1, 0], -T[..., 0, 0]], axis=-1)
    else:
        n = xp.cross(T[..., :, 0], T[..., :, 1])
    return N, n * w[None, :, None]


def _assemble(mesh, facets, fe):
    """Scatter-add element forces `(n_f, n_fn, dim)` into nodal forces `(n_nodes, dim)`."""
    if _xp(fe) is np:
        out = np.zeros((mesh.n_nodes, mesh.dim))
        np.add.at(out, facets, fe)
        return jnp.asarray(out)
    return jnp.zeros((mesh.n_nodes, mesh.dim)).at[facets].add(fe)


def facet_area(mesh: "Mesh", facets: ArrayLike) -> float:
    """Total reference area of `facets` (length of edges in 2D).

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.
    - `facets`: `(n_facets, n_facet_nodes)` node indices.

    **Returns:**

    The area, a Python float.
    """
    _, n = _geometry(mesh, _check_facets(mesh, facets))
    return float(np.sum(np.linalg.norm(np.asarray(n), axis=-1)))


def traction_load(mesh: "Mesh", facets: ArrayLike, traction: ArrayLike) -> jax.Array:
    r"""Consistent nodal forces of a dead traction: $f_a = \int_{\Gamma_0} N_a t_0\,dA$.

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.
    - `facets`: `(n_facets, n_facet_nodes)` node indices, e.g. from `boundary_facets`.
    - `traction`: force per unit reference area (per unit edge length in 2D, thickness
      1), `(dim,)` constant or `(n_facets, dim)` one per facet.

    **Returns:**

    Nodal forces `(n_nodes, dim)`, float64.
    """
    facets = _check_facets(mesh, facets)
    t = _check_values("traction", traction, len(facets), mesh.dim)
    N, n = _geometry(mesh, facets)
    xp = _xp(mesh.points, t)
    fe = xp.einsum("qa,fq,fi->fai", N, xp.linalg.norm(n, axis=-1), t)
    return _assemble(mesh, facets, fe)


def pressure_load(mesh: "Mesh", facets: ArrayLike, pressure: ArrayLike) -> jax.Array:
    r"""Consistent nodal forces of a dead pressure: $f_a = -p \int_{\Gamma_0} N_a n_0\,dA$.

    `p > 0` pushes into the body when the facets are outward oriented (as
    `boundary_facets` returns them); the normal is the reference one and does not follow
    the deformation.

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.
    - `facets`: `(n_facets, n_facet_nodes)` node indices.
    - `pressure`: scalar or `(n_facets,)` one per facet.

    **Returns:**

    Nodal forces `(n_nodes, dim)`, float64.
    """
    facets = _check_facets(mesh, facets)
    p = _check_values("pressure", pressure, len(facets), 0)
    N, n = _geometry(mesh, facets)
    fe = -_xp(mesh.points, p).einsum("qa,fqi,f->fai", N, n, p)
    return _assemble(mesh, facets, fe)
