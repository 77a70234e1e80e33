"""Bad input that used to fail deep inside `simulate` (issue 15): a `load_time` that JAX
cannot trace or that does not return a scalar is rejected when the scene is built."""

import os

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


# ------------------------------------------------------------------ schedules


@pytest.mark.parametrize("dt, t_end, pattern", [
    ([(0.2, 0.1), (0.1, 0.05)], 0.3, r"schedule times must increase: piece 1 ends at t_until = 0.1 after piece 0 "
                                     r"ended at 0.2"),
    ([(20.0, 0.1), (30.0, 1.0)], 40.0, r"the dt schedule ends at t = 30, before t1 = 40: extend its last piece "
                                       r"\(e.g. \(40, 1\)\), or give float\('inf'\)"),
    ([(float("inf"), 0.1), (3.0, 1.0)], 4.0, r"piece 0 has t_until = inf; accepted: finite times, and inf for the "
                                             r"last piece only"),
    ([(1.0, 0.0)], 1.0, r"dt must be positive and finite, got dt = 0.0 in schedule piece 0"),
])
def test_bad_schedule(dt, t_end, pattern):
    with pytest.raises(ValueError, match=pattern):
        jv.StepTo.from_schedule(0.0, t_end, dt)
    scene = jv.Scene(_square(), jv.NeoHooke(lam=1.0, mu=1.0), 1.0)
    with pytest.raises(ValueError, match=pattern):  # simulate checks before it compiles anything
        jv.simulate(scene, jv.eG(1), t1=t_end, stepsize_controller=jv.Schedule(dt))


def test_schedule_times_exact():
    """Step end times are t0 + m h within a piece and the piece's end exactly, never a sum."""
    _, ts = jv._integrate._schedule.step_times(0.0, 2.0, 0.1)
    assert ts[-1] == 2.0 and len(ts) == 21
    np.testing.assert_array_equal(ts[:-1], 0.1 * np.arange(20))
    _, ts = jv._integrate._schedule.step_times(0.0, 25.0, [(20.0, 0.1), (float("inf"), 1.0)])
    assert ts[200] == 20.0 and ts[-1] == 25.0 and np.array_equal(ts[201:], 20.0 + np.arange(1, 6))
    steps = jv.StepTo.from_schedule(0.0, 0.3, 0.1)
    assert steps.ts[-1] == 0.3 and len(steps) == 3
    with pytest.raises(ValueError, match=r"StepTo times must increase strictly, got ts\[1\] = 0.2 then ts\[2\] = 0.2"):
        jv.StepTo([0.0, 0.2, 0.2])
    with pytest.raises(ValueError, match=r"t0 = 1.0 disagrees with the StepTo times"):
        jv._integrate._schedule.step_times(1.0, None, jv.StepTo([0.0, 0.5]))


@pytest.mark.parametrize("argv, needle", [
    (["--schedule", "20:0.1,10:1.0", "--t-end", "30"], "--schedule '20:0.1,10:1.0' ends at t = 10, before --t-end 30"),
    (["--schedule", "20:0.1,10:1.0", "--t-end", "10"], "--schedule '20:0.1,10:1.0': schedule times must increase"),
    (["--schedule", "1:0.1", "--t-end", "2"], "add a piece that reaches it, e.g. '1:0.1,2:0.1'"),
    (["--commit-every", "-1"], "--commit-every must be a number of seconds >= 0"),
])
def test_cli_bad_schedule(argv, needle, capsys, tmp_path):
    from jaxvisco.cli import main

    assert main(["run", *argv, "--out", str(tmp_path / "x.h5"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxvisco: error:") and needle in err, err
    assert not (tmp_path / "x.h5").exists()


def test_cli_refuses_to_overwrite(tmp_path, capsys):
    from jaxvisco.cli import main

    out = tmp_path / "x.h5"
    out.write_bytes(b"precious")
    assert main(["run", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"results file {str(out)!r} exists; pass --overwrite to replace it" in err, err
    assert out.read_bytes() == b"precious"
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "eG1_large.h5").write_bytes(b"precious")
    assert main(["paper", "--quick", "--out", str(tmp_path / "p"), "--quiet"]) == 2
    assert "eG1_large.h5' exists; pass --overwrite" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path / "p")) == ["eG1_large.h5"]
