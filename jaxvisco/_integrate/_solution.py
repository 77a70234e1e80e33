"""What a run returns: `Solution`, its status codes, and `SolverError`."""

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import device_array, jit
from .._export import register_type
from .._scene import State

RUNNING, FAILED, EQUILIBRIUM, DONE, MAX_STEPS = 0, 1, 2, 3, 4
STATUS = {RUNNING: "running", FAILED: "failed", EQUILIBRIUM: "equilibrium", DONE: "done", MAX_STEPS: "max_steps"}
# The per-frame fields of a `Solution` (leading axis: the saved frame); the diagnostics,
# `gamma` and the reactions among them are None where the run does not save them.
FRAME_FIELDS = ("t", "x", "p", "gamma", "energy", "kinetic", "free_energy", "dissipated", "dissipation_rate",
              "external_work", "linear_momentum", "angular_momentum", "reaction", "reaction_mean")
STEP_KEYS = ("step_t", "step_h", "newton_iterations", "krylov_iterations", "chord_iterations", "residual",
             "rejections")


class SolverError(RuntimeError):
    """Raised by `simulate` (with `throw=True`) when a time step could not be solved even
    at the smallest step allowed. `simulate(..., throw=False)` returns the `Solution`
    with `status == "failed"` instead.

    **Attributes:**

    - `t`: the time of the last good state.
    - `state`: that `State`.
    - `solution`: the `Solution` with everything saved up to it.
    """

    def __init__(self, message, t, state, solution):
        super().__init__(message)
        self.t, self.state, self.solution = t, state, solution


@register_type  # a cached time loop returns one (`_export`: rebuilt from its fields, as data)
class Solution(eqx.Module):
    """What `simulate` returns: the saved frames and per-step solver statistics of a run.

    **Attributes:**

    - Frames (leading axis: the saved frame): `t`, `x` (positions), `p` (momenta),
      `gamma` (the internal variable, where `SaveAt(gamma=True)`), `energy` (the total
      energy H), `kinetic`, `free_energy`, `dissipated` (cumulative), `dissipation_rate`,
      `external_work` (cumulative work of the loads and moving supports),
      `linear_momentum`, `angular_momentum` (the diagnostics, None where
      `SaveAt(diagnostics=False)`), and with `SaveAt(reactions=True)` the force
      the supports exert on each held component (zero on the free ones): `reaction` at
      the frame's time (what a load cell reads: the rate of the momenta from the step's
      time polynomial plus the internal minus the external force), and `reaction_mean`,
      its mean over the step that ends at the frame (the time element's own discrete
      reaction, whose work is the energy balance's reaction work); at the initial frame
      both are the internal minus the external force.
    - Steps (one entry per step): `step_t` (end time), `step_h`, `newton_iterations`,
      `krylov_iterations`, `chord_iterations`, `residual`, `rejections`.
    - `status`: `"done"`, `"equilibrium"` (stopped by `Equilibrium`), `"failed"` (with
      `throw=False`) or `"max_steps"` (an adaptive run that used all its `max_steps`
      accepted steps before `t1`).
    - `end_velocity`: the predictor velocity after the last step; pass it as
      `initial_velocity` to continue the run exactly.
    - `strain_scale`: adaptive runs, the largest strain reached (to continue the run
      with `PIDController.continued`).
    - `integrator`: a description of the time element; `n_saved`, `n_steps`: the
      numbers of valid frames and steps.
    """

    t: jax.Array
    x: jax.Array
    p: jax.Array
    gamma: Optional[jax.Array]
    energy: Optional[jax.Array]  # the diagnostics: None with SaveAt(diagnostics=False)
    kinetic: Optional[jax.Array]
    free_energy: Optional[jax.Array]
    dissipated: jax.Array
    dissipation_rate: Optional[jax.Array]
    external_work: jax.Array
    linear_momentum: Optional[jax.Array]
    angular_momentum: Optional[jax.Array]
    step_t: jax.Array
    step_h: jax.Array
    newton_iterations: jax.Array
    krylov_iterations: jax.Array
    chord_iterations: jax.Array
    residual: jax.Array
    rejections: jax.Array
    n_saved: jax.Array
    n_steps: jax.Array
    status_code: jax.Array
    integrator: str = eqx.field(static=True, default="")
    end_velocity: jax.Array | None = None  # predictor velocity after the last step (restarts)
    strain_scale: jax.Array | None = None  # adaptive runs: the largest strain reached (restarts: PIDController)
    reaction: jax.Array | None = None  # SaveAt(reactions=True): the supports' forces (frames, n_nodes, dim)
    reaction_mean: jax.Array | None = None  # and their means over the steps that end at the frames

    def reaction_force(self, nodes=None, component: int | None = None, mean: bool = False) -> jax.Array:
        """The resultant force the supports exert, per frame.

        **Arguments:**

        - `nodes`: node indices or a boolean mask of the nodes to sum over (default: all
          held ones).
        - `component`: one component of the force (default: all).
        - `mean`: sum `reaction_mean` (the means over the steps) instead of `reaction`.

        **Returns:**

        The nodal forces summed over `nodes`, shape `(frames, dim)`, or `(frames,)` with
        `component`.

        **Raises:**

        `ValueError` for a run without `SaveAt(reactions=True)`.
        """
        if self.reaction is None:
            raise ValueError("this Solution holds no reaction forces: run simulate with "
                             "saveat=SaveAt(reactions=True) on a scene with held components.")
        if nodes is not None:
            nodes = np.asarray(nodes)
            nodes = np.flatnonzero(nodes) if nodes.dtype == bool else nodes
        r = self.reaction_mean if mean else self.reaction
        r = r if nodes is None else r[:, nodes]
        total = jnp.sum(r, axis=1)
        return total if component is None else total[:, component]

    @property
    def status(self) -> str:
        """How the run ended: `"done"`, `"equilibrium"`, `"failed"` or `"max_steps"`."""
        return STATUS[int(self.status_code)]

    def trimmed(self) -> "Solution":
        """Drop the unused tail of the preallocated buffers (host side; `simulate` does this
        outside `jax.jit`)."""
        ns, nt = int(self.n_saved), int(self.n_steps)
        out = self
        for name in FRAME_FIELDS:
            if getattr(self, name) is not None:
                out = eqx.tree_at(lambda s: getattr(s, name), out, _index(getattr(self, name), slice(ns)))
        for name in STEP_KEYS:
            out = eqx.tree_at(lambda s: getattr(s, name), out, _index(getattr(self, name), slice(nt)))
        return out

    def state(self, i: int = -1) -> State:
        """The `State` of frame `i` (default: the last), e.g. to continue the run with
        `simulate(..., initial_state=sol.state(), initial_velocity=sol.end_velocity)`.
        A negative `i` counts from the last valid frame (`n_saved`), also where the
        frames are not trimmed: under `jax.jit` an adaptive run's frames are padded to
        `max_steps`, and `sol.x[-1]` reads the padding."""
        if isinstance(i, (int, np.integer)) and i < 0 and np.ndim(self.n_saved) == 0:
            if isinstance(self.n_saved, jax.core.Tracer):
                i = self.n_saved + i
            elif int(self.n_saved) + int(i) >= 0:
                i = int(self.n_saved) + int(i)
        at = lambda a: None if a is None else _index(a, i)  # noqa: E731
        return State(at(self.x), at(self.p), at(self.gamma))


def _index(a, index):
    """`a[index]`, on the host where both are concrete: indexing or slicing a device array
    compiles a small program per field and shape (20 of them were 0.2 s of a cold first
    call of the paper scene), and so does `jnp.asarray` of the result (`device_array`).
    Traced values (a derivative of the run) are indexed as they are."""
    if isinstance(a, jax.core.Tracer) or isinstance(index, jax.core.Tracer):
        return a[index]
    return device_array(np.asarray(a)[index])


def initial_solution(scene, state=None, t0=0.0, velocity=None) -> Solution:
    """A `Solution` of one frame and no step: `state` (default: the scene's initial
    state) at `t0`, with its diagnostics and the full internal variable; `velocity`
    (default: that of the momenta) is its `end_velocity`, the first step's predictor
    velocity. What a results file commits before the first step is computed."""
    state = scene.initial_state() if state is None else state
    frame, v = _initial_frame(scene, state)
    v = v if velocity is None else device_array(velocity, v.dtype)
    # host values put on the device as they are (`device_array`: no small programs to compile)
    one = lambda a: device_array(np.asarray([a], dtype=float))  # noqa: E731
    zf, zi = device_array(np.zeros(0)), device_array(np.zeros(0, dtype=int))
    return Solution(
        t=one(t0), dissipated=one(0.0), external_work=one(0.0), **frame, step_t=zf, step_h=zf,
        newton_iterations=zi, krylov_iterations=zi, chord_iterations=zi, residual=zf, rejections=zi,
        n_saved=device_array(1), n_steps=device_array(0), status_code=device_array(DONE), end_velocity=v)


@jit
def _initial_frame(scene, state):
    """The frame fields of `state` (positions, momenta, internal variable, diagnostics), each
    with a leading frame axis of length one, and its velocity $M^{-1}p$."""
    one = lambda a: None if a is None else a[None]  # noqa: E731
    diag = scene.diagnostics(state)
    frame = dict(x=one(state.x), p=one(state.p), gamma=one(state.gamma), **{k: one(v) for k, v in diag.items()})
    return frame, scene.velocity(state.p)
