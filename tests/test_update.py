"""Array updates without scatters (`_fem._update`): the same values as JAX's indexed
updates, and a time loop that XLA:CPU does not have to expand scatters in."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import capture_time_loop

import jaxvisco as jv
from jaxvisco._fem._update import pad_to_3d, put, put_or_drop


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_put_equals_an_indexed_set(axis):
    x = jnp.asarray(np.random.default_rng(0).normal(size=(4, 5, 3)))
    for i in range(x.shape[axis]):
        v = jnp.full(x.shape[:axis] + x.shape[axis + 1:], 7.0 + i)
        want = x.at[(slice(None),) * axis + (i,)].set(v)
        np.testing.assert_array_equal(put(x, i, v, axis=axis), want)
        np.testing.assert_array_equal(jax.jit(lambda x, i, v: put(x, i, v, axis=axis))(x, i, v), want)


def test_put_or_drop_equals_a_dropping_set():
    x = jnp.arange(6.0)
    for i in (-3, -1, 0, 2, 5, 6, 9):
        want = x.at[i].set(-1.0, mode="drop") if 0 <= i else x  # (negative indices: dropped here, not wrapped)
        np.testing.assert_array_equal(jax.jit(put_or_drop)(x, i, -1.0), want)


def test_pad_to_3d_embeds_the_plane_block():
    a = jnp.asarray(np.random.default_rng(1).normal(size=(2, 4, 2, 2)))
    want = jnp.zeros((2, 4, 3, 3)).at[..., :2, :2].set(a)
    np.testing.assert_array_equal(pad_to_3d(a), want)
    b = jnp.ones((3, 3))
    assert pad_to_3d(b) is b


@pytest.mark.timeout(300)
@pytest.mark.parametrize("scheme", [jv.eG(1), jv.eG(2)], ids=lambda s: s.name)
def test_time_loop_has_no_scatter(monkeypatch, scheme):
    """The paper scene's compiled time loop (default solver) holds no scatter: XLA:CPU
    expands each into a while loop of its own, with a simplification pass after the
    expansion (65 of them cost ~0.5 s of the cold first call's 6.5 s)."""
    run, captured = capture_time_loop(monkeypatch)
    jv.simulate(jv.scenes.lshape(), scheme, t1=0.2, dt0=0.1)
    text = run.lower(*captured["args"], **captured["kwargs"]).as_text()
    assert "dynamic_update_slice" in text  # (the updates are there, as in-place slices)
    assert text.count("stablehlo.scatter") == 0, text.count("stablehlo.scatter")
