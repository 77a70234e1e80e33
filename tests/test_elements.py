import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvisco._fem._elements import ElementType, element_type
from jaxvisco._fem._mesh import Mesh
from jaxvisco._fem._quadrature import gauss_legendre, quadrature

NAMES = ["tri3", "quad4", "tet4", "hex8", "tri6", "quad8", "quad9", "tet10", "hex20", "hex27"]
REF_VOLUME = {"tri": 0.5, "quad": 4.0, "tet": 1 / 6, "hex": 8.0}


def _shape(name):
    return name.rstrip("0123456789")


def _exact_monomial(shape, alpha):
    """Integral of prod x_i^alpha_i over the reference cell."""
    if shape in ("tri", "tet"):
        num = np.prod([math.factorial(a) for a in alpha])
        return num / math.factorial(len(alpha) + sum(alpha))
    return np.prod([0.0 if a % 2 else 2.0 / (a + 1) for a in alpha])


@functools.cache
def _batched(name):
    """Jitted batched shape functions and gradients (eager dispatch is slow)."""
    e = element_type(name)
    return jax.jit(jax.vmap(e.shape_functions)), jax.jit(jax.vmap(e.shape_gradients))


def _random_points(e, n, rng):
    if e.is_simplex:
        x = rng.dirichlet(np.ones(e.dim + 1), size=n)[:, 1:]
    else:
        x = rng.uniform(-1, 1, size=(n, e.dim))
    return x


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_gauss_legendre_unit_interval(n):
    x, w = gauss_legendre(n)
    assert x.shape == w.shape == (n,)
    assert np.all((x > 0) & (x < 1))
    for k in range(2 * n):
        assert np.isclose(np.sum(w * x**k), 1.0 / (k + 1), rtol=0, atol=1e-14)


@pytest.mark.parametrize("bad", [0, -1, 2.0, "3", True])
def test_gauss_legendre_rejects(bad):
    with pytest.raises(ValueError, match="integer >= 1"):
        gauss_legendre(bad)


@pytest.mark.parametrize("shape", ["tri", "quad", "tet", "hex"])
@pytest.mark.parametrize("order", range(0, 7))
def test_quadrature_exact_on_monomials(shape, order):
    dim = 2 if shape in ("tri", "quad") else 3
    p, w = quadrature(shape, order)
    assert p.shape == (len(w), dim) and p.dtype == np.float64
    assert np.isclose(w.sum(), REF_VOLUME[shape], rtol=1e-14)
    for alpha in itertools.product(range(order + 1), repeat=dim):
        if sum(alpha) > order:
            continue
        got = np.sum(w * np.prod(p ** np.array(alpha), axis=1))
        assert abs(got - _exact_monomial(shape, alpha)) < 1e-14, alpha


def test_quadrature_points_inside_and_positive():
    for shape in ("tri", "tet"):
        for order in range(0, 7):
            p, w = quadrature(shape, order)
            assert np.all(w > 0) and np.all(p >= 0) and np.all(p.sum(1) <= 1 + 1e-15)


def test_quadrature_errors():
    with pytest.raises(ValueError, match="'pentagon'.*accepted"):
        quadrature("pentagon", 2)
    with pytest.raises(ValueError, match="order must be an integer >= 0, got -1"):
        quadrature("tri", -1)


@pytest.mark.parametrize("name", NAMES)
def test_element_metadata(name):
    e = element_type(name)
    assert isinstance(e, ElementType) and e.name == name
    assert element_type(e.meshio_name) is e
    assert e.reference_nodes().shape == (e.n_nodes, e.dim)
    assert e.default_order == 2 * e.degree
    p, w = e.quadrature()
    assert np.isclose(w.sum(), REF_VOLUME[_shape(name)], rtol=1e-14)
    assert np.isclose(e.reference_volume, REF_VOLUME[_shape(name)])
    if name in ("quad4", "hex8"):
        assert len(w) == 2**e.dim
    if name in ("quad8", "quad9", "hex20", "hex27"):
        assert len(w) == 3**e.dim


def test_element_type_unknown():
    with pytest.raises(ValueError, match="'hex9'.*accepted.*hex20"):
        element_type("hex9")


@pytest.mark.parametrize("name", NAMES)
def test_shape_function_properties(name):
    e = element_type(name)
    rng = np.random.default_rng(0)
    nodes = e.reference_nodes()
    shape_fn, grad_fn = _batched(name)
    N_nodes = shape_fn(jnp.asarray(nodes))
    np.testing.assert_allclose(N_nodes, np.eye(e.n_nodes), atol=1e-14)
    x = jnp.asarray(_random_points(e, 20, rng))
    N = shape_fn(x)
    dN = grad_fn(x)
    assert N.shape == (20, e.n_nodes) and dN.shape == (20, e.n_nodes, e.dim)
    np.testing.assert_allclose(N.sum(1), 1.0, atol=1e-14)
    np.testing.assert_allclose(dN.sum(1), 0.0, atol=1e-13)
    # Linear completeness: sum_a N_a X_a = x and sum_a dN_a X_a = I.
    np.testing.assert_allclose(N @ nodes, x, atol=1e-14)
    np.testing.assert_allclose(np.einsum("qad,ae->qed", dN, nodes),
                               np.broadcast_to(np.eye(e.dim), (20, e.dim, e.dim)),
                               atol=1e-13)  # fmt: skip
    # Central finite differences.
    h = 1e-6
    for d in range(e.dim):
        step = np.zeros(e.dim)
        step[d] = h
        fd = (shape_fn(x + step) - shape_fn(x - step)) / (2 * h)
        np.testing.assert_allclose(dN[..., d], fd, atol=1e-8)


@pytest.mark.parametrize("name", [n for n in NAMES if element_type(n).degree == 2])
def test_quadratic_completeness(name):
    """Degree-2 elements interpolate quadratics exactly (serendipity: no x^2 y^2 terms)."""
    e = element_type(name)
    nodes = e.reference_nodes()
    f = lambda x: 1 + x[..., 0] ** 2 - 2 * x[..., 0] * x[..., 1] + 3 * x[..., -1] ** 2
    x = jnp.asarray(_random_points(e, 10, np.random.default_rng(1)))
    N = _batched(name)[0](x)
    np.testing.assert_allclose(N @ f(nodes), f(np.asarray(x)), atol=1e-13)


def _distorted_element(e, rng, nonlinear=0.05):
    A = np.eye(e.dim) + 0.3 * rng.standard_normal((e.dim, e.dim))
    if np.linalg.det(A) < 0:
        A[:, 0] *= -1
    b = rng.standard_normal(e.dim)
    ref = e.reference_nodes()
    return A, b, ref @ A.T + b + nonlinear * rng.standard_normal(ref.shape) * (
        e.degree == 1
    )


@pytest.mark.parametrize("name", NAMES)
def test_affine_element_volume_and_gradients(name):
    e = element_type(name)
    rng = np.random.default_rng(42)
    A, b, X = _distorted_element(e, rng, nonlinear=0.0)
    mesh = Mesh(points=X, cells=np.arange(e.n_nodes)[None], cell_type=name).validate()
    assert np.isclose(float(mesh.volume()), abs(np.linalg.det(A)) * e.reference_volume)
    qd = mesh.quadrature_data()
    nq = len(e.quadrature()[1])
    assert qd.N.shape == (nq, e.n_nodes)
    assert qd.dN_dX.shape == (1, nq, e.n_nodes, e.dim) and qd.JxW.shape == (1, nq)
    assert np.isclose(float(qd.JxW.sum()), np.linalg.det(A) * e.reference_volume)
    np.testing.assert_allclose(qd.dN_dX.sum(2), 0.0, atol=1e-12)
    # Gradient of the field X is the identity; of a general affine field, its matrix.
    np.testing.assert_allclose(np.einsum("cqad,ae->cqed", qd.dN_dX, X),
                               np.broadcast_to(np.eye(e.dim), (1, nq, e.dim, e.dim)),
                               atol=1e-12)  # fmt: skip
    B = rng.standard_normal((e.dim, e.dim))
    u = X @ B.T
    np.testing.assert_allclose(np.einsum("cqad,ae->cqed", qd.dN_dX, u)[0, 0], B,
                               atol=1e-12)  # fmt: skip


@pytest.mark.parametrize("name", NAMES)
def test_perturbed_element(name):
    """Non-affine element: volume by an independent fine rule, patch-like gradients."""
    e = element_type(name)
    rng = np.random.default_rng(7)
    A, b, X = _distorted_element(e, rng, nonlinear=0.0)
    X = X + 0.04 * rng.standard_normal(X.shape)
    mesh = Mesh(points=X, cells=np.arange(e.n_nodes)[None], cell_type=name).validate()
    qd = mesh.quadrature_data(order=10)
    assert np.isclose(float(mesh.volume()), float(qd.JxW.sum()), rtol=1e-10)
    np.testing.assert_allclose(qd.dN_dX.sum(2), 0.0, atol=1e-11)
    I = np.broadcast_to(np.eye(e.dim), qd.dN_dX.shape[:2] + (e.dim, e.dim))
    np.testing.assert_allclose(np.einsum("cqad,ae->cqed", qd.dN_dX, X), I, atol=1e-11)
