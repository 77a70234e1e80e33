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
STEP_KEYS = ("step_t", "step_h", "newton_iterations", "krylov_iterations", "chord_iterations", "residual",
             "rejections")


class SolverError(RuntimeError):
    """A time step could not be solved even at the smallest allowed step size.

    **Attributes:** `t` (time of the last good state), `state` (that `State`),
    `solution` (everything saved up to it).
    """

    def __init__(self, message, t, state, solution):
        super().__init__(message)
        self.t, self.state, self.solution = t, state, solution


@register_type  # a cached time loop returns one (`_export`: rebuilt from its fields, as data)
class Solution(eqx.Module):
    """Saved frames and per-step solver statistics of a run.

    Frames (leading axis = saved frame): `t`, `x`, `p`, `gamma` (if asked), `energy` (H),
    `kinetic`, `free_energy`, `dissipated` (cumulative dissipation of the scheme),
    `dissipation_rate`, `external_work`, `linear_momentum`, `angular_momentum`, and with
    ``SaveAt(reactions=True)`` the force the supports exert on each held component (zero
    on the free ones): `reaction` at the frame's time (what a load cell reads: the rate of
    the momenta from the step's time polynomial plus the internal minus the external
    force), and `reaction_mean`, its mean over the step that ends at the frame (the time
    element's own discrete reaction, whose work is the energy balance's reaction work);
    at the initial frame both are the internal minus the external force. Steps: `step_t` (end time), `step_h`, `newton_iterations` (Newton–Krylov
    iterations), `krylov_iterations`, `chord_iterations` (iterations on the stored
    factorization, `NewtonKrylov(chord=...)`), `residual`, `rejections`. `n_saved`, `n_steps` count the valid entries; `status` is
    one of "done", "equilibrium", "failed", "max_steps" (an adaptive run that used all
    its `max_steps` accepted steps before `t1`).
    """

    t: jax.Array
    x: jax.Array
    p: jax.Array
    gamma: Optional[jax.Array]
    energy: jax.Array
    kinetic: jax.Array
    free_energy: jax.Array
    dissipated: jax.Array
    dissipation_rate: jax.Array
    external_work: jax.Array
    linear_momentum: jax.Array
    angular_momentum: jax.Array
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

    def reaction_force(self, nodes=None, component=None, mean=False):
        """The resultant force the supports exert, per frame: the nodal `reaction` (with
        `mean`: `reaction_mean`) summed over `nodes` (indices or a boolean mask of the
        nodes, default all held ones), (frames, dim), or one `component` of it, (frames,).
        Needs a run with ``SaveAt(reactions=True)``."""
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
    def status(self):
        return STATUS[int(self.status_code)]

    def trimmed(self):
        """Drop the unused tail of the preallocated buffers (host side)."""
        ns, nt = int(self.n_saved), int(self.n_steps)
        frames = ("t", "x", "p", "gamma", "energy", "kinetic", "free_energy", "dissipated",
                  "dissipation_rate", "external_work", "linear_momentum", "angular_momentum", "reaction",
                  "reaction_mean")
        out = self
        for name in frames:
            if getattr(self, name) is not None:
                out = eqx.tree_at(lambda s: getattr(s, name), out, _index(getattr(self, name), slice(ns)))
        for name in STEP_KEYS:
            out = eqx.tree_at(lambda s: getattr(s, name), out, _index(getattr(self, name), slice(nt)))
        return out

    def state(self, i=-1) -> State:
        """The state of frame `i`."""
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
