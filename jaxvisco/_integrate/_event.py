"""When a run ends early: `Equilibrium`."""

import math

import equinox as eqx


class AbstractEvent(eqx.Module):
    """A condition checked after every (accepted) step; the run ends at the first step
    where it holds, with ``Solution.status == "equilibrium"``."""


class Equilibrium(AbstractEvent):
    """The body has come to rest: the kinetic energy relative to its rigid-body motion
    and the step's dissipated energy both fall below ``tol * H_0`` (`H_0` the initial
    total energy). With fixed steps the test runs after each nominal step, with a
    `PIDController` after each accepted step."""

    tol: float = eqx.field(static=True)

    def __init__(self, tol):
        try:
            tol = float(tol)
        except (TypeError, ValueError):
            raise ValueError(f"Equilibrium: tol must be a positive number, got {tol!r}.") from None
        if not (tol > 0 and math.isfinite(tol)):
            raise ValueError(f"Equilibrium: tol must be positive and finite, got {tol!r}.")
        self.tol = tol
