"""Total Lagrangian finite elements: the semi-discrete operators (THEORY §2).

Everything here is written for all elements and quadrature points at once (gather,
`einsum`, sums over each node's element entries); nothing knows about time stepping.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._export import register_wrapper
from ._tensor import det3
from ._update import pad_to_3d


@register_wrapper  # cached programs' entries hold them as data (`_export`)
class StaticArray:
    """A numpy array usable as an equinox static field (hashable by content).

    Mesh connectivity is structure, not data: it fixes gather/scatter patterns and the
    sparsity of assembled tangents, and must be known when the program is traced.
    """

    def __init__(self, array):
        self.array = np.asarray(array)
        self.array.setflags(write=False)
        self._hash = hash((self.array.shape, self.array.dtype.str, self.array.tobytes()))

    def __hash__(self):
        return self._hash

    def __reduce__(self):  # by content: Python's hash of bytes differs between processes
        return (StaticArray, (self.array,))

    def __eq__(self, other):
        return (
            isinstance(other, StaticArray)
            and self._hash == other._hash
            and self.array.shape == other.array.shape
            and np.array_equal(self.array, other.array)
        )


def embed_3d(F_d):
    """Embed a (..., d, d) gradient into (..., 3, 3); plane strain has F33 = 1."""
    d = F_d.shape[-1]
    if d == 3:
        return F_d
    return pad_to_3d(F_d) + jnp.asarray(np.diag([0.0, 0.0, 1.0]), dtype=F_d.dtype)


class Discretization(eqx.Module):
    """Quadrature data of a mesh, ready for the vectorized kernels.

    **Fields:** `N` (nq, n_en) shape values, `dN` (n_cells, nq, n_en, dim) reference
    gradients $\\nabla_X N$, `JxW` (n_cells, nq) quadrature weights times $\\det J$
    (thickness 1 in plane strain), `mass_el` (n_cells, n_en, n_en) element mass matrices
    for unit density (consistent, or lumped by HRZ diagonal scaling: the diagonal of the
    consistent matrix scaled to the element's mass, positive for every element type);
    `X` (n_nodes, dim) the reference positions; `cells` (static) the connectivity.
    """

    N: jax.Array
    dN: jax.Array
    JxW: jax.Array
    mass_el: jax.Array
    X: jax.Array
    cells: StaticArray = eqx.field(static=True)
    n_nodes: int = eqx.field(static=True)
    dim: int = eqx.field(static=True)

    def __init__(self, mesh, order=None, mass="consistent"):
        if mass not in ("consistent", "lumped"):
            raise ValueError(f"mass must be 'consistent' or 'lumped', got {mass!r}.")
        qd = mesh.quadrature_data(order)
        self.N = jnp.asarray(qd.N)
        self.dN = jnp.asarray(qd.dN_dX)
        self.JxW = jnp.asarray(qd.JxW)
        self.mass_el = _element_mass(self.JxW, self.N, mass == "lumped")
        self.X = jnp.asarray(mesh.points, dtype=float)
        self.cells = StaticArray(np.asarray(mesh.cells))
        self.n_nodes = int(mesh.n_nodes)
        self.dim = int(mesh.dim)

    @property
    def n_cells(self):
        return self.cells.array.shape[0]

    @property
    def n_qp(self):
        return self.N.shape[0]

    # -- gather / scatter ----------------------------------------------------------
    def gather(self, u):
        """Nodal field (..., n_nodes, c) -> element arrays (..., n_cells, n_en, c)."""
        return u[..., self.cells.array, :]

    def scatter(self, u_el):
        """Element arrays (..., n_cells, n_en, c) -> summed nodal field (..., n_nodes, c),
        by gathers: every node sums its element entries (`_incidence`).

        Why not a scatter-add: XLA:CPU expands every scatter into a loop of its own
        (`_update` replaced the time loop's other scatters). By gathers the paper scene's
        eG(1) loop compiled 158 separate kernels instead of 185. Its cold first call, four
        alternating pairs of fresh processes (AMD EPYC, load ~1): XLA 5.29 / 5.02 / 5.46 /
        5.11 s -> 5.01 / 5.06 / 5.12 / 5.13 s, wall 7.09 / 6.60 / 7.17 / 6.74 s -> 6.66 /
        6.72 / 6.77 / 6.87 s (a day before: XLA medians 5.13 -> 4.88 s). Steps no slower
        (`benchmarks/revision_cost.py`, three alternating rounds, medians): 2D r4 lumped
        eG(1) 5.76 -> 5.72 ms, 3D r1 eG(1) 4.81 -> 4.69 ms (alone, an assembly by gathers
        was measured at 21 against 9.5 us at 2D r4)."""
        lead, c = u_el.shape[:-3], u_el.shape[-1]
        flat = u_el.reshape(lead + (-1, c))
        flat = jnp.concatenate([flat, jnp.zeros(lead + (1, c), dtype=flat.dtype)], axis=-2)
        return jnp.sum(flat[..., _incidence(self.cells, self.n_nodes), :], axis=-2)

    # -- kinematics and forces -----------------------------------------------------
    def gradient(self, u):
        """Nodal vectors (..., n_nodes, d) -> their material gradient at every quadrature
        point, zero-padded to (..., n_cells, nq, 3, 3) (no F33 = 1: for increments)."""
        return pad_to_3d(self._gradient_d(u))

    def _gradient_d(self, u):
        # (broadcast products and sums: as an einsum XLA:CPU ran a batched dot per cell)
        return jnp.sum(self.gather(u)[..., :, None, :, :, None] * self.dN[:, :, :, None, :], axis=-3)

    def deformation_gradient(self, x):
        """Positions (..., n_nodes, d) -> F at every quadrature point (..., n_cells, nq, 3, 3),
        as $I + \\nabla_X(x - X)$: the gradient of the nodal positions themselves carries
        rounding of ~1e-16 |x| / (element size) (F - I ~ 2e-15 on the L-shape at rest), that of
        the displacement only of the displacement (F = I exactly for a body at rest, whose
        residual was otherwise that rounding's stress: 6e-8 of the scale of a step at rest,
        near Newton's acceptance)."""
        d = x.shape[-1]
        return embed_3d(jnp.eye(d, dtype=x.dtype) + self._gradient_d(x - self.X))

    def force(self, P):
        """Nodal forces $f_A = \\sum_{qp} w\\, P \\nabla_X N_A$ of first Piola–Kirchhoff
        stresses P (..., n_cells, nq, 3, 3)."""
        d = self.dim
        wP = self.JxW[..., None, None] * P[..., :d, :d]  # (..., e, q, i, J)
        f_el = jnp.sum(wP[..., :, :, None, :, :] * self.dN[:, :, :, None, :], axis=(-4, -1))
        return self.scatter(f_el)

    def integrate(self, f_qp):
        """$\\int f\\,dV$ of a quadrature-point field (..., n_cells, nq)."""
        return jnp.sum(f_qp * self.JxW, axis=(-2, -1))

    # -- mass ----------------------------------------------------------------------
    def mass_matvec(self, v, density):
        """Consistent mass times a nodal field: $(Mv)_A = \\int\\rho N_A N_B v_B$;
        `density` one number or one per cell (n_cells,)."""
        if jnp.ndim(density) == 0:
            return density * self.scatter(_cell_matvec(self.mass_el, self.gather(v)))
        return self.scatter(_cell_matvec(density[:, None, None] * self.mass_el, self.gather(v)))

    def mass_diagonal(self, density):
        """Diagonal of the consistent mass matrix (n_nodes,)."""
        diag_el = jnp.diagonal(self.mass_el, axis1=-2, axis2=-1)[..., None]
        if jnp.ndim(density) == 0:
            return density * self.scatter(diag_el)[:, 0]
        return self.scatter(density[:, None, None] * diag_el)[:, 0]

    def cell_mass(self, density):
        """Element mass matrices (n_cells, n_en, n_en) for `density` (one or per cell)."""
        return (density if jnp.ndim(density) == 0 else density[:, None, None]) * self.mass_el

    def volume(self):
        return jnp.sum(self.JxW)

    def min_jacobian(self, x):
        """Smallest det F over all quadrature points (inversion check)."""
        return jnp.min(det3(self.deformation_gradient(x)))


def _cell_matvec(M, u):
    """(e, a, b) times (..., e, b, i) -> (..., e, a, i), as broadcast products and sums."""
    return jnp.sum(M[..., :, :, None] * u[..., :, None, :, :], axis=-2)


@functools.lru_cache(maxsize=16)
def _incidence(cells, n_nodes):
    """(n_nodes, valence) positions in the flattened element arrays (n_cells * n_en) of
    each node's entries, in element order; padded with n_cells * n_en (a zero row).

    One host array per mesh (cached by the connectivity's content, read-only): every
    assembly site of a traced program reads the same array, which JAX embeds as it
    embeds the connectivity (the 3D hex8 r1 time loop: three copies of each, 8 184
    integer constant elements; a new array per site had made 27 896)."""
    flat = cells.array.reshape(-1)
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n_nodes)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(flat.size) - np.repeat(starts, counts)
    inc = np.full((n_nodes, max(int(counts.max()), 1)), flat.size)
    inc[flat[order], rank] = order
    inc = inc.astype(np.int32)
    inc.setflags(write=False)
    return inc


@functools.partial(jax.jit, static_argnames="lumped")
def _element_mass(JxW, N, lumped):
    """Element mass matrices (n_cells, n_en, n_en), consistent or row-sum lumped (scaled so
    that each element keeps its mass), as one program: its operations called one by one
    compiled one small program each (six for a lumped mesh)."""
    mass_el = jnp.einsum("eq,qa,qb->eab", JxW, N, N)
    if lumped:
        diag = jnp.diagonal(mass_el, axis1=-2, axis2=-1)
        scale = jnp.sum(JxW, axis=1) / jnp.sum(diag, axis=1)
        mass_el = jax.vmap(jnp.diag)(diag * scale[:, None])
    return mass_el
