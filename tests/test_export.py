"""Traced programs kept on disk (`jaxvisco._export`): what the key sees, what it refuses,
and damaged entries. The second-process round trip of the time loop is in test_host_lu."""

import json
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


class _Planted:
    """A pickle that, if ever loaded, leaves a marker file (the reproduction of #63)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _use_cache_dir(path):
    prev = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(path))
    _export.clear()
    return prev


def test_planted_entries_are_never_executed(tmp_path):
    """Entries hold data, never a pickle: a planted pickle with a side effect, random
    bytes, and a header naming a class outside the registered outputs are each a miss
    (the entry is traced and written again), and nothing of them runs."""
    import pickle

    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    marker = tmp_path / "marker"
    prev = _use_cache_dir(cache)
    try:
        expected = np.asarray(_scaled(jnp.arange(4.0), 2))
        (entry,) = os.listdir(cache / "jaxvisco-export")
        path = cache / "jaxvisco-export" / entry
        good = path.read_bytes()
        assert good.startswith(_export._MAGIC)
        n = int.from_bytes(good[len(_export._MAGIC):len(_export._MAGIC) + 8], "little")
        start = len(_export._MAGIC) + 8
        header = json.loads(good[start:start + n])
        header["out_skeleton"] = {"module": "os.system", "fields": {}}  # a well-formed entry naming code
        head = json.dumps(header).encode()
        forged = _export._MAGIC + len(head).to_bytes(8, "little") + head + good[start + n:]
        rng = np.random.default_rng(0)
        for planted in (pickle.dumps(_Planted(marker)), rng.bytes(4096), forged):
            path.write_bytes(planted)
            _export.clear()
            before = dict(_export.stats)
            np.testing.assert_array_equal(_scaled(jnp.arange(4.0), 2), expected)
            assert not marker.exists()
            assert _export.stats["loaded"] == before["loaded"]
            assert _export.stats["exported"] == before["exported"] + 1  # a miss: traced again, stored again
            assert path.read_bytes().startswith(_export._MAGIC)
    finally:
        jax.config.update("jax_compilation_cache_dir", prev)
        _export.clear()


def test_entry_data_round_trip():
    """What an entry stores of a time loop's output: the `Solution`'s static part and
    structure, rebuilt from data as the same object."""
    scene = jv.scenes.lshape(2, 1)
    sol = jv.simulate(scene, jv.eG(1), t1=0.2, dt0=0.1)
    dyn, static = eqx.partition((sol, jnp.zeros(())), eqx.is_array)
    skeleton = jax.tree_util.tree_map(lambda _: _export._Leaf(), dyn)
    for obj in (static, skeleton):
        back = _export._from_data(json.loads(json.dumps(_export._to_data(obj))))
        assert jax.tree_util.tree_structure(back) == jax.tree_util.tree_structure(obj)
    back = _export._from_data(json.loads(json.dumps(_export._to_data(static))))
    assert back[0].integrator == sol.integrator and isinstance(back[0], jv.Solution)
    cells = scene.disc.cells
    assert _export._from_data(_export._to_data((cells, 3, None))) == (cells, 3, None)
    for bad in (_outside_jaxvisco, object(), np.array(["a"]), {1: 2}):
        with pytest.raises(_export.Unstorable):
            _export._to_data(bad)


def test_a_directory_others_can_write_is_refused(tmp_path, monkeypatch):
    """A cache directory writable by group or others (or below a parent that is, with no
    sticky bit) is refused with one warning that names it, its mode and owner and the
    fix; nothing is cached and runs go on. `shared=True` opts in deliberately."""
    monkeypatch.delenv("JAXVISCO_CACHE_SHARED", raising=False)
    prev = jax.config.jax_compilation_cache_dir
    open_dir = tmp_path / "open"
    open_dir.mkdir()
    os.chmod(open_dir, 0o777)
    below = tmp_path / "wide"
    below.mkdir()
    os.chmod(below, 0o777)
    (below / "cache").mkdir(mode=0o700)
    sticky = tmp_path / "sticky"
    sticky.mkdir()
    os.chmod(sticky, 0o1777)
    try:
        with pytest.warns(jv.CacheWarning) as w:
            assert jv.enable_compilation_cache(open_dir) is None
        (msg,) = [str(x.message) for x in w]
        assert str(open_dir) in msg and "777" in msg and "owner" in msg and "chmod 700" in msg and "\n" not in msg
        assert jax.config.jax_compilation_cache_dir == prev
        with pytest.warns(jv.CacheWarning, match="parent .*wide"):
            assert jv.enable_compilation_cache(below / "cache") is None
        assert jv.enable_compilation_cache(sticky / "cache") == str(sticky / "cache")  # like /tmp
        # pointed at it through JAX's own option: jaxvisco stores no traced program there
        _use_cache_dir(open_dir)
        before = dict(_export.stats)
        with pytest.warns(jv.CacheWarning, match="not cached"):
            np.testing.assert_array_equal(_scaled(jnp.arange(3.0), 1), [0.0, 1.0, 3.0])
        assert _export.stats == before and not (open_dir / "jaxvisco-export").exists()
        # a shared cache, deliberately
        assert jv.enable_compilation_cache(open_dir, shared=True) == str(open_dir)
        _export.clear()
        np.testing.assert_array_equal(_scaled(jnp.arange(3.0), 1), [0.0, 1.0, 3.0])
        assert _export.stats["exported"] == before["exported"] + 1
    finally:
        _export._TRUSTED.discard(str(open_dir))
        jax.config.update("jax_compilation_cache_dir", prev)
        _export.clear()


def test_a_new_default_directory_is_private(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXVISCO_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "a" / "b"))
    prev = jax.config.jax_compilation_cache_dir
    try:
        path = jv.enable_compilation_cache()
        assert path == str(tmp_path / "a" / "b" / "jaxvisco")
        for p in (tmp_path / "a", tmp_path / "a" / "b", tmp_path / "a" / "b" / "jaxvisco"):
            assert os.stat(p).st_mode & 0o777 == 0o700, p
    finally:
        jax.config.update("jax_compilation_cache_dir", prev)
        _export.clear()


def test_the_command_line_says_so_in_one_line(tmp_path, monkeypatch, capsys):
    from jaxvisco.cli import main

    open_dir = tmp_path / "open"
    open_dir.mkdir()
    os.chmod(open_dir, 0o777)
    monkeypatch.setenv("JAXVISCO_CACHE_DIR", str(open_dir))
    monkeypatch.delenv("JAXVISCO_CACHE_SHARED", raising=False)
    prev = jax.config.jax_compilation_cache_dir
    try:
        assert main(["scene-template"]) == 0
    finally:
        jax.config.update("jax_compilation_cache_dir", prev)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxvisco: warning: compilation cache not used:") and str(open_dir) in err[0]
