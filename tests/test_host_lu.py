"""The host sparse LU behind XLA foreign-function targets (issue 16): the time loop is
served from the exported-program store and JAX's persistent compilation cache in a new
process, and the FFI path gives the same steps as the `pure_callback` path."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import jaxvisco as jv
import jaxvisco._solver._sparse as sparse
from jaxvisco import _config

from helpers import subprocess_env

pytestmark = pytest.mark.skipif(sparse._hostlu is None and not os.environ.get("CI"),
                                reason="jaxvisco was built without its FFI extension")


def test_extension_built():
    """`pip install .` builds the extension (it is optional only so that an install
    without a compiler still works); CI must not silently fall back to the callback."""
    assert sparse._hostlu is not None and sparse.backend() == "ffi"

SCRIPT = r"""
import json, logging, sys
import jax
jax.config.update("jax_enable_x64", True)
seen = []
class Keep(logging.Handler):
    def emit(self, record):
        seen.append(record.getMessage())
log = logging.getLogger("jax._src.compiler")
log.setLevel(logging.DEBUG)
log.addHandler(Keep())
events = {"requests": 0, "hits": 0}
def count(name, **kw):
    key = {"/jax/compilation_cache/compile_requests_use_cache": "requests",
           "/jax/compilation_cache/cache_hits": "hits"}.get(name)
    if key:
        events[key] += 1
jax.monitoring.register_event_listener(count)
compiled = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: compiled.append(kw.get("fun_name")) if name.endswith("backend_compile_duration") else None)
import jaxvisco as jv
jv.enable_compilation_cache(sys.argv[1])
from jaxvisco import _export
scene = jv.scenes.lshape(dim=2, refinement=1)
del compiled[:]
sol = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1)
events["call_compiled"] = list(compiled)
run = [m for m in seen if "'jit__run'" in m or "'jit_exported__run'" in m]
print("RESULT " + json.dumps(dict(log=run, x=float(abs(sol.x[-1]).sum()), H=float(sol.energy[-1]),
                                  export=_export.stats, **events)))
"""


def _run(tmp_path, backend):
    env = subprocess_env()
    env.pop("JAXVISCO_CACHE_DIR")
    env["JAXVISCO_HOST_LU"] = backend
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    p = subprocess.run([sys.executable, str(script), str(tmp_path / "cache")], capture_output=True, text=True,
                       env=env, timeout=600, cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(next(line[7:] for line in p.stdout.splitlines() if line.startswith("RESULT ")))


def test_second_process_served_from_cache(tmp_path):
    """The first process traces the time loop once (`jax.export`), stores the traced
    program and its compiled form; the second loads both: it neither traces nor compiles
    the loop, and computes the same numbers."""
    first = _run(tmp_path, "ffi")
    assert not any("hit" in m for m in first["log"]), first["log"]
    assert first["export"] == {"exported": 1, "loaded": 0, "uncacheable": 0}, first["export"]
    assert len([f for f in os.listdir(tmp_path / "cache") if f.startswith("jit_exported__run-")]) == 1
    assert len(os.listdir(tmp_path / "cache" / "jaxvisco-export")) == 1
    # what the first call compiles besides the loop: the initial momenta and the probe of
    # XLA's options, no small program per host value (`_config.device_array`; acee867 compiled 12)
    assert len(first["call_compiled"]) <= 3, first["call_compiled"]
    second = _run(tmp_path, "ffi")
    assert second["export"] == {"exported": 0, "loaded": 1, "uncacheable": 0}, second["export"]
    assert any("Persistent compilation cache hit for 'jit_exported__run'" in m for m in second["log"]), second["log"]
    assert second["x"] == first["x"] and second["H"] == first["H"]
    # and so are the small programs around the loop (each compiles in milliseconds, below
    # JAX's default threshold of a second for caching; `enable_compilation_cache` lowers it):
    # the second process compiles nothing
    assert second["hits"] == second["requests"] > 1, second
    # #63's reproduction: an entry overwritten with a pickle that would leave a marker
    # when loaded. The next process does not run it: a miss, traced and stored again,
    # the same numbers (JAX's compiled program of the loop is still found).
    (entry,) = os.listdir(tmp_path / "cache" / "jaxvisco-export")
    marker = tmp_path / "marker"
    (tmp_path / "cache" / "jaxvisco-export" / entry).write_bytes(
        b"cposix\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.")  # pickle protocol 0: os.system(...)
    planted = _run(tmp_path, "ffi")
    assert not marker.exists()
    assert planted["export"] == {"exported": 1, "loaded": 0, "uncacheable": 0}, planted["export"]
    assert planted["x"] == first["x"] and planted["H"] == first["H"]
    # the pure_callback path is what JAX refuses to cache (and jax.export to serialize)
    callback = _run(tmp_path, "callback")
    assert any("'jit__run' because it uses host callbacks" in m for m in callback["log"]), callback["log"]
    assert callback["export"]["exported"] == 0 and callback["export"]["loaded"] == 0, callback["export"]
    assert callback["x"] == first["x"] and callback["H"] == first["H"]


def _held_scene(dim):
    scene = jv.scenes.lshape(dim=dim, refinement=1)
    X = np.asarray(scene.mesh.points)
    fixed = np.zeros(X.shape, bool)
    fixed[X[:, 1] == X[:, 1].min()] = True
    return jv.Scene(scene.mesh, scene.material, scene.density, velocities=scene.v0, fixed=fixed)


def _both_paths(monkeypatch, run):
    """`run()` on the foreign-function path and on the callback path.

    Both are compiled with XLA's default options: the two programs differ around the
    solve (a foreign-function call against a host callback), and with jaxvisco's
    loop-emitter option (`_config.compiler_options`) XLA's element-wise code around it
    rounded differently in the two (x by 1.8e-15 after 3 steps of cG(2)); with XLA's
    default code generator both round alike, so what is compared is the LU binding
    itself, bit for bit."""
    out = {}
    monkeypatch.setenv("JAXVISCO_XLA_OPTIONS", "off")
    _config.compiler_options.cache_clear()
    try:
        for backend in ("ffi", "callback"):
            monkeypatch.setenv("JAXVISCO_HOST_LU", backend)
            jax.clear_caches()
            out[backend] = run()
    finally:
        monkeypatch.undo()
        _config.compiler_options.cache_clear()
        jax.clear_caches()
    return out["ffi"], out["callback"]


# CI compares one case (it compiles twice); `-m slow` runs the whole matrix, 3D included.
CASES = [(2, "cG", 2, True)]
SLOW_CASES = [(d, s, k, held) for d in (2, 3) for s in ("cG", "eG") for k in (1, 2, 3) for held in (False, True)
              if (d, s, k, held) not in CASES]


def _compare(monkeypatch, dim, scheme, k, held):
    scene = _held_scene(dim) if held else jv.scenes.lshape(dim=dim, refinement=1)
    integrator = jv.eG(k) if scheme == "eG" else jv.cG(k)
    a, b = _both_paths(monkeypatch, lambda: jv.simulate(scene, integrator, t1=0.3, dt0=0.1,
                                                        saveat=jv.SaveAt(gamma=True)))
    for key in ("x", "p", "gamma", "energy", "newton_iterations", "krylov_iterations"):
        np.testing.assert_array_equal(np.asarray(getattr(a, key)), np.asarray(getattr(b, key)), err_msg=key)


@pytest.mark.parametrize("dim, scheme, k, held", CASES)
def test_ffi_path_equals_callback_path(monkeypatch, dim, scheme, k, held):
    """Both paths run the same SuperLU code: the same iterations and the same end state, bit for bit."""
    _compare(monkeypatch, dim, scheme, k, held)


@pytest.mark.slow
@pytest.mark.parametrize("dim, scheme, k, held", SLOW_CASES)
def test_ffi_path_equals_callback_path_all(monkeypatch, dim, scheme, k, held):
    _compare(monkeypatch, dim, scheme, k, held)


@pytest.mark.slow
def test_ffi_gradient(monkeypatch):
    """Transposed solves (reverse mode through the implicit step derivative) through the
    FFI targets equal the callback path's (CI checks gradients through the FFI path
    against finite differences in test_gradients.py)."""
    scene = jv.scenes.lshape(dim=2, refinement=1)

    def loss(eta):
        sc = jv.with_parameters(scene, {"eta_dev": eta})
        return jv.simulate(sc, jv.eG(1), t1=0.2, dt0=0.1).dissipated[-1]

    a, b = _both_paths(monkeypatch, lambda: jax.value_and_grad(loss)(5e4))
    assert float(a[0]) == float(b[0]) and float(a[1]) == float(b[1]) and float(a[1]) != 0.0


def _superlu_solves(monkeypatch, run):
    """`run()` with the extension's triangular solves, then with SuperLU's own (the path
    of factors too large to publish: the foreign-function target hands each solve to
    Python, as every solve went before the extension solved)."""
    out = []
    try:
        for limit in (sparse.PUBLISH_NNZ, 0):
            monkeypatch.setattr(sparse, "PUBLISH_NNZ", limit)
            jax.clear_caches()
            out.append(run())
    finally:
        monkeypatch.undo()
        jax.clear_caches()
    return out


SOLVE_CASES = [(2, "eG", 2, True)]
SLOW_SOLVE_CASES = [c for c in SLOW_CASES + CASES if c not in SOLVE_CASES]


def _compare_solves(monkeypatch, dim, scheme, k, held):
    scene = _held_scene(dim) if held else jv.scenes.lshape(dim=dim, refinement=1)
    integrator = jv.eG(k) if scheme == "eG" else jv.cG(k)
    a, b = _superlu_solves(monkeypatch, lambda: jv.simulate(scene, integrator, t1=0.5, dt0=0.1,
                                                             saveat=jv.SaveAt(gamma=True)))
    assert int(a.n_steps) == int(b.n_steps) == 5
    for key in ("newton_iterations", "chord_iterations"):
        np.testing.assert_array_equal(np.asarray(getattr(a, key)), np.asarray(getattr(b, key)), err_msg=key)
    for key in ("x", "p", "gamma", "energy"):
        u, v = np.asarray(getattr(a, key)), np.asarray(getattr(b, key))
        np.testing.assert_allclose(u, v, rtol=0, atol=1e-9 * np.abs(v).max(), err_msg=key)


@pytest.mark.parametrize("dim, scheme, k, held", SOLVE_CASES)
def test_extension_solves_equal_superlu_solves(monkeypatch, dim, scheme, k, held):
    """The extension's triangular solves against SuperLU's own (issue 16: the new solver
    path against the old): the same iterations and the same states to the Newton
    tolerance (rtol 1e-10; bound 1e-9 of each field's largest value; measured 2e-16 to
    1e-14 on the CI case)."""
    _compare_solves(monkeypatch, dim, scheme, k, held)


@pytest.mark.slow
@pytest.mark.parametrize("dim, scheme, k, held", SLOW_SOLVE_CASES)
def test_extension_solves_equal_superlu_solves_all(monkeypatch, dim, scheme, k, held):
    _compare_solves(monkeypatch, dim, scheme, k, held)
