"""Error-controlled steps: `PIDController`.

The controller keeps diffrax's `PIDController` names (`rtol`, `atol`, `pcoeff`, `icoeff`,
`dcoeff`, `dtmin`, `dtmax`, `factormin`, `factormax`, `safety`), with the error estimate
of `_time_element._estimate` (order k + 1 for cG(k)/eG(k)), and differs where implicit
steps with a stored factorization and the run's end error ask for it (issue #62,
`benchmarks/adaptive_work_precision.py`): the tolerance is the run's, shared out over
the steps (`over_run`) of the time over which their errors count (`horizon`); the
internal variable's follows the energy (`_estimate.energy_tolerance`); a step size is
kept while its error allows and a change would not pay for the new tangent
(`change_cost`, and Radau5's band `keep_band`); the steps divide the run into whole
steps.

Every tolerance and bound is a float64 array leaf: a run with another `rtol` reuses the
compiled program.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._config import device_array
from ._schedule import AbstractStepSizeController


def _positive(name, value, allow_zero=False, allow_inf=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"PIDController: {name} must be a number, got {value!r}.") from None
    ok = (v >= 0 if allow_zero else v > 0) and (allow_inf or math.isfinite(v)) and not math.isnan(v)
    if not ok:
        accepted = ("a number >= 0" if allow_zero else "a number > 0") + ("" if allow_inf else ", finite")
        raise ValueError(f"PIDController: {name} must be {accepted}; got {value!r}.")
    return v


# A step's share of the run's tolerance is (h / span) ** RUN_EXPONENT (`over_run`): the
# steps' errors of the paper's L-shape add up like a random walk (see `PIDController`).
RUN_EXPONENT = 0.5


class PIDController(AbstractStepSizeController):
    r"""Error-controlled step sizes (`simulate(..., stepsize_controller=...)`), with
    diffrax's names.

    The tolerance is that of the run's end: the positions' error over the body's size
    (`atol` a length, `rtol` relative to the root mean square distance from the
    centroid) and the energy's over the energy in the frame of the centre of mass. Each
    step's error is estimated from the defect of its own time polynomial (order $k + 1$)
    and held to the step's share $\sqrt{h / T}$ of the tolerance ($T$ the run's length,
    or, where shorter, the time in which the body would dissipate its energy at its mean
    rate so far: a damped body forgets its errors over that time; ``scope="step"``: the
    whole tolerance, as diffrax). The internal variable $\Gamma$ is
    held to what changes the energy by `rtol` of the body's energy, and at least to
    `rtol` of its distance from the virgin state with `atol` in units of the largest
    strain the run has reached (``internal_variable="strain"``: only the latter, which
    keeps the dissipated energy accurate to `rtol` of itself).

    A step is accepted where its scaled error is at most 1 and retried smaller
    otherwise; a failed Newton solve halves it. After an accepted step the integral
    controller proposes a new size (diffrax's PID form, order $k + 1/2$); the size is
    kept unless the proposal is longer by more than `keep_band` and saves more than
    `change_cost` steps of the rest of the run (a new size needs a new factorization).
    An accepted step is never shortened; a new size divides the rest of the run into
    whole steps. A step at `dtmin` is accepted whatever its error; a Newton failure
    there ends the run (`status == "failed"`). Step sizes are constants of the
    derivative.

    **Arguments:**

    - `rtol`, `atol`: relative and absolute tolerance (>= 0, at least one positive).
    - `dtmin`, `dtmax`: the smallest and largest step (0 and inf).
    - `pcoeff`, `icoeff`, `dcoeff`: the PID coefficients (0, 1, 0: integral control).
    - `safety`: the safety factor (0.9).
    - `factormin`, `factormax`: the smallest and largest change of the step (0.2, 10).
    - `keep_band`: the largest proposed factor that keeps the step (1.2).
    - `change_cost`: the steps a new step size costs (5; 0: none).
    - `internal_variable`: ``"energy"`` (default) or ``"strain"`` (above).
    - `scope`: ``"run"`` (default) or ``"step"`` (above).
    - `span`: the run's length T (0: ``t1 - t0`` of the call; see `for_run`).
    - `strain_scale`: the least strain that `atol` on Γ is measured in (0; a
      continued run passes the earlier one's `Solution.strain_scale`, see `continued`).

    **Raises:**

    `ValueError` for a value out of its range (named with the value).

    **Example:**

    ```python
    import jaxvisco as jv

    ctrl = jv.PIDController(rtol=1e-4, atol=1e-4)   # simulate(..., stepsize_controller=ctrl)
    ```
    """

    rtol: jax.Array
    atol: jax.Array
    dtmin: jax.Array
    dtmax: jax.Array
    pcoeff: jax.Array
    icoeff: jax.Array
    dcoeff: jax.Array
    safety: jax.Array
    factormin: jax.Array
    factormax: jax.Array
    keep_band: jax.Array
    change_cost: jax.Array
    span: jax.Array
    strain_scale: jax.Array
    internal_variable: str = eqx.field(static=True)
    scope: str = eqx.field(static=True)

    def __init__(self, rtol, atol, dtmin=0.0, dtmax=math.inf, pcoeff=0.0, icoeff=1.0, dcoeff=0.0, safety=0.9,
                 factormin=0.2, factormax=10.0, keep_band=1.2, strain_scale=0.0, change_cost=5.0,
                 internal_variable="energy", span=0.0, scope="run"):
        rtol = _positive("rtol", rtol, allow_zero=True)
        atol = _positive("atol", atol, allow_zero=True)
        if rtol == 0 and atol == 0:
            raise ValueError("PIDController: rtol and atol are both 0; give at least one positive tolerance.")
        dtmin = _positive("dtmin", dtmin, allow_zero=True)
        dtmax = _positive("dtmax", dtmax, allow_inf=True)
        if dtmin >= dtmax:
            raise ValueError(f"PIDController: dtmin = {dtmin!r} must be less than dtmax = {dtmax!r}.")
        pcoeff = _positive("pcoeff", pcoeff, allow_zero=True)
        icoeff = _positive("icoeff", icoeff)
        dcoeff = _positive("dcoeff", dcoeff, allow_zero=True)
        safety = _positive("safety", safety)
        if safety > 1:
            raise ValueError(f"PIDController: safety must be in (0, 1], got {safety!r}.")
        factormin = _positive("factormin", factormin)
        factormax = _positive("factormax", factormax)
        if not factormin < 1 < factormax:
            raise ValueError(f"PIDController: need factormin < 1 < factormax, got factormin = {factormin!r}, "
                             f"factormax = {factormax!r}.")
        keep_band = _positive("keep_band", keep_band)
        if not 1 <= keep_band <= factormax:
            raise ValueError(f"PIDController: keep_band must be in [1, factormax], got {keep_band!r}.")
        strain_scale = _positive("strain_scale", strain_scale, allow_zero=True)
        change_cost = _positive("change_cost", change_cost, allow_zero=True)
        span = _positive("span", span, allow_zero=True)
        if scope not in ("run", "step"):
            raise ValueError(f"PIDController: scope must be 'run' or 'step', got {scope!r}.")
        if internal_variable not in ("energy", "strain"):
            raise ValueError(f"PIDController: internal_variable must be 'energy' or 'strain', got {internal_variable!r}.")
        f = lambda v: device_array(v, jnp.float64)  # noqa: E731
        self.rtol, self.atol, self.dtmin, self.dtmax = f(rtol), f(atol), f(dtmin), f(dtmax)
        self.pcoeff, self.icoeff, self.dcoeff = f(pcoeff), f(icoeff), f(dcoeff)
        self.safety, self.factormin, self.factormax, self.keep_band = f(safety), f(factormin), f(factormax), f(keep_band)
        self.strain_scale, self.change_cost, self.span = f(strain_scale), f(change_cost), f(span)
        self.internal_variable, self.scope = internal_variable, scope

    def continued(self, strain) -> "PIDController":
        """This controller for a run that continues one whose largest strain was `strain`
        (its `Solution.strain_scale`): the same, with `strain_scale` at least `strain`."""
        if isinstance(strain, jax.core.Tracer) or isinstance(self.strain_scale, jax.core.Tracer):
            scale = jnp.maximum(self.strain_scale, jnp.asarray(strain, float))
        else:  # on the host (`device_array`)
            scale = device_array(max(float(self.strain_scale), float(strain)), jnp.float64)
        return eqx.tree_at(lambda c: c.strain_scale, self, scale)

    def for_run(self, t0, t1) -> "PIDController":
        """This controller for a run from `t0` to `t1` that is computed in parts (the
        command line's chunks): the tolerance is that run's end error, where no `span` is
        set yet."""
        if float(self.span) > 0:
            return self
        return eqx.tree_at(lambda c: c.span, self, device_array(float(t1) - float(t0), jnp.float64))

    def order(self, k):
        """The order in h of `over_run`'s error for cG(k)/eG(k): that of the estimate
        (k + 1), less the share's `RUN_EXPONENT` with ``scope="run"``."""
        return k + 1 - (RUN_EXPONENT if self.scope == "run" else 0.0)

    def horizon(self, span, h, elapsed, energy, dissipated):
        """The time over which a step's error counts (``scope="run"``): the run's `span`,
        or, where shorter, the time in which the body dissipates its `energy` (in the frame
        of its centre of mass) at the mean rate of the run so far, `dissipated` over
        `elapsed`: a damped body forgets its errors over that time, so they do not add up
        over the whole run (at least `h`; `energy` None: `span`)."""
        if energy is None or self.scope == "step":
            return span
        lost = dissipated > 0
        memory = jnp.where(lost, energy * elapsed / jnp.where(lost, dissipated, 1.0), span)
        return jnp.clip(memory, h, span)

    def over_run(self, err, h, span):
        """A step's error `err` (in units of the tolerance) in units of its share
        ``(h / span) ** RUN_EXPONENT`` of the run's tolerance (``scope="run"``), or
        `err` itself (``scope="step"``)."""
        if self.scope == "step":
            return err
        return err * (span / h) ** RUN_EXPONENT

    def accepted_factor(self, order, err, err1, err2, steps_left=math.inf):
        """Step growth after an accepted step with errors `err` (this), `err1`, `err2`
        (the two accepted before it; 1 where there were none): 1 (keep the step) or the
        new step over the old. `steps_left`: the rest of the run in steps of this size."""
        tiny = jnp.finfo(jnp.float64).tiny
        e0, e1, e2 = (jnp.maximum(e, tiny) for e in (err, err1, err2))
        expo = lambda c: c / order  # noqa: E731
        factor = (self.safety * e0 ** -expo(self.pcoeff + self.icoeff + self.dcoeff)
                  * e1 ** expo(self.pcoeff + 2.0 * self.dcoeff) * e2 ** -expo(self.dcoeff))
        factor = jnp.clip(factor, self.factormin, self.factormax)
        # A longer step pays for its new tangent where it saves more than `change_cost`
        # steps of the rest of the run, (1 - 1/factor) * steps_left > change_cost; an
        # accepted step is never shortened (a step that fails is retried shorter).
        saved = 1.0 - self.change_cost / jnp.maximum(steps_left, tiny)
        band = jnp.where(saved > 0, jnp.maximum(self.keep_band, 1.0 / jnp.where(saved > 0, saved, 1.0)), jnp.inf)
        return jnp.where(factor <= band, 1.0, factor)

    def whole_steps(self, h, remaining):
        """`h` lowered to divide the `remaining` time into whole steps (at most one more
        than `h` would take), where that keeps it at least `dtmin`: a kept step size then
        ends the run at `t1` with no short last step (a tangent of its own)."""
        n = jnp.maximum(jnp.ceil(remaining / h * (1.0 - 1e-9)), 1.0)
        fitted = remaining / n
        return jnp.where((remaining > 0) & (fitted >= self.dtmin), fitted, h)

    def rejected_factor(self, order, err):
        """Step reduction after a rejected step (`err` > 1)."""
        return jnp.clip(self.safety * jnp.maximum(err, 1.0) ** (-1.0 / order), self.factormin, self.safety)

    def __repr__(self):
        return f"PIDController(rtol={float(self.rtol):g}, atol={float(self.atol):g})"
