"""A homogeneous material point under a prescribed deformation history.

The internal variable is integrated with the same time elements as in `simulate` (the
evolution part of `point_kernel`), so `drive` isolates the time discretization of the
constitutive law: useful for calibrating materials and for convergence studies.
"""

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._config import jit
from .._fem._tensor import small_solve, sym_to_vec, vec_to_sym
from .._materials import ReeseGovindjee
from .._time_element._time_element import AbstractTimeElement, eG
from .._validation import check_finite


def drive(material: ReeseGovindjee, F: Callable, ts: ArrayLike, integrator: AbstractTimeElement = eG(1),
          gamma0: ArrayLike | None = None,
          rtol: float = 1e-13, max_iterations: int = 30) -> dict:
    """Drive one material point through a prescribed deformation history `F(t)`.

    The internal variable is integrated with the evolution part of the same time
    element as in `simulate`, so `drive` isolates the time discretization of the
    constitutive law (for calibrating materials and convergence studies).

    **Arguments:**

    - `material`: a `ReeseGovindjee` material.
    - `F`: a function `t -> (3, 3)` deformation gradient (JAX-traceable).
    - `ts`: increasing output times; the steps are their differences.
    - `integrator`: the time element of the evolution law (default `eG(1)`).
    - `gamma0`: the initial internal variable (default the identity).
    - `rtol`: Newton's tolerance on the point's evolution residual (max norm).
      Default 1e-13, tighter than `NewtonKrylov`'s 1e-10: the residual of one point
      is dimensionless and a dense 6k x 6k Newton step reaches rounding in a few
      iterations, so there is nothing to save by stopping earlier.
    - `max_iterations`: Newton iterations per step (30).

    **Returns:**

    A dict of arrays over `ts`: `S` (second Piola–Kirchhoff stress), `P` (first), `gamma`,
    `psi` (free energy), `D` (dissipation rate) and `converged` (per step).

    **Raises:**

    `TypeError` for a material or `F` of the wrong kind; `ValueError` for times that are
    not finite and strictly increasing.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import jaxvisco as jv

    stretch = lambda t: jnp.diag(jnp.array([1.0 + 0.1 * t, 1.0, 1.0]))
    out = jv.drive(jv.paper_material(), stretch, jnp.linspace(0.0, 1.0, 11))
    ```
    """
    if not isinstance(material, ReeseGovindjee):
        raise TypeError(f"material must be a ReeseGovindjee material, got {type(material).__name__}.")
    if not callable(F):
        raise TypeError("F must be a function t -> (3, 3) deformation gradient.")
    ts_np = np.asarray(ts, dtype=float)
    if ts_np.ndim != 1 or len(ts_np) < 2:
        raise ValueError(f"ts must be a 1-D array of at least two times, got shape {ts_np.shape}.")
    check_finite("ts", ts_np)
    if np.any(np.diff(ts_np) <= 0):
        raise ValueError("ts must be strictly increasing.")
    return _drive(material, F, jnp.asarray(ts_np), integrator, gamma0, rtol, max_iterations)


@jit
def _drive(material, F, ts, scheme, gamma0, rtol, max_iterations):
    k = scheme.k
    m = scheme.matrices()[0]
    # Nodal values whose interpolant matches F exactly at t_n and at the k quadrature
    # points: the history is known, and interpolating it through the equally spaced
    # nodes would cap the order at k + 1 instead of the scheme's 2k.
    fit_points = np.concatenate([[0.0], m["points"][:k]])
    fit = jnp.asarray(np.linalg.inv(np.vstack([np.eye(k + 1)[:1], m["V"][:k]])))
    viscous = material.has_internal_variable
    G0 = jnp.eye(3) if gamma0 is None else jnp.asarray(gamma0, dtype=float)

    def outputs(t, G):
        Ft = F(t)
        C = Ft.T @ Ft
        Gm = G if viscous else None
        S = material.stress(C, Gm)
        D = material.dissipation(C, G) if viscous else jnp.zeros(())
        return dict(S=S, P=Ft @ S, gamma=G, psi=material.free_energy(C, Gm), D=D)

    def step(G, t_pair):
        t0, t1 = t_pair
        h = t1 - t0
        Fn = jnp.einsum("IJ,Jab->Iab", fit, jax.vmap(F)(t0 + jnp.asarray(fit_points) * h))
        if not viscous:
            return G, jnp.asarray(True)

        def res(g):
            Gn = jnp.concatenate([G[None], vec_to_sym(g.reshape(k, 6))])
            return scheme.point_kernel(material, Fn, Gn, h)[1].reshape(-1)

        def cond(c):
            g, r, it = c
            return (jnp.max(jnp.abs(r)) > rtol) & (it < max_iterations)

        def body(c):
            g, r, it = c
            g = g - small_solve(jax.jacfwd(res)(g), r)
            return g, res(g), it + 1

        g0 = jnp.tile(sym_to_vec(G), k)
        g, r, _ = jax.lax.while_loop(cond, body, (g0, res(g0), 0))
        return vec_to_sym(g.reshape(k, 6)[-1]), jnp.max(jnp.abs(r)) <= rtol

    pairs = jnp.stack([ts[:-1], ts[1:]], axis=-1)
    _, (Gs, conv) = jax.lax.scan(lambda G, tp: (lambda r: (r[0], r))(step(G, tp)), G0, pairs)
    Gall = jnp.concatenate([G0[None], Gs])
    out = jax.vmap(outputs)(ts, Gall)
    out["converged"] = jnp.concatenate([jnp.array([True]), conv])
    return out
