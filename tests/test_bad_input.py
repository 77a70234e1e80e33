"""Bad input that used to fail deep inside `simulate` (issue 15): a `load_time` that JAX
cannot trace or that does not return a scalar is rejected when the scene is built."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv


def _square():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return jv.Mesh(points=pts, cells=np.array([[0, 1, 2, 3]]), cell_type="quad4")


def _scene(load_time, load=np.ones((4, 2)), mesh=None):
    mesh = _square() if mesh is None else mesh
    return jv.Scene(mesh, jv.NeoHooke(lam=1.0, mu=1.0), 1.0, load=load, load_time=load_time)


FIX = r"jnp\.where\(t < 3\.0, 1\.0, 0\.0\)"


@pytest.mark.parametrize("load_time, pattern", [
    (lambda t: 1.0 if t < 3 else 0.0, r"TracerBoolConversionError.*JAX-traceable function of one scalar time t "
                                      r"returning a scalar.*Python `if`.*" + FIX),
    (lambda t: float(t) * 2.0, r"could not be traced by JAX.*`float\(\)`.*" + FIX),
    (lambda t: np.sin(t), r"TracerArrayConversionError.*numpy on t.*" + FIX),
    (lambda: 1.0, r"failed on a traced scalar t \(TypeError.*" + FIX),
    (lambda t: jnp.ones(3) * t, r"must return a scalar \(shape \(\)\), got shape \(3,\)"),
    (lambda t: (t, 2.0 * t), r"must return one scalar, got a tuple of 2 values"),
    (lambda t: 1j * t, r"real scalar, got dtype complex128"),
])
def test_untraceable_or_nonscalar_load_time(load_time, pattern):
    with pytest.raises(ValueError, match=pattern):
        _scene(load_time)


def test_load_time_not_callable():
    with pytest.raises(TypeError, match=r"load_time must be a function of t, got float 2\.0"):
        _scene(2.0)


@pytest.mark.parametrize("load_time", [lambda t: jnp.where(t < 3.0, 1.0, 0.0), lambda t: 1.0,
                                       lambda t: jnp.sin(2.0 * t), lambda t: t > 1.0])
def test_traceable_load_time_accepted(load_time):
    scene = _scene(load_time)
    assert scene.external_force(jnp.asarray(0.5)).shape == (4, 2)


def test_scene_with_load_time_under_vmap_grad_jit():
    """The construction check traces load_time abstractly, also when the scene itself is
    built inside a transformation from traced parameters."""

    mesh = _square()

    def total_force(s):
        scene = _scene(lambda t: jnp.sin(s * t), load=s * np.ones((4, 2)), mesh=mesh)
        return jnp.sum(jax.vmap(scene.external_force)(jnp.array([0.25, 0.5])))

    s = jnp.array([0.5, 1.0, 2.0])
    expected = 8 * s * (jnp.sin(0.25 * s) + jnp.sin(0.5 * s))
    np.testing.assert_allclose(jax.vmap(total_force)(s), expected, rtol=1e-14)
    np.testing.assert_allclose(jax.jit(total_force)(2.0), expected[2], rtol=1e-14)
    d = 8 * (np.sin(0.5) + np.sin(1.0) + 2.0 * (0.25 * np.cos(0.5) + 0.5 * np.cos(1.0)))
    np.testing.assert_allclose(jax.grad(total_force)(2.0), d, rtol=1e-12)
