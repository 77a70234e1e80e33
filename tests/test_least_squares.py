"""Weighted nonlinear least squares with uncertainty (`jaxvisco.least_squares`)."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import jaxvisco as jv
from jaxvisco._tools._bounds import BOX, FREE, LOG_BOX, LOWER, POSITIVE, UPPER, make_bounds

T = jnp.linspace(0.0, 5.0, 100)
TRUE = np.array([2.0, 1.3, 0.5])
LOWER_B, UPPER_B = [0.0, 0.1, -np.inf], [np.inf, 10.0, np.inf]  # a positive, tau in a box, c free
NAMES = ["a", "tau", "c"]
NOISE = 0.05


def model(x, t):
    return x[0] * jnp.exp(-t / x[1]) + x[2]


def residual(x, y):
    return model(x, T) - y


def fit(start, y, **kwargs):
    return jv.least_squares(residual, start, y, lower=LOWER_B, upper=UPPER_B, names=NAMES, **kwargs)


def noisy(seed, sigma=NOISE):
    return model(TRUE, T) + sigma * jax.random.normal(jax.random.PRNGKey(seed), T.shape)


@pytest.mark.parametrize("factors", list(itertools.product([3.0, 1 / 3], repeat=3)))
def test_exact_data_recovered_from_starts_off_by_three(factors):
    start = TRUE * np.asarray(factors)
    result = fit(start, model(TRUE, T))
    assert result.converged, result.message
    np.testing.assert_allclose(result.values, TRUE, rtol=1e-8, atol=0)
    assert int(result.iterations) <= 15  # residual + Jacobian evaluations after the start
    cost, values = result.history
    assert len(cost) == int(result.steps) + 1 and np.all(np.diff(cost) < 0)
    np.testing.assert_allclose(values[0], start, rtol=1e-14)
    np.testing.assert_allclose(values[-1], result.values, rtol=1e-14)


@pytest.mark.parametrize("absolute_sigma", [False, True])
def test_interval_coverage_over_noise_seeds(absolute_sigma):
    """500 noisy data sets fitted at once (vmap): each parameter's 95 % interval covers
    the truth in 90-99 % of them, and the standard errors match the spread of the
    estimates."""
    Y = jax.vmap(noisy)(jnp.arange(500))
    sigma = NOISE if absolute_sigma else None
    fits = jax.vmap(lambda y: fit(TRUE * 3.0, y, sigma=sigma, absolute_sigma=absolute_sigma))(Y)
    assert np.all(np.isin(np.asarray(fits.status_code), [1, 2, 3]))  # all converged
    lo, hi = np.asarray(fits.intervals[..., 0]), np.asarray(fits.intervals[..., 1])
    coverage = np.mean((lo <= TRUE) & (TRUE <= hi), axis=0)
    assert np.all((0.90 <= coverage) & (coverage <= 0.99)), coverage
    spread = np.std(np.asarray(fits.values), axis=0)
    np.testing.assert_allclose(np.mean(np.asarray(fits.standard_errors), axis=0), spread, rtol=0.1)
    if absolute_sigma:  # the noise level given, not estimated
        np.testing.assert_allclose(fits.noise_variance, 1.0)
    else:
        np.testing.assert_allclose(np.mean(np.asarray(fits.noise_variance)), NOISE**2, rtol=0.02)


def test_matches_scipy_and_curve_fit():
    """The optimum of noisy data equals scipy's, and the covariance equals curve_fit's
    (both given the exact Jacobian)."""
    y = np.asarray(noisy(7))
    result = fit(TRUE * 3.0, y)
    jac = jax.jit(jax.jacfwd(lambda x: model(x, T)))
    ref = scipy.optimize.least_squares(lambda x: np.asarray(residual(x, y)), TRUE * 3.0,
                                       jac=lambda x: np.asarray(jac(x)), bounds=(LOWER_B, UPPER_B), xtol=1e-15,
                                       ftol=1e-15, gtol=1e-15)  # fmt: skip
    np.testing.assert_allclose(result.values, ref.x, rtol=1e-7)
    np.testing.assert_allclose(result.cost, ref.cost, rtol=1e-12)
    popt, pcov = scipy.optimize.curve_fit(lambda t, *x: np.asarray(model(x, t)), np.asarray(T), y, p0=ref.x,
                                          jac=lambda t, *x: np.asarray(jac(np.asarray(x))))  # fmt: skip
    np.testing.assert_allclose(result.covariance, pcov, rtol=1e-6)
    np.testing.assert_allclose(result.standard_errors, np.sqrt(np.diag(pcov)), rtol=1e-6)
    d = np.sqrt(np.diag(pcov))
    np.testing.assert_allclose(result.correlation, pcov / np.outer(d, d), atol=1e-6)
    assert np.all(result.identifiable)


def test_parameter_the_data_cannot_see_is_flagged():
    """A fourth parameter the model ignores: flagged, infinite standard error, interval =
    its bounds, and the others fitted as without it; nothing is NaN."""
    y = noisy(3)
    three = fit(TRUE * 3.0, y)
    four = jv.least_squares(lambda x, y: residual(x[:3], y), [6.0, 3.9, 1.5, 2.0], y, lower=LOWER_B + [0.0],
                            upper=UPPER_B + [np.inf], names=NAMES + ["ghost"])  # fmt: skip
    assert four.converged
    np.testing.assert_array_equal(four.identifiable, [True, True, True, False])
    assert "not identifiable from these data: ghost" in four.message
    np.testing.assert_allclose(four.values[:3], three.values, rtol=1e-7)
    # The same Jacobian columns; s^2 = 2 cost / (m - p) counts the ghost among the p.
    np.testing.assert_allclose(four.standard_errors[:3], three.standard_errors * np.sqrt(97 / 96), rtol=1e-6)
    assert float(four.values[3]) == 2.0 and np.isinf(four.standard_errors[3])
    np.testing.assert_array_equal(four.intervals[3], [0.0, np.inf])
    for a in (four.values, four.intervals[:3], four.covariance, four.correlation, four.relative_errors[:3]):
        assert np.all(np.isfinite(a))
    np.testing.assert_allclose(four.correlation[3], [0, 0, 0, 1], atol=1e-6)


def test_parameters_seen_only_together_are_flagged():
    """y = a b exp(-t/tau) + c: a and b only as their product; both flagged, correlation
    -1 between them (in log variables their sum is fixed), tau and c identifiable."""
    y = noisy(4)
    result = jv.least_squares(lambda x, y: residual(jnp.stack([x[0] * x[1], x[2], x[3]]), y), [3.0, 2.0, 3.9, 1.5],
                              y, lower=[0, 0] + LOWER_B[1:], upper=[np.inf, np.inf] + UPPER_B[1:],
                              names=["a", "b", "tau", "c"])  # fmt: skip
    assert result.converged
    np.testing.assert_array_equal(result.identifiable, [False, False, True, True])
    np.testing.assert_allclose(result.values[0] * result.values[1], fit(TRUE * 3.0, y).values[0], rtol=1e-7)
    assert result.correlation[0, 1] < -0.999
    assert np.all(np.isfinite(result.correlation)) and np.all(np.isfinite(result.covariance))
    assert np.all(np.isinf(result.standard_errors[:2])) and np.all(np.isfinite(result.standard_errors[2:]))


def test_weakly_determined_parameter_is_flagged_by_its_relative_error():
    """A term 1e-3 d sin(2 pi t), far below the noise: d is resolved in rank (its column
    is independent) but its relative standard error is far above 1; nothing else is
    affected."""
    bump = 1e-3 * jnp.sin(2 * jnp.pi * T)
    y = noisy(5) + bump

    def with_bump(x, y):
        return residual(x[:3], y) + x[3] * bump

    result = jv.least_squares(with_bump, [6.0, 3.9, 1.5, 1.0], y, lower=LOWER_B + [-np.inf],
                              upper=UPPER_B + [np.inf], names=NAMES + ["d"])  # fmt: skip
    assert result.converged
    assert np.all(np.isfinite(result.standard_errors))
    assert result.relative_errors[3] > 1.0 and np.all(result.relative_errors[:3] < 0.1)
    np.testing.assert_array_equal(result.identifiable, [True, True, True, False])
    assert "not identifiable from these data: d" in result.message


A, TAU, C = "parameter 'a'", "parameter 'tau'", "parameter 'c'"


@pytest.mark.parametrize(
    "lower, upper, start, message",
    [
        ([0, 2.0, -np.inf], [np.inf, 1.0, np.inf], [1.0, 1.5, 0.0],
         f"{TAU}: lower bound 2.0 must be below upper bound 1.0"),
        (LOWER_B, UPPER_B, [1.0, 20.0, 0.0], rf"{TAU}: start value 20.0 must lie strictly inside .*\(0.1, 10.0\)"),
        (LOWER_B, UPPER_B, [-1.0, 1.0, 0.0], rf"{A}: start value -1.0 must lie strictly inside .*\(0.0, inf\)"),
        (LOWER_B, UPPER_B, [0.0, 1.0, 0.0], f"{A}: start value 0.0 must lie strictly inside"),
        ([0.0, np.nan, -np.inf], UPPER_B, [1.0, 1.0, 0.0], f"{TAU}: bounds must be numbers, .* got lower=nan"),
        (LOWER_B, UPPER_B, [1.0, 1.0, np.inf], f"{C}: start value must be finite, got inf"),
        ([0.0, 0.1], UPPER_B, [1.0, 1.0, 0.0], r"lower must have one entry per parameter \(3\)"),
    ],
)
def test_bad_bounds_are_refused(lower, upper, start, message):
    with pytest.raises(ValueError, match=message):
        jv.least_squares(residual, start, model(TRUE, T), lower=lower, upper=upper, names=NAMES)


def test_bad_options_are_refused():
    y = model(TRUE, T)
    with pytest.raises(ValueError, match=r"cannot determine 3 parameters and the noise level"):
        jv.least_squares(lambda x, y: residual(x, y)[:3], TRUE, y)
    with pytest.raises(ValueError, match="residual must return a vector"):
        jv.least_squares(lambda x, y: jnp.sum(residual(x, y)), TRUE, y)
    with pytest.raises(ValueError, match="sigma must be positive"):
        jv.least_squares(residual, TRUE, y, sigma=0.0)
    with pytest.raises(ValueError, match="names must be 3 distinct names"):
        jv.least_squares(residual, TRUE, y, names=["a", "a", "c"])
    with pytest.raises(ValueError, match="max_steps must be an integer >= 1"):
        jv.least_squares(residual, TRUE, y, max_steps=0)
    with pytest.raises(ValueError, match="confidence=1.5 is out of range"):
        jv.least_squares(residual, TRUE, y, confidence=1.5)


def test_progress_callback_and_stops():
    seen = []
    result = fit(TRUE * 3.0, noisy(1), callback=lambda step, cost, values: seen.append((step, cost, values)))
    steps = [s for s, _, _ in seen]
    assert steps == list(range(int(result.steps) + 1))
    np.testing.assert_allclose([c for _, c, _ in seen], result.history[0], rtol=1e-14)
    np.testing.assert_allclose(seen[-1][2], result.values, rtol=1e-14)
    short = fit(TRUE * 3.0, noisy(1), max_steps=2)
    assert not short.converged and int(short.iterations) == 2
    assert "max_steps" in short.message
    broken = jv.least_squares(lambda x, y: residual(x, y) / (x[2] - 1.5), TRUE * 3.0, noisy(1))
    assert not broken.converged and "not finite at the start" in broken.message


def test_residual_in_blocks_equals_the_whole():
    """A residual given in blocks (two halves of the data, with their own functions)
    fits as the whole vector does: at top level (the blocks in threads, one program
    each) and under vmap (one program); a wrong number of args is refused."""
    y = noisy(2)
    half = T.shape[0] // 2
    first = lambda x, a: model(x, T[:half]) - a  # noqa: E731
    second = lambda x, a: model(x, T[half:]) - a  # noqa: E731
    kw = dict(lower=LOWER_B, upper=UPPER_B, names=NAMES, sigma=jnp.linspace(1.0, 2.0, T.shape[0]))
    whole = jv.least_squares(residual, TRUE * 3.0, y, **kw)
    blocks = jv.least_squares([first, second], TRUE * 3.0, (y[:half], y[half:]), **kw)
    for a, b in ((whole.values, blocks.values), (whole.intervals, blocks.intervals),
                 (whole.residuals, blocks.residuals), (whole.correlation, blocks.correlation)):
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-14)
    assert int(blocks.iterations) == int(whole.iterations)
    mapped = jax.vmap(lambda s: jv.least_squares([first, second], s, (y[:half], y[half:]), **kw).values)(
        jnp.stack([TRUE * 3.0, TRUE / 3.0]))
    # another program (the iteration nested in a while loop): it stops within xtol = 1e-10
    # (relative) of the optimum, maybe an iteration earlier or later than the top level
    np.testing.assert_allclose(mapped, np.stack([whole.values] * 2), rtol=1e-8)
    with pytest.raises(ValueError, match="args must be a sequence of as many"):
        jv.least_squares([first, second], TRUE, y)


def test_blocks_compile_once_each():
    """At top level each block's program is compiled ahead of its first evaluation (its
    tracing one block at a time); the evaluations then run that program, not a second
    compile of it."""
    y = noisy(3)
    compiles = []

    def listen(event, duration, fun_name="", **kw):
        if event == "/jax/core/compile/backend_compile_duration" and fun_name == "jit(_block)":
            compiles.append(fun_name)

    def fit_blocks(split):  # blocks of new sizes: programs the session's persistent cache cannot hold yet
        first = lambda x, a: model(x, T[:split]) - a  # noqa: E731
        second = lambda x, a: model(x, T[split:]) - a  # noqa: E731
        return jv.least_squares([first, second], TRUE * 3.0, (y[:split], y[split:]), lower=LOWER_B, upper=UPPER_B)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        fits = [fit_blocks(split) for split in (T.shape[0] // 2 - 1, T.shape[0] // 2 + 1)]
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert len(compiles) == 4  # two blocks per fit, each compiled once
    np.testing.assert_allclose(fits[1].values, fits[0].values, rtol=1e-8)  # the same data, split elsewhere


def test_vmap_over_start_points():
    starts = jnp.asarray([TRUE * f for f in itertools.product([3.0, 1 / 3], repeat=3)])
    fits = jax.vmap(lambda s: fit(s, model(TRUE, T)))(starts)
    np.testing.assert_allclose(fits.values, np.broadcast_to(TRUE, (8, 3)), rtol=1e-8)


@pytest.mark.parametrize(
    "lower, upper, kind",
    [(-np.inf, np.inf, FREE), (0.0, np.inf, POSITIVE), (-1.0, np.inf, LOWER), (-np.inf, 2.0, UPPER),
     (0.5, 50.0, LOG_BOX), (-3.0, 4.0, BOX)],
)  # fmt: skip
def test_bound_transforms(lower, upper, kind):
    """Each transform maps onto its interval, increasing, and inverts exactly."""
    x = np.asarray([1.5])
    bounds = make_bounds(x, [lower], [upper], ["p"])
    assert tuple(np.asarray(bounds.kinds)) == (kind,)
    z = bounds.to_unconstrained(x)
    np.testing.assert_allclose(bounds.to_physical(z), x, rtol=1e-14)
    values = jax.vmap(bounds.to_physical)(jnp.linspace(-30.0, 30.0, 201)[:, None])[:, 0]
    assert np.all(np.diff(values) >= 0) and np.all((values >= lower) & (values <= upper))
    slope = jax.grad(lambda z: bounds.to_physical(z)[0])(z)
    assert np.all(np.isfinite(slope)) and slope[0] > 0
