"""What a run keeps: `SaveAt`."""

import equinox as eqx
import numpy as np

from ._schedule import checked_times


class SaveAt(eqx.Module):
    """Which frames `simulate` keeps (as diffrax's `SaveAt`).

    The initial state and the last step are always kept, and the run's last predictor
    velocity is always returned (`Solution.end_velocity`).

    **Arguments:**

    - `ts`: times within `[t0, t1]` (non-decreasing; the sample times of data, say),
      with fixed or error-controlled steps. A frame inside a step is that step's own
      time polynomial there (dense output: positions, momenta and internal variable; no
      step is shortened to hit it); `dissipated` and `external_work` are exact at step
      ends and linear within a step. Differentiated, where in its step a frame lies is a
      constant of the derivative, like the step sizes.
    - `every`: without `ts`, keep every `every`-th step (default 1). With fixed steps a
      step is a nominal step (its halvings are inside it); with a `PIDController`, an
      accepted step.
    - `gamma`: also keep the internal variable at the frames (default False: it is the
      largest field).
    - `reactions`: also keep the force the supports exert on every held component
      (`Solution.reaction`, `Solution.reaction_force`; default False); needs a scene with
      held components.
    - `diagnostics`: keep the energies and momenta of each frame (`energy`, `kinetic`,
      `free_energy`, `dissipation_rate`, `linear_momentum`, `angular_momentum`; default
      True). False leaves them None: a frame is then its state, the cumulative
      `dissipated` and `external_work` (and reactions), and neither the run nor its
      derivative evaluates the energy at the frames (a fit that reads positions or
      forces only; `Experiment` runs so).

    **Raises:**

    `ValueError` for `every` below 1, `ts` together with `every`, flags that are not
    booleans, or times that are not finite and non-decreasing.

    **Example:**

    ```python
    import jaxvisco as jv

    every_tenth = jv.SaveAt(every=10, gamma=True)
    at_times = jv.SaveAt(ts=[0.5, 1.0, 1.5], reactions=True)
    ```
    """

    ts: np.ndarray = None
    every: int = eqx.field(static=True, default=1)
    gamma: bool = eqx.field(static=True, default=False)
    reactions: bool = eqx.field(static=True, default=False)
    diagnostics: bool = eqx.field(static=True, default=True)

    def __init__(self, ts=None, *, every=1, gamma=False, reactions=False, diagnostics=True):
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise ValueError(f"SaveAt: every must be an integer >= 1, got {every!r}.")
        for name, flag in (("gamma", gamma), ("reactions", reactions), ("diagnostics", diagnostics)):
            if not isinstance(flag, (bool, np.bool_)):
                raise ValueError(f"SaveAt: {name} must be True or False, got {flag!r}.")
        if ts is not None and every != 1:
            raise ValueError(f"SaveAt: give ts or every, not both (got every = {every!r} with ts).")
        self.ts = None if ts is None else checked_times(ts, "SaveAt", 1, strict=False)
        self.every = int(every)
        self.gamma = bool(gamma)
        self.reactions = bool(reactions)
        self.diagnostics = bool(diagnostics)

    def check(self, t0, t1):
        if self.ts is not None and (self.ts[0] < t0 or self.ts[-1] > t1):
            raise ValueError(f"SaveAt: ts must lie within [t0, t1] = [{t0:g}, {t1:g}], got "
                             f"[{self.ts[0]:g}, {self.ts[-1]:g}].")

    def __repr__(self):
        gamma = ((", gamma=True" if self.gamma else "") + (", reactions=True" if self.reactions else "")
                 + ("" if self.diagnostics else ", diagnostics=False"))
        if self.ts is None:
            return f"SaveAt(every={self.every}{gamma})"
        return f"SaveAt({self.ts.size} times from {self.ts[0]:g} to {self.ts[-1]:g}{gamma})"
