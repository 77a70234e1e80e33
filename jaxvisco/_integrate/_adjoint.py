"""How a run is differentiated: `RecursiveCheckpointAdjoint`."""

import equinox as eqx
import numpy as np


class AbstractAdjoint(eqx.Module):
    """How `jax.grad`/`jax.jvp` of `simulate` are computed."""


class RecursiveCheckpointAdjoint(AbstractAdjoint):
    """The default, and the only adjoint: differentiate the run along its accepted steps.

    The loop records its accepted (sub-)steps; a derivative replays them with every step
    differentiated implicitly (one linear solve with the converged tangent; Newton is
    never differentiated) in a checkpointed scan (see `_differentiable`). Step sizes are
    constants of the derivative, as in diffrax.

    **Arguments:**
    - `checkpoint_every`: frames per checkpointed segment in reverse mode (default None:
      ceil(sqrt(K)) sub-steps for K recorded sub-steps, so memory grows like sqrt(K)).
      More frames per segment: fewer stored states, longer re-runs in the backward pass.
    """

    checkpoint_every: int = eqx.field(static=True, default=None)

    def __check_init__(self):
        c = self.checkpoint_every
        if c is not None and (isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 1):
            raise ValueError(f"RecursiveCheckpointAdjoint: checkpoint_every must be a positive number of frames or "
                             f"None, got {c!r}.")
