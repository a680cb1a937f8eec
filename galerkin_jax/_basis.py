"""Lagrange and Legendre bases on the master element [0, 1].

Everything purely polynomial is built once per degree in NumPy float64 (exact up to
round-off); only the values at quadrature points, which may be traced, are
evaluated in JAX.
"""

import functools

import jax.numpy as jnp
import numpy as np
from numpy.polynomial import legendre as npleg


def legendre_values(alpha, n):
    """P_j(2 alpha - 1) for j < n, by the three-term recurrence; differentiable in alpha.

    Args:
        alpha: shape ``(m,)``.
        n: number of polynomials (static).
    Returns:
        shape ``(m, n)``.
    """
    x = 2.0 * alpha - 1.0
    values = [jnp.ones_like(x), x][:n]
    for j in range(1, n - 1):
        values.append(((2 * j + 1) * x * values[j] - j * values[j - 1]) / (j + 1))
    return jnp.stack(values, axis=-1)


@functools.lru_cache(maxsize=None)
def lobatto_nodes(k):
    """The k + 1 Gauss-Lobatto nodes on [0, 1] (k >= 1), well-conditioned nodes for P^k."""
    if k == 0:
        return np.array([1.0])
    p_k = np.zeros(k + 1)
    p_k[-1] = 1.0
    interior = np.sort(np.real(npleg.legroots(npleg.legder(p_k)))) if k > 1 else np.array([])
    return (np.concatenate([[-1.0], interior, [1.0]]) + 1.0) / 2.0


@functools.lru_cache(maxsize=None)
def lagrange_in_legendre(k):
    """C with M_J(alpha) = sum_j C[j, J] P_j(2 alpha - 1): the Lagrange basis of eq. (11) [GBS].

    Nodes are ``lobatto_nodes(k)``; for k = 0 the single basis function is M_1 = 1.
    """
    vander = npleg.legvander(2.0 * lobatto_nodes(k) - 1.0, k)  # vander[i, j] = P_j(x_i)
    return np.linalg.inv(vander)


def lagrange_values(alpha, k):
    """M_J(alpha_l) for the degree-k Lagrange basis; shape ``(m, k + 1)``, traceable."""
    coeffs = jnp.asarray(lagrange_in_legendre(k), dtype=jnp.result_type(alpha))
    return legendre_values(alpha, k + 1) @ coeffs


def lagrange_values_np(alpha, k):
    """NumPy version of ``lagrange_values`` for constant points (also outside [0, 1])."""
    return npleg.legvander(2.0 * np.asarray(alpha, dtype=float) - 1.0, k) @ lagrange_in_legendre(k)


@functools.lru_cache(maxsize=None)
def stiffness(n_test, k):
    """K[I, J] = int_0^1 P_I(2a - 1) M_J'(a) da, I < n_test, J <= k; exact (Gauss, k + 1 points).

    # exact: the integrand has degree n_test - 1 + k - 1 <= 2k - 1.
    """
    x, w = npleg.leggauss(k + 1)
    test = npleg.legvander(x, n_test - 1)
    d_coeffs = np.stack([2.0 * npleg.legder(c) for c in lagrange_in_legendre(k).T], axis=1)
    d_values = npleg.legvander(x, max(k - 1, 0)) @ d_coeffs if k > 0 else np.zeros((len(x), 1))
    return (test * (w / 2.0)[:, None]).T @ d_values


@functools.lru_cache(maxsize=None)
def extrapolation(k):
    """E[i, J] = M_J(1 + alpha_i): the previous element's polynomial at this element's nodes."""
    return lagrange_values_np(1.0 + lobatto_nodes(k), k)
