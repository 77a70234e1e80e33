"""Finite-strain viscoelasticity after Reese & Govindjee (IJSS 35, 1998).

Free energies are plain scalar functions of a (3, 3) tensor; every stress, rate and
tangent below is obtained by automatic differentiation of them (THEORY §1).
"""

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp

from ._config import device_array
from ._fem._tensor import ddot, det3, dev, inv3, mm, sym
from ._validation import check_positive


class NeoHooke(eqx.Module):
    r"""Compressible Neo-Hookean energy
    $\psi(C) = \frac{\mu}{2}(\operatorname{tr} C - 3) - \mu \ln J + \frac{\lambda}{2} (\ln J)^2$,
    $J = \sqrt{\det C}$.

    It depends on invariants only, so it may be called with the non-symmetric
    $C_e = C\Gamma^{-1}$ of the non-equilibrium branch. Called on a 3x3 tensor $C$ it
    returns $\psi(C)$.

    **Arguments:**

    - `lam`, `mu`: the Lamé parameters (> 0; array leaves, so differentiable).

    **Raises:**

    `ValueError` for a parameter that is not positive and finite.

    **Example:**

    ```python
    import jaxvisco as jv

    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    ```
    """

    lam: jax.Array
    mu: jax.Array

    def __init__(self, lam, mu):
        check_positive("NeoHooke lam", lam)
        check_positive("NeoHooke mu", mu)
        self.lam = device_array(lam, float)
        self.mu = device_array(mu, float)

    def __call__(self, C):
        return self.from_invariants(jnp.trace(C), 0.5 * jnp.log(det3(C)))

    def from_invariants(self, i1, ln_j):
        r"""$\psi$ from the two invariants it depends on, $I_1 = \operatorname{tr} C$ and
        $\ln J = \frac12 \ln\det C$. `ReeseGovindjee` evaluates a non-equilibrium branch
        that has this method at $C_e = C\Gamma^{-1}$ without forming $C_e$:
        $\operatorname{tr} C_e = C : \Gamma^{-T}$, $\ln J_e = \frac12(\ln\det C - \ln\det\Gamma)$."""
        return 0.5 * self.mu * (i1 - 3.0) - self.mu * ln_j + 0.5 * self.lam * ln_j**2

    def increment_from_invariants(self, d_i1, ln_j0, d_ln_j):
        r"""$\psi_1 - \psi_0$ from the increments of the invariants ($\Delta I_1$,
        $\Delta\ln J$) and $\ln J_0$: no difference of two energies is formed."""
        return 0.5 * self.mu * d_i1 - self.mu * d_ln_j + 0.5 * self.lam * d_ln_j * (2.0 * ln_j0 + d_ln_j)

    def increment(self, C, dC):
        r"""$\psi(C + dC) - \psi(C)$ without cancellation: from $\operatorname{tr} dC$ and
        $\ln(\det(C + dC)/\det C)$ (`log_det_ratio`), so its rounding error is relative to
        the increment. The plain difference of two energies near $C = I$ carries ~1e-16
        (tr C) mu of rounding whatever the increment (see
        `ReeseGovindjee.free_energy_increment`)."""
        return self.increment_from_invariants(jnp.trace(dC), 0.5 * jnp.log(det3(C)),
                                              0.5 * log_det_ratio(inv3(C), dC))

    @property
    def bulk_modulus(self):
        return self.lam + 2.0 * self.mu / 3.0


# _INVARIANTS. A non-equilibrium energy of the invariants of C_e = C Gamma^-1 alone (one
# with `from_invariants` and `increment_from_invariants`, as `NeoHooke`) is evaluated
# without forming C_e: tr C_e = C : Gamma^-T and ln J_e = (ln det C - ln det Gamma) / 2,
# and its increment over a step from the increments of C and Gamma (exact algebra, no
# difference of energies). Measured (session 35, 2D L-shape r4, lumped mass, eG(1),
# h = 0.1; 50 residuals chained in one compiled loop, minimum of 10): the step residual
# 1.46 / 1.53 -> 1.20 / 1.25 ms (the energy 0.17 ms of it, the increment 0.09 ms), one
# right-hand side of the ODE 0.44-0.48 ms either way. Other energies take C_e as before.
class ReeseGovindjee(eqx.Module):
    r"""Reese–Govindjee viscoelastic material:
    $\Psi(C, \Gamma) = \Psi_{eq}(C) + \Psi_{neq}(C\Gamma^{-1})$ and the evolution law
    $\dot\Gamma = 2\Gamma(\mathbb{V}^{-1}:M_e)$ with
    $\mathbb{V}^{-1}:A = \operatorname{dev}A/(2\eta_{dev}) + \operatorname{tr}A/(9\eta_{vol})\,I$.

    **Arguments:**

    - `equilibrium`: the scalar energy $\Psi_{eq}(C)$ (a `NeoHooke`, or any function of
      a 3x3 tensor).
    - `nonequilibrium`: the scalar energy $\Psi_{neq}(C_e)$, a function of the
      invariants of $C_e$, or None for an elastic material (no internal variable). One
      with `from_invariants` and `increment_from_invariants` (as `NeoHooke`) is
      evaluated without forming $C_e$ (the same function, faster).
    - `eta_dev`, `eta_vol`: the deviatoric and volumetric viscosities (> 0; `inf`
      freezes that flow).

    All parameters are array leaves: `jax.grad` with respect to them and
    `eqx.tree_at(lambda m: m.eta_dev, material, value)` work.

    **Raises:**

    `TypeError` for an energy that is not callable; `ValueError` for a viscosity that
    is not positive.

    **Example:**

    ```python
    import jaxvisco as jv

    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=50000.0, eta_vol=10000.0)
    elastic = jv.ReeseGovindjee(nh)
    ```
    """

    equilibrium: Callable
    nonequilibrium: Optional[Callable]
    eta_dev: jax.Array
    eta_vol: jax.Array

    def __init__(self, equilibrium, nonequilibrium=None, eta_dev=jnp.inf, eta_vol=jnp.inf):
        if not callable(equilibrium):
            raise TypeError(f"equilibrium must be a callable energy psi(C), got {type(equilibrium).__name__}.")
        if nonequilibrium is not None and not callable(nonequilibrium):
            raise TypeError(
                f"nonequilibrium must be a callable energy psi(C_e) or None, got {type(nonequilibrium).__name__}."
            )
        check_positive("eta_dev", eta_dev, allow_inf=True)
        check_positive("eta_vol", eta_vol, allow_inf=True)
        self.equilibrium = equilibrium
        self.nonequilibrium = nonequilibrium
        self.eta_dev = device_array(eta_dev, float)
        self.eta_vol = device_array(eta_vol, float)

    @property
    def has_internal_variable(self) -> bool:
        """Whether the material is viscous (has a non-equilibrium branch)."""
        return self.nonequilibrium is not None

    # -- energy and its derivatives ------------------------------------------------
    def free_energy(self, C, Gamma=None):
        psi = self.equilibrium(C)
        if self.has_internal_variable:
            ne = self.nonequilibrium
            if hasattr(ne, "from_invariants"):
                # psi_neq of the invariants of C_e = C Gamma^-1, C_e not formed (`_INVARIANTS`)
                i1 = ddot(C, jnp.swapaxes(inv3(Gamma), -1, -2))
                psi = psi + ne.from_invariants(i1, 0.5 * (jnp.log(det3(C)) - jnp.log(det3(Gamma))))
            else:
                psi = psi + ne(mm(C, inv3(Gamma)))
        return psi

    def free_energy_increment(self, C0, dC, Gamma0=None, Gamma1=None):
        r"""$\Psi(C_0 + dC, \Gamma_1) - \Psi(C_0, \Gamma_0)$, from the increments.

        Branch energies that have an ``increment(C, dC)`` method (`NeoHooke`) are
        differenced without cancellation; others as $\psi(C_0 + dC) - \psi(C_0)$. This is
        what eG's energy defect needs: the plain difference of two energies near
        $C = I$ carries a rounding error ~1e-16 mu (that of tr C) however small the
        increment, and eG's algorithmic stress divides the defect by the squared strain
        increment, which put a noise floor of ~2e-10 (relative) into the step residual of
        the paper's L-shape at h = 0.1: right at Newton's default tolerance.
        The non-equilibrium branch's increment is
        $dC_e = dC\,\Gamma_1^{-1} - C_0\Gamma_0^{-1} (\Gamma_1 - \Gamma_0)\,\Gamma_1^{-1}$ (exact)."""
        d = _branch_increment(self.equilibrium, C0, dC)
        if self.has_internal_variable:
            ne = self.nonequilibrium
            G0inv, G1inv = inv3(Gamma0), inv3(Gamma1)
            dG = Gamma1 - Gamma0
            if hasattr(ne, "increment_from_invariants"):
                # tr C_e1 - tr C_e0 = dC : G1^-T - (C0 G0^-1) : (dG G1^-1)^T and
                # ln J_e1 - ln J_e0 = (ln(det C1 / det C0) - ln(det G1 / det G0)) / 2,
                # both exact algebra on the increments (`_INVARIANTS`)
                T = lambda A: jnp.swapaxes(A, -1, -2)  # noqa: E731
                d_i1 = ddot(dC, T(G1inv)) - ddot(mm(C0, G0inv), T(mm(dG, G1inv)))
                ln_j0 = 0.5 * (jnp.log(det3(C0)) - jnp.log(det3(Gamma0)))
                d_ln_j = 0.5 * (log_det_ratio(inv3(C0), dC) - log_det_ratio(G0inv, dG))
                d = d + ne.increment_from_invariants(d_i1, ln_j0, d_ln_j)
            else:
                Ce0 = mm(C0, G0inv)
                d = d + _branch_increment(ne, Ce0, mm(dC, G1inv) - mm(mm(Ce0, dG), G1inv))
        return d

    # By automatic differentiation, not in closed form, by measurement (session 41): S and
    # dPsi/dGamma written through the invariants' slopes (psi_1 Gamma^-T + psi_J C^-T / 2,
    # ...) left the paper scene's cold compile as it was (XLA 5.6-5.9 s against 5.4-6.0 s)
    # and made the 2D L-shape r4 step (lumped, eG(1), h = 0.1, alternating processes)
    # 1.36x slower: 8.1 against 6.0 ms (median of 3 each), with the same 6.275 chord
    # iterations per step: the residual alone 1.04 against 0.94 ms.
    def stress(self, C, Gamma=None):
        """Second Piola–Kirchhoff stress $S = 2\\,\\partial\\Psi/\\partial C$."""
        return 2.0 * sym(jax.grad(self.free_energy, argnums=0)(C, Gamma))

    def stress_and_gamma_gradient(self, C, Gamma):
        r"""$(S, \partial\Psi/\partial\Gamma)$ from one reverse pass (`stress` and
        `energy_gradient_gamma` together: the programs that differentiate them again hold
        one copy of the energy's derivative instead of two)."""
        dC, dG = jax.grad(self.free_energy, argnums=(0, 1))(C, Gamma)
        return 2.0 * sym(dC), sym(dG)

    def energy_gradient_gamma(self, C, Gamma):
        r"""$\partial\Psi/\partial\Gamma$ (symmetrized)."""
        return sym(jax.grad(self.free_energy, argnums=1)(C, Gamma))

    def mandel_stress(self, C, Gamma):
        """Elastic Mandel stress $M_e = C_e^T S_e$, $S_e = 2\\,\\partial\\Psi_{neq}/\\partial C_e$."""
        Ce = mm(C, inv3(Gamma))
        Se = 2.0 * jax.grad(self.nonequilibrium)(Ce)
        return mm(Ce.T, Se)

    def inverse_viscosity(self, A):
        r"""$\mathbb{V}^{-1}:A$."""
        tr = jnp.trace(A)
        return dev(A) / (2.0 * self.eta_dev) + tr / (9.0 * self.eta_vol) * jnp.eye(3, dtype=A.dtype)

    def gamma_rate(self, C, Gamma):
        r"""$\dot\Gamma = 2\Gamma(\mathbb{V}^{-1}:M_e)$; zero for an elastic material."""
        if not self.has_internal_variable:
            raise ValueError("gamma_rate: this material has no internal variable (nonequilibrium=None).")
        return sym(2.0 * mm(Gamma, self.inverse_viscosity(self.mandel_stress(C, Gamma))))

    def gamma_rate_from_force(self, Y, Gamma):
        r"""The evolution law written in its driving force $Y$ (symmetric, in place of
        $\partial\Psi/\partial\Gamma$): $\dot\Gamma = 2\Gamma(\mathbb{V}^{-1}:M)$ with
        $M = -2Y\Gamma$, which is $M_e$ when $Y = \partial\Psi/\partial\Gamma$.

        For every symmetric $Y$ and SPD $\Gamma$, $-Y:\dot\Gamma = \operatorname{tr}(M\,
        \mathbb{V}^{-1}:M) \ge 0$ ($M$ is similar to a symmetric tensor): eG drives the flow
        with its algorithmic force so that its dissipation is non-negative by construction.
        """
        M = -2.0 * mm(Y, Gamma)
        return sym(2.0 * mm(Gamma, self.inverse_viscosity(M)))

    def dissipation(self, C, Gamma):
        r"""Dissipation per reference volume $D = -\partial\Psi/\partial\Gamma : \dot\Gamma \ge 0$,
        the rate taken in its driving force (`gamma_rate_from_force`), so that D is
        $\operatorname{tr}(M\,\mathbb{V}^{-1}:M)$ of one $M = -2\,\partial_\Gamma\Psi\,\Gamma$
        (as eG's per-point dissipation): with the rate from the Mandel stress, the two
        factors' rounding differs and at $C = \Gamma$ (both zero) D came out -1.9e-30."""
        if not self.has_internal_variable:
            return jnp.zeros((), dtype=C.dtype)
        Y = self.energy_gradient_gamma(C, Gamma)
        return -ddot(Y, self.gamma_rate_from_force(Y, Gamma))

    def tangent(self, C, Gamma=None):
        r"""Material tangent $\mathbb{C} = 2\,\partial S/\partial C$, shape (3, 3, 3, 3)."""
        return 2.0 * jax.jacfwd(self.stress, argnums=0)(C, Gamma)

    def gamma_rate_tangent(self, C, Gamma):
        r"""$(\partial\dot\Gamma/\partial C, \partial\dot\Gamma/\partial\Gamma)$, each (3, 3, 3, 3)."""
        return jax.jacfwd(self.gamma_rate, argnums=(0, 1))(C, Gamma)


def log_det_ratio(A_inv, dA):
    r"""$\ln(\det(A + dA) / \det A)$ from $A^{-1}$ and $dA$: $\det(I + M) - 1 = I_1 + I_2 +
    I_3$, the invariants of $M = A^{-1} dA$ (exact for 3x3), so the rounding error is
    relative to the increment, not to $\ln\det A$. Written with `det3` and products
    only, whose derivatives are closed forms (a cofactor expansion here, differentiated
    in the tangent, made the time loop 20 % slower to compile)."""
    M = mm(A_inv, dA)
    tr = jnp.trace(M)
    return jnp.log1p(tr + 0.5 * (tr**2 - jnp.sum(M * jnp.swapaxes(M, -1, -2))) + det3(M))


def _branch_increment(psi, C, dC):
    r"""$\psi(C + dC) - \psi(C)$ of one branch energy (its own `increment` where it has one)."""
    increment = getattr(psi, "increment", None)
    if increment is not None:
        return increment(C, dC)
    return psi(C + dC) - psi(C)


def paper_material() -> ReeseGovindjee:
    """The material of the paper's example (Groß & Betsch 2005; the theory page's
    "The paper's example"): both branches Neo-Hookean with λ = 30000, μ = 7500;
    η_dev = 50000, η_vol = 10000.

    **Returns:**

    A `ReeseGovindjee` material.
    """
    nh = NeoHooke(lam=30000.0, mu=7500.0)
    return ReeseGovindjee(equilibrium=nh, nonequilibrium=nh, eta_dev=50000.0, eta_vol=10000.0)
