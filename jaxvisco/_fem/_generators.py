"""Structured mesh generators: rectangles, boxes and Simo–Tarnow's L-shaped block.

Every generator works on a lattice of unit squares/cubes. Each lattice cell becomes one
quadrilateral/hexahedron, two triangles, or six tetrahedra (Kuhn/Freudenthal subdivision
along the main diagonal, which is conforming across neighbouring cells). Element nodes
are placed on a lattice of half the spacing and merged by their integer coordinates, so
shared corner, mid-edge and face nodes are never duplicated and no node is unused.
"""

import itertools
import warnings
from typing import Sequence

import numpy as np

from ._elements import element_type
from ._mesh import Mesh

_SIMPLEX_OF = {"tri3": "quad4", "tri6": "quad4", "tet4": "hex8", "tet10": "hex8"}


def _kuhn_simplices(dim: int) -> np.ndarray:
    """Vertices (in {0,1}^dim) of the positively oriented Kuhn simplices of a unit cell."""
    out = []
    for perm in itertools.permutations(range(dim)):
        v = [np.zeros(dim)]
        for axis in perm:
            nxt = v[-1].copy()
            nxt[axis] = 1.0
            v.append(nxt)
        v = np.array(v)
        if np.linalg.det(v[1:] - v[0]) < 0:  # mesh generation: runs once, not under jit
            v[[1, 2]] = v[[2, 1]]
        out.append(v)
    return np.array(out)  # (dim!, dim + 1, dim)


def _cell_offsets(name: str) -> np.ndarray:
    """Element node positions inside a unit lattice cell, in half-units.

    **Returns:**

    Integer array `(n_sub, n_nodes, dim)`: `n_sub` elements per lattice cell.
    """
    element = element_type(name)
    ref = element.reference_nodes()
    if not element.is_simplex:
        return np.rint(ref + 1.0).astype(np.int64)[None]
    verts = _kuhn_simplices(element.dim)  # (n_sub, dim+1, dim)
    # x = v0 + sum_j xi_j (v_j - v0), doubled.
    x = verts[:, :1, :] + np.einsum("nj,sjd->snd", ref, verts[:, 1:] - verts[:, :1])
    return np.rint(2.0 * x).astype(np.int64)


def _from_lattice(cells_lo, cell_type, spacing, origin) -> Mesh:
    """Mesh the unit lattice cells with lower corners `cells_lo` (int, `(n, dim)`)."""
    element = element_type(cell_type)
    cells_lo = np.asarray(cells_lo, dtype=np.int64)
    if cells_lo.shape[1] != element.dim:
        raise ValueError(
            f"cell type {element.name!r} is {element.dim}D but this generator makes "
            f"{cells_lo.shape[1]}D meshes."
        )
    offsets = _cell_offsets(element.name)  # (n_sub, n_en, dim)
    nodes = 2 * cells_lo[:, None, None, :] + offsets[None]
    nodes = nodes.reshape(-1, element.dim)
    keys, inverse = np.unique(nodes, axis=0, return_inverse=True)
    cells = inverse.reshape(-1, element.n_nodes)
    points = np.asarray(origin, dtype=np.float64) + 0.5 * keys * np.asarray(spacing)
    return Mesh(points=points, cells=cells, cell_type=element.name)


def _check_count(value, name):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}.")
    return int(value)


def _check_length(value, name):
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite length, got {value!r}.")
    return float(value)


def _grid(counts):
    axes = [np.arange(n) for n in counts]
    return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=-1)


def rectangle(nx: int, ny: int, lx: float = 1.0, ly: float = 1.0, cell_type: str = "quad4",
              origin: Sequence[float] = (0.0, 0.0)) -> Mesh:
    """Structured mesh of the rectangle `origin + [0, lx] x [0, ly]`.

    **Arguments:**

    - `nx`, `ny`: numbers of lattice cells per direction (>= 1).
    - `lx`, `ly`: side lengths (> 0).
    - `cell_type`: `"quad4"`, `"quad8"`, `"quad9"`, `"tri3"` or `"tri6"` (two triangles
      per lattice cell).
    - `origin`: lower-left corner.

    **Returns:**

    A `Mesh`.
    """
    counts = (_check_count(nx, "nx"), _check_count(ny, "ny"))
    spacing = (_check_length(lx, "lx") / counts[0], _check_length(ly, "ly") / counts[1])
    return _from_lattice(_grid(counts), cell_type, spacing, _origin(origin, 2))


def box(nx: int, ny: int, nz: int, lx: float = 1.0, ly: float = 1.0, lz: float = 1.0, cell_type: str = "hex8",
        origin: Sequence[float] = (0.0, 0.0, 0.0)) -> Mesh:
    """Structured mesh of the box `origin + [0, lx] x [0, ly] x [0, lz]`.

    **Arguments:**

    - `nx`, `ny`, `nz`: numbers of lattice cells per direction (>= 1).
    - `lx`, `ly`, `lz`: side lengths (> 0).
    - `cell_type`: `"hex8"`, `"hex20"`, `"hex27"`, `"tet4"` or `"tet10"` (six
      tetrahedra per lattice cell).
    - `origin`: lower corner.

    **Returns:**

    A `Mesh`.
    """
    counts = tuple(_check_count(n, k) for n, k in ((nx, "nx"), (ny, "ny"), (nz, "nz")))
    lengths = [_check_length(v, k) for v, k in ((lx, "lx"), (ly, "ly"), (lz, "lz"))]
    spacing = tuple(L / n for L, n in zip(lengths, counts))
    return _from_lattice(_grid(counts), cell_type, spacing, _origin(origin, 3))


def _origin(origin, dim):
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (dim,) or not np.all(np.isfinite(o)):
        raise ValueError(f"origin must be {dim} finite numbers, got {origin!r}.")
    return o


def lshape_mesh(dim: int = 2, refinement: int = 1, cell_type: str | None = None, *,
                element: str | None = None) -> Mesh:
    """Simo & Tarnow's L-shaped block.

    2D (plane strain): `[0, 6] x [0, 3]  U  [0, 3] x [0, 10]`, area 39; 3D: the same
    extruded over `z` in `[0, 3]`, volume 117. Squares/cubes of edge `1 / refinement`;
    at `refinement=1` the 2D `quad4` mesh has 39 cells and 56 nodes, the 3D `hex8` mesh
    117 cells and 224 nodes (the nodes of moofeKIT's `LShapeH1Medium.inp`).

    **Arguments:**

    - `dim`: 2 or 3.
    - `refinement`: lattice cells per unit length (>= 1).
    - `cell_type`: `"quad4"` (2D default), `"tri3"`, `"tri6"`, `"quad8"`, `"quad9"`;
      `"hex8"` (3D default), `"tet4"`, `"tet10"`, `"hex20"`, `"hex27"`.
    - `element`: deprecated name of `cell_type`.

    **Returns:**

    A `Mesh`.
    """
    if dim not in (2, 3) or isinstance(dim, bool):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}.")
    r = _check_count(refinement, "refinement")
    if element is not None:
        if cell_type is not None:
            raise TypeError("lshape_mesh(): give cell_type or the deprecated element, not both.")
        warnings.warn("lshape_mesh(): element= is deprecated, use cell_type=.", DeprecationWarning, stacklevel=2)
        cell_type = element
    element = cell_type if cell_type is not None else "quad4" if dim == 2 else "hex8"
    lo = _grid((6 * r, 10 * r))
    keep = (lo[:, 0] < 3 * r) | (lo[:, 1] < 3 * r)
    lo = lo[keep]
    if dim == 3:
        z = np.arange(3 * r)
        lo = np.concatenate(
            [np.repeat(lo, len(z), axis=0), np.tile(z, len(lo))[:, None]], axis=1
        )
    return _from_lattice(lo, element, (1.0 / r,) * dim, np.zeros(dim))
