"""Error-controlled steps: `PIDController`.

The controller follows diffrax's `PIDController` (same names and meaning of `rtol`,
`atol`, `pcoeff`, `icoeff`, `dcoeff`, `dtmin`, `dtmax`, `factormin`, `factormax`,
`safety`), with the error estimate of `_estimate` (order k + 1 for cG(k)/eG(k)) and one
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
    """Error-controlled step sizes for `simulate(..., stepsize_controller=...)`.

    A step is accepted where its error estimate, in units of ``atol + rtol * scale``,
    is at most 1 (positions, momenta and the internal variable are scaled separately:
    see `_estimate.scaled_error`); the next step is ``h * factor`` with

    ``factor = safety * e_n^(-(pcoeff + icoeff + dcoeff)/r) * e_{n-1}^((pcoeff + 2 dcoeff)/r)
    * e_{n-2}^(-dcoeff/r)``, ``r = k + 1``,

    clipped to ``[factormin, factormax]`` (a PI controller by default: see below). A rejected
    step is retried with ``safety * e^(-1/r)`` (at most 1, at least `factormin`); a step
    whose Newton solve fails, with half the step. Steps stay within ``[dtmin, dtmax]``;
    a step at `dtmin` is accepted whatever its error (as diffrax's ``force_dtmin``), and
    a Newton failure there ends the run (``status == "failed"``).

    **Arguments:** `rtol`, `atol` (> 0 together: at least one positive);
    `dtmin` (0), `dtmax` (inf); `pcoeff` (0.2), `icoeff` (0.4), `dcoeff` (0); `safety` (0.9);
    `factormin` (0.2), `factormax` (10); `keep_band` (1.2: keep h where the proposed
    factor lies in ``[1, keep_band]``; 1 disables it); `strain_scale` (0): the least
    strain that `atol` on the internal variable is measured in (see below).

    The internal variable Γ is a strain: its tolerance is ``atol * a + rtol * |Γ - I|``
    (root mean squares over the body), where ``a`` is the largest strain ``|C - I|``
    the run has reached so far, from its initial state on, and at least `strain_scale`.
    A body that comes to rest thereby keeps the tolerance of its largest deformation and
    its steps grow (measured against the strain of the moment, they kept the size of its
    vibrations: `benchmarks/adaptive_relaxation.py`). A run continued from another's end
    state (in chunks, as the ``jaxvisco`` command runs) passes the earlier run's
    `Solution.strain_scale` here to keep the same tolerance. The tolerance on Γ is never
    below 16 units of its rounding (3.6e-15): a body that starts undeformed (``a`` and
    ``|Γ - I|`` ~ 0) would otherwise be held to less than rounding at its first step
    where atol < 2.4e-7 (at 1e-9 every step was rejected).

    The default coefficients differ from diffrax's integral controller (0, 1), by
    measurement (paper's 2D L-shape to t = 10, eG(1..3), rtol = atol = 1e-3 and 1e-5,
    medians of 3 alternating runs; `benchmarks/controller_coefficients.py`): with (0.2,
    0.4) every run took 0.68-0.85 times the wall time of (0, 1) (two sessions of rounds)
    and was more accurate (position error 1.4-3.3 times, dissipated energy 1.5-6.9 times
    smaller), rejected 0-8 steps instead of 2-46 and reused the tangent more (fewer
    Newton iterations), in 1.3-1.8 times as many steps; (0.3, 0.3) was slower in five of
    six cases (by up to 24 %), faster in one (3 %).

    Step sizes are constants of the derivative: `jax.grad` of an adaptive run
    differentiates the run along its accepted steps (see `simulate`).
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

    def continued(self, strain):
        """This controller for a run that continues one whose largest strain was `strain`
        (its `Solution.strain_scale`): `strain_scale` at least that."""
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
