"""Traced programs kept on disk (`jaxvisco._export`): what the key sees, what it refuses,
and damaged entries. The second-process round trip of the time loop is in test_host_lu."""

import math
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv
from jaxvisco import _export
from jaxvisco._config import compiler_options, jit


def _key(args, kwargs=None):
    dyn, static = eqx.partition((args, kwargs or {}), eqx.is_array)
    return _export._key("test", static, jax.tree_util.tree_map(_export._Aval, dyn), compiler_options())


def test_key_sees_every_static_part_and_every_shape():
    scene = jv.scenes.lshape(2, 1)
    base = _key((scene, jv.eG(1), jv.NewtonKrylov()))
    assert base == _key((jv.scenes.lshape(2, 1), jv.eG(1), jv.NewtonKrylov()))  # same inputs, same key
    # Same shapes, other connectivity: a cell's nodes in another (still valid) order.
    cells = np.asarray(scene.mesh.cells).copy()
    cells[0] = np.roll(cells[0], 2)
    turned = jv.Scene(jv.Mesh(scene.mesh.points, cells, scene.mesh.cell_type), scene.material, scene.density,
                      velocities=scene.v0)
    others = [
        _key((scene, jv.eG(2), jv.NewtonKrylov())),
        _key((scene, jv.cG(1), jv.NewtonKrylov())),
        _key((scene, jv.eG(1), jv.NewtonKrylov(rtol=1e-11))),
        _key((turned, jv.eG(1), jv.NewtonKrylov())),
        _key((jv.scenes.lshape(2, 2), jv.eG(1), jv.NewtonKrylov())),
        _key((scene, jv.eG(1), jv.NewtonKrylov()), {"n": 3}),
    ]
    assert len({base, *others}) == 1 + len(others)
    # Array values are arguments of the program, not part of it: other values, same key.
    assert _key((jnp.ones(3),)) == _key((jnp.zeros(3),)) != _key((jnp.zeros(4),))
    assert _key((jnp.zeros(3),)) != _key((jnp.zeros(3, dtype=jnp.int64),))


def _outside_jaxvisco(x):
    return x


def test_code_the_key_cannot_see_is_refused():
    with pytest.raises(_export.Uncacheable, match="lambda"):
        _key((jnp.zeros(2), lambda x: x))
    with pytest.raises(_export.Uncacheable, match="_outside_jaxvisco"):
        _key((jnp.zeros(2), _outside_jaxvisco))
    assert _key((jnp.zeros(2), math.hypot))  # a function of the standard library is named safely


@jit(export=True)
def _scaled(x, n):
    return jnp.cumsum(x) * n


def test_damaged_entry_is_written_again(tmp_path):
    prev = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    _export.clear()
    try:
        before = dict(_export.stats)
        np.testing.assert_array_equal(_scaled(jnp.arange(4.0), 2), [0.0, 2.0, 6.0, 12.0])
        assert _export.stats["exported"] == before["exported"] + 1
        (entry,) = os.listdir(tmp_path / "jaxvisco-export")
        path = tmp_path / "jaxvisco-export" / entry
        path.write_bytes(b"not a pickle")
        _export.clear()
        np.testing.assert_array_equal(_scaled(jnp.arange(4.0), 2), [0.0, 2.0, 6.0, 12.0])
        assert _export.stats["exported"] == before["exported"] + 2 and _export.stats["loaded"] == before["loaded"]
        assert path.read_bytes() != b"not a pickle" and os.listdir(tmp_path / "jaxvisco-export") == [entry]
        _export.clear()
        np.testing.assert_array_equal(_scaled(jnp.arange(4.0), 3), [0.0, 3.0, 9.0, 18.0])  # another static n
        _export.clear()
        np.testing.assert_array_equal(_scaled(jnp.arange(4.0), 2), [0.0, 2.0, 6.0, 12.0])
        assert _export.stats["loaded"] == before["loaded"] + 1
    finally:
        jax.config.update("jax_compilation_cache_dir", prev)
        _export.clear()


def test_pattern_recorder_is_per_thread():
    """The host patterns a program names are recorded per thread, so two threads that
    trace at once (`jaxvisco paper` runs its integrators in two) each store their own."""
    import threading

    mine = _export._recorder.patterns = []
    try:
        other = threading.Thread(target=lambda: _export.record_pattern("position_pattern", ("other",)))
        other.start()
        other.join()
        assert mine == []
        _export.record_pattern("position_pattern", ("mine",))
        assert mine == [("position_pattern", ("mine",))]
    finally:
        _export._recorder.patterns = None
