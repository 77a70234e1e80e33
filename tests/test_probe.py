"""Material-point probes (`jaxvisco.Probe`): location, interpolation, strains, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import fd_check

import jaxvisco as jv
from jaxvisco._fem._probe import _polynomial

NAMES_2D = ["tri3", "quad4", "tri6", "quad8", "quad9"]
NAMES_3D = ["tet4", "hex8", "tet10", "hex20", "hex27"]
NAMES = NAMES_2D + NAMES_3D
QUADRATIC = ["tri6", "quad8", "quad9", "tet10", "hex20", "hex27"]
SIZE = {2: np.array([1.5, 0.8]), 3: np.array([1.5, 0.8, 1.2])}
ORIGIN = {2: np.array([0.3, -0.2]), 3: np.array([0.3, -0.2, 0.1])}


def _straight(name):
    """A generated mesh whose element maps are affine (scaled lattice cells)."""
    e = jv.element_type(name)
    o, s = ORIGIN[e.dim], SIZE[e.dim]
    if e.dim == 2:
        return jv.rectangle(3, 2, *s, cell_type=name, origin=o)
    return jv.box(3, 2, 2, *s, cell_type=name, origin=o)


def _warp(X):
    """A smooth map that bends element edges (curved quadratic elements, non-affine
    bilinear/trilinear ones) while keeping every element valid."""
    X = np.asarray(X)
    x, y = X[:, 0], X[:, 1]
    if X.shape[1] == 2:
        return np.stack([x + 0.1 * np.sin(3 * y), y + 0.08 * np.sin(2 * x) + 0.05 * x * x], 1)
    z = X[:, 2]
    return np.stack(
        [x + 0.08 * np.sin(3 * y) + 0.05 * z * z, y + 0.1 * np.sin(2 * x) * z, z + 0.07 * np.cos(2 * x + y)], 1
    )


def _warped(name):
    m = _straight(name)
    return jv.Mesh(_warp(m.points), m.cells, name).validate()


def _random_xi(name, n, rng, margin=0.0):
    """Random reference coordinates inside the cell (at least `margin` from its faces)."""
    e = jv.element_type(name)
    if e.is_simplex:
        lam = rng.dirichlet(np.ones(e.dim + 1), size=n)
        lam = margin + (1.0 - (e.dim + 1) * margin) * lam
        return lam[:, 1:]
    return rng.uniform(-1.0 + margin, 1.0 - margin, size=(n, e.dim))


def _points_in_elements(mesh, n, rng, margin=0.0):
    """(element, xi, X) of `n` random material points, mapped by the mesh's own geometry."""
    element = rng.integers(0, mesh.n_cells, n)
    xi = _random_xi(mesh.cell_type, n, rng, margin)
    N = jax.vmap(mesh.element.shape_functions)(jnp.asarray(xi))
    X = np.einsum("na,nad->nd", N, np.asarray(mesh.points)[np.asarray(mesh.cells)[element]])
    return element, xi, X


def _affine(dim, rng):
    A = np.eye(dim) + 0.3 * rng.standard_normal((dim, dim))
    return A, rng.standard_normal(dim)


@pytest.mark.parametrize("name", NAMES)
def test_host_shape_functions_are_the_library_ones(name):
    e = jv.element_type(name)
    xi = np.random.default_rng(0).uniform(-1.2, 1.2, size=(50, e.dim))
    N, dN = _polynomial(name).evaluate(xi)
    np.testing.assert_allclose(N, jax.vmap(e.shape_functions)(xi), rtol=0, atol=1e-14)
    np.testing.assert_allclose(dN, jax.vmap(e.shape_gradients)(xi), rtol=0, atol=1e-13)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("geometry", ["straight", "warped"])
def test_linear_field_is_interpolated_exactly(name, geometry):
    """x = A X + b is in every isoparametric space: positions, displacements, F and E
    at random interior points are exact, also on curved elements."""
    rng = np.random.default_rng(1)
    mesh = _straight(name) if geometry == "straight" else _warped(name)
    _, _, P = _points_in_elements(mesh, 200, rng)
    if geometry == "straight":  # and points drawn in the box, not through the elements
        P = np.concatenate([P, ORIGIN[mesh.dim] + SIZE[mesh.dim] * rng.uniform(size=(200, mesh.dim))])
    probe = jv.Probe(mesh, P)
    A, b = _affine(mesh.dim, rng)
    x = np.asarray(mesh.points) @ A.T + b
    np.testing.assert_allclose(probe.positions(x), P @ A.T + b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(probe.displacements(x), P @ (A - np.eye(mesh.dim)).T + b, rtol=0, atol=1e-12)
    F = probe.deformation_gradient(x)
    assert F.shape == (len(P), mesh.dim, mesh.dim)
    np.testing.assert_allclose(F, np.broadcast_to(A, F.shape), rtol=0, atol=1e-12)
    E = 0.5 * (A.T @ A - np.eye(mesh.dim))
    np.testing.assert_allclose(probe.green_strain(x), np.broadcast_to(E, F.shape), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", QUADRATIC)
def test_quadratic_field_is_exact_on_quadratic_elements(name):
    """On affine element maps every quadratic element (serendipity included) holds the
    complete quadratic polynomials: a quadratic motion and its gradient are exact."""
    rng = np.random.default_rng(2)
    mesh = _straight(name)
    d = mesh.dim
    P = ORIGIN[d] + SIZE[d] * rng.uniform(size=(300, d))
    c, B = rng.standard_normal(d), np.eye(d) + 0.2 * rng.standard_normal((d, d))
    Q = 0.3 * rng.standard_normal((d, d, d))
    Q = 0.5 * (Q + np.swapaxes(Q, 1, 2))

    def motion(X):
        return c + X @ B.T + np.einsum("ijk,nj,nk->ni", Q, X, X)

    probe = jv.Probe(mesh, P)
    x = motion(np.asarray(mesh.points))
    np.testing.assert_allclose(probe.positions(x), motion(P), rtol=0, atol=1e-12)
    grad = B + 2.0 * np.einsum("ijk,nk->nij", Q, P)
    np.testing.assert_allclose(probe.deformation_gradient(x), grad, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_points_are_found_in_their_element(name):
    """Points strictly inside an element of a curved mesh are assigned to it, with the
    reference coordinates they were made from."""
    rng = np.random.default_rng(3)
    mesh = _warped(name)
    element, xi, P = _points_in_elements(mesh, 100, rng, margin=0.02)
    probe = jv.Probe(mesh, P)
    np.testing.assert_array_equal(probe.element, element)
    np.testing.assert_allclose(probe.xi, xi, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["quad9", "tri6", "hex20", "tet4"])
def test_nodes_and_boundary_points(name):
    """Mesh nodes (on faces, edges and corners shared by several elements) are accepted
    and read the nodal values exactly."""
    mesh = _warped(name)
    x = np.asarray(mesh.points) + np.random.default_rng(4).standard_normal(mesh.points.shape)
    probe = jv.Probe(mesh, mesh.points)
    np.testing.assert_allclose(probe.positions(x), x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(probe.displacements(x), x - np.asarray(mesh.points), rtol=0, atol=1e-12)
    # The node positions with the rounding of a user's coordinates are still inside.
    jv.Probe(mesh, np.asarray(mesh.points) * (1.0 + 1e-14))


@pytest.mark.parametrize("dim", [2, 3])
def test_points_outside_are_rejected(dim):
    """The L-shape's notch lies inside the bounding box but outside the body."""
    mesh = jv.lshape_mesh(dim, 1, "tri6" if dim == 2 else "tet10")
    inside = [1.0, 1.0] + [1.5] * (dim - 2)
    notch = [5.0, 5.0] + [1.5] * (dim - 2)
    beyond = [3.0 + 1e-6, 4.0] + [1.5] * (dim - 2)  # just past the inner face x = 3
    far = [-20.0, 1.0] + [1.5] * (dim - 2)
    jv.Probe(mesh, [inside, [3.0, 4.0] + [1.5] * (dim - 2)])  # on the face: fine
    with pytest.raises(ValueError) as info:
        jv.Probe(mesh, [inside, notch, beyond, inside, far])
    message = str(info.value)
    assert "3 of 5 points lie outside the body" in message
    assert "point 1 at (5, 5" in message and "point 2 at (3.000001, 4" in message
    assert "tol=1e-08" in message
    with pytest.raises(ValueError, match="tol=0.01"):
        jv.Probe(mesh, [notch], tol=0.01)


def test_bad_arguments():
    mesh = jv.rectangle(2, 2)
    with pytest.raises(ValueError, match=r"points must have shape \(m, 2\)"):
        jv.Probe(mesh, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="point 1 has non-finite coordinates"):
        jv.Probe(mesh, [[0.5, 0.5], [np.nan, 0.5]])
    with pytest.raises(ValueError, match="tol must be"):
        jv.Probe(mesh, [[0.5, 0.5]], tol=-1.0)
    probe = jv.Probe(mesh, [0.5, 0.5])  # one point
    assert probe.n_points == 1
    with pytest.raises(ValueError, match=r"x must hold node positions of shape \(n_nodes, dim\) = \(9, 2\)"):
        probe.positions(np.zeros((8, 2)))


def test_frames_vmap_and_jit():
    """A stack of frames gives the frames' results; vmap and jit agree with it."""
    rng = np.random.default_rng(5)
    mesh = _warped("hex8")
    _, _, P = _points_in_elements(mesh, 7, rng)
    probe = jv.Probe(mesh, P)
    xs = np.asarray(mesh.points) + 0.1 * rng.standard_normal((4, mesh.n_nodes, 3))
    for method in (probe.positions, probe.displacements, probe.deformation_gradient, probe.green_strain):
        stacked = method(xs)
        assert stacked.shape[:2] == (4, 7)
        for k in range(4):
            np.testing.assert_allclose(stacked[k], method(xs[k]), rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(jax.vmap(method)(xs), stacked, rtol=1e-14, atol=1e-15)
    jitted = jax.jit(lambda p, x: p.green_strain(x))(probe, xs)
    np.testing.assert_allclose(jitted, probe.green_strain(xs), rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("name", ["quad8", "tet10"])
def test_gradients_against_central_differences(name):
    """Reverse (`jax.grad`) and forward (`jax.jvp`) derivatives of a functional of the
    probes' displacements and strains against central differences."""
    rng = np.random.default_rng(6)
    mesh = _warped(name)
    _, _, P = _points_in_elements(mesh, 5, rng)
    probe = jv.Probe(mesh, P)
    x0 = jnp.asarray(np.asarray(mesh.points) + 0.05 * rng.standard_normal(mesh.points.shape))
    w = jnp.asarray(rng.standard_normal((5, mesh.dim)))

    @jax.jit
    def f(x):
        E = probe.green_strain(x)
        return jnp.sum(E * E) + jnp.sum(w * probe.displacements(x)) + jnp.sum(probe.positions(x) ** 3)

    direction = jnp.asarray(rng.standard_normal(x0.shape))
    fd_check(f, x0, direction, eps=1e-4, order=4, rtol=1e-8)  # forward mode
    reverse = jnp.vdot(jax.grad(f)(x0), direction)
    fd_check(f, x0, direction, eps=1e-4, order=4, rtol=1e-8, derivative=reverse)
