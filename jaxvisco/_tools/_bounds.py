"""Bounded parameters as smooth functions of unconstrained ones.

A least-squares solver works in unconstrained variables `z`; the physical value of each
parameter is `x = to_physical(z)`, increasing in `z`, with one transform per kind of bound:

| bounds                      | transform                                            |
|-----------------------------|------------------------------------------------------|
| none                        | $x = s z$, $s$ = `|start|` (1 if zero)              |
| `lower = 0` (positive)      | $x = e^z$ (steps are relative changes)               |
| `lower` only                | $x = \\ell + e^z$                                     |
| `upper` only                | $x = u - e^{-z}$                                     |
| box, `lower > 0`            | $\\log x = \\log\\ell + (\\log u - \\log\\ell)\\,\\sigma(z)$   |
| box, `lower <= 0`           | $x = \\ell + (u - \\ell)\\,\\sigma(z)$                    |

with $\\sigma$ the logistic function. A positive box is logistic in $\\log x$ so that a
range of several decades (a viscosity between 1e-2 and 1e3) is resolved evenly.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

FREE, POSITIVE, LOWER, UPPER, LOG_BOX, BOX = range(6)
KIND_NAMES = {FREE: "free", POSITIVE: "positive", LOWER: "lower bound", UPPER: "upper bound",
              LOG_BOX: "positive box", BOX: "box"}  # fmt: skip


class Bounds(eqx.Module):
    """Per-parameter bounds and the transform they select.

    **Fields:** `lower`, `upper` (arrays `(p,)`, `-inf`/`inf` where unbounded); `scale`
    (`(p,)`: a free parameter is $x = $ `scale` $z$, so that every unconstrained variable
    is dimensionless); `kinds` (`(p,)` integer transform codes; an array, not a static
    field, so that a fit's program does not depend on which kind of bound each parameter
    has: every transform is evaluated and one selected).
    """

    lower: jax.Array
    upper: jax.Array
    scale: jax.Array
    kinds: jax.Array

    def to_physical(self, z):
        """Physical values `x` `(p,)` of unconstrained values `z` `(p,)`."""
        kinds = self.kinds
        lo = jnp.where(jnp.isfinite(self.lower), self.lower, 0.0)
        hi = jnp.where(jnp.isfinite(self.upper), self.upper, 1.0)
        # Every branch sees safe arguments (finite bounds; exp of a clipped z where the
        # branch is not taken) so that no NaN reaches the selected values or gradients.
        log_lo = jnp.log(jnp.where(kinds == LOG_BOX, lo, 1.0))
        log_hi = jnp.log(jnp.where(kinds == LOG_BOX, hi, 2.0))
        s = jax.nn.sigmoid(z)
        branches = [
            self.scale * z,
            jnp.exp(jnp.where(kinds == POSITIVE, z, 0.0)),
            lo + jnp.exp(jnp.where(kinds == LOWER, z, 0.0)),
            hi - jnp.exp(jnp.where(kinds == UPPER, -z, 0.0)),
            jnp.exp(log_lo + (log_hi - log_lo) * s),
            lo + (hi - lo) * s,
        ]
        return jnp.select([kinds == k for k in range(len(branches))], branches)

    def slope(self, z):
        """`dx/dz` `(p,)` at `z`: each physical value depends on its own unconstrained one."""
        return jax.jvp(self.to_physical, (z,), (jnp.ones_like(z),))[1]

    def to_unconstrained(self, x):
        """Unconstrained values `z` `(p,)` of physical values `x` strictly inside the
        bounds (the inverse of `to_physical`)."""
        kinds = self.kinds
        x = jnp.asarray(x, dtype=jnp.float64)
        lo = jnp.where(jnp.isfinite(self.lower), self.lower, 0.0)
        hi = jnp.where(jnp.isfinite(self.upper), self.upper, 1.0)
        positive = jnp.where(kinds == POSITIVE, x, 1.0)
        above = jnp.where(kinds == LOWER, x - lo, 1.0)
        below = jnp.where(kinds == UPPER, hi - x, 1.0)
        log_lo = jnp.log(jnp.where(kinds == LOG_BOX, lo, 1.0))
        log_hi = jnp.log(jnp.where(kinds == LOG_BOX, hi, 2.0))
        log_x = jnp.log(jnp.where(kinds == LOG_BOX, x, 1.5))
        log_box = (log_x - log_lo) / (log_hi - log_lo)
        box = jnp.where(kinds == BOX, (x - lo) / (hi - lo), 0.5)
        branches = [x / self.scale, jnp.log(positive), jnp.log(above), -jnp.log(below),
                    jnp.log(log_box) - jnp.log1p(-log_box), jnp.log(box) - jnp.log1p(-box)]  # fmt: skip
        return jnp.select([kinds == k for k in range(len(branches))], branches)


def make_bounds(start, lower, upper, names) -> Bounds:
    """Check `start` against `lower`/`upper` and pick each parameter's transform.

    **Arguments:** `start` `(p,)`, concrete values or traced ones (a vmap over start
    points: then only the bounds are checked, and free parameters get scale 1);
    `lower`, `upper`: `None` (unbounded) or `(p,)` (`-inf`/`inf` for no bound;
    `lower = 0` makes a parameter positive); `names`: the parameters' names, for messages.

    **Returns:** a `Bounds`.

    **Raises:** `ValueError` naming the parameter and the values, for a NaN bound or
    start, an infinite start, `lower >= upper`, or a start not strictly inside its bounds.
    """
    p = len(names)
    concrete = not isinstance(start, jax.core.Tracer)
    lower = np.full(p, -np.inf) if lower is None else np.asarray(lower, dtype=np.float64)
    upper = np.full(p, np.inf) if upper is None else np.asarray(upper, dtype=np.float64)
    for label, a in (("lower", lower), ("upper", upper)):
        if a.shape != (p,):
            raise ValueError(f"{label} must have one entry per parameter ({p}), got shape {a.shape}.")
    kinds = []
    for i, (name, lo, hi) in enumerate(zip(names, lower.tolist(), upper.tolist())):
        where = f"parameter {name!r}"
        if np.isnan(lo) or np.isnan(hi) or lo == np.inf or hi == -np.inf:
            raise ValueError(f"{where}: bounds must be numbers, -inf or inf, got lower={lo!r}, upper={hi!r}.")
        if not lo < hi:
            raise ValueError(f"{where}: lower bound {lo!r} must be below upper bound {hi!r}.")
        if concrete:
            x0 = float(np.asarray(start, dtype=np.float64)[i])
            if not np.isfinite(x0):
                raise ValueError(f"{where}: start value must be finite, got {x0!r}.")
            if not lo < x0 < hi:
                raise ValueError(
                    f"{where}: start value {x0!r} must lie strictly inside its bounds ({lo!r}, {hi!r})."
                )
        finite_lo, finite_hi = np.isfinite(lo), np.isfinite(hi)
        if finite_lo and finite_hi:
            kinds.append(LOG_BOX if lo > 0 else BOX)
        elif finite_lo:
            kinds.append(POSITIVE if lo == 0 else LOWER)
        elif finite_hi:
            kinds.append(UPPER)
        else:
            kinds.append(FREE)
    if concrete:
        x0 = np.asarray(start, dtype=np.float64)
        scale = jnp.asarray(np.where(x0 != 0, np.abs(x0), 1.0))
    else:
        scale = jnp.ones(p)
    return Bounds(lower=jnp.asarray(lower), upper=jnp.asarray(upper), scale=scale,
                  kinds=jnp.asarray(kinds, dtype=jnp.int32))
