"""Weighted nonlinear least squares for a few parameters, with their uncertainty.

`least_squares` fits parameters `x` (p of them, a handful) to a long residual vector
`r(x)` (m entries, m >> p): $\\min_x \\tfrac12 \\sum_i (r_i(x)/\\sigma_i)^2$ subject to
each parameter's bounds, by Levenberg–Marquardt in unconstrained variables (`_bounds`),
and reports the Gauss–Newton (Fisher) statistics at the optimum: covariance, standard
errors, confidence intervals, correlations, and which parameters the data do not fix.

How it is built, and why (numbers: `benchmarks/least_squares_solver.py`, results in
`benchmarks/results/least_squares_solver.json`):

1. The Jacobian is forward mode, `jax.jacfwd`, evaluated with the residual in one pass:
   p tangents ride along the primal computation (a time loop) and nothing is stored.
   optimistix's `LevenbergMarquardt` (0.1) linearizes (`jax.linearize`), which keeps
   the primal's intermediates for the tangent program: on a 2000-step scan of a 200-state
   ODE (p = 3) XLA's temporaries are 10.9 MB against 1.3 MB with `jacfwd`, and the store
   grows with steps times state size.
2. Levenberg–Marquardt with the damping divided by 10 after an accepted step and doubled
   after a rejected one ("delayed gratification", Transtrum & Sethna 2012), isotropic in
   the dimensionless unconstrained variables (`_bounds`). From starts off by a factor 3
   in every direction it needed 57 and 118 evaluations in all on the benchmark's two
   problems (8 and 16 starts, exact data), optimistix's `LevenbergMarquardt` 82 and
   187; with noise 64 and 128 against 120 and 272.
3. One iteration is one residual + Jacobian evaluation (`_block`) and its acceptance, the
   convergence tests and the next trial (`_advance`). Called at top level,
   `least_squares` compiles the two as programs of their own and drives them from the
   host; under `jax.vmap` or `jax.jit` (a batch of fits over data sets, noise seeds or
   start points) they run in a `lax.while_loop`. Host-driven, XLA compiles the
   residual's own loops without nesting them in another: nested, the iteration with a
   20-step `simulate` residual took 1.5-1.8 times as long to compile (`--compile` in the
   benchmark). The evaluation alone is also what `evaluate` runs (an experiment's
   sensitivities, `Experiment.sensitivities`), so that a fit reuses its program. A
   rejected trial keeps the last Jacobian.
4. Statistics come from the SVD of the column-scaled Jacobian: a rank-deficient Jacobian
   gives finite numbers and flags, never NaN.
5. A residual given in blocks (several experiments of a joint fit) is evaluated block by
   block at top level, each block its own compiled program, the blocks in threads: a
   run and its tangents keep one CPU core busy (XLA's CPU programs of a time loop are
   sequential), so on a machine with several cores the experiments compile and run side
   by side (`benchmarks/identification.py`: its part `serial` is the one-program layout).

Per-iteration progress reaches the host through `jax.debug.callback`.
"""

import concurrent.futures
import os
import threading
from typing import Any, Callable, Optional, Sequence, Union

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats
from jax.typing import ArrayLike

from .._config import _top_level, jit
from ._bounds import make_bounds

RUNNING, XTOL, FTOL, GTOL, ZERO, MAX_STEPS, NOT_FINITE = range(7)
STATUS = {
    RUNNING: "running",
    XTOL: "converged: the next step is below xtol",
    FTOL: "converged: the Gauss-Newton decrement fell below ftol times the cost",
    GTOL: "converged: the scaled gradient fell below gtol",
    ZERO: "converged: the residuals are zero",
    MAX_STEPS: "not converged: max_steps evaluations reached",
    NOT_FINITE: "not converged: the residual or its Jacobian is not finite at the start",
}


class LeastSquaresResult(eqx.Module):
    """A least-squares fit and its statistics, what `least_squares` (and `identify_batch`)
    return; p parameters, m residuals.

    **Attributes:**

    - `names`: parameter names (static).
    - `values`: fitted values `(p,)`.
    - `standard_errors`: `(p,)`, by the delta method through the bound transform; `inf`
      for a parameter in a direction the data do not resolve (see `identifiable`).
    - `intervals`: `(p, 2)` confidence intervals at level `confidence`, taken in the
      unconstrained variable and mapped back: they lie within the bounds (a positive
      parameter's interval is positive; these are log-normal intervals for it).
    - `covariance`: `(p, p)` Gauss–Newton covariance of the values,
      $s^2 (J^T J)^+$ mapped through the transform; unresolved directions are left out
      (pseudo-inverse), so entries of an unidentifiable parameter are not its
      uncertainty.
    - `correlation`: `(p, p)` correlation matrix; for unresolved parameters the limit of
      a vanishing singular value (two parameters the data see only together: -1 or +1).
    - `identifiable`: `(p,)` bools, see `least_squares` for the criterion.
    - `relative_errors`: `standard_errors / |values|`, `(p,)`.
    - `singular_values`: of the column-scaled Jacobian in the unconstrained variables,
      descending, `(p,)`.
    - `cost`: $\\tfrac12 \\sum_i (r_i/\\sigma_i)^2$ at the optimum.
    - `residuals`: the weighted residuals $r_i/\\sigma_i$ at the optimum, `(m,)`.
    - `noise_variance`: $s^2$: `2 cost / (m - p)`, or 1 with `absolute_sigma=True`.
    - `iterations`: residual + Jacobian evaluations after the start.
    - `steps`: accepted steps.
    - `status_code`: an entry of `STATUS`.
    - `history_cost`, `history_values`: the cost and values of the start and of every
      accepted step, `(max_steps + 1,)` and `(max_steps + 1, p)`, NaN after `steps`
      (see `history`).
    - `confidence`: the confidence level of `intervals` (static).
    """

    names: tuple = eqx.field(static=True)
    values: jax.Array
    standard_errors: jax.Array
    intervals: jax.Array
    covariance: jax.Array
    correlation: jax.Array
    identifiable: jax.Array
    relative_errors: jax.Array
    singular_values: jax.Array
    cost: jax.Array
    residuals: jax.Array
    noise_variance: jax.Array
    iterations: jax.Array
    steps: jax.Array
    status_code: jax.Array
    history_cost: jax.Array
    history_values: jax.Array
    confidence: float = eqx.field(static=True)

    @property
    def converged(self) -> bool:
        """Whether a convergence test stopped the iteration."""
        return int(self.status_code) in (XTOL, FTOL, GTOL, ZERO)

    @property
    def message(self) -> str:
        """Why the iteration stopped, and which parameters the data do not determine."""
        text = f"{STATUS[int(self.status_code)]} after {int(self.iterations)} evaluations"
        bad = [n for n, ok in zip(self.names, np.asarray(self.identifiable)) if not ok]
        if bad:
            text += f"; not identifiable from these data: {', '.join(bad)}"
        return text + "."

    @property
    def history(self):
        """`(cost, values)` of the start and every accepted step, as NumPy arrays
        `(steps + 1,)` and `(steps + 1, p)`."""
        n = int(self.steps) + 1
        return np.asarray(self.history_cost)[:n], np.asarray(self.history_values)[:n]

    def summary(self) -> str:
        """A table: value, standard error, interval and identifiability per parameter."""
        width = max(len(n) for n in self.names)
        lines = [f"{'':{width}}  {'value':>12}  {'std. error':>10}  {round(100 * self.confidence):>2}% interval"]
        rows = zip(self.names, *(np.asarray(a) for a in (self.values, self.standard_errors, self.intervals,
                                                          self.identifiable)))  # fmt: skip
        for name, value, se, (lo, hi), ok in rows:
            note = "" if ok else "  not identifiable"
            lines.append(f"{name:{width}}  {value:12.6g}  {se:10.3g}  [{lo:.6g}, {hi:.6g}]{note}")
        lines.append(self.message)
        return "\n".join(lines)


def least_squares(
    residual: Union[Callable, Sequence[Callable]],
    start: ArrayLike,
    args: Any = None,
    *,
    lower: Optional[ArrayLike] = None,
    upper: Optional[ArrayLike] = None,
    names: Optional[Sequence[str]] = None,
    sigma: Optional[ArrayLike] = None,
    absolute_sigma: bool = False,
    xtol: float = 1e-10,
    ftol: float = 1e-14,
    gtol: float = 1e-10,
    max_steps: int = 50,
    confidence: float = 0.95,
    rcond: float = 1e-8,
    max_relative_error: float = 1.0,
    callback: Optional[Callable] = None,
) -> LeastSquaresResult:
    """Fit a few parameters to many residuals by Levenberg–Marquardt, with statistics.

    Minimizes $\\tfrac12\\sum_i (r_i(x)/\\sigma_i)^2$ over `x` within the bounds, in one
    compiled program; vmappable over `args` (data) and `start`, so a batch of fits runs
    as one program.

    **Arguments:**

    - `residual`: `residual(values, args) -> (m,)` array, differentiable in forward mode
      (`jax.jacfwd`) and traceable by `jax.jit`; `values` is `(p,)`. Or a sequence of
      such functions (blocks, e.g. experiments) with a sequence of `args`: concatenated,
      evaluated in parallel threads.
    - `start`: start values `(p,)`, strictly inside their bounds.
    - `args`: passed to `residual` (data, a scene); a pytree of arrays.
    - `lower`, `upper`: `(p,)` bounds, `-inf`/`inf` (or `None` for all) where absent.
      `lower = 0` without an upper bound makes a parameter positive (fitted in `log x`).
    - `names`: one name per parameter (default `x0`, `x1`, ...).
    - `sigma`: noise standard deviations (scalar or `(m,)`): the residuals are divided by
      them. Default 1.
    - `absolute_sigma`: `True` if `sigma` is the noise level itself: covariance
      $(J^T J)^{-1}$, normal quantiles. `False` (default): only relative weights are
      known, the noise variance is estimated as $s^2 = 2\\,\\text{cost}/(m - p)$,
      covariance $s^2 (J^T J)^{-1}$, Student-t quantiles with m - p degrees of freedom
      (as `scipy.optimize.curve_fit`).
    - `xtol`: stop when every component of the next step in the unconstrained variables
      is at most `xtol` (relative changes for a positive parameter).
    - `ftol`: stop when the Gauss–Newton decrement (the most the linear model can still
      reduce the cost) is at most `ftol` times the cost.
    - `gtol`: stop when $\\max_j |J_j^T r| / (\\|J_j\\|\\,\\|r\\|) \\le$ `gtol` (the largest
      cosine between the residual and a Jacobian column).
    - `max_steps`: the most residual + Jacobian evaluations after the start.
    - `confidence`: the level of the intervals.
    - `rcond`: singular values of the column-scaled Jacobian below `rcond` times the
      largest count as zero.
    - `max_relative_error`: the largest relative standard error of an identifiable
      parameter.
    - `callback`: `callback(step, cost, values)` on the host at the start (step 0) and
      after every accepted step, e.g. to print progress; a new function object compiles
      the solve again.

    **Returns:**

    A `LeastSquaresResult`. A parameter is flagged not identifiable when a null
    direction of the column-scaled Jacobian (singular values below `rcond` times the
    largest) dominates its variance (its standard error is then `inf`), or when its
    relative standard error exceeds `max_relative_error`.

    **Raises:**

    `ValueError` for bounds that are not numbers, `lower >= upper`, a start that is not
    finite or not strictly inside its bounds (each naming the parameter and values), a
    residual that is not a vector, `sigma` of the wrong shape or not positive, too few
    residuals (m < p, or m = p without `absolute_sigma`), or bad options.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import jaxvisco as jv

    def residual(x, data):
        t, y = data
        return x[0] * jnp.exp(-t / x[1]) + x[2] - y

    t = jnp.linspace(0.0, 5.0, 100)
    y = 2.0 * jnp.exp(-t / 1.3) + 0.5 + 0.05 * jax.random.normal(jax.random.PRNGKey(0), t.shape)
    fit = jv.least_squares(residual, [1.0, 0.5, 0.0], (t, y), lower=[0.0, 0.1, -jnp.inf],
                           upper=[jnp.inf, 10.0, jnp.inf], names=["a", "tau", "c"])
    print(fit.summary())  # a, tau (positive, in [0.1, 10]) and c with 95 % intervals
    ```
    """
    p = np.shape(start)[0] if np.ndim(start) == 1 else 0
    if p == 0:
        raise ValueError(f"start must be a vector of p >= 1 values, got shape {np.shape(start)}.")
    names = tuple(f"x{i}" for i in range(p)) if names is None else tuple(str(n) for n in names)
    if len(names) != p or len(set(names)) != p:
        raise ValueError(f"names must be {p} distinct names, got {names}.")
    bounds = make_bounds(start, lower, upper, names)
    start = jnp.asarray(start, dtype=jnp.float64)
    for label, value, ok in (("xtol", xtol, xtol > 0), ("ftol", ftol, ftol >= 0), ("gtol", gtol, gtol >= 0),
                             ("confidence", confidence, 0 < confidence < 1), ("rcond", rcond, 0 < rcond < 1),
                             ("max_relative_error", max_relative_error, max_relative_error > 0)):  # fmt: skip
        if not ok:
            raise ValueError(f"{label}={value!r} is out of range.")
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps must be an integer >= 1, got {max_steps!r}.")

    if callable(residual):
        residuals, args = (residual,), (args,)
    else:
        residuals = tuple(residual)
        if not residuals or not all(callable(f) for f in residuals):
            raise ValueError(f"residual must be a function or a sequence of functions, got {residual!r}.")
        if not isinstance(args, (list, tuple)) or len(args) != len(residuals):
            raise ValueError(f"with {len(residuals)} residual functions, args must be a sequence of as many "
                             f"(one per block), got {type(args).__name__}.")
        args = tuple(args)
    sizes = []
    for f, a in zip(residuals, args):
        out = eqx.filter_eval_shape(f, jnp.zeros(p), a)
        if not hasattr(out, "shape") or len(out.shape) != 1:
            raise ValueError(f"residual must return a vector (m,), got {getattr(out, 'shape', out)!r}.")
        sizes.append(out.shape[0])
    m = sum(sizes)
    if m < p or (m == p and not absolute_sigma):
        raise ValueError(f"{m} residuals cannot determine {p} parameters and the noise level; need "
                         "m > p, or m >= p with the noise level as sigma and absolute_sigma=True.")
    sigma = jnp.ones(m) if sigma is None else jnp.asarray(sigma, dtype=jnp.float64)
    if sigma.shape not in ((), (m,)):
        raise ValueError(f"sigma must be a number or have one entry per residual ({m},), got shape {sigma.shape}.")
    sigma = jnp.broadcast_to(sigma, (m,))
    if not isinstance(sigma, jax.core.Tracer) and not np.all((np.asarray(sigma) > 0) & np.isfinite(sigma)):
        raise ValueError("sigma must be positive and finite.")
    dof = m - p
    q = scipy.stats.norm.ppf(0.5 + confidence / 2) if absolute_sigma else scipy.stats.t.ppf(0.5 + confidence / 2, dof)
    options = jnp.asarray([xtol, ftol, gtol, rcond, max_relative_error, q, 0.0 if absolute_sigma else 1.0 / dof])
    return _solve(residuals, tuple(sizes), bounds.to_unconstrained(start), args, sigma, bounds, options,
                  int(max_steps), callback, names, float(confidence))


class _State(eqx.Module):
    z: jax.Array  # the accepted point (unconstrained), its residuals, Jacobian and cost
    r: jax.Array
    J: jax.Array
    cost: jax.Array
    trial: jax.Array  # the point the next evaluation is at, and its predicted reduction
    predicted: jax.Array
    lam: jax.Array
    scale: jax.Array  # the largest column norm of J seen: the damping is lam * scale^2
    evaluations: jax.Array
    steps: jax.Array
    status: jax.Array
    history_cost: jax.Array
    history_z: jax.Array


def _column_norms(J):
    n = jnp.linalg.norm(J, axis=0)
    return jnp.where(jnp.isfinite(n) & (n > 0), n, 1.0)


def _scaled_svd(Js, r):
    """Singular values `S` (descending), right singular vectors `Vt` of `Js` (m x p, m >=
    p), and the residual's components `U^T r`, from a thin QR then the SVD of R."""
    Q, R = jnp.linalg.qr(Js)
    U, S, Vt = jnp.linalg.svd(R)
    return S, Vt, U.T @ (Q.T @ r)


def _cosine(r, J):
    """The largest cosine between `r` and a column of `J` (0 for zero columns)."""
    norms = jnp.linalg.norm(J, axis=0) * jnp.linalg.norm(r)
    ok = norms > 0
    return jnp.max(jnp.where(ok, jnp.abs(J.T @ r) / jnp.where(ok, norms, 1.0), 0.0))


class _Problem(eqx.Module):
    """What every iteration needs: the residual blocks, their sizes and the callback
    (static), the data (one `args` per block), the weights, the bounds and the options."""

    residuals: tuple = eqx.field(static=True)
    sizes: tuple = eqx.field(static=True)
    callback: Optional[Callable] = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    args: tuple
    sigma: jax.Array
    bounds: object
    options: jax.Array


def _solve(residuals, sizes, z0, args, sigma, bounds, options, max_steps, callback, names, confidence):
    problem = _Problem(residuals, sizes, callback, max_steps, args, sigma, bounds, options)
    m, p = sigma.shape[0], z0.shape[0]
    # Typed as the iteration returns them (no weak types), or its program is compiled twice.
    f64 = lambda v: jnp.asarray(v, dtype=jnp.float64)  # noqa: E731
    i32 = lambda v: jnp.asarray(v, dtype=jnp.int32)  # noqa: E731
    state = _State(
        z=f64(z0), r=jnp.zeros(m), J=jnp.zeros((m, p)), cost=f64(jnp.inf), trial=f64(z0), predicted=f64(0.0),
        lam=f64(1e-2), scale=f64(1.0), evaluations=i32(0), steps=i32(0), status=i32(RUNNING),
        history_cost=f64(jnp.full(max_steps + 1, jnp.nan)), history_z=f64(jnp.full((max_steps + 1, p), jnp.nan)),
    )  # fmt: skip
    if _top_level():  # see the module notes (3., 5.)
        with concurrent.futures.ThreadPoolExecutor(min(len(residuals), os.cpu_count() or 1)) as pool:
            run_block = _first_block
            while int(state.status) == RUNNING:
                blocks = list(pool.map(run_block, _blocks(problem, state.trial)))
                run_block = lambda b: _block_jit(*b)  # noqa: E731
                J = jnp.concatenate([b[0] for b in blocks])
                r = jnp.concatenate([b[1] for b in blocks])
                state = _advance_jit(problem, state, J, r)
        return _statistics_jit(problem, state, names, confidence)
    state = jax.lax.while_loop(lambda s: s.status == RUNNING, lambda s: _iteration(problem, s), state)
    return _statistics(problem, state, names, confidence)


_LOWERING = threading.Lock()


def _first_block(block):
    """A block's first evaluation, its program compiled ahead (its jit call then finds
    it) with tracing and lowering (or loading the traced program, with the persistent
    cache on) taken one block at a time: they hold Python's lock, so blocks traced side by
    side would all finish late; one at a time, the first compiles (which releases the
    lock) and runs while the next is traced (the module notes, 5.)."""
    with _LOWERING:
        lowered = _block_jit.ahead(*block)
    if lowered is not None:
        lowered.compile()
    return _block_jit(*block)


def evaluate(residual, args, values, lower=None, upper=None):
    """A residual `residual(x, args)` `(m,)` and its Jacobian `(m, p)` in the parameters at
    `values` `(p,)` (bounds: as `least_squares`'), by the program a fit of them evaluates
    at each iteration: a fit after this call compiles nothing new for it."""
    values = np.asarray(values, dtype=np.float64)
    names = tuple(f"x{i}" for i in range(values.size))
    bounds = make_bounds(values, lower, upper, names)
    z = bounds.to_unconstrained(jnp.asarray(values))
    m = eqx.filter_eval_shape(residual, jnp.zeros(values.size), args).shape[0]
    J, r = _block_jit(residual, args, jnp.ones(m), bounds, z)
    return r, J / bounds.slope(z)


def _block(residual, args, sigma, bounds, z):
    """One block's weighted residuals `residual(x(z), args) / sigma` and their Jacobian
    in `z` (forward mode)."""

    def weighted(z):
        r = residual(bounds.to_physical(z), args) / sigma
        return r, r

    return jax.jacfwd(weighted, has_aux=True)(z)


def _blocks(problem: _Problem, z):
    """The arguments of `_block` for every block at `z`."""
    offsets = np.cumsum((0,) + problem.sizes)
    return [(problem.residuals[k], problem.args[k], problem.sigma[offsets[k]:offsets[k + 1]], problem.bounds, z)
            for k in range(len(problem.sizes))]


def _iteration(problem: _Problem, s: _State) -> _State:
    """One residual + Jacobian evaluation (the start, or a trial step), its acceptance,
    the convergence tests, and the next trial step."""
    blocks = [_block(*b) for b in _blocks(problem, s.trial)]
    return _advance(problem, s, jnp.concatenate([b[0] for b in blocks]), jnp.concatenate([b[1] for b in blocks]))


def _advance(problem: _Problem, s: _State, J, r) -> _State:
    """The evaluation `J`, `r` at `s.trial`: its acceptance, the convergence tests, and
    the next trial step."""
    xtol, ftol, gtol = problem.options[0], problem.options[1], problem.options[2]
    bounds = problem.bounds
    cost = 0.5 * jnp.dot(r, r)
    finite = jnp.isfinite(cost) & jnp.all(jnp.isfinite(J))
    first = s.evaluations == 0
    rho = (s.cost - cost) / jnp.where(s.predicted > 0, s.predicted, 1.0)
    accept = finite & (first | ((s.predicted > 0) & (rho > 1e-4)))
    # "Delayed gratification" (Transtrum & Sethna 2012): damping / 10 after a success,
    # x 2 after a failure.
    lam = jnp.where(first, s.lam, jnp.where(accept, s.lam / 10.0, s.lam * 2.0))
    z = jnp.where(accept, s.trial, s.z)
    r = jnp.where(accept, r, s.r)
    J = jnp.where(accept, J, s.J)
    cost = jnp.where(accept, cost, s.cost)
    scale = jnp.maximum(jnp.where(first, 0.0, s.scale), jnp.max(_column_norms(J)))
    steps = s.steps + (accept & ~first).astype(jnp.int32)
    history_cost = jnp.where(accept, jax.lax.dynamic_update_index_in_dim(s.history_cost, cost, steps, 0),
                             s.history_cost)  # fmt: skip
    history_z = jnp.where(accept, jax.lax.dynamic_update_index_in_dim(s.history_z, z, steps, 0), s.history_z)
    evaluations = s.evaluations + 1
    if problem.callback is not None:  # (under vmap, iterations of stopped fits run on: not reported)
        jax.debug.callback(_report(problem.callback), accept & (s.status == RUNNING), steps, cost,
                           bounds.to_physical(z))  # fmt: skip

    # The next trial: the damped Gauss-Newton step, min |J u + r|^2 + lam scale^2 |u|^2
    # (isotropic in the dimensionless unconstrained variables), by the SVD of
    # J / scale = U S V^T.
    S, Vt, g = _scaled_svd(J / scale, r)
    step = -(Vt.T @ (S / (S**2 + lam) * g)) / scale
    predicted = 0.5 * jnp.sum(g**2 * (1.0 - (lam / (S**2 + lam)) ** 2))
    # A step below xtol stops before it is evaluated: z is that close to where the
    # linear model (or, after rejections, the trust region) puts the optimum.
    small_step = jnp.all(jnp.abs(step) <= xtol)
    # The Gauss-Newton decrement |U^T r|^2 / 2: the most the linear model can still
    # gain, i.e. cost times the squared cosine between r and the range of J.
    small_cost = 0.5 * jnp.sum(g**2) <= ftol * cost
    status = jnp.select(
        [first & ~finite, accept & (cost == 0), small_cost, accept & (_cosine(r, J) <= gtol), small_step,
         evaluations > problem.max_steps],
        [NOT_FINITE, ZERO, FTOL, GTOL, XTOL, MAX_STEPS], RUNNING,
    ).astype(jnp.int32)  # fmt: skip
    return _State(z, r, J, cost, z + step, predicted, lam, scale, evaluations, steps, status, history_cost, history_z)


def _report(callback):
    def call(accepted, steps, cost, x):
        if accepted:
            callback(int(steps), float(cost), np.asarray(x))

    return call


def _statistics(problem: _Problem, s: _State, names, confidence) -> LeastSquaresResult:
    """Gauss-Newton statistics at the final point of the iteration."""
    rcond, max_relative_error, q, inv_dof = problem.options[3:]
    bounds = problem.bounds
    z, r, J = s.z, s.r, s.J
    x = bounds.to_physical(z)
    dxdz = bounds.slope(z)
    D = _column_norms(J)
    S, Vt, _ = _scaled_svd(J / D, r)
    floor = rcond * S[0] + jnp.finfo(S.dtype).tiny
    null = S <= floor
    inverse = jnp.where(null, 0.0, 1.0 / jnp.where(null, 1.0, S**2))
    s2 = jnp.where(inv_dof > 0, 2.0 * s.cost * inv_dof, 1.0)
    Cz = s2 * (Vt.T * inverse) @ Vt / jnp.outer(D, D)
    # Unresolved: the null directions, even at the floor, would dominate the variance.
    unresolved = jnp.sum(jnp.where(null[:, None], Vt**2, 0.0), axis=0) / floor**2 > inverse @ Vt**2
    se_z = jnp.where(unresolved, jnp.inf, jnp.sqrt(jnp.maximum(jnp.diag(Cz), 0.0)))
    se = jnp.where(unresolved, jnp.inf, jnp.abs(dxdz) * jnp.where(unresolved, 0.0, se_z))
    # Correlations are invariant to the column scaling; a vanishing singular value is
    # regularized to rcond times the largest, so it dominates its parameters' rows.
    w = 1.0 / (S**2 + floor**2)
    Cs = (Vt.T * (w / jnp.max(w))) @ Vt
    d = jnp.sqrt(jnp.diag(Cs))
    correlation = Cs / jnp.outer(d, d)
    correlation = jnp.where(jnp.eye(len(z), dtype=bool), 1.0, correlation)
    half = q * se_z
    intervals = jnp.stack([bounds.to_physical(z - half), bounds.to_physical(z + half)], axis=-1)
    relative = jnp.where(x != 0, se / jnp.abs(jnp.where(x != 0, x, 1.0)), jnp.inf)
    return LeastSquaresResult(
        names=names, values=x, standard_errors=se, intervals=intervals, covariance=Cz * jnp.outer(dxdz, dxdz),
        correlation=correlation, identifiable=~unresolved & (relative <= max_relative_error),
        relative_errors=relative, singular_values=S, cost=s.cost, residuals=r, noise_variance=s2,
        iterations=s.evaluations - 1, steps=s.steps, status_code=s.status, history_cost=s.history_cost,
        history_values=jax.vmap(bounds.to_physical)(s.history_z), confidence=confidence,
    )  # fmt: skip


_statistics_jit = jit(_statistics)
_advance_jit = jit(_advance)
_block_jit = jit(_block, export=True)
