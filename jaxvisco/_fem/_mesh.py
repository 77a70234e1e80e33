"""Unstructured meshes of one element type: construction, I/O, checks, quadrature data."""

import functools
import os
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import device_array, require_x64
from ._elements import ElementType, element_type

# Topological dimension of meshio cell types we may meet in files (to pick the blocks of
# highest dimension, including ones we do not support).
_MESHIO_DIM = {
    "vertex": 0, "line": 1, "line3": 1, "line4": 1,
    "triangle": 2, "triangle6": 2, "triangle7": 2, "quad": 2, "quad8": 2, "quad9": 2,
    "polygon": 2,
    "tetra": 3, "tetra10": 3, "hexahedron": 3, "hexahedron20": 3, "hexahedron27": 3,
    "wedge": 3, "wedge15": 3, "wedge18": 3, "pyramid": 3, "pyramid13": 3,
    "pyramid14": 3,
}  # fmt: skip


def _det(J):
    """Closed-form determinant of a batch of 2x2 or 3x3 matrices `(..., d, d)`."""
    if J.shape[-1] == 2:
        return J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    return (
        J[..., 0, 0] * (J[..., 1, 1] * J[..., 2, 2] - J[..., 1, 2] * J[..., 2, 1])
        - J[..., 0, 1] * (J[..., 1, 0] * J[..., 2, 2] - J[..., 1, 2] * J[..., 2, 0])
        + J[..., 0, 2] * (J[..., 1, 0] * J[..., 2, 1] - J[..., 1, 1] * J[..., 2, 0])
    )


def _inv(J, det):
    """Closed-form inverse of a batch of 2x2 or 3x3 matrices, given their determinant."""
    xp = jnp if isinstance(J, jax.Array) else np
    if J.shape[-1] == 2:
        adj = xp.stack(
            [
                xp.stack([J[..., 1, 1], -J[..., 0, 1]], -1),
                xp.stack([-J[..., 1, 0], J[..., 0, 0]], -1),
            ],
            -2,
        )
    else:
        cols = [J[..., :, k] for k in range(3)]
        # Rows of the inverse are cross products of the columns of J.
        rows = [xp.cross(cols[1], cols[2]), xp.cross(cols[2], cols[0]),
                xp.cross(cols[0], cols[1])]  # fmt: skip
        adj = xp.stack(rows, -2)
    return adj / det[..., None, None]


@functools.partial(jax.jit, static_argnums=0)
def _jacobians(name: str, points, cells, xi):
    """Jacobians `dX/dxi` `(n_cells, nq, dim, dim)` and reference gradients `(nq, n_en, dim)`."""
    dN = jax.vmap(element_type(name).shape_gradients)(xi)
    J = jnp.einsum("cai,qaj->cqij", points[cells], dN)
    return J, dN


@functools.partial(jax.jit, static_argnums=0)
def _quadrature_data(name: str, points, cells, xi, w):
    J, dN = _jacobians(name, points, cells, xi)
    det = _det(J)
    dN_dX = jnp.einsum("qaj,cqjk->cqak", dN, _inv(J, det))
    N = jax.vmap(element_type(name).shape_functions)(xi)
    return N, dN_dX, det * w


@functools.partial(jax.jit, static_argnums=0)
def _volume(name: str, points, cells, xi, w):
    J, _ = _jacobians(name, points, cells, xi)
    return jnp.sum(jnp.abs(_det(J)) * w)


class QuadratureData(eqx.Module):
    """Shape functions and their physical gradients at the quadrature points.

    **Fields:**

    - `N`: shape-function values, `(nq, n_en)`.
    - `dN_dX`: gradients with respect to the reference configuration,
      `(n_cells, nq, n_en, dim)`.
    - `JxW`: quadrature weight times `det J` (thickness 1 in 2D), `(n_cells, nq)`.
    """

    N: jax.Array
    dN_dX: jax.Array
    JxW: jax.Array


class Mesh(eqx.Module):
    """A mesh of a single element type.

    **Fields:**

    - `points`: node coordinates, float64 `(n_nodes, dim)`, `dim` 2 or 3.
    - `cells`: connectivity, int32 `(n_cells, n_nodes_per_cell)`, meshio/VTK node order.
    - `cell_type`: element name (static), e.g. `"hex8"`; meshio names are accepted and
      normalised.
    """

    points: jax.Array
    cells: jax.Array
    cell_type: str = eqx.field(static=True)

    def __init__(self, points, cells, cell_type: str):
        """**Arguments:**

        - `points`: `(n_nodes, dim)` coordinates, `dim` 2 or 3.
        - `cells`: `(n_cells, n_nodes_per_cell)` node indices.
        - `cell_type`: element name or meshio name.

        Raises `ValueError` for wrong shapes, out-of-range indices, empty meshes and
        non-finite coordinates; `RuntimeError` if JAX is not in float64.
        """
        require_x64()
        element = element_type(cell_type)
        p_shape, c_shape = np.shape(points), np.shape(cells)
        if len(p_shape) != 2 or p_shape[1] not in (2, 3):
            raise ValueError(
                f"points must be a 2D array with 2 or 3 columns, got shape {p_shape}."
            )
        if len(c_shape) != 2 or c_shape[1] != element.n_nodes:
            raise ValueError(
                f"cells must be a 2D array with {element.n_nodes} columns for cell type "
                f"{element.name!r}, got shape {c_shape}."
            )
        if p_shape[1] != element.dim:
            raise ValueError(
                f"cell type {element.name!r} is {element.dim}D but points have "
                f"{p_shape[1]} coordinates."
            )
        if p_shape[0] == 0 or c_shape[0] == 0:
            raise ValueError(
                f"empty mesh: {p_shape[0]} points and {c_shape[0]} cells; need at least "
                "one of each."
            )
        if not isinstance(points, jax.core.Tracer):
            p = np.asarray(points, dtype=np.float64)
            bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1))
            if bad.size:
                raise ValueError(f"node {bad[0]} has non-finite coordinates {p[bad[0]]}.")
        if not isinstance(cells, jax.core.Tracer):
            c = np.asarray(cells)
            if not np.issubdtype(c.dtype, np.integer):
                if not np.all(c == np.round(c)):
                    raise ValueError(f"cells must hold integer indices, got {c.dtype}.")
            c = c.astype(np.int64)
            out = np.flatnonzero(np.any((c < 0) | (c >= p_shape[0]), axis=1))
            if out.size:
                raise ValueError(
                    f"element {out[0]} has node indices {c[out[0]].tolist()} outside "
                    f"[0, {p_shape[0] - 1}]."
                )
        self.points = device_array(points, jnp.float64)
        self.cells = device_array(cells, jnp.int32)
        self.cell_type = element.name

    @property
    def element(self) -> ElementType:
        """The `ElementType` of the cells."""
        return element_type(self.cell_type)

    @property
    def dim(self) -> int:
        """Spatial dimension, 2 or 3."""
        return self.points.shape[1]

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return self.points.shape[0]

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return self.cells.shape[0]

    # ------------------------------------------------------------------ I/O

    @classmethod
    def read(cls, path, cell_type: str | None = None, prune: bool = True) -> "Mesh":
        """Read a mesh file with meshio (any format it reads: .inp, .msh, .vtu, .xdmf...).

        The cell blocks of highest topological dimension are kept (lower-dimensional
        blocks such as Gmsh boundary lines are dropped) and blocks of the same type are
        merged. A 2D mesh whose z-coordinates are all zero is returned with 2 columns.
        Abaqus `*Instance` transformations are ignored by meshio: the coordinates are
        those of the part.

        **Arguments:**

        - `path`: file path.
        - `cell_type`: keep only blocks of this type (jaxvisco or meshio name); by default
          the single type of highest dimension.
        - `prune`: remove nodes no cell uses and renumber the cells (default `True`).

        **Returns:**

        A `Mesh`. Raises `FileNotFoundError` for a missing file, `ValueError` for an
        unreadable one, mixed cell types, or unsupported cell types.
        """
        import meshio

        path = os.fspath(path)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"mesh file {path!r} does not exist.")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m = meshio.read(path)
        except (Exception, SystemExit) as e:
            # meshio raises many exception types, and calls sys.exit(1) when no reader
            # accepts the file; normalise all of them.
            reason = "no meshio reader accepts it" if isinstance(e, SystemExit) else e
            raise ValueError(f"could not read mesh file {path!r}: {reason}") from e
        blocks = [b for b in m.cells if len(b.data)]
        if cell_type is not None:
            want = element_type(cell_type).meshio_name
            blocks = [b for b in blocks if b.type == want]
            if not blocks:
                found = sorted({b.type for b in m.cells})
                raise ValueError(f"no {want!r} cells in {path!r}; found {found}.")
        if not blocks:
            raise ValueError(f"mesh file {path!r} contains no cells.")
        top = max(_MESHIO_DIM.get(b.type, -1) for b in blocks)
        types = sorted({b.type for b in blocks if _MESHIO_DIM.get(b.type, -1) == top})
        if len(types) > 1:
            raise ValueError(
                f"mixed cell types {types} in {path!r} are not supported; pass "
                "cell_type= to pick one."
            )
        ctype = types[0]
        if ctype not in [element_type(n).meshio_name for n in _SUPPORTED]:
            raise ValueError(
                f"cell type {ctype!r} in {path!r} is not supported; accepted meshio "
                f"types: {[element_type(n).meshio_name for n in _SUPPORTED]}."
            )
        element = element_type(ctype)
        cells = np.concatenate([b.data for b in blocks if b.type == ctype], axis=0)
        points = np.asarray(m.points, dtype=np.float64)
        if element.dim == 2 and points.shape[1] == 3:
            scale = max(np.abs(points).max(), 1.0)
            if np.abs(points[:, 2]).max() > 1e-12 * scale:
                raise ValueError(
                    f"{path!r} holds 2D cells ({ctype!r}) with non-zero z coordinates "
                    "(a surface in 3D); only planar meshes in the xy-plane are supported."
                )
            points = points[:, :2]
        if prune:
            used, cells = np.unique(cells, return_inverse=True)
            cells = cells.reshape(-1, element.n_nodes)
            points = points[used]
        return cls(points=points, cells=cells, cell_type=element.name)

    def write(self, path, file_format: str | None = None, **kwargs) -> None:
        """Write the mesh with meshio; the format follows the extension unless given.

        2D meshes are written with a zero z-coordinate (which `Mesh.read` drops).

        **Arguments:**

        - `path`: output file.
        - `file_format`: meshio format name, e.g. `"gmsh22"`; inferred if `None`.
        - `**kwargs`: passed to meshio's writer (e.g. `binary=False`).
        """
        import meshio

        points = np.asarray(self.points)
        if self.dim == 2:
            points = np.column_stack([points, np.zeros(len(points))])
        cells = np.asarray(self.cells)
        cell_data = None
        fmt = file_format or os.fspath(path)
        if str(fmt).startswith("gmsh") or str(fmt).endswith(".msh"):
            # Gmsh wants physical/geometrical tags; tag everything 1.
            tags = [np.ones(len(cells), dtype=np.int32)]
            cell_data = {"gmsh:physical": tags, "gmsh:geometrical": tags}
        m = meshio.Mesh(points, [(self.element.meshio_name, cells)], cell_data=cell_data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m.write(os.fspath(path), file_format=file_format, **kwargs)

    # ----------------------------------------------------------- geometry

    def quadrature_data(self, order: int | None = None) -> QuadratureData:
        """Shape functions, physical gradients and weights at the quadrature points.

        **Arguments:**

        - `order`: quadrature order; the element's `default_order` if `None`.

        **Returns:**

        A `QuadratureData` with `N (nq, n_en)`, `dN_dX (n_cells, nq, n_en, dim)` and
        `JxW (n_cells, nq)`.
        """
        xi, w = self.element.quadrature(order)
        N, dN_dX, JxW = _quadrature_data(
            self.cell_type, self.points, self.cells, device_array(xi), device_array(w)
        )
        return QuadratureData(N=N, dN_dX=dN_dX, JxW=JxW)

    def volume(self) -> jax.Array:
        """Total volume (area in 2D): sum of `|det J| w` over all quadrature points."""
        xi, w = self.element.quadrature()
        return _volume(self.cell_type, self.points, self.cells, device_array(xi), device_array(w))

    def validate(self, tol: float = 1e-8) -> "Mesh":
        """Check the mesh; return it unchanged or raise `ValueError` naming the culprit.

        Checks, in order: repeated node indices within an element; inverted or degenerate
        elements (`det J <= tol * mean|det J|` at the quadrature points or at the element
        nodes); nodes used by no element.

        **Arguments:**

        - `tol`: relative tolerance on `det J`.

        **Returns:**

        `self`.
        """
        cells = np.asarray(self.cells)
        srt = np.sort(cells, axis=1)
        dup = np.flatnonzero(np.any(srt[:, 1:] == srt[:, :-1], axis=1))
        if dup.size:
            raise ValueError(
                f"element {dup[0]} repeats a node index: {cells[dup[0]].tolist()}."
            )
        xi_q, _ = self.element.quadrature()
        xi = np.concatenate([xi_q, self.element.reference_nodes()], axis=0)
        J, _ = _jacobians(self.cell_type, self.points, self.cells, jnp.asarray(xi))
        det = _det(np.asarray(J))
        typical = np.mean(np.abs(det))
        if not typical > 0:
            raise ValueError("all elements are degenerate (det J = 0 everywhere).")
        worst = det.min(axis=1)
        bad = np.flatnonzero(worst <= tol * typical)
        if bad.size:
            e = bad[0]
            kind = "inverted" if worst[e] < -tol * typical else "degenerate"
            raise ValueError(
                f"element {e} is {kind}: det J = {worst[e]:.6g} (typical "
                f"{typical:.6g}); nodes {cells[e].tolist()}."
            )
        used = np.zeros(self.n_nodes, dtype=bool)
        used[cells.ravel()] = True
        unused = np.flatnonzero(~used)
        if unused.size:
            raise ValueError(
                f"node {unused[0]} is used by no element ({unused.size} unused nodes); "
                "read with prune=True or remove it."
            )
        return self


_SUPPORTED = ("tri3", "quad4", "tet4", "hex8", "tri6", "quad8", "quad9", "tet10",
              "hex20", "hex27")  # fmt: skip
