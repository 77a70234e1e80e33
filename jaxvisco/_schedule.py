"""Step schedules: a constant step or piecewise-constant steps."""

import numpy as np


def step_sizes(t0, t_end, dt):
    """Per-step sizes from t0 to t_end.

    `dt` is a positive number or a list of `(t_until, dt)` pairs (piecewise constant; the
    last step size continues up to `t_end`). A piece whose length is not a multiple of its
    step is split into equal steps no longer than the given one.
    """
    t0 = float(t0)
    t_end = float(t_end)
    if not np.isfinite(t0) or not np.isfinite(t_end):
        raise ValueError(f"t0 and t_end must be finite, got t0={t0!r}, t_end={t_end!r}.")
    if t_end <= t0:
        raise ValueError(f"t_end must be greater than t0 = {t0}, got t_end = {t_end}.")
    if np.isscalar(dt):
        pieces = [(t_end, float(dt))]
    else:
        try:
            pieces = [(float(a), float(b)) for a, b in dt]
        except (TypeError, ValueError):
            raise ValueError(f"dt must be a positive number or a list of (t_until, dt) pairs, got {dt!r}.") from None
        if not pieces:
            raise ValueError("dt schedule is empty; give at least one (t_until, dt) pair.")
    hs = []
    start = t0
    for i, (until, h) in enumerate(pieces):
        if not np.isfinite(h) or h <= 0:
            raise ValueError(f"dt must be positive and finite, got dt = {h!r}.")
        if i == len(pieces) - 1:
            until = max(until, t_end)
        until = min(until, t_end)
        if until <= start:
            if i < len(pieces) - 1 and until < start:
                raise ValueError(f"schedule times must increase: t_until = {until} after {start}.")
            continue
        n = int(np.ceil((until - start) / h - 1e-9))
        hs.extend([(until - start) / n] * n)
        start = until
        if start >= t_end:
            break
    return np.asarray(hs, dtype=float)
