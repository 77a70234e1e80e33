"""Time finite elements on [t_n, t_n + h]: cG(k), eG(k) and two baselines (THEORY §3).

A scheme is described by its degree k and its time quadrature. Everything it does at one
spatial quadrature point lives in `point_kernel`: given the deformation gradients and
internal variables at the k+1 time nodes it returns the first Piola–Kirchhoff stresses
that enter the weak momentum balance at the time quadrature points, and the weak
residual of the evolution law. The spatial assembly (`residual`) is shared by all.
"""

import abc
import functools
import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._fem._quadrature import gauss_legendre
from .._fem._tensor import ddot, mm, right_cauchy_green, sym, sym_to_vec
from ._time_basis import time_element_matrices

# Regularization of eG's algorithmic factor, (strain increment)^2 units:
# beta = G den / (den^2 + floor^2) with den = |C'|^2 + 4|Gamma'|^2 (beta = G / den without it).
# G / den amplifies the rounding error of the energy defect G without bound as C' -> 0
# (a rigidly translating body got S_alg ~ 1e-4 mu of pure noise and Newton could not
# converge: the rigid-translation test). With the floor the gain is at most
# 1.14 / sqrt(floor) ~ 1e5. What the regularization leaves in the energy balance is
# G floor^2 / (den^2 + floor^2): a fraction (floor / den)^2 of the defect where the
# increment is resolved (den = 4e-3: 6e-16), and all of it only where den < floor, where
# G, third order in the increment, is below ~1e-15 (lam + mu) per unit volume. The earlier
# form G / (den + floor) left a fraction floor / den: 1.3e-9 H_0 per step in a drawn case
# (lam = 7343, H_0 = 1.04), above the 1e-9 H_0 the scheme promises.
# G's rounding error itself is kept relative to the increment: Psi(1) - Psi(0) comes
# from the increments of C and Gamma (`ReeseGovindjee.free_energy_increment`), not as the
# difference of two energies, which carried ~1e-16 (lam + mu) of noise per point and,
# through the gain, a floor of ~1e-11 (relative) in the step residual (see
# test_eg_residual_has_no_rounding_floor_above_1e_13).
_BETA_FLOOR = 1e-10


class AbstractTimeElement(eqx.Module):
    """A time element: how one step $[t_n, t_n + h]$ is formed. Its degree `k`, its
    quadrature in time, and what it does at one spatial quadrature point; the concrete
    ones are `cG`, `eG`, `Midpoint` and `Newmark`."""

    k: eqx.AbstractVar[int]
    n_quad: eqx.AbstractVar[int]

    @abc.abstractmethod
    def _rules(self):
        """((points, weights) of the momentum equations, (points, weights) of the
        evolution law), as tuples."""

    @abc.abstractmethod
    def point_kernel(self, material, F, G, h):
        """What the time element does at one spatial quadrature point.

        **Arguments:**

        - `material`: the point's material.
        - `F`: (k+1, 3, 3) deformation gradients at the time nodes.
        - `G`: (k+1, 3, 3) internal variables at the time nodes, or None.
        - `h`: the step.

        **Returns:**

        `(P, R_G)`: the stresses P = F S (nq_t, 3, 3) at the momentum quadrature points,
        and the weak evolution residual (k, 6) (None if elastic).
        """

    @abc.abstractmethod
    def point_dissipation(self, material, F, G, h):
        """Energy dissipated at one spatial point over the step (per reference volume)."""

    @property
    def enhanced(self) -> bool:
        """Whether the scheme drives the flow with assumed strains (eG)."""
        return False

    @property
    def name(self) -> str:
        """A short name, e.g. `"eG(1)"`."""
        return f"{type(self).__name__}({self.k})"

    def _rule_description(self):
        (pts, _), _ = self._rules()
        return f"{len(pts)}-point Gauss-Legendre"

    def describe(self) -> str:
        """The name and the quadrature in time, as results files record them."""
        return f"{self.name}, time quadrature: {self._rule_description()}"

    def matrices(self):
        """The time-element matrices of the momentum and of the evolution quadrature."""
        (pts, wts), (gpts, gwts) = self._rules()
        return time_element_matrices(self.k, pts, wts), time_element_matrices(self.k, gpts, gwts)


class AbstractStandardTimeElement(AbstractTimeElement):
    """A scheme that evaluates the stresses and the evolution law at the interpolated
    strains (cG(k) and the baselines)."""

    def point_kernel(self, material, F, G, h):
        m, mg = self.matrices()
        V = m["V"]
        Fl = _combine(V, F)
        Gl = None if G is None else _combine(V, G)
        Cl = right_cauchy_green(Fl)
        S = jax.vmap(material.stress)(Cl, Gl) if G is not None else jax.vmap(material.stress)(Cl)
        P = mm(Fl, S)
        if G is None:
            return P, None
        if mg is m:
            Cg, Gg = Cl, Gl
        else:  # a separate rule for the evolution law (Newmark's midpoint)
            Vg = mg["V"]
            Cg = right_cauchy_green(_combine(Vg, F))
            Gg = _combine(Vg, G)
        Gd = _combine(mg["D"], G)
        rate = jax.vmap(material.gamma_rate)(Cg, Gg)
        R_G = _combine(mg["W"], Gd - h * rate)
        return P, sym_to_vec(R_G)

    def point_dissipation(self, material, F, G, h):
        """The time quadrature of the physical dissipation rate."""
        if G is None:
            return jnp.zeros((), dtype=F.dtype)
        _, mg = self.matrices()
        Vg, wg = mg["V"], jnp.asarray(mg["weights"])
        Cg = right_cauchy_green(_combine(Vg, F))
        Gg = _combine(Vg, G)
        return h * jnp.sum(wg * jax.vmap(material.dissipation)(Cg, Gg))


def _combine(M, A):
    """``einsum("lI,I...->l...", M, A)`` for a small constant matrix M (numpy: the
    scheme's interpolation, derivative and test matrices) as weighted sums of the rows of
    A, which XLA fuses with the point kernel's arithmetic. As an einsum every one of them
    was a `dot` of its own over all points, with layout copies around it (2D L-shape r4,
    eG(1): 5 such dots and ~50 copies in one step residual)."""
    M = np.asarray(M)
    rows = []
    for row in M:
        terms = [float(c) * A[i] for i, c in enumerate(row) if c != 0.0]
        rows.append(functools.reduce(operator.add, terms) if terms else jnp.zeros_like(A[0]))
    return jnp.stack(rows)


def _check_degree(k, n_quad, name):
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"{name}: polynomial degree k must be an integer >= 1, got {k!r}.")
    if n_quad is None:
        return int(k), int(k)
    if isinstance(n_quad, bool) or not isinstance(n_quad, (int, np.integer)) or n_quad < k:
        raise ValueError(
            f"{name}({k}): the time quadrature needs at least k = {k} Gauss points to integrate "
            f"the linear terms exactly; got quadrature={n_quad!r}."
        )
    return int(k), int(n_quad)


def _gauss(n):
    p, w = gauss_legendre(n)
    return tuple(float(v) for v in p), tuple(float(v) for v in w)


class cG(AbstractStandardTimeElement):
    """The continuous Galerkin time element of degree k: trial functions of degree k,
    test functions of degree k - 1, stresses from the trial strains.

    With k Gauss points (the default) it is the k-stage Gauss collocation method: order
    2k at the time nodes, momentum-conserving, symplectic for elastic bodies, but
    energy-conserving only for quadratic energies; cG(1) is the implicit midpoint rule.
    With large steps its energy can grow (see `eG`).

    **Arguments:**

    - `k`: the polynomial degree (>= 1).
    - `quadrature`: the number of Gauss–Legendre points in time (>= k; default k).

    **Raises:**

    `ValueError` for a degree below 1 or fewer points than `k`.

    **Example:**

    ```python
    import jaxvisco as jv

    integrator = jv.cG(2)
    ```
    """

    k: int = eqx.field(static=True)
    n_quad: int = eqx.field(static=True)

    def __init__(self, k=1, quadrature=None):
        self.k, self.n_quad = _check_degree(k, quadrature, "cG")

    def _rules(self):
        rule = _gauss(self.n_quad)
        return rule, rule


class eG(AbstractTimeElement):
    r"""The enhanced, energy-consistent Galerkin time element of degree k (Groß &
    Betsch): stresses at assumed strains interpolated over the time nodes plus an
    algorithmic stress, so that $H_{n+1} - H_n = W_n - D_n$ with $D_n \ge 0$ holds for
    every step size (to the Newton tolerance). Order 2k at the time nodes; linear and
    angular momentum are conserved for free bodies. eG(1) is the midpoint rule with a
    discrete-gradient stress.

    **Arguments:**

    - `k`: the polynomial degree (>= 1).
    - `quadrature`: the number of Gauss–Legendre points in time of the momentum
      equations and the energy terms (>= k; default k). The flow rule stays collocated
      at the k Gauss points, so $D_n \ge 0$ holds for every choice; with more points
      than k angular momentum is no longer conserved exactly. `eG(2, quadrature=4)`
      converges at steps longer than the body's vibration periods, where eG(2) halves
      its steps (see the FAQ).

    **Raises:**

    `ValueError` for a degree below 1 or fewer points than `k`.

    **Example:**

    ```python
    import jaxvisco as jv

    integrator = jv.eG(1)
    ```
    """

    k: int = eqx.field(static=True)
    n_quad: int = eqx.field(static=True)

    def __init__(self, k=1, quadrature=None):
        self.k, self.n_quad = _check_degree(k, quadrature, "eG")

    def _rules(self):
        # The flow rule is always collocated at the k Gauss points (D_n >= 0, see
        # `point_dissipation`); the momentum and energy terms take `quadrature` points.
        return _gauss(self.n_quad), _gauss(self.k)

    def _rule_description(self):
        if self.n_quad == self.k:
            return super()._rule_description()
        points = "the Gauss point" if self.k == 1 else f"the {self.k} Gauss points"
        return f"{self.n_quad}-point Gauss-Legendre, flow rule at {points}"

    @property
    def enhanced(self) -> bool:
        return True

    def point_kernel(self, material, F, G, h):
        return self._kernel(material, F, G, h, self._enhanced_terms(material, F, G))

    def point_kernel_and_dissipation(self, material, F, G, h):
        """`point_kernel` and `point_dissipation` from one evaluation of the enhanced terms
        (G not None): the Newton loop's residual then carries the step's dissipation, and
        the compiled time loop holds no second copy of the point kernel for it (shorter
        compiles, faster steps: measured on the internals page)."""
        e = self._enhanced_terms(material, F, G)
        P, R_G = self._kernel(material, F, G, h, e)
        return P, R_G, _dissipation(e)

    def _kernel(self, material, F, G, h, e):
        m, mg = self.matrices()
        Fl = _combine(m["V"], F)
        P = mm(Fl, e["S"] + 2.0 * e["beta"] * e["Cd"])
        if G is None:
            return P, None
        # The flow is driven by the algorithmic force (the energy gradient at the
        # assumed strains plus its share of the correction), the same force the
        # dissipation pairs with Gamma': with collocation at the Gauss points every
        # point's D_n is a sum of non-negative terms (see `point_dissipation`).
        Gg = _combine(mg["V"], G)
        rate = jax.vmap(material.gamma_rate_from_force)(e["Y"], Gg)
        R_G = _combine(mg["W"], e["Gd"] - h * rate)
        return P, sym_to_vec(R_G)

    def _enhanced_terms(self, material, F, G):
        """eG at one spatial point: stresses at the assumed strains
        $\\bar C = \\sum M_I C_I$ and the factor beta of the algorithmic correction.

        The correction is the least-squares smallest pair
        $(S_{alg}, Y_{alg}) = (2\\beta C', 4\\beta\\Gamma')$ that closes the energy defect
        $G = \\Delta\\Psi - \\int [\\bar S : C'/2 + \\partial_\\Gamma\\Psi : \\Gamma'] d\\alpha$. With no
        internal variable this is the paper's $S_{alg} = 2 G C' / \\int\\|C'\\|^2$; with one,
        a point at rest that still relaxes ($C' = 0$) puts the defect on $\\Gamma'$
        instead of dividing by zero (THEORY §3, second point). The strain terms are
        integrated with the momentum rule, the internal-variable terms ($\\Gamma'$,
        $\\partial_\\Gamma\\Psi$, $Y$) with the flow rule's k Gauss points (`_rules`).
        """
        m, mg = self.matrices()
        V, D, w = m["V"], m["D"], jnp.asarray(m["weights"])
        CI = right_cauchy_green(F)
        Cbar = _combine(V, CI)
        Fl = _combine(V, F)
        Cd = 2.0 * sym(mm(jnp.swapaxes(Fl, -1, -2), _combine(D, F)))
        # C_k - C_0 from the increment of F (exact algebra, no cancellation near C = I).
        dF = F[-1] - F[0]
        dC = mm(jnp.swapaxes(F[0], -1, -2), dF)
        dC = dC + jnp.swapaxes(dC, -1, -2) + mm(jnp.swapaxes(dF, -1, -2), dF)
        if G is None:
            S = jax.vmap(material.stress)(Cbar)
            dpsi = material.free_energy_increment(CI[0], dC)
            power = jnp.sum(w * ddot(S, Cd)) / 2.0
            den = jnp.sum(w * ddot(Cd, Cd))
            Gd = dpsi_dG = wg = None
        else:
            Gl = _combine(V, G)
            if mg is m:
                S, dpsi_dG = jax.vmap(material.stress_and_gamma_gradient)(Cbar, Gl)
                Gd, wg = _combine(D, G), w
            else:  # the flow rule's own points (collocation at the k Gauss points)
                Vg, Dg, wg = mg["V"], mg["D"], jnp.asarray(mg["weights"])
                S = jax.vmap(material.stress)(Cbar, Gl)
                dpsi_dG = jax.vmap(material.energy_gradient_gamma)(_combine(Vg, CI),
                                                                   _combine(Vg, G))
                Gd = _combine(Dg, G)
            dpsi = material.free_energy_increment(CI[0], dC, G[0], G[-1])
            power = jnp.sum(w * ddot(S, Cd)) / 2.0 + jnp.sum(wg * ddot(dpsi_dG, Gd))
            den = jnp.sum(w * ddot(Cd, Cd)) + 4.0 * jnp.sum(wg * ddot(Gd, Gd))
        beta = (dpsi - power) * den / (den**2 + _BETA_FLOOR**2)
        # The algorithmic driving force of the flow rule and the dissipation.
        Y = None if G is None else dpsi_dG + 4.0 * beta * Gd
        return dict(Cbar=Cbar, S=S, Cd=Cd, Gd=Gd, Y=Y, beta=beta, w=w, wg=wg)

    def point_dissipation(self, material, F, G, h):
        """$-\\int Y : \\Gamma_h' d\\alpha$ with the algorithmic driving force
        $Y = \\partial_\\Gamma\\Psi(\\bar C, \\Gamma_h) + Y_{alg}$, which closes the discrete
        energy balance exactly. The flow rule is collocated at the Gauss points with the
        same $Y$ (the k-point rule whatever the momentum quadrature), so this
        equals $h\\sum_l w_l \\operatorname{tr}(M_l\\,\\mathbb{V}^{-1}:M_l) \\ge 0$,
        $M_l = -2Y_l\\Gamma_l$. Until the two rules were separated, more momentum points
        than k made the weak flow rule non-collocated and the sign free: drawn point
        histories of a fast-relaxing material over h = 1 dissipated D < 0 in 32 of 115
        with eG(1, quadrature=2) (`tests/test_time_integration.py`)."""
        if G is None:
            return jnp.zeros((), dtype=F.dtype)
        return _dissipation(self._enhanced_terms(material, F, G))


def _dissipation(e):
    """eG's dissipation at a point, $-\\int Y : \\Gamma_h' d\\alpha$, from its enhanced terms."""
    return -jnp.sum(e["wg"] * ddot(e["Y"], e["Gd"]))


class Midpoint(AbstractStandardTimeElement):
    """The implicit midpoint rule: cG(1) with one Gauss point (for comparison).

    **Example:**

    ```python
    import jaxvisco as jv

    integrator = jv.Midpoint()
    ```
    """

    k: int = eqx.field(static=True, default=1)
    n_quad: int = eqx.field(static=True, default=1)

    def _rules(self):
        rule = _gauss(1)
        return rule, rule

    @property
    def name(self) -> str:
        return "Midpoint"


class Newmark(AbstractStandardTimeElement):
    """Average-acceleration Newmark (the trapezoidal rule on positions and momenta), the
    internal variable advanced by the midpoint rule (for comparison).

    **Example:**

    ```python
    import jaxvisco as jv

    integrator = jv.Newmark()
    ```
    """

    k: int = eqx.field(static=True, default=1)
    n_quad: int = eqx.field(static=True, default=2)

    def _rules(self):
        return ((0.0, 1.0), (0.5, 0.5)), _gauss(1)

    @property
    def name(self) -> str:
        return "Newmark"

    def _rule_description(self):
        return "trapezoidal, internal variable by the midpoint rule"
