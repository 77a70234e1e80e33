"""Time functions that scale dead loads: a small, safe set (no user code is evaluated).

Each is an equinox module called as ``g(t)`` with a JAX scalar time and returning a
scalar; its parameters are float64 arrays, so a new value (a later switch-off time, a
larger amplitude) does not recompile a run, and a run may be differentiated with respect
to them. A scene scales each of its loads by one of these (`Scene(loads=[(f, g), ...])`);
scene files name them as tables, ``{ type = "ramp", t0 = 0.0, t1 = 1.0 }``, whose keys are
the constructor's keywords. `_time_function` turns what a scene is given as the time of a
load or a prescribed motion (None, one of these, or a user's plain function of t, checked
by tracing it once) into a time function.
"""

import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def _number(where, name, value):
    """A float64 scalar; checked (a number, finite) unless it is traced."""
    if isinstance(value, jax.core.Tracer):
        if jnp.shape(value) != ():
            raise ValueError(f"{where}{name} must be a scalar, got shape {jnp.shape(value)}.")
        return jnp.asarray(value, dtype=float)
    if isinstance(value, (jax.Array, np.ndarray)) and np.shape(value) == ():
        value = float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{where}{name} must be a number, got {value!r}.")
    if not math.isfinite(float(value)):
        raise ValueError(f"{where}{name} must be finite, got {value!r}.")
    return jnp.asarray(float(value), dtype=float)


def _known(x):
    """The value of a scalar parameter, None where it is traced (then unchecked)."""
    return None if isinstance(x, jax.core.Tracer) else float(x)


class AbstractTimeFunction(eqx.Module):
    """A scalar function of time, ``g(t)``, traceable by JAX."""

    def __call__(self, t):
        raise NotImplementedError


class Constant(AbstractTimeFunction):
    """``g(t) = value`` (default 1)."""

    value: jax.Array

    def __init__(self, value=1.0):
        self.value = _number("Constant: ", "value", value)

    def __call__(self, t):
        return self.value + 0.0 * t


class Step(AbstractTimeFunction):
    """``before`` for ``t < at``, ``after`` from ``at`` on: a load switched on or off."""

    at: jax.Array
    before: jax.Array
    after: jax.Array

    def __init__(self, at, before=0.0, after=1.0):
        self.at = _number("Step: ", "at", at)
        self.before = _number("Step: ", "before", before)
        self.after = _number("Step: ", "after", after)

    def __call__(self, t):
        return jnp.where(t < self.at, self.before, self.after)


class Ramp(AbstractTimeFunction):
    """``v0`` up to ``t0``, linear to ``v1`` at ``t1``, ``v1`` after (``t1 > t0``)."""

    t0: jax.Array
    t1: jax.Array
    v0: jax.Array
    v1: jax.Array

    def __init__(self, t0, t1, v0=0.0, v1=1.0):
        self.t0 = _number("Ramp: ", "t0", t0)
        self.t1 = _number("Ramp: ", "t1", t1)
        if None not in (_known(self.t0), _known(self.t1)) and not _known(self.t1) > _known(self.t0):
            raise ValueError(f"Ramp: t1 must be greater than t0, got t0 = {float(self.t0)!r}, t1 = {float(self.t1)!r}.")
        self.v0 = _number("Ramp: ", "v0", v0)
        self.v1 = _number("Ramp: ", "v1", v1)

    def __call__(self, t):
        s = jnp.clip((t - self.t0) / (self.t1 - self.t0), 0.0, 1.0)
        return self.v0 + s * (self.v1 - self.v0)


class Table(AbstractTimeFunction):
    """Piecewise linear through the points ``(times[i], values[i])``, constant beyond the
    first and last time; ``times`` strictly increasing, at least one point."""

    times: jax.Array
    values: jax.Array

    def __init__(self, times, values):
        try:
            ts = np.asarray(times, dtype=float)
            vs = np.asarray(values, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"Table: times and values must be lists of numbers, got times = {times!r}, "
                             f"values = {values!r}.") from None
        if ts.ndim != 1 or ts.size == 0 or vs.shape != ts.shape:
            raise ValueError(f"Table: times and values must be non-empty lists of the same length, got "
                             f"{ts.shape} and {vs.shape}.")
        if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(vs))):
            raise ValueError("Table: times and values must be finite.")
        if np.any(np.diff(ts) <= 0):
            i = int(np.flatnonzero(np.diff(ts) <= 0)[0])
            raise ValueError(f"Table: times must increase strictly, got {float(ts[i])!r} then {float(ts[i + 1])!r}.")
        self.times = jnp.asarray(ts)
        self.values = jnp.asarray(vs)

    def __call__(self, t):
        return jnp.interp(t, self.times, self.values)


class Sine(AbstractTimeFunction):
    """``offset + amplitude * sin(2 pi t / period + phase)``; ``period > 0``."""

    period: jax.Array
    amplitude: jax.Array
    phase: jax.Array
    offset: jax.Array

    def __init__(self, period, amplitude=1.0, phase=0.0, offset=0.0):
        self.period = _number("Sine: ", "period", period)
        if _known(self.period) is not None and not _known(self.period) > 0:
            raise ValueError(f"Sine: period must be > 0, got {float(self.period)!r}.")
        self.amplitude = _number("Sine: ", "amplitude", amplitude)
        self.phase = _number("Sine: ", "phase", phase)
        self.offset = _number("Sine: ", "offset", offset)

    def __call__(self, t):
        return self.offset + self.amplitude * jnp.sin(2.0 * jnp.pi * t / self.period + self.phase)


TIME_FUNCTIONS = {"constant": Constant, "step": Step, "ramp": Ramp, "table": Table, "sine": Sine}


def time_function_from_dict(spec: dict | float, where: str = "") -> "AbstractTimeFunction":
    """Build a time function from a table such as ``{"type": "step", "at": 1.0,
    "before": 1.0, "after": 0.0}``: ``type`` is one of `TIME_FUNCTIONS`, the other keys
    are the constructor's keywords. A bare number is a `Constant`. `where` prefixes error
    messages (e.g. ``"beam.toml: [[load]] 1: time: "``)."""
    import inspect

    if isinstance(spec, (int, float)) and not isinstance(spec, bool):
        return Constant(spec)
    if not isinstance(spec, dict):
        raise ValueError(f"{where}expected a table such as {{ type = \"step\", at = 1.0 }} or a number, "
                         f"got {spec!r}.")
    kind = spec.get("type")
    if kind not in TIME_FUNCTIONS:
        raise ValueError(f"{where}type must be one of {sorted(TIME_FUNCTIONS)}, got {kind!r}.")
    cls = TIME_FUNCTIONS[kind]
    params = inspect.signature(cls.__init__).parameters
    accepted = [p for p in params if p != "self"]
    required = [p for p in accepted if params[p].default is inspect.Parameter.empty]
    args = {k: v for k, v in spec.items() if k != "type"}
    unknown = sorted(set(args) - set(accepted))
    if unknown:
        raise ValueError(f"{where}unknown key {unknown[0]!r} for type {kind!r}; accepted: {accepted}.")
    missing = [p for p in required if p not in args]
    if missing:
        raise ValueError(f"{where}type {kind!r} needs {missing[0]!r} (keys: {accepted}, required: {required}).")
    try:
        return cls(**args)
    except ValueError as e:
        raise ValueError(f"{where}{e}") from None


_LOAD_TIME_RULE = "load_time must be a JAX-traceable function of one scalar time t returning a scalar"
_LOAD_TIME_FIX = "e.g. `lambda t: jnp.where(t < 3.0, 1.0, 0.0)` instead of `lambda t: 1.0 if t < 3 else 0.0`"


def _check_load_time(load_time):
    """Trace `load_time` once on an abstract scalar time (nothing is computed): reject a
    function that JAX cannot trace, or whose value is not a real scalar, here rather than
    deep inside `simulate`."""
    if not callable(load_time):
        raise TypeError(f"load_time must be a function of t, got {type(load_time).__name__} {load_time!r}.")
    try:
        out = jax.eval_shape(load_time, jax.ShapeDtypeStruct((), jnp.float64))
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
            jax.errors.TracerIntegerConversionError) as e:
        raise ValueError(f"load_time could not be traced by JAX ({type(e).__name__}: {_first_line(e)}). "
                         f"{_LOAD_TIME_RULE}: t is a tracer, so Python `if`, `float()`, `math` or numpy on t are not "
                         f"allowed; write it with jax.numpy, {_LOAD_TIME_FIX}.") from e
    except Exception as e:
        raise ValueError(f"load_time(t) failed on a traced scalar t ({type(e).__name__}: {_first_line(e)}). "
                         f"{_LOAD_TIME_RULE}, {_LOAD_TIME_FIX}.") from e
    if not isinstance(out, jax.ShapeDtypeStruct):
        n = len(jax.tree_util.tree_leaves(out))
        raise ValueError(f"load_time(t) must return one scalar, got a {type(out).__name__} of {n} values.")
    if out.shape != ():
        raise ValueError(f"load_time(t) must return a scalar (shape ()), got shape {out.shape}; the load is scaled by "
                         "one number at each time.")
    if not (jnp.issubdtype(out.dtype, jnp.floating) or jnp.issubdtype(out.dtype, jnp.integer) or out.dtype == bool):
        raise ValueError(f"load_time(t) must return a real scalar, got dtype {out.dtype}.")


class _PlainTimeFunction(AbstractTimeFunction):
    """A user's function of t, kept static (hashed by identity) like any callable."""

    fn: Callable = eqx.field(static=True)

    def __call__(self, t):
        return self.fn(t)


def _time_function(g):
    if g is None:
        return Constant(1.0)
    if isinstance(g, AbstractTimeFunction):
        return g
    _check_load_time(g)
    return _PlainTimeFunction(g)


def _first_line(e):
    lines = str(e).strip().splitlines()
    return lines[0] if lines else ""
