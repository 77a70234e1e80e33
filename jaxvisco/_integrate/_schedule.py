"""Step schedules: a constant step, piecewise-constant steps, or explicit step times.

Every form is expanded on the host into the nominal step sizes `hs` and the exact end
time of every step `ts`. Times are never accumulated step by step (``t + h + h + ...``
drifts: 20 steps of 0.1 end at 2.0000000000000004): inside a piece that starts at `s`
with step `h`, step `m` ends at ``s + m * h`` and the piece's last step ends at its
`t_until` exactly.
"""

import abc
import math

import equinox as eqx
import numpy as np


class AbstractStepSizeController(eqx.Module):
    """How `simulate` chooses its steps: `ConstantStepSize`, `Schedule`, `StepTo` (steps
    fixed before the run) or `PIDController` (error-controlled)."""


class AbstractFixedSteps(AbstractStepSizeController):
    """Steps known before the run. A step whose Newton solve fails is halved, at most
    `max_halvings` times (the smallest step tried is ``h / 2**max_halvings``; after
    successes the sub-steps grow back dyadically to ``h``); a step that still fails ends
    the run (``status == "failed"``)."""

    max_halvings: eqx.AbstractVar[int]

    @abc.abstractmethod
    def step_times(self, t0, t1, dt0):
        """``(hs, ts)``: the nominal step sizes (n,) and `t0` followed by every step's
        exact end time (n + 1,)."""

    def _check_halvings(self):
        m = self.max_halvings
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 0 <= m <= 30:
            raise ValueError(f"{type(self).__name__}: max_halvings must be an integer in [0, 30], got {m!r}.")


class ConstantStepSize(AbstractFixedSteps):
    """Steps of the size `dt0` (the default controller of `simulate`): from `t0` to `t1`
    in equal steps, the last ending at `t1` exactly (a run whose length is not a
    multiple of `dt0` takes equal steps just below it). A step whose Newton solve fails
    is halved, at most `max_halvings` times, and the sub-steps grow back after
    successes; a step that still fails ends the run (`status == "failed"`).

    **Arguments:**

    - `max_halvings`: how often a failed step may be halved (0 to 30; default 6, so the
      smallest step tried is `dt0 / 64`).

    **Raises:**

    `ValueError` for `max_halvings` outside `[0, 30]`.

    **Example:**

    ```python
    import jaxvisco as jv

    ctrl = jv.ConstantStepSize(max_halvings=3)   # simulate(..., dt0=0.1, stepsize_controller=ctrl)
    ```
    """

    max_halvings: int = eqx.field(static=True, default=6)

    def __check_init__(self):
        self._check_halvings()

    def step_times(self, t0, t1, dt0):
        if dt0 is None or isinstance(dt0, bool) or np.ndim(dt0) != 0:
            raise ValueError(f"dt0 must be a positive step size with ConstantStepSize, got {dt0!r}; for piecewise-"
                             "constant steps pass stepsize_controller=Schedule([(t_until, dt), ...]), for given step "
                             "times StepTo(ts).")
        return step_times(t0, t1, dt0)


class Schedule(AbstractFixedSteps):
    """Piecewise-constant steps, given in absolute times. Pass it with `dt0=None`; `t1`
    defaults to the last piece's end. A piece whose length is not a multiple of its step
    is split into equal steps no longer than the given one. Failed steps are halved as
    with `ConstantStepSize`.

    **Arguments:**

    - `pieces`: `[(t_until, dt), ...]`, e.g. `[(20.0, 0.1), (40.0, 0.5)]`: steps of
      `dt` up to `t_until`. Pieces that end at or before `t0` are skipped; the last must
      reach `t1`, or have `t_until = inf` to continue its step to any `t1`.
    - `max_halvings`: as in `ConstantStepSize` (6).

    **Raises:**

    `ValueError` for times that do not increase or steps that are not positive.

    **Example:**

    ```python
    import jaxvisco as jv

    ctrl = jv.Schedule([(20.0, 0.1), (60.0, 1.0)])   # the paper's step change at t = 20
    ```
    """

    pieces: tuple = eqx.field(static=True)
    max_halvings: int = eqx.field(static=True, default=6)

    def __init__(self, pieces, max_halvings=6):
        self.pieces = tuple(_pieces(pieces))
        self.max_halvings = max_halvings

    def __check_init__(self):
        self._check_halvings()

    def step_times(self, t0, t1, dt0):
        if dt0 is not None:
            raise ValueError(f"dt0 = {dt0!r} conflicts with a Schedule, which gives the steps; pass dt0=None.")
        if t1 is None and math.isfinite(self.pieces[-1][0]):
            t1 = self.pieces[-1][0]
        return step_times(t0, t1, list(self.pieces))


class StepTo(AbstractFixedSteps):
    """Steps that end exactly at given times (as diffrax's `StepTo`). Pass it with
    `dt0=None`; `t0` and `t1` may be left out (they are `ts[0]` and `ts[-1]`).

    `StepTo.from_schedule(t0, t1, dt)` expands a constant step or a list of
    `(t_until, dt)` pieces, so that a run can be advanced in parts
    (`StepTo(steps.ts[i:j + 1])`) that repeat the whole run's steps exactly.

    **Arguments:**

    - `ts`: the start time and then the end of every step, strictly increasing and
      finite; step `i` runs from `ts[i]` to `ts[i + 1]`.
    - `max_halvings`: as in `ConstantStepSize` (6).

    **Raises:**

    `ValueError` for times that are not finite and strictly increasing.

    **Example:**

    ```python
    import jaxvisco as jv

    steps = jv.StepTo([0.0, 0.1, 0.3, 0.6])   # simulate(..., stepsize_controller=steps)
    ```
    """

    ts: np.ndarray
    max_halvings: int = eqx.field(static=True, default=6)

    def __init__(self, ts, max_halvings=6):
        self.ts = checked_times(ts, "StepTo", 2, strict=True)
        self.max_halvings = max_halvings

    def __check_init__(self):
        self._check_halvings()

    @classmethod
    def from_schedule(cls, t0, t1, dt, max_halvings=6, t1_name="t1") -> "StepTo":
        """The steps of a constant step `dt` or a list of `(t_until, dt)` pieces from `t0`
        to `t1`, with exact end times (`t1_name`: what error messages call `t1`)."""
        return cls(step_times(t0, t1, dt, t1_name)[1], max_halvings)

    def step_times(self, t0, t1, dt0):
        if dt0 is not None:
            raise ValueError(f"dt0 = {dt0!r} conflicts with StepTo, which gives the steps; pass dt0=None.")
        return step_times(t0, t1, self)

    @property
    def t0(self):
        return float(self.ts[0])

    @property
    def t1(self):
        return float(self.ts[-1])

    @property
    def t_end(self):
        return self.t1

    def __len__(self):
        return self.ts.size - 1

    def __repr__(self):
        return f"StepTo({len(self)} steps from t = {self.t0:.17g} to {self.t1:.17g})"


def checked_times(ts, name, min_size, strict):
    """`ts` as a read-only float64 array, checked: 1-D, at least `min_size` entries,
    finite, increasing (strictly if `strict`)."""
    try:
        ts = np.array(ts, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} needs a 1-D sequence of times, got {ts!r}.") from None
    if ts.ndim != 1 or ts.size < min_size:
        raise ValueError(f"{name} needs a 1-D sequence of at least {min_size} time(s)"
                         f"{' (a start and one step end)' if min_size == 2 else ''}, got shape {ts.shape}.")
    if not np.all(np.isfinite(ts)):
        i = int(np.flatnonzero(~np.isfinite(ts))[0])
        raise ValueError(f"{name} times must be finite, got ts[{i}] = {float(ts[i])!r}.")
    steps = np.diff(ts)
    bad = ~(steps > 0) if strict else steps < 0
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} times must {'increase strictly' if strict else 'not decrease'}, got "
                         f"ts[{i}] = {float(ts[i])!r} then ts[{i + 1}] = {float(ts[i + 1])!r}.")
    ts.setflags(write=False)
    return ts


def _pieces(dt):
    if isinstance(dt, (int, float, np.integer, np.floating)) and not isinstance(dt, bool):
        return None
    if np.ndim(dt) == 0:
        raise ValueError(f"dt must be a positive number, a list of (t_until, dt) pairs or a StepTo, got {dt!r}.")
    try:
        pieces = [(float(a), float(b)) for a, b in dt]
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a positive number, a list of (t_until, dt) pairs or a StepTo, "
                         f"got {dt!r}.") from None
    if not pieces:
        raise ValueError("dt schedule is empty; give at least one (t_until, dt) pair.")
    for i, (until, h) in enumerate(pieces):
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"dt must be positive and finite, got dt = {h!r} in schedule piece {i}.")
        if math.isnan(until) or (math.isinf(until) and (until < 0 or i < len(pieces) - 1)):
            raise ValueError(f"schedule piece {i} has t_until = {until!r}; accepted: finite times, and inf for the "
                             "last piece only (its step then continues to any t1).")
        if i and not until > pieces[i - 1][0]:
            raise ValueError(f"schedule times must increase: piece {i} ends at t_until = {until:g} after piece "
                             f"{i - 1} ended at {pieces[i - 1][0]:g}; got {list(dt)!r}.")
    return pieces


def step_times(t0, t1, dt, t1_name="t1"):
    """Nominal step sizes and exact end times of a run from `t0` to `t1`.

    `dt` is a positive number (a constant step), a list of ``(t_until, dt)`` pairs in
    absolute times (piecewise constant; pieces that end at or before `t0` are skipped,
    the last piece must reach `t1`, or have ``t_until = inf`` to continue its step to
    any `t1`), or a `StepTo`. A piece whose length is not a multiple of its step is
    split into equal steps no longer than the given one.

    `t1_name`: what error messages call `t1`.

    **Returns:** ``(hs, ts)``: `hs` (n,) the step sizes, `ts` (n + 1,) ``t0`` and the end
    time of every step.
    """
    if isinstance(dt, StepTo):
        ts = dt.ts
        for name, value, ref in (("t0", t0, ts[0]), (t1_name, t1, ts[-1])):
            if value is not None and float(value) != float(ref):
                raise ValueError(f"{name} = {value!r} disagrees with the StepTo times ({name} = {float(ref)!r}); give "
                                 f"{name}=None or the same time.")
        return np.diff(ts), np.array(ts)
    t0 = 0.0 if t0 is None else float(t0)
    if t1 is None:
        raise ValueError(f"{t1_name} is required unless the steps are a StepTo.")
    t1 = float(t1)
    if not np.isfinite(t0) or not np.isfinite(t1):
        raise ValueError(f"t0 and {t1_name} must be finite, got t0={t0!r}, {t1_name}={t1!r}.")
    if t1 <= t0:
        raise ValueError(f"{t1_name} must be greater than t0 = {t0}, got {t1_name} = {t1}.")
    pieces = _pieces(dt)
    if pieces is None:
        h = float(dt)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"dt must be positive and finite, got dt = {h!r}.")
        pieces = [(math.inf, h)]
    last = pieces[-1][0]
    if last < t1 and not math.isclose(last, t1, rel_tol=1e-12, abs_tol=0.0):
        raise ValueError(f"the dt schedule ends at t = {last:g}, before {t1_name} = {t1:g}: extend its last piece "
                         f"(e.g. ({t1:g}, {pieces[-1][1]:g})), or give float('inf') as its t_until to continue "
                         f"the last step to any {t1_name}.")
    hs, ts = [], [t0]
    start = t0
    for until, h in pieces:
        until = min(until, t1)
        if math.isclose(until, t1, rel_tol=1e-12, abs_tol=0.0):
            until = t1  # a schedule that ends at t1 up to rounding ends there exactly
        if until <= start:
            continue
        n = int(np.ceil((until - start) / h - 1e-9))
        h_piece = (until - start) / n
        hs.extend([h_piece] * n)
        ts.extend(start + h_piece * np.arange(1, n))
        ts.append(until)
        start = until
        if start >= t1:
            break
    return np.asarray(hs, dtype=float), np.asarray(ts, dtype=float)


def step_sizes(t0, t1, dt):
    """Per-step sizes from `t0` to `t1` (see `step_times`)."""
    return step_times(t0, t1, dt)[0]
