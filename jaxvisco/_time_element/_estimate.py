r"""A posteriori estimate of a time element's error over one step, from its defect.

A converged cG(k)/eG(k) step is a polynomial $y_h = (x_h, p_h, \Gamma_h)$ of degree k on
$[t_n, t_n + h]$. Its *integral defect* at $t_n + \sigma h$,

$$e(\sigma) = y_h(\sigma) - y_n - h\int_0^\sigma f(t_n + sh, y_h(s))\,ds,$$

with $f$ the semi-discrete right-hand side ($\dot x = M^{-1}p$,
$\dot p = -f_{int} + f_{ext}$, $\dot\Gamma$ the evolution law), is the error of the
polynomial against the exact solution from $y_n$ to leading order: the local error
$y_h - y$ solves the variational equation with the defect $y_h' - f(y_h)$ as its source,
and over one step its propagator is $I + O(h)$. The polynomial is exact at the Galerkin
points only, so inside the step $e = O(h^{k+1})$ (while the step's end value is
superconvergent, $O(h^{2k+1})$): this estimate controls the whole time polynomial, which
is what dense output, the energy and the dissipation curves are made of. eG's
algorithmic stress is not $f$, so its share of the error is measured too.

The momenta are left out of the estimate, by measurement: their defect carries the
internal force of the polynomial's interior positions, and a linear (k = 1) position
polynomial between two turned configurations of the paper's rotating L-shape is shortened
by $(\omega h)^2/8$, so the stiff elastic response turns a small position error into a
large force defect. At h = 0.1 the momentum defect was 11 % of the momenta where the
interior momentum error itself is $(\omega h)^2/8 \approx 5 \cdot 10^{-4}$: the
propagator of a stiff system is not I + O(h) (the reason Radau5 filters its estimate
through $(I - h\gamma J)^{-1}$). The position defect involves only $M^{-1}p$ and the
internal-variable defect the evolution law, so both measure their errors. For eG the
evolution law is evaluated at eG's assumed strains (interpolated through the time nodes,
as its flow rule sees them), not at the strains of the interior positions: those carry
the same shortening, and measured against the true local error the internal-variable
estimate of eG(1) then overestimated 18-40 times (rtol = 1e-3), its position estimate
0.7-1.2 times.

The defect's integral is taken of the interpolant of the evolution rate at $k + 2$ Gauss
points of the step (and exactly for $\int p_h$) and checked at those points: $k + 2$
mass solves and evaluations of the evolution law, against some 60 residual evaluations
of a step.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._fem._quadrature import gauss_legendre
from .._fem._tensor import right_cauchy_green, sym_to_vec, vec_to_sym
from ._step import increments, momenta
from ._time_basis import lagrange, lobatto_nodes


@functools.lru_cache(maxsize=None)
def defect_matrices(k):
    """Check points `sigma` (k + 2 Gauss points on [0, 1]), the nodal basis there
    `V` (q, k+1), and the integrals from 0 to each check point of the nodal basis `A`
    (q, k+1) and of the Lagrange basis on the check points `B` (q, q)."""
    nodes = lobatto_nodes(k)
    sigma, _ = gauss_legendre(k + 2)
    V, _ = lagrange(nodes, sigma)
    s, w = gauss_legendre(k + 4)  # exact for the degree k + 1 integrands
    pts = sigma[:, None] * s[None]  # (q, m) points of [0, sigma_c]
    wts = sigma[:, None] * w[None]
    A = np.stack([wts[c] @ lagrange(nodes, pts[c])[0] for c in range(len(sigma))])
    B = np.stack([wts[c] @ lagrange(sigma, pts[c])[0] for c in range(len(sigma))])
    return sigma, V, A, B


def nodal_values(scheme, scene, ctx, U):
    """The step's polynomial at its k + 1 time nodes: position increments (k+1, n, d),
    momenta (k+1, n, d) and internal variables (k+1, n_cells, nq, 3, 3) or None."""
    X = increments(ctx, U)
    P = jnp.concatenate([ctx.state.p[None], momenta(scheme, scene, ctx, X)], axis=0)
    G = None if U.g is None else jnp.concatenate([ctx.state.gamma[None], vec_to_sym(U.g)], axis=0)
    return X, P, G


def defects(scheme, scene, ctx, U):
    """Integral defects at the k + 2 check points: positions (q, n, d) and internal
    variable (q, n_cells, nq, 6; None without one)."""
    sigma, V, A, B = (jnp.asarray(a) for a in defect_matrices(scheme.k))
    X, P, G = nodal_values(scheme, scene, ctx, U)
    h = ctx.h
    Xs = jnp.einsum("cI,Ind->cnd", V, X)
    e_x = Xs - h * jax.vmap(scene.velocity)(jnp.einsum("cI,Ind->cnd", A, P))
    if G is None:
        return e_x, None
    Gs = jnp.einsum("cI,I...->c...", V, G)

    if scheme.enhanced:
        # eG drives the flow with its assumed strains, interpolated through the nodes.
        CI = jax.vmap(lambda dx: right_cauchy_green(scene.disc.deformation_gradient(ctx.state.x + dx)))(X)
        Cs = jnp.einsum("cI,I...->c...", V, CI)
    else:
        Cs = jax.vmap(lambda dx: right_cauchy_green(scene.disc.deformation_gradient(ctx.state.x + dx)))(Xs)
    gdot = jax.vmap(lambda C, g: sym_to_vec(scene.map_points(lambda m, c, gg: m.gamma_rate(c, gg), C, g)))(Cs, Gs)
    e_g = sym_to_vec(Gs) - sym_to_vec(ctx.state.gamma)[None] - h * jnp.einsum("cj,j...->c...", B, gdot)
    return e_x, e_g


def _rms(a, axes):
    return jnp.sqrt(jnp.mean(a * a, axis=axes))


def scaled_error(scheme, scene, ctx, U, new, rtol, atol):
    """The step's error estimate in units of the tolerance (accept where <= 1): per group
    (positions, internal variable) the root mean square of the defect over the body,
    divided by that group's `atol * a + rtol * scale`, maximal over the check points and
    groups.

    Positions: ``a = 1`` (`atol` is a length), the scale their distance from the
    centroid (a body's size, not its distance from the origin). Internal variable: the
    scale its distance from the virgin state ``Γ = I`` (the viscous strain), and `atol` in
    units of the body's strain ``a = |C - I|`` (root mean square over the points; at least
    sqrt(eps)), the strain that Γ relaxes towards. Measured against ``|Γ| ≈ 1`` (as
    before), a tolerance on Γ left the viscous strain of the paper's L-shape (|Γ - I| ≈
    3e-4) uncontrolled: the dissipated energy at t = 2 was off by 230-800 times rtol = atol
    (eG(1)), 23-27 times with this scale
    (`benchmarks/adaptive_proportionality.py`)."""
    e_x, e_g = defects(scheme, scene, ctx, U)
    x = new.x - jnp.mean(new.x, axis=0)
    sx = atol + rtol * _rms(x, None)
    err = jnp.max(_rms(e_x, (1, 2))) / sx
    if e_g is not None:
        eye = jnp.eye(3)
        C = right_cauchy_green(scene.disc.deformation_gradient(new.x))
        strain = jnp.maximum(_rms(sym_to_vec(C - eye), None), jnp.sqrt(jnp.finfo(C.dtype).eps))
        sg = atol * strain + rtol * _rms(sym_to_vec(new.gamma - eye), None)
        err = jnp.maximum(err, jnp.max(_rms(e_g, tuple(range(1, e_g.ndim)))) / sg)
    return err


def step_polynomial(scheme, scene, ctx, U):
    """The step's time polynomial, as `dense_state` evaluates it: the start positions and
    the nodal values (`nodal_values`)."""
    return (ctx.state.x,) + nodal_values(scheme, scene, ctx, U)


def polynomial_state(scheme, poly, sigma):
    """A `step_polynomial` at `t_n + sigma h` (`sigma` in [0, 1], traced): a `State`."""
    from .._scene import State

    x0, X, P, G = poly
    nodes = lobatto_nodes(scheme.k)
    ell = jnp.stack([jnp.prod(jnp.stack([(sigma - nodes[j]) / (nodes[i] - nodes[j])
                                         for j in range(len(nodes)) if j != i] or [jnp.ones_like(sigma)]))
                     for i in range(len(nodes))])
    x = x0 + jnp.einsum("I,Ind->nd", ell, X)
    p = jnp.einsum("I,Ind->nd", ell, P)
    g = None if G is None else jnp.einsum("I,I...->...", ell, G)
    return State(x, p, g)


def dense_state(scheme, scene, ctx, U, sigma):
    """The step's polynomial at `t_n + sigma h` (`sigma` in [0, 1], traced): a `State`."""
    return polynomial_state(scheme, step_polynomial(scheme, scene, ctx, U), sigma)
