"""Identification of material parameters from experiments: `identify`.

The data are what a laboratory measures in one or several tests of the material
(`Experiment`: load cells, markers, extensometers at the data's own sample times); the
parameters any named ones (`PARAMETERS`), each positive or within bounds. The fit is
Levenberg–Marquardt on the weighted residuals of all experiments (`least_squares`), its
Jacobian by forward mode through the runs (one tangent solve per step and parameter,
`_integrate._differentiable`); it reports each parameter's confidence interval, the correlations,
and which parameters the data do not determine. L-BFGS (optax) on the same cost is
kept as ``method="lbfgs"``.
"""

import copy
import dataclasses
import functools
import time
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence

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
from .._scene import Scene
from .._solver._newton import NewtonKrylov

if TYPE_CHECKING:  # imported where used (`_experiment` imports this module's neighbours)
    from ._experiment import Experiment
    from ._least_squares import LeastSquaresResult

PARAMETERS = {
    "eta_dev": lambda s: s.material.eta_dev,
    "eta_vol": lambda s: s.material.eta_vol,
    "lam": lambda s: s.material.equilibrium.lam,
    "mu": lambda s: s.material.equilibrium.mu,
    "lam_neq": lambda s: s.material.nonequilibrium.lam,
    "mu_neq": lambda s: s.material.nonequilibrium.mu,
    "density": lambda s: s.density,
}
"""The material parameters `with_parameters` and `identify` can set, by name: `eta_dev`,
`eta_vol` (viscosities), `lam`, `mu` (equilibrium branch), `lam_neq`, `mu_neq`
(non-equilibrium branch) and `density`; each maps a scene to where the value sits."""


class Identification(eqx.Module):
    """What the deprecated form `identify(scene, integrator, observe, data, ...)` returns
    (the current form returns a `Fit`).

    **Attributes:**

    - `params`: name -> fitted value.
    - `loss`: the final relative misfit.
    - `history`: the loss per iteration; `params_history`: name -> values per iteration.
    - `converged`, `iterations`, `message`: how the optimization ended.
    """

    params: dict
    loss: float
    history: np.ndarray
    params_history: dict
    converged: bool
    iterations: int
    message: str


def with_parameters(scene: Scene, values: dict) -> Scene:
    """A copy of `scene` with material parameters replaced; differentiable in the values.

    **Arguments:**

    - `scene`: a `Scene` of one material.
    - `values`: name -> value, names from `PARAMETERS` (`eta_dev`, `eta_vol`, `lam`,
      `mu`, `lam_neq`, `mu_neq`, `density`); values may be traced (`jax.grad`).

    **Returns:**

    The new `Scene`.

    **Raises:**

    `ValueError` for an unknown name, or a scene of several materials (replace a part's
    parameters with `eqx.tree_at` on `scene.material`, whose leaves hold one value per
    material).

    **Example:**

    ```python
    import jaxvisco as jv

    slow = jv.with_parameters(jv.scenes.lshape(), {"eta_dev": 1e5})
    print(float(slow.material.eta_dev))
    ```
    """
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


def _identify_trajectory(scene, integrator, observe: Callable, data, t1=None, dt0=None, initial: Optional[dict] = None, *,
             t0=None, stepsize_controller: Optional[AbstractStepSizeController] = None,
             saveat: Optional[SaveAt] = None, optimizer: Optional["optax.GradientTransformation"] = None,
             max_iterations=50, gtol=1e-7, ftol=1e-12, solver: NewtonKrylov = NewtonKrylov(rtol=1e-11),
             verbose=False, names: Optional[Sequence[str]] = None, **deprecated) -> Identification:
    """jaxvisco 0.2's `identify` (one scene, any `observe`, L-BFGS), kept for its callers:
    fit material parameters so that `observe(simulate(scene', ...))` matches `data`.

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
                            saveat=self.saveat, root_finder=solver, throw=False)
        return simulate(scene, integrator, stepsize_controller=StepTo(np.asarray(self.steps), self.max_halvings),
                        saveat=self.saveat, root_finder=solver, throw=False)


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


class Parameter(eqx.Module):
    """A parameter to fit: its start value and bounds.

    **Arguments:**

    - `start`: the value the fit starts from, strictly inside the bounds.
    - `lower`, `upper`: the bounds (default: positive, `lower = 0` and no upper bound).

    The fit works in an unconstrained variable: `log x` for a positive parameter, a
    logistic function of `log x` between two positive bounds (of `x` for a box that
    reaches zero or below).

    **Example:**

    ```python
    import jaxvisco as jv

    viscosity = jv.Parameter(6.0, lower=0.1, upper=100.0)
    ```
    """

    start: float = eqx.field(static=True)
    lower: float = eqx.field(static=True, default=0.0)
    upper: float = eqx.field(static=True, default=np.inf)

    def __init__(self, start, lower=0.0, upper=np.inf):
        self.start, self.lower, self.upper = float(start), float(lower), float(upper)


class _Problem(eqx.Module):
    """The experiments of a fit (arrays) and the names of its parameters (static)."""

    experiments: tuple
    names: tuple = eqx.field(static=True)


def _residuals(values, problem):
    """The weighted residuals of every experiment, one vector."""
    out = []
    for e in problem.experiments:
        sol = e.run(with_parameters(e.scene, dict(zip(problem.names, values))))
        out.append(((e.model(sol) - e.data) / e.scale()).ravel())
    return jnp.concatenate(out)


def _parameters(parameters, exps, where):
    """The names, start values, lower and upper bounds of a fit's `parameters` (name ->
    start value or `Parameter`), checked against the experiments `exps`."""
    if not parameters:
        raise ValueError(f"{where}: parameters must name at least one parameter, e.g. {{'eta_dev': 1e4}}.")
    specs = {}
    for n, v in parameters.items():
        if n not in PARAMETERS:
            raise ValueError(f"{where}: unknown parameter {n!r}; accepted: {sorted(PARAMETERS)}.")
        specs[n] = v if isinstance(v, Parameter) else Parameter(v)
        if n in ("lam_neq", "mu_neq") and any(e.scene.material.nonequilibrium is None for e in exps):
            raise ValueError(f"{where}: {n} belongs to the non-equilibrium branch, which a scene here lacks "
                             "(an elastic material).")
    keys = tuple(specs)
    return (keys, np.array([specs[n].start for n in keys]), np.array([specs[n].lower for n in keys]),
            np.array([specs[n].upper for n in keys]))


def sensitivities(experiment, parameters):
    """`Experiment.sensitivities`: the model and its derivatives, from the program of a
    fit of `parameters` (`least_squares.evaluate`)."""
    from ._least_squares import evaluate

    keys, values, lower, upper = _parameters(parameters, [experiment], "Experiment.sensitivities")
    residuals, args = _by_experiment(_Problem((experiment,), keys))
    r, J = evaluate(residuals[0], args[0], values, lower, upper)
    m, c = np.shape(experiment.data)
    scale = np.asarray(experiment.scale())
    model = np.asarray(r).reshape(m, c) * scale + np.asarray(experiment.data)
    J = np.asarray(J).reshape(m, c, len(keys)) * scale[None, :, None]
    return model, {n: J[..., i] for i, n in enumerate(keys)}


def _unlabelled(module, **fields):
    """A copy of `module` with `fields` replaced and its `name` blanked where that is a
    static field (an experiment's, an observable's): names only label reports and plots,
    and as static fields they would make two experiments that differ in nothing else two
    compiled programs (a fit file names a marker's column, Python need not)."""
    out = copy.copy(module)
    if any(f.name == "name" and f.metadata.get("static") for f in dataclasses.fields(module)):
        fields["name"] = ""
    for k, v in fields.items():
        object.__setattr__(out, k, v)
    return out


def _by_experiment(problem):
    """`least_squares`'s residual blocks and their arguments: one per experiment (one
    function, so that an experiment's program serves every fit it is part of, whatever
    the names of the test and its columns; the blocks run in parallel threads)."""
    exps = tuple(_unlabelled(e, observe=tuple(map(_unlabelled, e.observe))) for e in problem.experiments)
    return (_residuals,) * len(exps), tuple(_Problem((e,), problem.names) for e in exps)


def _progress(step, cost, values):
    print(f"identify: step {int(step):3d}  cost {float(cost):.6e}  "
          + "  ".join(f"{float(v):.6g}" for v in np.asarray(values)), flush=True)


class Fit:
    """What `identify` found.

    **Attributes:**

    - `names`: the fitted parameters, in order.
    - `params`: name -> fitted value.
    - `intervals`: name -> `(low, high)`, the confidence interval at level
      `confidence`, within the parameter's bounds.
    - `standard_errors`: name -> standard error (`inf` where the data do not resolve it).
    - `correlation`, `covariance`: `(p, p)` arrays in the order of `names`.
    - `identifiable`: name -> False where the data do not determine the parameter (it
      is seen only together with others, or its relative standard error exceeds 1).
    - `model`, `residuals`: experiment name -> `(m, c)`: what the fitted parameters
      predict, and prediction minus data.
    - `cost`: half the sum of the squared weighted residuals.
    - `converged`, `message`, `iterations`: how the fit ended.
    - `confidence`: the level of the intervals.
    - `result`: the `LeastSquaresResult` with every statistic.
    - `experiments`: the experiments fitted.
    """

    def __init__(self, result, experiments, model):
        self.result, self.experiments = result, tuple(experiments)
        self.names = tuple(result.names)
        as_dict = lambda a: {n: float(v) for n, v in zip(self.names, np.asarray(a))}  # noqa: E731
        self.params, self.standard_errors = as_dict(result.values), as_dict(result.standard_errors)
        self.intervals = {n: (float(lo), float(hi)) for n, (lo, hi) in zip(self.names, np.asarray(result.intervals))}
        self.identifiable = {n: bool(ok) for n, ok in zip(self.names, np.asarray(result.identifiable))}
        self.correlation, self.covariance = np.asarray(result.correlation), np.asarray(result.covariance)
        self.cost, self.confidence = float(result.cost), float(result.confidence)
        self.converged, self.message, self.iterations = bool(result.converged), result.message, int(result.iterations)
        self.model = {e.name: np.asarray(m) for e, m in zip(self.experiments, model)}
        self.residuals = {e.name: self.model[e.name] - np.asarray(e.data) for e in self.experiments}

    def summary(self) -> str:
        """One line per parameter: value, standard error and interval; then the message."""
        return self.result.summary()

    def report(self) -> dict:
        """The fit as JSON-ready data: per parameter its value, standard error, interval
        and identifiability; the correlations, cost and convergence; per experiment the
        RMS of its weighted residuals and its columns."""
        return dict(parameters={n: dict(value=self.params[n], standard_error=self.standard_errors[n],
                                        interval=list(self.intervals[n]), identifiable=self.identifiable[n])
                                for n in self.names},
                    confidence=self.confidence, correlation=self.correlation.tolist(), cost=self.cost,
                    converged=self.converged, message=self.message, iterations=self.iterations,
                    experiments={e.name: dict(rms_residual=np.sqrt(np.mean((self.residuals[e.name]
                                                                            / np.asarray(e.scale())) ** 2)).item(),
                                              columns=list(e.labels)) for e in self.experiments})

    def plot(self, path: str) -> str:
        """Draw the fit against the data, one panel per column of each experiment, with
        the residuals below, into `path` (PNG); returns `path`."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        cols = [(e, j) for e in self.experiments for j in range(np.asarray(e.data).shape[1])]
        fig, axes = plt.subplots(2, len(cols), figsize=(3.6 * len(cols), 5), squeeze=False,
                                 gridspec_kw=dict(height_ratios=[3, 1]), sharex="col")
        for k, (e, j) in enumerate(cols):
            t = np.asarray(e.times)
            top, bottom = axes[0, k], axes[1, k]
            top.plot(t, np.asarray(e.data)[:, j], ".", ms=3, label="data")
            top.plot(t, self.model[e.name][:, j], "-", lw=1.2, label="fit")
            top.set_title(f"{e.name}: {e.labels[j]}", fontsize=9)
            bottom.plot(t, self.residuals[e.name][:, j], ".", ms=2)
            bottom.axhline(0.0, color="k", lw=0.5)
            bottom.set_xlabel("t")
            if k == 0:
                top.legend(fontsize=8)
                bottom.set_ylabel("fit - data")
        fig.suptitle(", ".join(f"{n} = {self.params[n]:.4g} [{lo:.4g}, {hi:.4g}]"
                               for n, (lo, hi) in self.intervals.items()), fontsize=9)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path


def identify(experiments: "Experiment | Sequence[Experiment]", parameters: Optional[dict] = None, *args,
             method: str = "lm", max_iterations: int = 50, confidence: float = 0.95, xtol: float = 1e-10,
             ftol: float = 1e-14, gtol: float = 1e-10, optimizer: Any = None, verbose: bool = False,
             **kwargs) -> "Fit":
    """Fit material parameters to experiments: what a lab measured in one or several
    tests, fitted jointly, with each parameter's confidence interval.

    **Arguments:**

    - `experiments`: an `Experiment` or a list of them (distinct names).
    - `parameters`: name -> start value or `Parameter(start, lower, upper)`; names from
      `PARAMETERS`, set in every experiment's scene. A plain number is a positive
      parameter (fitted in `log x`).
    - `method`: `"lm"` (default: Levenberg–Marquardt with a forward-mode Jacobian) or
      `"lbfgs"` (optax L-BFGS on the same cost, its statistics from one more
      Levenberg–Marquardt step at the point it reached).
    - `max_iterations`: residual + Jacobian evaluations (LM) or L-BFGS iterations.
    - `confidence`: the level of the intervals (default 0.95).
    - `xtol`, `ftol`, `gtol`: the stopping tests, as in `least_squares`.
    - `optimizer`: with `method="lbfgs"`, an optax optimizer instead of L-BFGS.
    - `verbose`: print the cost and values after each accepted step.

    The residuals are (model - data) / sigma per column. Where every experiment gives its
    noise level (`Experiment.sigma`) the intervals take it as known (normal quantiles);
    otherwise the noise level is estimated from the residuals (Student t quantiles).

    The form of jaxvisco 0.2, `identify(scene, integrator, observe, data, t1, dt0,
    initial)`, still works with a `DeprecationWarning` and returns an `Identification`.

    **Returns:**

    A `Fit`: values, intervals, standard errors, correlations, identifiability, the
    model and residuals per experiment, `report()` and `plot()`.

    **Raises:**

    `TypeError` for experiments that are not `Experiment`s or positional options;
    `ValueError` for an unknown parameter, one the scenes lack (`lam_neq`, `mu_neq` of
    an elastic material), experiments of the same name, an unknown `method`, and as
    `least_squares` for bad bounds or options.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import jaxvisco as jv

    test = jv.scenes.specimen("relaxation", elements=(2, 1, 1), t1=1.0, dt0=0.1)
    times = np.linspace(0.0, 1.0, 11)
    load_cell = jv.ReactionForce(test.grip, "x", name="force")
    model = jv.Experiment(test.scene, jv.eG(2), times, np.zeros((11, 1)), load_cell, dt0=0.1)
    force = model.model(model.run())            # what the test measures at eta_dev = 2

    e = jv.Experiment(test.scene, jv.eG(2), times, force, load_cell, dt0=0.1, name="relaxation")
    fit = jv.identify(e, {"eta_dev": jv.Parameter(6.0, lower=0.1, upper=100.0)})
    print(fit.params["eta_dev"], fit.intervals["eta_dev"])
    ```
    """
    if isinstance(experiments, Scene):
        import warnings

        warnings.warn("identify(scene, integrator, observe, data, ...) is deprecated: describe the test as "
                      "jv.Experiment(scene, integrator, times, data, observe) and call identify(experiments, "
                      "parameters).", DeprecationWarning, stacklevel=2)
        return _identify_trajectory(experiments, parameters, *args, **kwargs)
    if args or kwargs:
        raise TypeError(f"identify(experiments, parameters, ...) takes keyword options only; got extra "
                        f"{list(args) + sorted(kwargs)}.")
    from ._experiment import Experiment
    from ._least_squares import least_squares

    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps or not all(isinstance(e, Experiment) for e in exps):
        raise TypeError("identify: experiments must be an Experiment or a list of them.")
    names = [e.name for e in exps]
    if len(set(names)) != len(names):
        raise ValueError(f"identify: experiments need distinct names, got {names}.")
    keys, start, lower, upper = _parameters(parameters, exps, "identify")
    if method not in ("lm", "lbfgs"):
        raise ValueError(f"identify: method must be 'lm' or 'lbfgs', got {method!r}.")
    problem = _Problem(tuple(exps), keys)
    known = all(e.sigma is not None for e in exps)
    common = dict(lower=lower, upper=upper, names=keys, absolute_sigma=known, xtol=xtol, ftol=ftol, gtol=gtol,
                  confidence=confidence, callback=_progress if verbose else None)
    if method == "lbfgs":  # the statistics from one Levenberg-Marquardt step where L-BFGS stopped
        start = _lbfgs(problem, start, lower, upper, keys, max_iterations, optimizer, verbose)
    residuals, args = _by_experiment(problem)
    result = least_squares(residuals, start, args, max_steps=1 if method == "lbfgs" else int(max_iterations),
                           **common)
    # what the fit predicts, from its weighted residuals (no run, no program to compile)
    r, model, k = np.asarray(result.residuals), [], 0
    for e in exps:
        d = np.asarray(e.data)
        model.append(d + r[k:k + d.size].reshape(d.shape) * np.asarray(e.scale()))
        k += d.size
    return Fit(result, exps, model)


def _lbfgs(problem, start, lower, upper, names, max_iterations, optimizer, verbose):
    """Minimize the fit's cost with optax (L-BFGS by default) in the unconstrained
    variables; returns the values it reached."""
    import optax

    from ._bounds import make_bounds

    bounds = make_bounds(start, lower, upper, names)
    opt = default_optimizer() if optimizer is None else optimizer
    z = bounds.to_unconstrained(jnp.asarray(start))
    state = jax.tree_util.tree_map(lambda a: jax.lax.convert_element_type(a, a.dtype) if eqx.is_array(a) else a,
                                   opt.init(z))
    prev = np.inf
    for it in range(1, int(max_iterations) + 1):
        z_new, state, value, grad = _lbfgs_step(problem, bounds, opt, z, state)
        value = float(value)
        if verbose:
            _progress(it, value, bounds.to_physical(z))
        if not np.isfinite(value) or abs(prev - value) <= 1e-14 * max(prev, 1e-300):
            break
        prev, z = value, z_new
    return np.asarray(bounds.to_physical(z))


class _BatchFit(eqx.Module):
    """One member's fit of `identify_batch`, from its data sets (one per experiment): a
    module, so that its experiments are inputs of the batch's program and a later batch
    of the same layout reuses it."""

    experiments: tuple
    names: tuple = eqx.field(static=True)
    start: tuple = eqx.field(static=True)  # numbers, checked against the bounds on the host
    lower: tuple = eqx.field(static=True)
    upper: tuple = eqx.field(static=True)
    known: bool = eqx.field(static=True)
    options: tuple = eqx.field(static=True)

    def __call__(self, *data):
        from ._least_squares import least_squares

        xtol, ftol, gtol, confidence, max_iterations = self.options
        exps = tuple(eqx.tree_at(lambda e: e.data, e, d) for e, d in zip(self.experiments, data))
        residuals, args = _by_experiment(_Problem(exps, self.names))
        return least_squares(residuals, np.array(self.start), args, lower=np.array(self.lower),
                             upper=np.array(self.upper), names=self.names,
                             absolute_sigma=self.known, xtol=xtol, ftol=ftol, gtol=gtol, confidence=confidence,
                             max_steps=max_iterations)


@eqx.filter_jit
def _lbfgs_step(problem, bounds, opt, z, state):
    import optax

    def cost(z):
        r = _residuals(bounds.to_physical(z), problem)
        return 0.5 * jnp.sum(r**2)

    value, grad = _fwd_value_and_grad(cost, z)
    updates, state = opt.update(grad, state, z, value=value, grad=grad, value_fn=cost)
    return optax.apply_updates(z, updates), state, value, grad


def identify_batch(experiments: "Experiment | Sequence[Experiment]", parameters: dict, data: Any, *,
                   devices: Optional[Sequence] = None, vectorize: bool = False, max_iterations: int = 50,
                   confidence: float = 0.95, xtol: float = 1e-10, ftol: float = 1e-14,
                   gtol: float = 1e-10) -> "LeastSquaresResult":
    """Many fits of the same experiments at once, one per data set of a batch (noise
    seeds, specimens), by Levenberg–Marquardt, spread over devices and processes.

    **Arguments:**

    - `experiments`, `parameters`: as `identify` (the experiments' own data are replaced).
    - `data`: one array per experiment, each `(B, m, c)`: member b's data; `B` a multiple
      of the number of devices.
    - `devices`: the devices to spread the batch over (default: every device of every
      process, as `sharded_map`).
    - `vectorize`: advance each device's members together (`jax.vmap`) instead of one
      after the other (`jax.lax.map`, the faster choice on CPUs).
    - `max_iterations`, `confidence`, `xtol`, `ftol`, `gtol`: as `identify`.

    With many processes, start each with `jax.distributed.initialize(...)` and call
    `identify_batch` with the same arguments in every process: each fits its share of
    the batch on its devices, and every process returns the whole batch.

    **Returns:**

    A `LeastSquaresResult` whose fields have a leading batch axis: `values` `(B, p)`,
    `intervals` `(B, p, 2)`, `identifiable` `(B, p)`, `status_code` `(B,)`, ...

    **Raises:**

    `ValueError` for an unknown parameter, or data of the wrong number or shape.
    """
    from jax.experimental import multihost_utils

    from ._batch import sharded_map
    from ._experiment import Experiment

    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    data = [data] if isinstance(experiments, Experiment) and not isinstance(data, (list, tuple)) else list(data)
    if len(data) != len(exps):
        raise ValueError(f"identify_batch: give one data array per experiment ({len(exps)}), got {len(data)}.")
    data = [np.asarray(d, dtype=float) for d in data]
    for e, d in zip(exps, data):
        want = np.asarray(e.data).shape
        if d.ndim != 3 or d.shape[1:] != want or d.shape[0] != data[0].shape[0]:
            raise ValueError(f"identify_batch: data of experiment {e.name!r} must be (B, {want[0]}, {want[1]}) "
                             f"with one B for all, got {d.shape}.")
    keys = tuple(parameters)
    specs = {n: v if isinstance(v, Parameter) else Parameter(v) for n, v in parameters.items()}
    for n in keys:
        if n not in PARAMETERS:
            raise ValueError(f"identify_batch: unknown parameter {n!r}; accepted: {sorted(PARAMETERS)}.")
    start, lower, upper = (tuple(float(getattr(specs[n], a)) for n in keys) for a in ("start", "lower", "upper"))
    known = all(e.sigma is not None for e in exps)

    one = _BatchFit(tuple(exps), keys, start, lower, upper, known,
                    (float(xtol), float(ftol), float(gtol), float(confidence), int(max_iterations)))

    devices = jax.devices() if devices is None else list(devices)
    if jax.process_count() == 1:
        return sharded_map(one, *data, devices=devices, vectorize=vectorize)
    # Each process places its own rows of the batch on its devices and gets the whole
    # result back.
    mesh = jax.sharding.Mesh(np.asarray(devices), ("batch",))
    spec = jax.sharding.PartitionSpec("batch")
    per = data[0].shape[0] // len(devices)
    mine = [i for i, d in enumerate(devices) if d.process_index == jax.process_index()]
    rows = np.concatenate([np.arange(i * per, (i + 1) * per) for i in mine]) if mine else np.arange(0)
    arrays = [multihost_utils.host_local_array_to_global_array(d[rows], mesh, spec) for d in data]
    out = sharded_map(one, *arrays, devices=devices, vectorize=vectorize)
    return multihost_utils.process_allgather(out, tiled=True)
