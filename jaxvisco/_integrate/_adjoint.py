"""How a run is differentiated: `RecursiveCheckpointAdjoint`."""

import warnings

import equinox as eqx
import numpy as np


class AbstractAdjoint(eqx.Module):
    """How `jax.grad` and `jax.jvp` of `simulate` are computed: the base of
    `RecursiveCheckpointAdjoint`, the only one."""


def _count(name, value, what):
    if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1):
        raise ValueError(f"RecursiveCheckpointAdjoint: {name} must be a positive {what} or None, got {value!r}.")


class RecursiveCheckpointAdjoint(AbstractAdjoint):
    """The default, and the only adjoint: a discrete adjoint along the run's accepted steps.

    A differentiated run records its accepted (sub-)steps: their sizes and, memory
    allowing, their converged unknowns. The derivative then takes one linear solve per
    step with the transposed (reverse mode) or plain (forward mode) step Jacobian,
    preconditioned by a condensed tangent that serves many steps; it never re-solves a
    step and never differentiates Newton's iterations. Step sizes are constants of the
    derivative, as in diffrax.

    **Arguments:**

    - `checkpoints`: None (default) stores every step while that fits `max_bytes`;
      beyond, the run stores its state at checkpoints and the derivative re-solves the
      steps between them (one more forward run of work). An integer: store that many
      checkpoints (evenly spaced) and re-solve between them, whatever the budget
      (memory O(checkpoints + steps / checkpoints)).
    - `max_bytes`: the memory the stored steps may take (default 1 GiB): 8 bytes per
      number of a step's unknowns, start positions and momenta (the paper's 2D L-shape
      with eG(1): 10 kB a step, so 100 000 steps fit).
    - `throw`: where the derivative cannot be computed accurately (a run that halved its
      steps beyond the record's room, a linear solve of the derivative that did not
      converge, a re-solved step that failed): False (default) makes it NaN, True raises
      an error that says which. True puts a host callback into the compiled derivative,
      which JAX's persistent compilation cache does not store.
    - `checkpoint_every`: deprecated (jaxvisco 0.2): frames per checkpointed segment;
      use `checkpoints` (`DeprecationWarning`).

    **Raises:**

    `ValueError` for a count that is not a positive integer, or a `throw` that is not a
    boolean.

    **Example:**

    ```python
    import jaxvisco as jv

    low_memory = jv.RecursiveCheckpointAdjoint(checkpoints=16)   # re-solve between 16 states
    strict = jv.RecursiveCheckpointAdjoint(throw=True)           # raise instead of NaN
    ```
    """

    checkpoints: int = eqx.field(static=True, default=None)
    max_bytes: int = eqx.field(static=True, default=2**30)
    throw: bool = eqx.field(static=True, default=False)
    checkpoint_every: int = eqx.field(static=True, default=None)

    def __check_init__(self):
        _count("checkpoints", self.checkpoints, "number of checkpoints")
        _count("max_bytes", self.max_bytes, "number of bytes")
        _count("checkpoint_every", self.checkpoint_every, "number of frames")
        if not isinstance(self.throw, (bool, np.bool_)):
            raise ValueError(f"RecursiveCheckpointAdjoint: throw must be True or False, got {self.throw!r}.")
        if self.checkpoint_every is not None:
            warnings.warn("RecursiveCheckpointAdjoint(checkpoint_every=n) is deprecated; use checkpoints= (a number "
                          "of stored states) or max_bytes=.", DeprecationWarning, stacklevel=3)
