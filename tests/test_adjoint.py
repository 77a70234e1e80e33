"""The discrete adjoint of a run (issue #59): against the replay adjoint it replaced, under
a memory budget, and from the persistent cache in a second process.

`tests/data/adjoint_reference.json` holds the gradients of the cases below computed by the
replay adjoint (each accepted sub-step re-solved by Newton and differentiated implicitly
with a fresh tangent), the implementation of jaxvisco up to commit 7e4db97. Regenerate
with that checkout on the path: ``PYTHONPATH=<checkout> python tests/test_adjoint.py``.
The adaptive case's steps changed with #62's controller: its reference is that checkout's
gradient along `StepTo` of the accepted steps the case takes now (34 steps; step sizes
are constants of the derivative, so this is the adaptive run's gradient).
"""

import json
import os
import pathlib
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvisco as jv

REFERENCE = pathlib.Path(__file__).parent / "data" / "adjoint_reference.json"
SOLVER = jv.NewtonKrylov(rtol=1e-12)


def _held_scene(dim):
    """The L-shape held at its bottom edge, which slides sideways (a prescribed motion),
    with a dead load ramped up on its top edge."""
    scene = jv.scenes.lshape(dim=dim, refinement=1)
    X = np.asarray(scene.mesh.points)
    fixed = np.zeros(X.shape, bool)
    bottom = X[:, 1] == X[:, 1].min()
    fixed[bottom] = True
    top = X[:, 1] == X[:, 1].max()
    grip = np.zeros(X.shape)
    grip[bottom, 0] = 0.05
    load = np.zeros(X.shape)
    load[top, 0] = 40.0 / top.sum()
    return jv.Scene(scene.mesh, scene.material, scene.density, fixed=fixed,
                    loads=[(load, jv.time_functions.Ramp(0.0, 0.5))],
                    prescribed=[(grip, jv.time_functions.Ramp(0.0, 1.0))])


CASES = {
    "free_2d_fixed": dict(scene=lambda: jv.scenes.lshape(dim=2, refinement=1), t1=2.0, kw=dict(dt0=0.1)),
    "free_2d_adaptive": dict(scene=lambda: jv.scenes.lshape(dim=2, refinement=1), t1=2.0,
                             kw=dict(dt0=0.05, stepsize_controller=jv.PIDController(1e-3, 1e-3, keep_band=1.0),
                                      max_steps=48)),
    "held_2d_fixed": dict(scene=lambda: _held_scene(2), t1=1.0, kw=dict(dt0=0.1)),
    "held_3d_fixed": dict(scene=lambda: _held_scene(3), t1=0.6, kw=dict(dt0=0.1)),
}


def _case(name, **extra):
    """(parameters, loss): log eta_dev, log eta_vol, log mu of the equilibrium branch; the
    loss reads the dissipated energy, free energy, positions and external work."""
    c = CASES[name]
    scene = c["scene"]()

    def loss(z):
        sc = eqx.tree_at(lambda s: (s.material.eta_dev, s.material.eta_vol, s.material.equilibrium.mu), scene,
                         (jnp.exp(z[0]), jnp.exp(z[1]), jnp.exp(z[2])))
        s = jv.simulate(sc, jv.eG(1), t1=c["t1"], solver=SOLVER, **c["kw"], **extra)
        i = s.n_saved - 1  # the last frame (traced, an adaptive run's frames are padded to max_steps)
        return (s.dissipated[i] + s.free_energy[i] + 1e-3 * jnp.mean((s.x[i] - scene.x0) ** 2)
                + 1e-3 * s.external_work[i])

    m = scene.material
    return jnp.log(jnp.array([m.eta_dev, m.eta_vol, m.equilibrium.mu])), loss


def _rel(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b)) / np.abs(np.asarray(b))))


@pytest.mark.timeout(900)
@pytest.mark.parametrize("name", sorted(CASES))
def test_the_adjoint_equals_the_replay_adjoint(name):
    """The same gradient as the replay adjoint to 1e-8 relative (measured 1e-13 to 3e-12):
    fixed and adaptive steps, a free body, and 2D and 3D bodies with held nodes, a moving
    support and a dead load."""
    ref = json.loads(REFERENCE.read_text())[name]
    z, loss = _case(name)
    g = eqx.filter_jit(jax.grad(loss))(z)
    assert _rel(g, ref) <= 1e-8, (np.asarray(g), ref)


@pytest.mark.timeout(900)
def test_forward_mode_equals_the_replay_adjoint():
    """`jax.jacfwd` (the forward sweep, a batch of three tangents) gives the reference
    gradient too (a held 2D body), and `jax.jacrev` of two outputs (the adjoint sweep, a
    batch of two cotangents) its multiples."""
    ref = json.loads(REFERENCE.read_text())["held_2d_fixed"]
    z, loss = _case("held_2d_fixed")
    assert _rel(eqx.filter_jit(jax.jacfwd(loss))(z), ref) <= 1e-8
    rows = eqx.filter_jit(jax.jacrev(lambda z: loss(z) * jnp.array([1.0, -2.0])))(z)
    assert _rel(rows, np.outer([1.0, -2.0], ref)) <= 1e-8


@pytest.mark.timeout(900)
def test_a_small_memory_budget_gives_the_unbounded_gradient():
    """A run of 200 steps whose record does not fit `max_bytes`: it stores states at
    checkpoints and the derivative re-solves the steps between them; the gradient equals
    the one that stores every step (to the Newton tolerance's effect, 1e-8 relative)."""
    from jaxvisco._integrate._differentiable import plan, plan_bytes, record_size

    scene = jv.scenes.lshape(dim=2, refinement=1)
    K = record_size(200)
    small = jv.RecursiveCheckpointAdjoint(max_bytes=200_000)
    stored, checked = plan(jv.RecursiveCheckpointAdjoint(), K, 1, jv.eG(1), scene), plan(small, K, 1, jv.eG(1), scene)
    assert stored.store and not checked.store
    assert plan_bytes(checked, K, jv.eG(1), scene) < 0.25 * plan_bytes(stored, K, jv.eG(1), scene)

    def loss_with(adjoint):
        def loss(z):
            sc = jv.with_parameters(scene, {"eta_dev": jnp.exp(z[0]), "eta_vol": jnp.exp(z[1])})
            s = jv.simulate(sc, jv.eG(1), t1=20.0, dt0=0.1, solver=SOLVER, adjoint=adjoint,
                            saveat=jv.SaveAt(every=20))
            return s.dissipated[-1] + jnp.sum(s.kinetic) + 1e-3 * jnp.mean((s.x[-1] - scene.x0) ** 2)
        return eqx.filter_jit(jax.grad(loss))

    z = jnp.log(jnp.array([scene.material.eta_dev, scene.material.eta_vol]))
    g_all, g_small = loss_with(None)(z), loss_with(small)(z)
    assert _rel(g_small, g_all) <= 1e-8, (g_small, g_all)


GRADIENT_SCRIPT = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
events = {"requests": 0, "hits": 0}
def count(name, **kw):
    key = {"/jax/compilation_cache/compile_requests_use_cache": "requests",
           "/jax/compilation_cache/cache_hits": "hits"}.get(name)
    if key:
        events[key] += 1
jax.monitoring.register_event_listener(count)
import jax.numpy as jnp, equinox as eqx
import jaxvisco as jv
jv.enable_compilation_cache(sys.argv[1])
scene = jv.scenes.lshape(dim=2, refinement=1)
def loss(z):
    s = jv.simulate(jv.with_parameters(scene, {"eta_dev": jnp.exp(z[0]), "eta_vol": jnp.exp(z[1])}), jv.eG(1),
                    t1=0.3, dt0=0.1)
    return s.dissipated[-1] + s.free_energy[-1]
z = jnp.log(jnp.array([scene.material.eta_dev, scene.material.eta_vol]))
g = jax.grad(loss)(z)
j = eqx.filter_jit(jax.jacfwd(loss))(z)
from jaxvisco import _export
print("RESULT " + json.dumps(dict(g=[float(v) for v in g], j=[float(v) for v in j], **events, **_export.stats)))
"""


@pytest.mark.timeout(900)
def test_a_second_process_takes_the_gradient_from_the_cache(tmp_path):
    """A process that computes a gradient (`jax.grad`, and `jax.jacfwd`: a batch of
    tangents) with the cache on stores its programs; a second process compiles none of
    them (every compile request is a cache hit), traces neither the derivatives'
    recording loop nor their sweeps (it loads the three traced programs:
    `_export.inline`) and gets the same derivatives."""
    from helpers import subprocess_env

    env = subprocess_env()
    env.pop("JAXVISCO_CACHE_DIR")
    script = tmp_path / "grad.py"
    script.write_text(GRADIENT_SCRIPT)

    def run():
        p = subprocess.run([sys.executable, str(script), str(tmp_path / "cache")], capture_output=True, text=True,
                           env=env, timeout=800, cwd=tmp_path)
        assert p.returncode == 0, p.stderr[-3000:]
        return json.loads(next(line[7:] for line in p.stdout.splitlines() if line.startswith("RESULT ")))

    first, second = run(), run()
    assert first["hits"] < first["requests"]
    assert second["hits"] == second["requests"] > 0, second
    assert first["exported"] >= 3 and second["exported"] == 0 and second["loaded"] >= 3, (first, second)
    assert second["g"] == first["g"] and second["j"] == first["j"]


if __name__ == "__main__":  # write the reference with the implementation on the path
    jax.config.update("jax_enable_x64", True)
    out = {}
    for name in sorted(CASES):
        z, loss = _case(name)
        out[name] = np.asarray(eqx.filter_jit(jax.grad(loss))(z)).tolist()
        print(name, out[name], flush=True)
    REFERENCE.write_text(json.dumps(dict(out, note="replay adjoint, jaxvisco commit 7e4db97"), indent=1))
