"""Error-controlled steps: `PIDController`.

The controller follows diffrax's `PIDController` (same names and meaning of `rtol`,
`atol`, `pcoeff`, `icoeff`, `dcoeff`, `dtmin`, `dtmax`, `factormin`, `factormax`,
`safety`), with the error estimate of `_time_element._estimate` (order k + 1 for cG(k)/eG(k)) and one
addition for implicit steps, as in Hairer & Wanner's Radau5: a proposed change of the
step by a factor in ``[1, keep_band]`` keeps the step, so that the stored factorization
of the condensed tangent (formed for one h) serves the next steps too.

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


class PIDController(AbstractStepSizeController):
    r"""Error-controlled step sizes (`simulate(..., stepsize_controller=...)`), with
    diffrax's names and meaning.

    Each step's error is estimated from the defect of its own time polynomial (order
    $k + 1$ for cG(k) and eG(k)); a step is accepted where the estimate, in units of
    `atol + rtol * scale`, is at most 1, and rejected and retried smaller otherwise. The
    next step is $h \cdot \mathrm{clip}(s\, e_n^{-(p + i + d)/r} e_{n-1}^{(p + 2d)/r}
    e_{n-2}^{-d/r},\ f_{min}, f_{max})$ with $r = k + 1$, $s$ `safety`, $p, i, d$ the
    coefficients; a PI controller by default. A proposed change by a factor within
    `[1, keep_band]` keeps the step, so that the stored factorization serves the next
    steps. A step whose Newton solve fails is halved. A step at `dtmin` is accepted
    whatever its error; a Newton failure there ends the run (`status == "failed"`).

    Positions are measured against their distance from the centroid; the internal
    variable $\Gamma$ (a strain) against its distance from the virgin state, with
    `atol` in units of the largest strain $|C - I|$ the run has reached (at least
    `strain_scale`), so that a body coming to rest keeps the tolerance of its largest
    deformation. Step sizes are constants of the derivative: `jax.grad` of an adaptive
    run differentiates it along its accepted steps.

    **Arguments:**

    - `rtol`, `atol`: relative and absolute tolerance (>= 0, at least one positive).
    - `dtmin`, `dtmax`: the smallest and largest step (0 and inf).
    - `pcoeff`, `icoeff`, `dcoeff`: the PID coefficients (0.2, 0.4, 0; diffrax's
      default is the integral controller 0, 1, 0).
    - `safety`: the safety factor (0.9).
    - `factormin`, `factormax`: the smallest and largest change of the step (0.2, 10).
    - `keep_band`: keep the step where the proposed factor lies in `[1, keep_band]`
      (1.2; 1 disables it).
    - `strain_scale`: the least strain that `atol` on the internal variable is measured
      in (0). A run continued from another (in chunks, as the `jaxvisco` command runs)
      passes the earlier run's `Solution.strain_scale`, see `continued`.

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
    strain_scale: jax.Array

    def __init__(self, rtol, atol, dtmin=0.0, dtmax=math.inf, pcoeff=0.2, icoeff=0.4, dcoeff=0.0, safety=0.9,
                 factormin=0.2, factormax=10.0, keep_band=1.2, strain_scale=0.0):
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
        f = lambda v: device_array(v, jnp.float64)  # noqa: E731
        self.rtol, self.atol, self.dtmin, self.dtmax = f(rtol), f(atol), f(dtmin), f(dtmax)
        self.pcoeff, self.icoeff, self.dcoeff = f(pcoeff), f(icoeff), f(dcoeff)
        self.safety, self.factormin, self.factormax, self.keep_band = f(safety), f(factormin), f(factormax), f(keep_band)
        self.strain_scale = f(strain_scale)

    def continued(self, strain) -> "PIDController":
        """This controller for a run that continues one whose largest strain was `strain`
        (its `Solution.strain_scale`): the same, with `strain_scale` at least `strain`."""
        if isinstance(strain, jax.core.Tracer) or isinstance(self.strain_scale, jax.core.Tracer):
            scale = jnp.maximum(self.strain_scale, jnp.asarray(strain, float))
        else:  # on the host (`device_array`)
            scale = device_array(max(float(self.strain_scale), float(strain)), jnp.float64)
        return eqx.tree_at(lambda c: c.strain_scale, self, scale)

    def accepted_factor(self, order, err, err1, err2):
        """Step growth after an accepted step with errors `err` (this), `err1`, `err2`
        (the two accepted before it; 1 where there were none)."""
        tiny = jnp.finfo(jnp.float64).tiny
        e0, e1, e2 = (jnp.maximum(e, tiny) for e in (err, err1, err2))
        expo = lambda c: c / order  # noqa: E731
        factor = (self.safety * e0 ** -expo(self.pcoeff + self.icoeff + self.dcoeff)
                  * e1 ** expo(self.pcoeff + 2.0 * self.dcoeff) * e2 ** -expo(self.dcoeff))
        factor = jnp.clip(factor, self.factormin, self.factormax)
        return jnp.where((factor >= 1.0) & (factor <= self.keep_band), 1.0, factor)

    def rejected_factor(self, order, err):
        """Step reduction after a rejected step (`err` > 1)."""
        return jnp.clip(self.safety * jnp.maximum(err, 1.0) ** (-1.0 / order), self.factormin, self.safety)

    def __repr__(self):
        return f"PIDController(rtol={float(self.rtol):g}, atol={float(self.atol):g})"
