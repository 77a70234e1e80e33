"""The semi-discrete equations of a scene as one first-order ODE system (for peers).

    y = (x, p, Γ) flattened,   ẋ = M⁻¹p,   ṗ = −f_int(x, Γ) + f_ext(t),   Γ̇ = 2Γ(𝕍⁻¹ : M_e)

with Γ stored as 6 Voigt components per spatial quadrature point. The right-hand side is
the scene's own (`Scene.internal_force`, `Scene.external_force`, the material's
`gamma_rate`); it is what a general-purpose ODE solver (scipy `solve_ivp`, diffrax)
integrates, so that they can be compared with the time elements on the same problem.

The Jacobian is sparse: ∂ṗ/∂(x, Γ) and ∂Γ̇/∂(x, Γ) couple only the unknowns of one
element, and ∂Γ̇/∂Γ only those of one quadrature point. It is formed element by element
(`jax.jacfwd` of the element kernel, vmapped over elements) and assembled into a scipy
CSC matrix with a fixed pattern; no dense global Jacobian is ever formed. With a
consistent mass matrix ẋ = M⁻¹p couples every node to every other (M⁻¹ is dense), so
the sparse Jacobian needs a lumped (diagonal) mass: `Scene(..., mass="lumped")`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .._config import jit
from .._fem._space import embed_3d
from .._fem._tensor import mm, right_cauchy_green, sym_to_vec, vec_to_sym
from .._scene import Scene, State


class SemiDiscrete:
    """The semi-discrete ODE of a scene, $y' = f(t, y)$ with $y = (x, p, \\Gamma)$
    flattened, for other ODE solvers (scipy's `solve_ivp`, diffrax); build it with
    `semidiscrete(scene)`.

    **Attributes and methods:**

    - `y0`: the initial state, flattened (a numpy array of length `n`).
    - `rhs(t, y)`: the jitted right-hand side (JAX arrays in and out).
    - `vector_field(t, y, args)`: the same, not jitted, for diffrax's `ODETerm`; compile
      the solve with `jax.jit(solve, compiler_options=jaxvisco.compiler_options())`.
    - `fun(t, y)`, `jac(t, y)`: numpy right-hand side and scipy CSC Jacobian, for
      `scipy.integrate.solve_ivp(..., jac=ode.jac, jac_sparsity=ode.sparsity)` (the
      Jacobian needs `Scene(mass="lumped")`).
    - `jac_values(t, y)`: the jitted values of the Jacobian in the order of `rows`,
      `cols` (duplicates summed when assembled).
    - `sparsity`: the CSC pattern (ones).
    - `unpack(y)` (a `State`), `pack(state)`, `energy(y)` (H), `dissipation_rate(y)`.
    """

    def __init__(self, scene: Scene):
        if not isinstance(scene, Scene):
            raise TypeError(f"semidiscrete needs a Scene, got {type(scene).__name__}.")
        self.scene = scene
        disc = scene.disc
        self.n_nodes, self.dim = disc.n_nodes, disc.dim
        self.n_x = self.n_nodes * self.dim
        self.has_gamma = scene.has_internal_variable
        self.n_g = disc.n_cells * disc.n_qp * 6 if self.has_gamma else 0
        self.n = 2 * self.n_x + self.n_g
        mass_el = np.asarray(disc.mass_el)
        off = mass_el - np.einsum("eab,ab->eab", mass_el, np.eye(mass_el.shape[-1]))
        self.lumped = bool(np.all(off == 0.0))
        self.y0 = np.asarray(self.pack(scene.initial_state()))

        # The scene is closed over (its arrays become constants): the least call overhead
        # for host-driven solvers that call these thousands of times.
        self._rhs = jit(lambda t, y: _rhs(scene, t, y, self.lumped), plain=True)
        self._energy = jit(lambda y: _energy(scene, y), plain=True)
        self._dissipation = jit(lambda y: scene.dissipation_rate(*_xg(scene, y)), plain=True)
        self.rows = self.cols = None
        if self.lumped:
            self.rows, self.cols = _pattern(scene)
            key = self.cols.astype(np.int64) * self.n + self.rows
            uniq, self._inverse = np.unique(key, return_inverse=True)
            self._indices = (uniq % self.n).astype(np.int32)
            self._indptr = np.concatenate([[0], np.cumsum(np.bincount(uniq // self.n, minlength=self.n))]).astype(
                np.int32)
            self.nnz = len(uniq)
            self._jac = jit(lambda t, y: _jac_values(scene, t, y), plain=True)

    # -- state ---------------------------------------------------------------------
    def pack(self, state: State):
        parts = [jnp.ravel(state.x), jnp.ravel(state.p)]
        if self.has_gamma:
            parts.append(jnp.ravel(sym_to_vec(state.gamma)))
        return jnp.concatenate(parts)

    def unpack(self, y) -> State:
        x, p, g = _split(self.scene, jnp.asarray(y))
        return State(x, p, None if g is None else vec_to_sym(g))

    # -- right-hand side -----------------------------------------------------------
    def rhs(self, t, y):
        return self._rhs(jnp.asarray(t, dtype=float), jnp.asarray(y))

    def vector_field(self, t, y, args=None):
        return _rhs(self.scene, t, y, self.lumped)

    def fun(self, t, y):
        return np.asarray(self.rhs(t, y))

    def energy(self, y):
        return self._energy(jnp.asarray(y))

    def dissipation_rate(self, y):
        return self._dissipation(jnp.asarray(y))

    # -- Jacobian ------------------------------------------------------------------
    def _need_lumped(self):
        if not self.lumped:
            raise ValueError("the sparse Jacobian needs a lumped mass (Scene(..., mass='lumped')): with the "
                             "consistent mass, dx/dt = M^-1 p couples all nodes (M^-1 is dense).")

    def jac_values(self, t, y):
        self._need_lumped()
        return self._jac(jnp.asarray(t, dtype=float), jnp.asarray(y))

    def assemble(self, values):
        vals = np.bincount(self._inverse, weights=np.asarray(values, dtype=np.float64), minlength=self.nnz)
        return sp.csc_matrix((vals, self._indices, self._indptr), shape=(self.n, self.n))

    def jac(self, t, y):
        return self.assemble(self.jac_values(t, y))

    @property
    def sparsity(self):
        self._need_lumped()
        return sp.csc_matrix((np.ones(self.nnz), self._indices, self._indptr), shape=(self.n, self.n))


def semidiscrete(scene: Scene) -> SemiDiscrete:
    """The semi-discrete ODE $y' = f(t, y)$, $y = (x, p, \\Gamma)$, of a scene.

    **Arguments:**

    - `scene`: the `Scene`.

    **Returns:**

    A `SemiDiscrete`.

    **Raises:**

    `TypeError` for anything but a `Scene`.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jaxvisco as jv

    ode = jv.semidiscrete(jv.scenes.lshape())
    dy = ode.fun(0.0, ode.y0)   # numpy in, numpy out
    ```
    """
    return SemiDiscrete(scene)


# -- the functions -------------------------------------------------------------------
def _split(scene, y):
    disc = scene.disc
    nx = disc.n_nodes * disc.dim
    x = y[:nx].reshape(disc.n_nodes, disc.dim)
    p = y[nx:2 * nx].reshape(disc.n_nodes, disc.dim)
    g = y[2 * nx:].reshape(disc.n_cells, disc.n_qp, 6) if scene.has_internal_variable else None
    return x, p, g


def _xg(scene, y):
    x, _, g = _split(scene, y)
    return x, None if g is None else vec_to_sym(g)


def _inverse_mass_diagonal(scene):
    return 1.0 / scene.disc.mass_diagonal(scene.density)[:, None]


def _rhs(scene, t, y, lumped):
    x, p, g = _split(scene, y)
    gamma = None if g is None else vec_to_sym(g)
    # Lumped (diagonal) mass: a division; otherwise CG on the consistent mass.
    xdot = p * _inverse_mass_diagonal(scene) if lumped else scene.velocity(p)
    pdot = -scene.internal_force(x, gamma) + scene.external_force(t)
    if scene.fixed is not None:
        mask = jnp.asarray(scene.fixed.array)
        xdot = jnp.where(mask, scene.held_velocity(t), xdot)
        pdot = jnp.where(mask, 0.0, pdot)
    parts = [xdot.ravel(), pdot.ravel()]
    if g is not None:
        C = right_cauchy_green(scene.disc.deformation_gradient(x))
        rate = scene.map_points(lambda m, c, g: m.gamma_rate(c, g), C, gamma)
        parts.append(sym_to_vec(rate).ravel())
    return jnp.concatenate(parts)


def _energy(scene, y):
    x, p, g = _split(scene, y)
    gamma = None if g is None else vec_to_sym(g)
    return scene.kinetic_energy(p) + scene.free_energy(x, gamma)


def _element_kernel(material, dim, dN, JxW, x_el, g_el):
    """Internal force of one element (n_en, d) and Γ̇ at its quadrature points (nq, 6)."""
    F = embed_3d(jnp.einsum("ai,qaJ->qiJ", x_el, dN))
    C = right_cauchy_green(F)
    if g_el is None:
        S = jax.vmap(material.stress)(C)
        rate = None
    else:
        G = vec_to_sym(g_el)
        S = jax.vmap(material.stress)(C, G)
        rate = sym_to_vec(jax.vmap(material.gamma_rate)(C, G))
    P = mm(F, S)
    f = jnp.einsum("q,qiJ,qaJ->ai", JxW, P[:, :dim, :dim], dN)
    return f, rate


def _element_dofs(scene):
    disc = scene.disc
    c = disc.cells.array
    d = disc.dim
    xdofs = (c[:, :, None] * d + np.arange(d)[None, None]).reshape(c.shape[0], -1)  # (e, n_en d)
    gdofs = None
    if scene.has_internal_variable:
        nq = disc.n_qp
        gdofs = (np.arange(c.shape[0])[:, None, None] * nq + np.arange(nq)[None, :, None]) * 6 + np.arange(6)
    return xdofs, gdofs


def _pattern(scene):
    """COO rows and cols of the Jacobian, in the order `_jac_values` returns values."""
    disc = scene.disc
    nx = disc.n_nodes * disc.dim
    xdofs, gdofs = _element_dofs(scene)
    ne, m = xdofs.shape
    diag = np.arange(nx)
    rows = [diag]  # dxdot/dp
    cols = [nx + diag]
    # dpdot/dx: element blocks
    rows.append(np.broadcast_to((nx + xdofs)[:, :, None], (ne, m, m)).ravel())
    cols.append(np.broadcast_to(xdofs[:, None, :], (ne, m, m)).ravel())
    if gdofs is not None:
        nq = gdofs.shape[1]
        gflat = 2 * nx + gdofs.reshape(ne, nq * 6)
        # dpdot/dGamma
        rows.append(np.broadcast_to((nx + xdofs)[:, :, None], (ne, m, nq * 6)).ravel())
        cols.append(np.broadcast_to(gflat[:, None, :], (ne, m, nq * 6)).ravel())
        # dGammadot/dx
        rows.append(np.broadcast_to(gflat[:, :, None], (ne, nq * 6, m)).ravel())
        cols.append(np.broadcast_to(xdofs[:, None, :], (ne, nq * 6, m)).ravel())
        # dGammadot/dGamma: 6x6 block per quadrature point
        gq = 2 * nx + gdofs  # (e, nq, 6)
        rows.append(np.broadcast_to(gq[:, :, :, None], (ne, nq, 6, 6)).ravel())
        cols.append(np.broadcast_to(gq[:, :, None, :], (ne, nq, 6, 6)).ravel())
    return np.concatenate(rows).astype(np.int64), np.concatenate(cols).astype(np.int64)


def _jac_values(scene, t, y):
    disc = scene.disc
    x, p, g = _split(scene, y)
    minv = _inverse_mass_diagonal(scene) * jnp.ones_like(p)
    if scene.fixed is not None:
        minv = jnp.where(jnp.asarray(scene.fixed.array), 0.0, minv)
    x_el = disc.gather(x)  # (e, n_en, d)
    ne, n_en, d = x_el.shape
    vals = [minv.ravel()]
    if g is None:
        def jf(mat, dN, w, xe):
            return jax.jacfwd(lambda u: _element_kernel(mat, d, dN, w, u.reshape(n_en, d), None)[0].ravel())(
                xe.ravel())

        Kxx = scene.map_cells(jf, disc.dN, disc.JxW, x_el)  # (e, m, m)
        Kxx = _mask_rows(scene, -Kxx)
        vals.append(Kxx.ravel())
        return jnp.concatenate(vals)
    nq = disc.n_qp

    def jf(mat, dN, w, xe, ge):
        def fn(u, v):
            f, r = _element_kernel(mat, d, dN, w, u.reshape(n_en, d), v.reshape(nq, 6))
            return f.ravel(), r.ravel()

        return jax.jacfwd(fn, argnums=(0, 1))(xe.ravel(), ge.ravel())

    (Kxx, Kxg), (Kgx, Kgg) = scene.map_cells(jf, disc.dN, disc.JxW, x_el, g)
    Kgg = Kgg.reshape(ne, nq, 6, nq, 6)
    Kgg = jnp.moveaxis(jnp.diagonal(Kgg, axis1=1, axis2=3), -1, 1)  # (e, nq, 6, 6)
    vals += [_mask_rows(scene, -Kxx).ravel(), _mask_rows(scene, -Kxg).ravel(), Kgx.ravel(), Kgg.ravel()]
    return jnp.concatenate(vals)


def _mask_rows(scene, K):
    """Zero the momentum rows of held components (their rates are zero)."""
    if scene.fixed is None:
        return K
    held = jnp.asarray(scene.fixed.array)[scene.disc.cells.array].reshape(K.shape[0], -1)  # (e, n_en d)
    return jnp.where(held[:, :, None], 0.0, K)
