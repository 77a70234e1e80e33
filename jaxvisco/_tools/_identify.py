"""Identification of the viscosities from observed trajectories (optax).

The unknowns are the logarithms of the chosen material parameters (positive by
construction, and steps in log space are relative changes). The loss is the relative
least-squares misfit between `observe(solution)` and the data; its gradient comes from
`simulate` (every run is differentiable): forward mode (`jax.jacfwd`, one tangent solve per
step and parameter, no storage) since there are only a few parameters. Each optimizer
step (optax L-BFGS with a backtracking line search by default) is one compiled program.
"""

import functools
import time
from typing import Callable, Optional, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import jit
from .._integrate._legacy import translate
from .._integrate._saveat import SaveAt
from .._integrate._schedule import (
    AbstractFixedSteps,
    AbstractStepSizeController,
    ConstantStepSize,
    StepTo,
)
from .._integrate._simulate import simulate
from .._integrate._solution import FAILED
from .._integrate._stepsize import PIDController
from .._solver._newton import NewtonKrylov

PARAMETERS = {
    "eta_dev": lambda s: s.material.eta_dev,
    "eta_vol": lambda s: s.material.eta_vol,
    "lam": lambda s: s.material.equilibrium.lam,
    "mu": lambda s: s.material.equilibrium.mu,
    "density": lambda s: s.density,
}


class Identification(eqx.Module):
    """Result of `identify`.

    **Attributes:** `params` (dict name -> fitted value), `loss` (final relative misfit),
    `history` (loss per iteration), `params_history` (dict name -> values per
    iteration), `converged` (bool), `iterations`, `message`.
    """

    params: dict
    loss: float
    history: np.ndarray
    params_history: dict
    converged: bool
    iterations: int
    message: str


def with_parameters(scene, values: dict):
    """A copy of `scene` with material parameters replaced (names in `PARAMETERS`); for a
    scene of one material."""
    if getattr(scene, "cell_material", None) is not None:
        raise ValueError(f"with_parameters/identify take a scene of one material; this one has "
                         f"{int(scene.cell_material.array.max()) + 1} (Scene(material=[(material, cells), ...])). "
                         "Replace a part's parameters with eqx.tree_at on scene.material, whose leaves hold one "
                         "value per material.")
    for name, v in values.items():
        if name not in PARAMETERS:
            raise ValueError(f"unknown parameter {name!r}; accepted: {sorted(PARAMETERS)}.")
        scene = eqx.tree_at(PARAMETERS[name], scene, jnp.asarray(v, dtype=float))
    return scene


def identify(scene, integrator, observe: Callable, data, t1=None, dt0=None, initial: Optional[dict] = None, *,
             t0=None, stepsize_controller: Optional[AbstractStepSizeController] = None,
             saveat: Optional[SaveAt] = None, optimizer: Optional["optax.GradientTransformation"] = None,
             max_iterations=50, gtol=1e-7, ftol=1e-12, solver: NewtonKrylov = NewtonKrylov(rtol=1e-11),
             verbose=False, names: Optional[Sequence[str]] = None, **deprecated) -> Identification:
    """Fit material parameters so that `observe(simulate(scene', ...))` matches `data`.

    **Arguments:**
    - `scene`, `integrator`, `t0`, `t1`, `dt0`, `stepsize_controller`, `saveat`, `solver`:
      the run, as in `simulate`.
    - `observe`: `Solution -> array`, e.g. `lambda s: jnp.stack([s.free_energy,
      s.dissipated])` or the positions of a few nodes `lambda s: s.x[:, nodes]`.
    - `data`: the observations, shaped like `observe`'s output.
    - `initial`: starting values, e.g. `{"eta_dev": 1e4, "eta_vol": 5e4}`; its keys are
      the parameters fitted (any of eta_dev, eta_vol, lam, mu, density), in log space.
    - `optimizer`: an optax transformation (default `default_optimizer()`: L-BFGS with a
      backtracking line search). It is called as `update(grad, state, params,
      value=..., grad=..., value_fn=...)`, so plain ones (`optax.adam(0.05)`) work too.
    - `max_iterations`; convergence when the gradient norm (in log space) falls below
      `gtol` or the loss changes by less than `ftol` (relative) between iterations.

    jaxvisco 0.1's `t_end`, `dt` and `save_every` are accepted as deprecated aliases.

    **Returns:** an `Identification`.
    """
    if deprecated:
        t1, dt0, saveat, stepsize_controller, _, _ = translate(deprecated, t1, dt0, saveat, stepsize_controller,
                                                               None, None, where="identify",
                                                               accepted=("t_end", "dt", "save_every"))
    if initial is None:
        raise TypeError("identify() needs initial, the starting values of the fitted parameters.")
    names = list(initial) if names is None else list(names)
    if not names:
        raise ValueError("initial must name at least one parameter to fit.")
    for n in names:
        if n not in PARAMETERS:
            raise ValueError(f"unknown parameter {n!r}; accepted: {sorted(PARAMETERS)}.")
        v = float(initial[n])
        if not (v > 0 and np.isfinite(v)):
            raise ValueError(f"initial[{n!r}] must be positive and finite, got {initial[n]!r}.")
    data = jnp.asarray(data, dtype=float)
    scale = jnp.sum(data**2)
    if not (float(scale) > 0 and np.isfinite(float(scale))):
        raise ValueError("data must be finite and not all zero.")

    opt = default_optimizer() if optimizer is None else optimizer
    static = _Static(tuple(names), integrator, observe, _Run.of(t0, t1, dt0, stepsize_controller, saveat), solver, opt)
    z = jnp.log(jnp.asarray([float(initial[n]) for n in names]))
    # The first iteration's inputs typed like the step's outputs, which the next ones
    # pass back: optax's L-BFGS state starts with a weakly typed counter
    # (num_linesearch_steps), and jit compiled the whole step a second time for the
    # strongly typed one it returns (60 s of a 3-iteration identification, measured).
    state = jax.tree_util.tree_map(lambda a: jax.lax.convert_element_type(a, a.dtype) if eqx.is_array(a) else a,
                                   opt.init(z))
    step = functools.partial(_step, static)
    history, zs = [], []
    converged, message = False, f"stopped after max_iterations = {max_iterations}"
    t_start = time.perf_counter()
    it = 0
    for it in range(1, max_iterations + 1):
        z_new, state, value, grad = step(scene, data, scale, z, state)
        value, gnorm = float(value), float(jnp.linalg.norm(grad))
        if not np.isfinite(value):
            message = f"the loss became non-finite at iteration {it} (a run failed); last finite values kept"
            break
        history.append(value)
        zs.append(np.asarray(z))
        if verbose:
            vals = ", ".join(f"{n}={float(np.exp(z[i])):.6g}" for i, n in enumerate(names))
            print(f"identify: it {it:3d}  loss {value:.3e}  |grad| {gnorm:.2e}  {vals}  "
                  f"({time.perf_counter() - t_start:.0f} s)", flush=True)
        if gnorm <= gtol:
            converged, message = True, f"gradient norm {gnorm:.2e} <= gtol"
            break
        if len(history) > 1 and abs(history[-2] - history[-1]) <= ftol * max(history[-2], 1e-300):
            converged, message = True, "loss no longer decreases (ftol)"
            break
        z = z_new
    zs = np.asarray(zs) if zs else np.asarray(z)[None]
    return Identification(
        params={n: float(np.exp(zs[-1][i])) for i, n in enumerate(names)},
        loss=float(history[-1]) if history else float("nan"), history=np.asarray(history),
        params_history={n: np.exp(zs[:, i]) for i, n in enumerate(names)}, converged=converged,
        iterations=it, message=message)


class _Run(eqx.Module):
    """The run of an identification, in a form a compiled step can hold: fixed steps as
    their exact times (static), an adaptive controller as its (dynamic) arrays."""

    t0: Optional[float] = eqx.field(static=True)
    t1: Optional[float] = eqx.field(static=True)
    dt0: Optional[float] = eqx.field(static=True)
    steps: Optional[tuple] = eqx.field(static=True)
    max_halvings: int = eqx.field(static=True)
    pid: Optional[PIDController]
    saveat: SaveAt

    @classmethod
    def of(cls, t0, t1, dt0, ctrl, saveat):
        saveat = SaveAt() if saveat is None else saveat
        if isinstance(ctrl, PIDController):
            num = lambda v: None if v is None else float(v)  # noqa: E731 (static fields: hashable numbers)
            return cls(num(t0), num(t1), num(dt0), None, 0, ctrl, saveat)
        ctrl = ConstantStepSize() if ctrl is None else ctrl
        if not isinstance(ctrl, AbstractFixedSteps):
            raise TypeError(f"stepsize_controller must be ConstantStepSize(), Schedule(...), StepTo(ts) or "
                            f"PIDController(...), got {ctrl!r}.")
        ts = ctrl.step_times(t0, t1, dt0)[1]
        return cls(None, None, None, tuple(float(t) for t in ts), ctrl.max_halvings, None, saveat)

    def simulate(self, scene, integrator, solver):
        if self.pid is not None:
            return simulate(scene, integrator, self.t0, self.t1, self.dt0, stepsize_controller=self.pid,
                            saveat=self.saveat, solver=solver, throw=False)
        return simulate(scene, integrator, stepsize_controller=StepTo(np.asarray(self.steps), self.max_halvings),
                        saveat=self.saveat, solver=solver, throw=False)


class _Static(eqx.Module):
    names: tuple = eqx.field(static=True)
    integrator: eqx.Module
    observe: Callable = eqx.field(static=True)
    run: _Run
    solver: NewtonKrylov
    opt: object = eqx.field(static=True)


def _loss(st, scene, data, scale, z):
    sc = with_parameters(scene, {n: jnp.exp(z[i]) for i, n in enumerate(st.names)})
    sol = st.run.simulate(sc, st.integrator, st.solver)
    pred = observe_checked(st.observe, sol, data.shape)
    # A failed run (a step that did not converge) counts as an infinitely bad fit: the
    # line search then backtracks instead of trusting a truncated trajectory.
    return jnp.where(sol.status_code == FAILED, jnp.inf, jnp.sum((pred - data) ** 2) / scale)


def observe_checked(observe, sol, shape):
    pred = observe(sol)
    if jnp.shape(pred) != shape:
        raise ValueError(f"observe(solution) has shape {jnp.shape(pred)}, data has {shape}.")
    return pred


@jit
def _step(st, scene, data, scale, z, state):
    """One optimizer iteration (compiled once per problem layout and reused)."""
    loss = functools.partial(_loss, st, scene, data, scale)
    value, grad = _fwd_value_and_grad(loss, z)
    updates, state = st.opt.update(grad, state, z, value=value, grad=grad, value_fn=loss)
    import optax  # imported where used: `import jaxvisco` without it is ~50 ms faster

    return optax.apply_updates(z, updates), state, value, grad


@functools.lru_cache(maxsize=1)
def default_optimizer():
    """optax L-BFGS with a backtracking (Armijo) line search: trial points need only the
    loss, not its gradient, so the compiled step holds one forward-mode gradient and one
    plain run."""
    import optax  # (see `_step`)

    return optax.lbfgs(linesearch=optax.scale_by_backtracking_linesearch(max_backtracking_steps=20))


def _fwd_value_and_grad(f, z):
    """Value and gradient of a scalar function of a few variables by forward mode."""
    basis = jnp.eye(z.shape[0], dtype=z.dtype)
    value, grads = jax.vmap(lambda d: jax.jvp(f, (z,), (d,)), out_axes=(None, 0))(basis)
    return value, grads
