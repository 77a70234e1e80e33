"""Semi-discrete operators of a Scene for every element type (THEORY §2): internal force
as the energy gradient, tangent, patch tests, consistent mass and momenta, diagnostics,
input errors."""

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helpers import random_rotation, random_spd_batch
from jaxvisco._fem._generators import box, lshape_mesh, rectangle
from jaxvisco._fem._mesh import Mesh
from jaxvisco._materials import NeoHooke, ReeseGovindjee, paper_material
from jaxvisco._scene import Scene, angular_momentum

DATA = os.path.join(os.path.dirname(__file__), "data")
ELEMENTS_2D = ["tri3", "quad4", "tri6", "quad8", "quad9"]
ELEMENTS_3D = ["tet4", "hex8", "tet10", "hex20", "hex27"]
ELEMENTS = ELEMENTS_2D + ELEMENTS_3D
LINEAR = {"tri3", "quad4", "tet4", "hex8"}
RHO = 8.93
MU = 7500.0

# A viscous material with both branches, and an elastic one.
VISCO = paper_material()
ELASTIC = ReeseGovindjee(NeoHooke(lam=30000.0, mu=MU))


def _dim(elem):
    return 2 if elem in ELEMENTS_2D else 3


@functools.cache
def _mesh(elem):
    """A small structured mesh, not at the origin, with unequal side lengths: 2x2 lattice
    cells in 2D, 2x2x2 for linear 3D elements, 2x2x1 for quadratic 3D elements (enough
    for interior nodes, and keeps the dense tangents small)."""
    if _dim(elem) == 2:
        return rectangle(2, 2, lx=2.0, ly=1.5, cell_type=elem, origin=(0.3, -0.2))
    nz = 2 if elem in LINEAR else 1
    return box(2, 2, nz, lx=1.5, ly=1.0, lz=0.6 * nz, cell_type=elem, origin=(0.1, 0.2, -0.3))


def _boundary(mesh):
    """Boolean mask of nodes on the boundary of the (axis-aligned) rectangle/box."""
    X = np.asarray(mesh.points)
    lo, hi = X.min(0), X.max(0)
    tol = 1e-9 * np.abs(X).max()
    return np.any((np.abs(X - lo) < tol) | (np.abs(X - hi) < tol), axis=1)


@functools.cache
def _patch_mesh(elem):
    """The small mesh, mapped by a global affine skew map (elements stay affine, or
    parallelograms); for linear elements the interior nodes are also moved randomly
    (isoparametric linear elements pass the patch test on any mesh with full quadrature).

    Returns the mesh and its mask of interior nodes."""
    mesh = _mesh(elem)
    X = np.asarray(mesh.points)
    interior = ~_boundary(mesh)
    d = X.shape[1]
    B = np.eye(d) + 0.2 * np.triu(np.ones((d, d)), 1) - 0.1 * np.tril(np.ones((d, d)), -1)
    if elem in LINEAR:
        rng = np.random.default_rng(hash(elem) % 2**32)
        X = X.copy()
        X[interior] += 0.08 * rng.uniform(-1, 1, size=(interior.sum(), d))
    Y = X @ B.T
    m = Mesh(points=Y, cells=np.asarray(mesh.cells), cell_type=elem).validate()
    return m, interior


def _smooth_deformation(X, rng, amp=0.05):
    d = X.shape[1]
    a = rng.uniform(1.0, 3.0, size=(d, d))
    b = rng.uniform(0, 2 * np.pi, size=d)
    return X + amp * np.sin(X @ a.T + b)


# ----------------------------------------------------------------- jitted kernels


# Compile-time light XLA options: these programs run once or twice, so XLA's compile time
# (not run time) dominates the test suite. Numerics are unaffected beyond round-off.
_FAST = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
fast_jit = functools.partial(jax.jit, compiler_options=_FAST)


@fast_jit
def _evaluate(scene, xs, gamma):
    """For each of a batch of configurations: energy, its gradient (reverse mode), the
    internal force and the stresses (one compilation per element type for all uses)."""

    def one(x):
        E, g = jax.value_and_grad(scene.free_energy)(x, gamma)
        return E, g, scene.internal_force(x, gamma), scene.stress(x, gamma)

    return jax.vmap(one)(xs)


@fast_jit
def _tangent_elastic(scene, x, xs):
    """Dense tangent d f_int / d x of an elastic scene (no internal variable) and the force
    at a batch of points."""
    n = x.size
    K = jax.jacfwd(lambda y: scene.internal_force(y.reshape(x.shape), None).ravel())(x.ravel())
    return K.reshape(n, n), jax.vmap(lambda y: scene.internal_force(y, None))(xs)


@fast_jit
def _velocity_and_kinetic(scene, p):
    return scene.velocity(p), scene.kinetic_energy(p)


def _gamma_field(scene, rng):
    return random_spd_batch(rng, (scene.disc.n_cells, scene.disc.n_qp), scale=0.3, min_eig=0.3)


# ----------------------------------------------------------------- force = gradient


@functools.cache
def _viscous_data(elem):
    """Energies, gradients, forces, stresses at a smooth deformed configuration x and at
    x +- eps V_k, for the viscous material and a random SPD Gamma field."""
    mesh = _mesh(elem)
    scene = Scene(mesh, VISCO, RHO)
    rng = np.random.default_rng(1)
    X = np.asarray(mesh.points)
    x = _smooth_deformation(X, rng)
    gamma = _gamma_field(scene, rng)
    eps = 1e-6
    V = rng.standard_normal((2,) + x.shape)
    xs = np.stack([x, x + eps * V[0], x - eps * V[0], x + eps * V[1], x - eps * V[1]])
    out = tuple(np.asarray(a) for a in _evaluate(scene, jnp.asarray(xs), jnp.asarray(gamma)))
    return scene, x, gamma, eps, V, out


@pytest.mark.timeout(180)
@pytest.mark.parametrize("elem", ELEMENTS)
def test_internal_force_is_energy_gradient(elem):
    scene, x, gamma, eps, V, (E, grad, f, S) = _viscous_data(elem)
    assert np.abs(gamma - np.eye(3)).max() > 0.1  # a genuinely non-identity field
    assert np.all(np.isfinite(E)) and E[0] > 0
    assert float(scene.disc.min_jacobian(jnp.asarray(x))) > 0.5
    fmax = np.abs(f[0]).max()
    assert fmax > 1.0  # the configuration is genuinely loaded
    np.testing.assert_allclose(f[0], grad[0], rtol=0, atol=1e-10 * fmax)
    for k in range(2):
        fd = (E[1 + 2 * k] - E[2 + 2 * k]) / (2 * eps)
        ad = np.sum(f[0] * V[k])
        assert abs(fd - ad) < 1e-6 * abs(ad), (elem, fd, ad)
    # The deformation is smooth and non-homogeneous: stresses vary over the mesh.
    assert np.std(S[0][..., 0, 0]) > 1e-3 * np.abs(S[0]).max()


# ----------------------------------------------------------------- tangent


def _check_tangent(K, f_plus_minus, V, eps, x, label):
    for k in range(len(V)):
        fd = ((f_plus_minus[2 * k] - f_plus_minus[2 * k + 1]) / (2 * eps)).ravel()
        kv = K @ V[k].ravel()
        err = np.abs(fd - kv).max() / np.abs(kv).max()
        assert err < 1e-6, (label, err)
    # Hessian of an energy in x: symmetric.
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-8 * np.abs(K).max())
    # Translations are exact null vectors (forces depend only on gradients of x).
    for i in range(x.shape[1]):
        t = np.zeros(x.shape)
        t[:, i] = 1.0
        assert np.abs(K @ t.ravel()).max() < 1e-9 * np.abs(K).max()


@pytest.mark.timeout(180)
@pytest.mark.parametrize("elem", ELEMENTS)
def test_tangent_matches_fd_and_is_symmetric(elem):
    """Hyperelastic scene (no internal variable): dense jacfwd tangent vs FD, symmetric."""
    mesh = _mesh(elem)
    scene = Scene(mesh, ELASTIC, RHO)
    assert scene.gamma0 is None and not scene.has_internal_variable
    rng = np.random.default_rng(2)
    x = _smooth_deformation(np.asarray(mesh.points), rng)
    eps = 1e-6
    V = rng.standard_normal((2,) + x.shape)
    xs = np.stack([x + eps * V[0], x - eps * V[0], x + eps * V[1], x - eps * V[1]])
    K, fs = (np.asarray(a) for a in _tangent_elastic(scene, jnp.asarray(x), jnp.asarray(xs)))
    _check_tangent(K, fs, V, eps, x, elem)


# ----------------------------------------------------------------- patch tests


@pytest.mark.timeout(180)
@pytest.mark.parametrize("elem", ELEMENTS)
def test_patch_tests(elem):
    mesh, interior = _patch_mesh(elem)
    assert interior.any()
    d = mesh.dim
    scene = Scene(mesh, VISCO, RHO)
    rng = np.random.default_rng(3)
    X = np.asarray(mesh.points)
    A = np.eye(d) + 0.15 * rng.standard_normal((d, d))
    assert np.linalg.det(A) > 0.3
    c = rng.standard_normal(d)
    Q = random_rotation(rng, d)
    H = rng.standard_normal((d, d))
    x_smooth = _smooth_deformation(X, rng)
    xs = np.stack([
        X @ A.T + c,  # homogeneous deformation
        X @ Q.T + c,  # rigid rotation
        X + 1e-3 * X @ (H + H.T).T,  # small strain: force scale
        x_smooth,
        x_smooth @ Q.T + c,  # rotated deformed configuration
    ])
    gamma = jnp.broadcast_to(jnp.eye(3), scene.gamma0.shape)
    E, _, f, S = (np.asarray(a) for a in _evaluate(scene, jnp.asarray(xs), gamma))

    # Homogeneous deformation: uniform S equal to the material's S(A^T A); no force on
    # interior nodes.
    S_aff = S[0].reshape(-1, 3, 3)
    mean = S_aff.mean(0)
    assert np.abs(mean).max() > 100.0
    assert np.std(S_aff, axis=0).max() / np.abs(mean).max() < 1e-10
    F = np.eye(3)
    F[:d, :d] = A
    S_mat = np.asarray(VISCO.stress(jnp.asarray(F.T @ F), jnp.eye(3)))
    np.testing.assert_allclose(mean, S_mat, rtol=0, atol=1e-10 * np.abs(S_mat).max())
    f_aff = f[0]
    assert np.abs(f_aff[interior]).max() < 1e-10 * np.abs(f_aff).max()
    assert np.abs(f_aff[~interior]).max() > 1.0
    # Total force of a free body vanishes (translation invariance).
    assert np.abs(f_aff.sum(0)).max() < 1e-10 * np.abs(f_aff).max()

    # Rigid rotation: zero force and zero energy.
    f_scale = np.abs(f[2]).max()
    assert f_scale > 0.1
    assert np.abs(f[1]).max() < 1e-9 * f_scale, (np.abs(f[1]).max(), f_scale)
    volume = float(mesh.volume())
    assert abs(E[1]) < 1e-9 * volume * MU

    # Objectivity of the discrete energy and force: E(Qx + c) = E(x), f(Qx + c) = Q f(x).
    assert E[4] == pytest.approx(E[3], rel=1e-11)
    np.testing.assert_allclose(f[4], f[3] @ Q.T, rtol=0, atol=1e-10 * np.abs(f[3]).max())


# ----------------------------------------------------------------- mass and momenta


def _continuum(mesh, rho, v_fn, order):
    """Mass, first moment and angular momentum of the continuum by the library's own
    quadrature of order `order` (exact for these polynomial integrands)."""
    qd = mesh.quadrature_data(order)
    Xq = np.einsum("qa,eai->eqi", np.asarray(qd.N), np.asarray(mesh.points)[np.asarray(mesh.cells)])
    w = rho * np.asarray(qd.JxW)
    m = w.sum()
    first = np.einsum("eq,eqi->i", w, Xq)
    v = v_fn(Xq)
    if mesh.dim == 2:
        L = np.sum(w * (Xq[..., 0] * v[..., 1] - Xq[..., 1] * v[..., 0]))
    else:
        L = np.einsum("eq,eqi->i", w, np.cross(Xq, v))
    return m, first, L


def _box_moments(lo, hi):
    """Exact volume, first moments int X_i and second moments int X_i X_j of an
    axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    L = hi - lo
    m0 = np.prod(L)
    m1 = (hi**2 - lo**2) / 2  # int x_i dx_i
    m2 = (hi**3 - lo**3) / 3  # int x_i^2 dx_i
    first = m0 / L * m1
    second = np.outer(first, first) / m0
    second[np.diag_indices(len(L))] = m0 / L * m2
    return m0, first, second


def _geometry_moments(case, mesh):
    """Exact (volume, first, second moments) of the meshed region: a union of disjoint
    axis-aligned boxes."""
    kind = case.partition("-")[0]
    if kind == "gen":
        X = np.asarray(mesh.points)
        boxes = [(X.min(0), X.max(0))]
    elif kind == "lshape2d":
        boxes = [((0, 0), (6, 3)), ((0, 3), (3, 10))]
    else:  # the 3D L-shape, generated or read from the Abaqus file
        boxes = [((0, 0, 0), (6, 3, 3)), ((0, 3, 0), (3, 10, 3))]
    parts = [_box_moments(lo, hi) for lo, hi in boxes]
    return tuple(sum(p[k] for p in parts) for k in range(3))


def _rigid_velocity(dim, rng):
    v_T = rng.standard_normal(dim)
    if dim == 2:
        om = rng.standard_normal()
        return lambda X: v_T + om * np.stack([-X[..., 1], X[..., 0]], -1), v_T, om
    om = rng.standard_normal(3)
    return lambda X: v_T + np.cross(om, X), v_T, om


def _mass_cases():
    cases = [(f"gen-{e}", e) for e in ELEMENTS]
    # lshape3d-hex8 and the Abaqus file have the same connectivity shapes (one compile).
    cases += [("lshape2d-quad4", None), ("lshape2d-tri6", None), ("lshape3d-hex8", None),
              ("abaqus-LShapeH1Medium", None)]
    return cases


def _mass_mesh(case):
    kind, _, elem = case.partition("-")
    if kind == "gen":
        return _mesh(elem), None
    if kind == "lshape2d":
        return lshape_mesh(2, 1, elem), 39.0
    if kind == "lshape3d":
        return lshape_mesh(3, 1, elem), 117.0
    return Mesh.read(os.path.join(DATA, "LShapeH1Medium.inp")), 117.0


@pytest.mark.timeout(180)
@pytest.mark.parametrize("case", [c for c, _ in _mass_cases()])
def test_mass_and_momenta(case):
    mesh, exact_volume = _mass_mesh(case)
    vol, first, second = _geometry_moments(case, mesh)
    if exact_volume is not None:
        assert vol == pytest.approx(exact_volume, rel=1e-15)
    d = mesh.dim
    scene = Scene(mesh, VISCO, RHO)
    disc = scene.disc
    # Total mass: sum of all entries of the consistent mass matrix.
    Mones = np.asarray(disc.mass_matvec(jnp.ones((mesh.n_nodes, d)), scene.density))
    assert Mones[:, 0].sum() == pytest.approx(RHO * vol, rel=1e-12)
    np.testing.assert_allclose(Mones, np.broadcast_to(Mones[:, :1], Mones.shape), rtol=1e-14, atol=0)
    # Rigid velocity field v = v_T + omega x X, interpolated exactly (it is affine).
    rng = np.random.default_rng(4)
    v_fn, v_T, om = _rigid_velocity(d, rng)
    X = np.asarray(mesh.points)
    v = v_fn(X)
    scene_v = Scene(mesh, VISCO, RHO, velocities=v)
    p = np.asarray(scene_v.initial_state().p)
    np.testing.assert_allclose(p, disc.mass_matvec(jnp.asarray(v), RHO), rtol=1e-14, atol=0)
    # Exact continuum values: P = m v_T + omega x (m X_c); L = int rho X x v.
    m, mX = RHO * vol, RHO * first
    if d == 2:
        P_exact = m * v_T + om * np.array([-mX[1], mX[0]])
        L_exact = v_T[1] * mX[0] - v_T[0] * mX[1] + om * RHO * np.trace(second)
    else:
        P_exact = m * v_T + np.cross(om, mX)
        L_exact = np.cross(mX, v_T) + RHO * (om * np.trace(second) - second @ om)
    P = p.sum(0)
    np.testing.assert_allclose(P, P_exact, rtol=0, atol=1e-12 * np.abs(P_exact).max())
    L = np.asarray(angular_momentum(jnp.asarray(X), jnp.asarray(p)))
    assert L.shape == (() if d == 2 else (3,))
    np.testing.assert_allclose(L, L_exact, rtol=0, atol=1e-12 * np.abs(L_exact).max())


@pytest.mark.parametrize("dim", [2, 3])
def test_continuum_moments_by_quadrature(dim):
    """The closed-form moments above agree with a higher-order quadrature over the mesh
    (mesh.quadrature_data), for the L-shape."""
    case = "lshape2d-quad4" if dim == 2 else "lshape3d-hex8"
    mesh, _ = _mass_mesh(case)
    vol, first, second = _geometry_moments(case, mesh)
    rng = np.random.default_rng(7)
    v_fn, v_T, om = _rigid_velocity(dim, rng)
    m, mX, L = _continuum(mesh, RHO, v_fn, 4)
    assert m == pytest.approx(RHO * vol, rel=1e-13)
    np.testing.assert_allclose(mX, RHO * first, rtol=1e-13)
    if dim == 2:
        L_exact = v_T[1] * RHO * first[0] - v_T[0] * RHO * first[1] + om * RHO * np.trace(second)
    else:
        L_exact = RHO * (np.cross(first, v_T) + om * np.trace(second) - second @ om)
    np.testing.assert_allclose(L, L_exact, rtol=1e-12)


def test_lshape_center_of_mass():
    """The continuum integrals used above are right: the L-shape's centroid in closed form."""
    mesh = lshape_mesh(2, 1)
    m, first, _ = _continuum(mesh, 1.0, lambda X: np.zeros_like(X), 2)
    # [0,6]x[0,3] (area 18, centroid (3, 1.5)) + [0,3]x[3,10] (area 21, centroid (1.5, 6.5)).
    expected = (18 * np.array([3.0, 1.5]) + 21 * np.array([1.5, 6.5])) / 39.0
    assert m == pytest.approx(39.0, rel=1e-14)
    np.testing.assert_allclose(first / m, expected, rtol=1e-14)


@pytest.mark.timeout(180)
@pytest.mark.parametrize("elem", ["quad8", "tet10"])
def test_velocity_inverts_mass(elem):
    mesh = _mesh(elem)
    scene = Scene(mesh, VISCO, RHO)
    rng = np.random.default_rng(5)
    v = rng.standard_normal((mesh.n_nodes, mesh.dim))
    Mv = scene.disc.mass_matvec(jnp.asarray(v), scene.density)
    v_back, T = _velocity_and_kinetic(scene, Mv)
    v_back, T = np.asarray(v_back), float(T)
    assert np.abs(v_back - v).max() < 1e-12 * np.abs(v).max()
    assert T == pytest.approx(0.5 * float(jnp.vdot(jnp.asarray(v), Mv)), rel=1e-12)
    assert T > 0


@pytest.mark.timeout(180)
@pytest.mark.parametrize("elem", ["quad4", "tet4"])
def test_diagnostics(elem):
    mesh = _mesh(elem)
    rng = np.random.default_rng(6)
    v_fn, _, _ = _rigid_velocity(mesh.dim, rng)
    X = np.asarray(mesh.points)
    scene = Scene(mesh, VISCO, RHO, positions=_smooth_deformation(X, rng), velocities=v_fn(X))
    state = scene.initial_state()
    diag = fast_jit(lambda sc, st: sc.diagnostics(st))(scene, state)
    assert set(diag) == {"kinetic", "free_energy", "energy", "dissipation_rate",
                         "linear_momentum", "angular_momentum"}
    for k in ("kinetic", "free_energy", "energy", "dissipation_rate"):
        assert np.shape(diag[k]) == () and np.isfinite(diag[k]), k
    assert diag["kinetic"] > 0 and diag["free_energy"] > 0
    assert float(diag["energy"]) == pytest.approx(float(diag["kinetic"] + diag["free_energy"]), rel=1e-14)
    # Virgin Gamma = I but a deformed body: the non-equilibrium branch is loaded and flows.
    assert diag["dissipation_rate"] > 0
    assert np.shape(diag["linear_momentum"]) == (mesh.dim,)
    np.testing.assert_allclose(diag["linear_momentum"], np.asarray(state.p).sum(0), rtol=1e-14)
    L = np.asarray(diag["angular_momentum"])
    assert L.shape == (() if mesh.dim == 2 else (3,))
    x, p = np.asarray(state.x), np.asarray(state.p)
    if mesh.dim == 2:
        L_ref = np.sum(x[:, 0] * p[:, 1] - x[:, 1] * p[:, 0])
    else:
        L_ref = np.cross(x, p).sum(0)
    np.testing.assert_allclose(L, L_ref, rtol=1e-12)


# ----------------------------------------------------------------- input errors


def test_scene_input_errors():
    mesh = _mesh("quad4")
    n, d = mesh.n_nodes, mesh.dim
    with pytest.raises(ValueError, match="velocities"):
        Scene(mesh, VISCO, RHO, velocities=np.zeros((n, d + 1)))
    with pytest.raises(ValueError, match="velocities"):
        Scene(mesh, VISCO, RHO, velocities=np.zeros((n - 1, d)))
    X = np.array(mesh.points)
    X[3, 1] = np.nan
    with pytest.raises(ValueError, match="positions"):
        Scene(mesh, VISCO, RHO, positions=X)
    with pytest.raises(ValueError, match="density"):
        Scene(mesh, VISCO, -1.0)
    with pytest.raises(ValueError, match="density"):
        Scene(mesh, VISCO, 0.0)
    with pytest.raises(ValueError, match="gamma"):
        Scene(mesh, ELASTIC, RHO, gamma=np.ones((mesh.n_cells, 4, 3, 3)))
    with pytest.raises(TypeError):
        Scene(mesh, 3.0, RHO)
    # A plain energy function is accepted as an elastic material.
    s = Scene(mesh, NeoHooke(lam=1.0, mu=1.0), RHO)
    assert not s.has_internal_variable and s.initial_state().gamma is None


@pytest.mark.parametrize("elem", ["quad4", "tri6", "hex8", "tet10"])
def test_reference_configuration_is_exactly_unstrained(elem):
    """F = I bit for bit at the reference positions (F = I + grad(x - X)), so a body at
    rest has exactly zero stress and internal force; the gradient of the positions
    themselves left ~1e-15 of rounding, a residual near Newton's acceptance for a body at
    rest (test_adaptive's equilibrium case took 62-82 Newton iterations per step)."""
    mesh = _mesh(elem)
    scene = Scene(mesh, VISCO, RHO)
    X = jnp.asarray(mesh.points)
    F = np.asarray(scene.disc.deformation_gradient(X))
    assert np.array_equal(F, np.broadcast_to(np.eye(3), F.shape))
    P = jax.vmap(jax.vmap(lambda f: f @ VISCO.stress(f.T @ f, jnp.eye(3))))(jnp.asarray(F))
    assert not np.any(np.asarray(scene.disc.force(P)))
    # and a translated copy is unstrained to rounding of the translation only
    Ft = np.asarray(scene.disc.deformation_gradient(X + 0.25))
    assert np.max(np.abs(Ft - np.eye(3))) <= 1e-14


@pytest.mark.timeout(120)
@pytest.mark.parametrize("elem", ELEMENTS)
def test_assembly_sums_every_element_entry(elem):
    """`Discretization.scatter` (the assembly of every residual and mass product) equals
    an unbuffered scatter-add of the element arrays (numpy's `add.at`), with leading
    axes; a node that no element uses (the mesh's extra last point) receives zero."""
    from jaxvisco._fem._space import Discretization

    base = _mesh(elem)
    points = np.vstack([np.asarray(base.points), np.asarray(base.points).max(0) + 1.0])
    mesh = Mesh(points, np.asarray(base.cells), cell_type=elem)
    disc = Discretization(mesh)
    cells = np.asarray(mesh.cells)
    u = np.random.default_rng(3).normal(size=(2, 3) + cells.shape + (4,))
    expected = np.zeros((2, 3, mesh.n_nodes, 4))
    np.add.at(expected, (slice(None), slice(None), cells), u)
    out = np.asarray(disc.scatter(jnp.asarray(u)))
    np.testing.assert_allclose(out, expected, rtol=1e-14, atol=1e-14)
    assert np.all(out[:, :, -1] == 0.0)
