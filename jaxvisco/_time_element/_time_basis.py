"""Polynomial bases on the time element [0, 1] (numpy, built once per scheme)."""

import functools

import numpy as np

from .._fem._quadrature import gauss_legendre


def lagrange(nodes, points):
    """Values and derivatives of the Lagrange polynomials on `nodes` at `points`.

    **Returns:** `(V, D)`, each (len(points), len(nodes)).
    """
    nodes = np.asarray(nodes, dtype=float)
    points = np.asarray(points, dtype=float)
    n = len(nodes)
    V = np.ones((len(points), n))
    D = np.zeros((len(points), n))
    for i in range(n):
        others = [j for j in range(n) if j != i]
        denom = np.prod([nodes[i] - nodes[j] for j in others]) if others else 1.0
        for j in others:
            V[:, i] *= points - nodes[j]
        for m in others:
            term = np.ones(len(points))
            for j in others:
                if j != m:
                    term *= points - nodes[j]
            D[:, i] += term
        V[:, i] /= denom
        D[:, i] /= denom
    return V, D


def lobatto_nodes(k):
    """The k+1 Gauss–Lobatto nodes on [0, 1] (equally spaced for k <= 2).

    eG evaluates its stresses at strains interpolated through the time nodes; with
    equally spaced nodes that interpolation caps eG(3) at order 4 (measured with `drive`:
    4.0), with Lobatto nodes it keeps the order 2k (measured: 5.8 and rising).
    """
    if k <= 2:
        return np.linspace(0.0, 1.0, k + 1)
    inner = np.sort(np.real(np.polynomial.legendre.Legendre.basis(k).deriv().roots()))
    return np.concatenate([[0.0], 0.5 * (inner + 1.0), [1.0]])


@functools.lru_cache(maxsize=None)
def time_element_matrices(k, points, weights):
    """Everything a degree-k time element needs for one quadrature rule.

    Trial functions $M_I$ on the k+1 Gauss–Lobatto nodes of [0, 1] ($M_0$ carries the
    known state), test functions of degree k-1 (Lagrange on the k Gauss points, so that
    with the k-point Gauss rule the weak form is collocation at the Gauss points).

    Momenta are eliminated exactly: the weak form of $M x' = h p$ gives the unknown nodal
    momenta as $p_{1:} = P_m (MX)/h + P_p\\,p_0$, and the momentum equation becomes
    $R_x = A (MX)/h + b\\,p_0 + h\\,W(f - f_{ext})$.
    """
    points = np.asarray(points, dtype=float)
    weights = np.asarray(weights, dtype=float)
    nodes = lobatto_nodes(k)
    V, D = lagrange(nodes, points)
    test_nodes = gauss_legendre(k)[0] if k > 1 else np.array([0.5])
    T, _ = lagrange(test_nodes, points)
    W = (weights[:, None] * T).T  # (k, nq): W[J, l] = w_l T_J(a_l)
    Q = W @ D  # (k, k+1)
    E = W @ V  # (k, k+1)
    E1_inv = np.linalg.inv(E[:, 1:])
    Pm = E1_inv @ Q
    Pp = -E1_inv @ E[:, 0]
    A = Q[:, 1:] @ Pm
    b = Q[:, 0] + Q[:, 1:] @ Pp
    _, Dend = lagrange(nodes, np.array([1.0]))
    _, D_test = lagrange(nodes, test_nodes)  # x_h' at the test nodes: reaction work
    return dict(nodes=nodes, points=points, weights=weights, V=V, D=D, W=W, Q=Q,
                Pm=Pm, Pp=Pp, A=A, b=b, D_end=Dend[0], D_test=D_test)
