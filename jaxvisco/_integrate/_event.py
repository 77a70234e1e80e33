"""When a run ends early: `Equilibrium`."""

import math

import equinox as eqx


class AbstractEvent(eqx.Module):
    """A condition checked after every (accepted) step: the run ends at the first step
    where it holds. The one event is `Equilibrium`."""


class Equilibrium(AbstractEvent):
    """End the run once the body has come to rest (`status == "equilibrium"`).

    The body is at rest when its kinetic energy relative to its rigid-body motion (its
    whole kinetic energy where components are held) and the energy it dissipated in the
    last step both fall below `tol` times the run's
    energy scale: the largest of the initial total energy $H_0$, the external work done
    so far and the energy dissipated so far. A free body is measured against $H_0$; a
    body that starts at rest and is then loaded ($H_0 = 0$) against the work of its
    loads. With fixed steps the test runs after each nominal step, with a
    `PIDController` after each accepted step.

    **Arguments:**

    - `tol`: the relative threshold (a positive number, e.g. `1e-6`).

    **Raises:**

    `ValueError` for a `tol` that is not a positive finite number.

    **Example:**

    ```python
    import jaxvisco as jv

    event = jv.Equilibrium(1e-6)   # simulate(..., event=event)
    ```
    """

    tol: float = eqx.field(static=True)

    def __init__(self, tol):
        try:
            tol = float(tol)
        except (TypeError, ValueError):
            raise ValueError(f"Equilibrium: tol must be a positive number, got {tol!r}.") from None
        if not (tol > 0 and math.isfinite(tol)):
            raise ValueError(f"Equilibrium: tol must be positive and finite, got {tol!r}.")
        self.tol = tol
