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
0.7-1.2 times. The interpolant through the nodes alone (degree k) under-stated instead
for k >= 2, by up to 5x: it misses its own interpolation error, which eG's flow rule
does see; there the strain path also follows the strain rates at the step's two ends
(`strain_path_matrices`).

The defect's integral is taken of the interpolant of the evolution rate at $k + 2$ Gauss
points of the step (and exactly for $\int p_h$) and checked at those points: $k + 2$
mass solves (and the end velocities, which the adaptive loop has) and $k + 2$
evaluations of the evolution law, against some 60 residual evaluations of a step.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._fem._quadrature import gauss_legendre
from .._fem._tensor import mm, right_cauchy_green, sym_to_vec, vec_to_sym
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


@functools.lru_cache(maxsize=None)
def strain_path_matrices(k):
    """eG's strain path for the internal-variable defect at the check points: the
    polynomial of degree k + 2 through the strains at the k + 1 time nodes with the strain
    rates at both ends of the step, as values `Hv` (q, k+1) and end-rate weights `Hd`
    (q, 2) (rates as d/dsigma).

    Why the rates: eG's flow rule sees the strains interpolated through its nodes (degree
    k), whose interpolation error inside the step is part of the internal variable's true
    error. Measured against the true local error (2D L-shape, as
    `benchmarks/adaptive_effectivity.py`), the internal-variable estimate with the degree-k
    interpolant under-stated by up to 5x: effectivity 0.20 at eG(3)'s first step (h = 0.1),
    0.34 at t = 2.95, 0.31 at t = 40; eG(2) 0.40 at its first step, 0.28-0.33 at t = 40;
    with the end rates 0.74, 0.43, 0.81; 2.0, 0.84-1.05. The rates at the ends come from
    the momenta there, which are the accurate ones for k >= 2 (p_n given, p_{n+1}
    superconvergent, O(h^2k)); the interior nodes' momenta are not used. Not for eG(1):
    its p_{n+1} is second-order, the order of the interpolation error itself, and on the
    rotating body at t = 40 the rates made its estimate 2.7-5.0 times the true error
    (0.95-1.09 without; 0.59-1.30 over the runs of the effectivity benchmark)."""
    nodes = np.asarray(lobatto_nodes(k), dtype=float)
    sigma = defect_matrices(k)[0]
    ends = nodes[[0, -1]]
    powers = np.arange(k + 3)
    rows = np.concatenate([nodes[:, None] ** powers,
                           powers * ends[:, None] ** np.maximum(powers - 1, 0)])
    H = (np.asarray(sigma)[:, None] ** powers) @ np.linalg.inv(rows)
    return H[:, : k + 1], H[:, k + 1:]


def nodal_values(scheme, scene, ctx, U):
    """The step's polynomial at its k + 1 time nodes: position increments (k+1, n, d),
    momenta (k+1, n, d) and internal variables (k+1, n_cells, nq, 3, 3) or None."""
    X = increments(ctx, U)
    P = jnp.concatenate([ctx.state.p[None], momenta(scheme, scene, ctx, X)], axis=0)
    G = None if U.g is None else jnp.concatenate([ctx.state.gamma[None], vec_to_sym(U.g)], axis=0)
    return X, P, G


def uses_end_velocities(scheme, scene, state):
    """Whether `defects` follows the strain rates at the step's ends, from the velocities
    $M^{-1}p$ there: eG(k), k >= 2, with an internal variable on a free body. (With held
    nodes the momenta's velocities are not the held nodes' motion; eG(1)'s end momenta
    are accurate to second order only, the order of the interpolation error the rates
    are to add: see `strain_path_matrices`. There the strain path is the interpolant
    through the nodes.)"""
    return scheme.enhanced and scheme.k >= 2 and scene.fixed is None and state.gamma is not None


def defects(scheme, scene, ctx, U, end_velocities=None):
    """Integral defects at the k + 2 check points: positions (q, n, d) and internal
    variable (q, n_cells, nq, 6; None without one). `end_velocities`: $M^{-1}p$ at the
    step's start and end where the caller has them (`uses_end_velocities`), else they
    are solved for here."""
    sigma, V, A, B = (jnp.asarray(a) for a in defect_matrices(scheme.k))
    X, P, G = nodal_values(scheme, scene, ctx, U)
    h = ctx.h
    Xs = jnp.einsum("cI,Ind->cnd", V, X)
    e_x = Xs - h * jax.vmap(scene.velocity)(jnp.einsum("cI,Ind->cnd", A, P))
    if G is None:
        return e_x, None
    Gs = jnp.einsum("cI,I...->c...", V, G)

    if scheme.enhanced:
        # eG drives the flow with strains interpolated through the nodes: here through the
        # nodal strains and, for k >= 2 on a free body, the strain rates at the step's two
        # ends (`strain_path_matrices`).
        disc = scene.disc
        F = jax.vmap(lambda dx: disc.deformation_gradient(ctx.state.x + dx))(X)
        CI = right_cauchy_green(F)
        if uses_end_velocities(scheme, scene, ctx.state):
            if end_velocities is None:
                # (a rate enters only the small difference from the nodal interpolant)
                end_velocities = jax.vmap(lambda p: scene.velocity(p, rtol=1e-10))(jnp.stack([P[0], P[-1]]))
            Fd = disc.gradient(jnp.stack(end_velocities))
            FF = jnp.stack([F[0], F[-1]])
            Cd = mm(jnp.swapaxes(FF, -1, -2), Fd)
            Cd = h * (Cd + jnp.swapaxes(Cd, -1, -2))  # dC/dsigma = h dC/dt at sigma = 0 and 1
            Hv, Hd = (jnp.asarray(a) for a in strain_path_matrices(scheme.k))
            Cs = jnp.einsum("cI,I...->c...", Hv, CI) + jnp.einsum("cE,E...->c...", Hd, Cd)
        else:
            Cs = jnp.einsum("cI,I...->c...", V, CI)
    else:
        Cs = jax.vmap(lambda dx: right_cauchy_green(scene.disc.deformation_gradient(ctx.state.x + dx)))(Xs)
    gdot = jax.vmap(lambda C, g: sym_to_vec(scene.map_points(lambda m, c, gg: m.gamma_rate(c, gg), C, g)))(Cs, Gs)
    e_g = sym_to_vec(Gs) - sym_to_vec(ctx.state.gamma)[None] - h * jnp.einsum("cj,j...->c...", B, gdot)
    return e_x, e_g


def _rms(a, axes):
    return jnp.sqrt(jnp.mean(a * a, axis=axes))


# The internal variable's tolerance is at least this many units of rounding of Γ (|Γ| ≈ 1):
# below it the estimate of a body that starts undeformed (|C - I| and |Γ - I| ~ 0, so
# `atol * sqrt(eps)`) measured rounding, and the step shrank without end. Paper L-shape
# from t = 0 without it: eG(3) at rtol = atol = 1e-9 and 1e-10 stopped at the first step
# ("failed"), eG(2) at 1e-9 took 4000 steps of ~1e-6 to t < 0.01; with it (1, 4 or 16 ulps
# all start) 447 / 803 / 1473 steps to t = 0.5. Runs with atol * sqrt(eps) above it
# (atol >= 2.4e-7) are unchanged bit for bit.
GAMMA_ROUNDING_ULPS = 16


def energy_tolerance(scene, state, rtol, energy):
    r"""The internal variable's tolerance from the energy (a root mean square over the
    body, as `scaled_error` measures Γ): an error δΓ changes the free energy by
    $\int \partial\Psi/\partial\Gamma : \delta\Gamma\,dV \le V\,|Y|\,\sqrt{12}\,
    \mathrm{rms}(\delta\Gamma)$ ($Y = \partial\Psi/\partial\Gamma$ at `state`, $|Y|$ the
    root mean square of its Frobenius norm over the points, $\sqrt{12}$ from the Voigt
    root mean square to the Frobenius norm), which this keeps at most `rtol` times
    `energy`. Infinite where Y vanishes (no viscous stress)."""
    C = right_cauchy_green(scene.disc.deformation_gradient(state.x))
    Y = scene.map_points(lambda m, c, g: m.energy_gradient_gamma(c, g), C, state.gamma)
    y = jnp.sqrt(jnp.mean(jnp.sum(Y * Y, axis=(-2, -1))))
    bound = jnp.sqrt(12.0) * jnp.sum(scene.disc.JxW) * y
    return jnp.where(bound > 0, rtol * jnp.maximum(energy, 0.0) / jnp.where(bound > 0, bound, 1.0), jnp.inf)


def scaled_error(scheme, scene, ctx, U, new, rtol, atol, end_velocities=None, strain_scale=0.0, energy=None):
    """The step's error estimate in units of the tolerance (accept where <= 1): per group
    (positions, internal variable) the root mean square of the defect over the body,
    divided by that group's `atol * a + rtol * scale`, maximal over the check points and
    groups. Returns it and the strain of the step's end (`a` below, before the maximum
    with `strain_scale`), which the loop carries as the run's largest.

    Positions: ``a = 1`` (`atol` is a length), the scale their distance from the
    centroid (a body's size, not its distance from the origin). Internal variable: the
    scale its distance from the virgin state ``Γ = I`` (the viscous strain), and `atol` in
    units of the body's strain ``a = |C - I|`` (root mean square over the points; at least
    sqrt(eps)), the strain that Γ relaxes towards; the whole at least
    `GAMMA_ROUNDING_ULPS` units of rounding. Measured against ``|Γ| ≈ 1`` (as
    before), a tolerance on Γ left the viscous strain of the paper's L-shape (|Γ - I| ≈
    3e-4) uncontrolled: the dissipated energy at t = 2 was off by 230-800 times rtol = atol
    (eG(1)), 23-27 times with this scale
    (`benchmarks/adaptive_proportionality.py`). ``a`` is at least `strain_scale`, the
    largest strain of the run so far (`PIDController.strain_scale`): measured against the
    strain of the moment alone, the tolerance on Γ shrank with the strain, and a body that
    comes to rest kept the step of its vibrations (`benchmarks/adaptive_relaxation.py`)."""
    e_x, e_g = defects(scheme, scene, ctx, U, end_velocities)
    x = new.x - jnp.mean(new.x, axis=0)
    sx = atol + rtol * _rms(x, None)
    err = jnp.max(_rms(e_x, (1, 2))) / sx
    strain = jnp.asarray(0.0, err.dtype)
    if e_g is not None:
        eye = jnp.eye(3)
        strain = body_strain(scene, new.x)
        a = jnp.maximum(jnp.maximum(strain, strain_scale), jnp.sqrt(jnp.finfo(strain.dtype).eps))
        sg = atol * a + rtol * _rms(sym_to_vec(new.gamma - eye), None)
        if energy is not None:  # at most the tolerance of Γ itself (|Γ| ~ 1), as of positions
            sg = jnp.maximum(sg, jnp.minimum(atol + rtol, energy_tolerance(scene, new, rtol, energy)))
        sg = jnp.maximum(sg, GAMMA_ROUNDING_ULPS * jnp.finfo(sg.dtype).eps)
        err = jnp.maximum(err, jnp.max(_rms(e_g, tuple(range(1, e_g.ndim)))) / sg)
    return err, strain


def body_strain(scene, x):
    """The body's strain at positions `x`: the root mean square of ``C - I`` over its
    quadrature points (Voigt components)."""
    C = right_cauchy_green(scene.disc.deformation_gradient(x))
    return _rms(sym_to_vec(C - jnp.eye(3)), None)


@eqx.filter_jit
def largest_strain(scene, xs):
    """The largest `body_strain` over positions `xs` (frames, n_nodes, dim): the
    `PIDController.strain_scale` that continues a run whose frames these are."""
    return jnp.max(jax.lax.map(lambda x: body_strain(scene, x), jnp.asarray(xs)))


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
