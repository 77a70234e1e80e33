"""A scene: what moves. Mesh, material, density, initial state, loads."""

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._config import device_array, require_x64
from ._export import register_type
from ._fem._krylov import mass_solve
from ._fem._passes import POINTS_PER_PASS, map_in_passes
from ._fem._space import Discretization, StaticArray
from ._fem._tensor import mm, right_cauchy_green
from ._materials import ReeseGovindjee
from ._time_functions import _time_function
from ._validation import _concrete, check_finite, check_positive


@register_type  # a stored derivative program returns one (`_export.inline`)
class State(eqx.Module):
    """The state of a body: nodal positions `x` `(n_nodes, dim)`, nodal momenta `p`
    `(n_nodes, dim)`, and the internal variable `gamma` `(n_cells, n_qp, 3, 3)` at every
    spatial quadrature point (None for elastic scenes)."""

    x: jax.Array
    p: jax.Array
    gamma: Optional[jax.Array]


class Scene(eqx.Module):
    r"""A body in motion: mesh, material, density, initial state, loads and supports.

    **Arguments:**

    - `mesh`: a `jaxvisco.Mesh`.
    - `material`: a `ReeseGovindjee` material, or a plain energy function $\psi(C)$
      (then the scene is elastic and carries no internal variable); or one material per
      part of the body, a sequence of pairs `(material, cells)` (`cells`: cell indices,
      e.g. a mesh group's) that gives every cell exactly one material. The materials must
      have the same form (the same energies, all viscous or all elastic); their
      parameters differ.
    - `density`: mass density in the reference configuration (> 0): one number, or one per
      cell (n_cells,) for a body whose parts differ.
    - `positions`: initial nodal positions (default: the mesh points, undeformed).
    - `velocities`: initial nodal velocities (default zero); momenta are $p_0 = M v_0$.
    - `gamma`: initial internal variable (n_cells, nq, 3, 3) (default identity: virgin).
    - `loads`: dead loads, a sequence of pairs `(force, time)`: nodal forces `force`
      (n_nodes, dim) scaled by the time function `time` (a `jaxvisco.time_functions`
      module such as `Step(at=1.0, before=1.0, after=0.0)`, any scalar function of t, or
      None for 1). The external force is $f_{ext}(t) = \sum_i g_i(t) f_i$. Surface loads
      become nodal forces with `traction_load`/`pressure_load`. None: free motion.
    - `load`, `load_time`: one dead load, the same as `loads=[(load, load_time)]`.
      A plain function of t is traced by JAX: write it with `jax.numpy`
      (`jnp.where(t < 3.0, 1.0, 0.0)`, not a Python `if`).
    - `fixed`: Dirichlet conditions: a boolean mask (n_nodes, dim) of position components
      held at their initial values (default: none; free motion); `clamp` builds one.
    - `prescribed`: motion of the held components in time, pairs `(displacement, time)`
      like `loads`: held components follow $x_0 + \sum_i g_i(t) u_i$ (`displacement`
      $u_i$ (n_nodes, dim), zero where not held). Start them at rest ($g_i'(0) = 0$, e.g.
      a `Ramp` or `Table` starting flat): the held nodes start with zero velocity. The work
      of the reactions is counted in the external work, so the energy balance stays exact.
    - `mass`: `"consistent"` (default) or `"lumped"` (HRZ diagonal scaling).
    - `quadrature_order`: spatial quadrature order (default: the element's full rule).

    Every array is a leaf of the scene, so `jax.grad` of a run can differentiate with
    respect to it (material parameters, density, initial positions and velocities,
    loads).

    **Raises:**

    `ValueError` for arrays of the wrong shape, non-finite or non-positive values,
    inverted cells, prescribed motion of components that are not held, or a material
    table that does not give every cell one material (each message names the value);
    `RuntimeError` when JAX runs in float32.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import jaxvisco as jv

    mesh = jv.rectangle(8, 2, lx=4.0, ly=1.0)
    nh = jv.NeoHooke(lam=300.0, mu=75.0)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=50.0)
    tip = np.zeros((mesh.n_nodes, 2))
    tip[jv.nodes_in(mesh, x=4.0)] = [0.0, -0.5]
    scene = jv.Scene(mesh, material, density=1.0, fixed=jv.clamp(mesh, jv.nodes_in(mesh, x=0.0)),
                     loads=[(tip, jv.time_functions.Step(at=1.0, before=1.0, after=0.0))])
    ```
    """

    mesh: eqx.Module
    material: ReeseGovindjee  # one material, or several stacked on a leading axis
    cell_material: Optional[StaticArray] = eqx.field(static=True)  # (n_cells,) index, None: one
    density: jax.Array
    disc: Discretization
    x0: jax.Array
    v0: jax.Array
    gamma0: Optional[jax.Array]
    loads: Optional[jax.Array]  # (n_loads, n_nodes, dim)
    load_times: tuple  # one time function per load
    prescribed: Optional[jax.Array]  # (n_prescribed, n_nodes, dim)
    prescribed_times: tuple
    fixed: Optional[StaticArray] = eqx.field(static=True)

    def __init__(self, mesh, material, density, positions=None, velocities=None, gamma=None,
                 load=None, load_time=None, fixed=None, mass="consistent", quadrature_order=None, loads=None,
                 prescribed=None):
        require_x64()
        if isinstance(material, (list, tuple)):
            material, self.cell_material = _material_table(material, mesh.n_cells)
        else:
            material, self.cell_material = _as_material(material, "material"), None
        check_positive("density", density)
        self.mesh = mesh
        self.material = material
        self.density = device_array(density, float)
        if self.density.shape not in ((), (mesh.n_cells,)):
            raise ValueError(f"density must be one number or one per cell, shape ({mesh.n_cells},); got shape "
                             f"{self.density.shape}.")
        self.disc = Discretization(mesh, quadrature_order, mass=mass)
        _check_orientation(self.disc.JxW)
        shape = (mesh.n_nodes, mesh.dim)
        self.x0 = _field("positions", positions, shape, mesh.points)
        self.v0 = _field("velocities", velocities, shape, np.zeros(shape))
        if fixed is None:
            self.fixed = None
        else:
            mask = np.asarray(fixed)
            if mask.shape != shape or mask.dtype != bool:
                raise ValueError(f"fixed must be a boolean mask of shape {shape}, got {mask.dtype} {mask.shape}.")
            self.fixed = StaticArray(mask) if mask.any() else None
            if self.fixed is not None:
                self.v0 = jnp.where(mask, 0.0, self.v0)
        pairs = _load_pairs(prescribed, "prescribed", "displacement")
        motions = [_field(f"prescribed[{i}] displacement", u, shape, None) for i, (u, _) in enumerate(pairs)]
        if motions and self.fixed is None:
            raise ValueError("prescribed motion was given but no component is held: mark the components it moves in "
                             "`fixed`.")
        for i, u in enumerate(motions):
            moving = _concrete(u)
            if moving is not None:
                free = np.argwhere((moving != 0) & ~self.fixed.array)
                if free.size:
                    a, c = free[0]
                    raise ValueError(f"prescribed[{i}] displacement is {float(moving[a, c])!r} at node {a}, component {c}, "
                                     "which is not held; it must be zero where `fixed` is False.")
        self.prescribed = jnp.stack(motions) if motions else None
        self.prescribed_times = tuple(_time_function(g) for _, g in pairs)
        if material.has_internal_variable:
            gshape = (self.disc.n_cells, self.disc.n_qp, 3, 3)
            self.gamma0 = _field("gamma", gamma, gshape, np.broadcast_to(np.eye(3), gshape))
        elif gamma is not None:
            raise ValueError("gamma was given but the material has no internal variable (nonequilibrium=None).")
        else:
            self.gamma0 = None
        if load_time is not None and load is None:
            raise ValueError("load_time was given without a load.")
        pairs = _load_pairs(loads)
        if load is not None:
            if pairs:
                raise ValueError("give either load (with load_time) or loads, not both.")
            pairs = [(load, load_time)]
        forces = [_field("load" if loads is None else f"loads[{i}] force", f, shape, None)
                  for i, (f, _) in enumerate(pairs)]
        self.loads = jnp.stack(forces) if forces else None
        self.load_times = tuple(_time_function(g) for _, g in pairs)

    @classmethod
    def from_file(cls, path) -> "Scene":
        """The scene a TOML scene file describes (`read_scene_file` reads the rest too:
        integrator, steps, output)."""
        from ._scenefile._scenefile import scene_from_file

        return scene_from_file(path)

    def mass(self) -> jax.Array:
        """The total mass $\\int \\rho\\, dV$."""
        rho = self.density if jnp.ndim(self.density) == 0 else self.density[:, None]
        return jnp.sum(rho * self.disc.JxW)

    @property
    def dim(self) -> int:
        """The space dimension, 2 or 3."""
        return self.mesh.dim

    @property
    def has_internal_variable(self) -> bool:
        """Whether the material is viscous (the state carries `gamma`)."""
        return self.material.has_internal_variable

    def held_positions(self, t):
        r"""Positions of the held components at time t: $x_0 + \sum_i g_i(t) u_i$ (`x0` when
        nothing moves them); meaningful where `fixed` is True."""
        return self.x0 + _scaled_sum(self.prescribed, self.prescribed_times, t)

    def held_velocity(self, t):
        r"""$\sum_i g_i'(t) u_i$: velocity of the held components (zeros when none moves)."""
        if self.prescribed is None:
            return jnp.zeros_like(self.x0)
        return jax.jvp(lambda s: _scaled_sum(self.prescribed, self.prescribed_times, s),
                       (jnp.asarray(t, dtype=float),), (jnp.ones((), dtype=float),))[1]

    def initial_state(self) -> State:
        """The `State` the scene starts from: positions, momenta $p_0 = M v_0$, `gamma`."""
        return State(self.x0, _initial_momenta(self.disc, self.v0, self.density), self.gamma0)

    @property
    def load(self):
        """The sum of the dead loads at full scale (n_nodes, dim), None for free motion."""
        return None if self.loads is None else jnp.sum(self.loads, axis=0)

    def external_force(self, t):
        r"""Nodal dead load at time t, $\sum_i g_i(t) f_i$ (zeros for free motion)."""
        return _scaled_sum(self.loads, self.load_times, t, like=self.x0)

    # -- diagnostics ---------------------------------------------------------------
    def velocity(self, p, rtol=1e-14):
        """$v = M^{-1}p$ on the scene's mass matrix (conjugate gradients, differentiable in
        both modes), max-norm relative accuracy `rtol`."""
        disc, rho = self.disc, self.density
        return mass_solve(lambda u: disc.mass_matvec(u, rho), disc.mass_diagonal(rho)[:, None], p, rtol)

    def kinetic_energy(self, p, velocity=None):
        """$p \\cdot M^{-1} p / 2$; `velocity`: $M^{-1}p$ where the caller has it already."""
        return 0.5 * jnp.vdot(p, self.velocity(p) if velocity is None else velocity)

    # -- materials per cell ----------------------------------------------------------
    def cell_materials(self):
        """The material of every cell, stacked on a leading cell axis; None when one
        material fills the body (then `material` is it)."""
        if self.cell_material is None:
            return None
        idx = jnp.asarray(self.cell_material.array)
        dyn, static = eqx.partition(self.material, eqx.is_array)
        return eqx.combine(jax.tree_util.tree_map(lambda a: a[idx], dyn), static)

    def point_materials(self):
        """The material of every spatial quadrature point, flat (n_cells * nq) on the
        leading axis like the tangent's point maps; None for one material."""
        mats = self.cell_materials()
        if mats is None:
            return None
        dyn, static = eqx.partition(mats, eqx.is_array)
        return eqx.combine(jax.tree_util.tree_map(lambda a: jnp.repeat(a, self.disc.n_qp, axis=0), dyn), static)

    def map_cells(self, fn, *args, per_pass=None):
        """`fn(material, *args_of_one_cell)` over the cells (leading axis of each of
        `args`, None passes through), each cell with its material; `per_pass`: at most
        this many cells at a time (in passes), None: all at once."""
        mats = self.cell_materials()
        if mats is None:
            dyn, one = None, lambda _, *a: fn(self.material, *a)
        else:
            dyn, static = eqx.partition(mats, eqx.is_array)
            one = lambda d, *a: fn(eqx.combine(d, static), *a)  # noqa: E731
        batched = lambda a: jax.vmap(one, in_axes=(None if dyn is None else 0,) + (0,) * len(args))(*a)  # noqa: E731
        n = jax.tree_util.tree_leaves(args)[0].shape[0]
        if per_pass is None or n <= per_pass:
            return batched((dyn,) + args)
        return map_in_passes(batched, (dyn,) + args, per_pass)

    def map_points(self, fn, F, G):
        """`fn(material, F, G)` at every spatial quadrature point; F (n_cells, nq, ...) and
        G alike or None. Large meshes in passes of `POINTS_PER_PASS` points."""
        return self.map_cells(lambda mat, f, g: jax.vmap(lambda a, b: fn(mat, a, b))(f, g), F, G,
                              per_pass=_cells_per_pass(F.shape[1]))

    def map_point_histories(self, fn, F, G):
        """`map_points` for fields given node-major, F (k+1, n_cells, nq, 3, 3) and G alike
        or None: `fn(material, F, G)` with F (k+1, 3, 3) at every spatial point, outputs
        (n_cells, nq, ...). The time-node axis stays outermost, so that the kernel's
        per-node slices are contiguous blocks (faster; measured on the internals page).
        Per-cell materials and meshes taken in passes go point-major."""
        if self.cell_materials() is None and F.shape[1] <= _cells_per_pass(F.shape[2]):
            inner = jax.vmap(lambda f, g: fn(self.material, f, g), in_axes=1)
            return jax.vmap(inner, in_axes=1)(F, G)
        point_major = lambda a: None if a is None else jnp.moveaxis(a, 0, 2)  # noqa: E731
        return self.map_points(fn, point_major(F), point_major(G))

    def _qp_map(self, fn, x, gamma):
        C = right_cauchy_green(self.disc.deformation_gradient(x))
        return self.map_points(fn, C, gamma)

    def free_energy(self, x, gamma):
        return self.disc.integrate(self._qp_map(lambda m, c, g: m.free_energy(c, g), x, gamma))

    def dissipation_rate(self, x, gamma):
        if gamma is None:
            return jnp.zeros((), dtype=x.dtype)
        return self.disc.integrate(self._qp_map(lambda m, c, g: m.dissipation(c, g), x, gamma))

    def stress(self, x, gamma):
        """Second Piola–Kirchhoff stress at every quadrature point."""
        return self._qp_map(lambda m, c, g: m.stress(c, g), x, gamma)

    def internal_force(self, x, gamma):
        F = self.disc.deformation_gradient(x)
        return self.disc.force(mm(F, self.stress(x, gamma)))

    def diagnostics(self, state: State, velocity=None) -> dict:
        """The diagnostics of a `State`, as `Solution` holds them per frame: a dict with
        `kinetic`, `free_energy`, `energy` (H), `dissipation_rate`, `linear_momentum` and
        `angular_momentum`. `velocity`: $M^{-1}p$ where the caller has it already."""
        kin = self.kinetic_energy(state.p, velocity)
        free = self.free_energy(state.x, state.gamma)
        return dict(
            kinetic=kin,
            free_energy=free,
            energy=kin + free,
            dissipation_rate=self.dissipation_rate(state.x, state.gamma),
            linear_momentum=jnp.sum(state.p, axis=0),
            angular_momentum=angular_momentum(state.x, state.p),
        )


def _cells_per_pass(n_qp):
    """Cells whose points `Scene.map_points` maps at once (`POINTS_PER_PASS` points)."""
    return max(1, POINTS_PER_PASS // n_qp)


def angular_momentum(x, p):
    """$L = \\sum_A x_A \\times p_A$ (a scalar in 2D)."""
    if x.shape[-1] == 2:
        return jnp.sum(x[..., 0] * p[..., 1] - x[..., 1] * p[..., 0], axis=-1)
    return jnp.sum(jnp.cross(x, p), axis=-2)


def _check_orientation(JxW, tol=1e-8):
    """Reject inverted or degenerate elements (det J <= tol * typical at a quadrature
    point); skipped for traced meshes."""
    j = _concrete(JxW)
    if j is None:
        return
    typical = np.mean(np.abs(j))
    worst = j.min(axis=1)
    bad = np.flatnonzero(~(worst > tol * typical))
    if bad.size:
        e = bad[0]
        kind = "inverted" if worst[e] < -tol * typical else "degenerate"
        raise ValueError(f"element {e} is {kind}: det J * w = {worst[e]:.6g} at a quadrature point (typical "
                         f"{typical:.6g}, accepted > {tol:g} * typical); check its node order (Mesh.validate() "
                         "reports more).")


def _as_material(material, name):
    if isinstance(material, ReeseGovindjee):
        return material
    if not callable(material):
        raise TypeError(f"{name} must be a ReeseGovindjee material or an energy function psi(C), "
                        f"got {type(material).__name__}.")
    return ReeseGovindjee(equilibrium=material)


def _material_table(pairs, n_cells):
    """Stack the materials of `(material, cells)` pairs on a leading axis, and the index
    of each cell's material; checks that every cell gets exactly one."""
    mats, owner = [], np.full(n_cells, -1)
    for i, item in enumerate(pairs):
        if not (isinstance(item, (tuple, list)) and len(item) == 2):
            raise ValueError(f"material[{i}] must be a pair (material, cell indices), got {type(item).__name__}.")
        mat, cells = item
        mats.append(_as_material(mat, f"material[{i}]"))
        idx = np.asarray(cells)
        if idx.dtype == bool and idx.shape == (n_cells,):
            idx = np.flatnonzero(idx)
        if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(f"material[{i}] cells must be a 1D array of cell indices or a boolean mask of "
                             f"shape ({n_cells},), got {idx.dtype} {idx.shape}.")
        bad = idx[(idx < 0) | (idx >= n_cells)]
        if bad.size:
            raise ValueError(f"material[{i}] cells: index {int(bad[0])} is outside [0, {n_cells - 1}].")
        taken = idx[owner[idx] >= 0]
        if taken.size:
            c = int(taken[0])
            raise ValueError(f"material[{i}]: cell {c} already has material[{int(owner[c])}]; each cell takes "
                             "one material.")
        owner[idx] = i
    missing = np.flatnonzero(owner < 0)
    if missing.size:
        raise ValueError(f"{missing.size} of {n_cells} cells have no material (the first: cell {int(missing[0])}); "
                         "the (material, cells) pairs must cover every cell.")
    dyns, statics = zip(*(eqx.partition(m, eqx.is_array) for m in mats))
    for i, st in enumerate(statics[1:], start=1):
        same = jax.tree_util.tree_structure(dyns[i]) == jax.tree_util.tree_structure(dyns[0])
        if not (same and eqx.tree_equal(st, statics[0]) is True):
            raise ValueError(f"material[{i}] differs in form from material[0]: the materials of one body must "
                             "have the same energies (e.g. NeoHooke branches), all viscous or all elastic; only "
                             "their parameters may differ.")
    if len(mats) == 1:
        return mats[0], None
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack([jnp.asarray(x, dtype=float) for x in a]), *dyns)
    return eqx.combine(stacked, statics[0]), StaticArray(owner.astype(np.int32))


def _scaled_sum(vectors, times, t, like=None):
    r"""$\sum_i g_i(t) v_i$ for stacked vectors (n, n_nodes, dim); zeros when None."""
    if vectors is None:
        return jnp.zeros_like(like) if like is not None else 0.0
    scales = jnp.stack([jnp.asarray(g(t), dtype=vectors.dtype) for g in times])
    return jnp.einsum("i,ind->nd", scales, vectors)


def _load_pairs(loads, name="loads", what="force"):
    if loads is None:
        return []
    try:
        pairs = list(loads)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of ({what}, time function) pairs, got {type(loads).__name__}.") \
            from None
    for i, item in enumerate(pairs):
        if not (isinstance(item, (tuple, list)) and len(item) == 2):
            raise ValueError(f"{name}[{i}] must be a pair ({what} (n_nodes, dim), time function or None), got "
                             f"{type(item).__name__}{'' if not hasattr(item, '__len__') else f' of length {len(item)}'}.")
    return pairs


@eqx.filter_jit
def _initial_momenta(disc, v, density):
    """M v0 as one program (called eagerly, its gathers, products and scatters compiled
    one by one: 0.3 s of a cold first `simulate` call of the paper scene)."""
    return disc.mass_matvec(v, density)


def _field(name, value, shape, default):
    if value is None:
        return jnp.asarray(default, dtype=float)
    value = jnp.asarray(value, dtype=float)
    if value.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {value.shape}.")
    check_finite(name, value)
    return value

