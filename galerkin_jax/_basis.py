"""Legendre polynomials on the master element [0, 1] and the exact matrices built from them.

The Galerkin methods use modal (Legendre) coefficients instead of nodal values. The trial and
test spaces are the paper's, so the element equations are the same; but with test functions
(2i + 1) P_i(2 alpha - 1) every purely polynomial matrix has integer entries, exact in
binary. A nodal basis rounds its matrices once, which perturbs the scheme itself and turns
cG(k)'s exact energy conservation into a drift of a few eps per step.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial import legendre as npleg


def combine(A, X):
    """``A @ X`` for a small coefficient array A (shape ``(m,)`` or ``(l, m)``) and X of shape
    ``(m, ...)``, unrolled over m as ``sum_j A[..., j] X[j]``: elementwise products that XLA
    fuses with their neighbours, alone and under vmap, where a matrix product of this size is
    a kernel launch of its own and a broadcast-and-reduce is slow once batched. The rows X[j]
    come from one ``lax.split``, whose transpose (reverse mode) is one concatenate, where m
    indexed rows transpose into m padded arrays added up, a kernel each."""
    A = jnp.asarray(A, X.dtype)
    a_shape, x_shape = A.shape[:-1] + (1,) * (X.ndim - 1), (1,) * (A.ndim - 1) + X.shape[1:]
    rows = jax.lax.split(X, (1,) * X.shape[0])
    total = A[..., 0].reshape(a_shape) * rows[0].reshape(x_shape)
    for j in range(1, A.shape[-1]):
        total = total + A[..., j].reshape(a_shape) * rows[j].reshape(x_shape)
    return total


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


def legendre_derivatives(alpha, n):
    """d/dalpha P_j(2 alpha - 1) for j < n, from P'_{j+1} = P'_{j-1} + (2j + 1) P_j; shape ``(m, n)``."""
    P = legendre_values(alpha, n)
    zero = jnp.zeros_like(alpha)
    derivatives = [zero, 2.0 * jnp.ones_like(alpha)][:n]
    for j in range(1, n - 1):
        derivatives.append(derivatives[j - 1] + 2.0 * (2 * j + 1) * P[:, j])
    return jnp.stack(derivatives, axis=-1)


def legendre_antiderivatives(alpha, n):
    """A_j(alpha) = int_0^alpha P_j(2t - 1) dt for j < n; shape ``(m, n)``.

    A_0 = alpha and A_j = (P_{j+1} - P_{j-1}) / (2 (2j + 1)) for j >= 1, so A_j(1) = delta_j0.
    """
    P = legendre_values(alpha, n + 1)
    columns = [alpha] + [(P[:, j + 1] - P[:, j - 1]) / (2 * (2 * j + 1)) for j in range(1, n)]
    return jnp.stack(columns, axis=-1)


def test_scale(n):
    """2i + 1 for i < n: (2i + 1) int_0^1 P_i P_j = delta_ij."""
    return np.arange(n) * 2.0 + 1.0


@functools.lru_cache(maxsize=None)
def antiderivative_matrix(n):
    """T, shape ``(n + 1, n)``: sum_j C_j A_j = sum_i (T @ C)_i P_i, exact in binary up to n = 2
    and to one rounding beyond (A_0 = (P_0 + P_1) / 2, A_j = (P_{j+1} - P_{j-1}) / (2 (2j + 1)))."""
    T = np.zeros((n + 1, n))
    T[0, 0] = T[1, 0] = 0.5
    for j in range(1, n):
        T[j + 1, j], T[j - 1, j] = 1.0 / (2 * (2 * j + 1)), -1.0 / (2 * (2 * j + 1))
    return T


@functools.lru_cache(maxsize=None)
def derivative_matrix(n):
    """D[i, j] = (2i + 1) int_0^1 P_i(2a - 1) d/da P_j(2a - 1) da, exact integers.

    int_{-1}^{1} P_i P_j' dx is 2 when j > i and i + j is odd, else 0.
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return np.where((j > i) & ((i + j) % 2 == 1), 2.0 * (2 * i + 1), 0.0)


@functools.lru_cache(maxsize=None)
def shift_matrix(n, subtract_end=False):
    """T[i, j] = (2i + 1) int_0^1 P_i(2a - 1) (P_j(2a + 1) - s_j) da: a Legendre series continued
    one element ahead, re-expanded on [0, 1] (s_j = P_j(1) = 1 if ``subtract_end`` else 0).

    # exact: Gauss with n points integrates the degree 2n - 2 products
    """
    x, _ = npleg.leggauss(n)
    return test_scale(n)[:, None] * (_moments(n) @ (npleg.legvander(x + 2.0, n - 1) - (1.0 if subtract_end else 0.0)))


def _moments(n):
    """w_g P_i(x_g) / 2, shape ``(n, n)``: applied to a polynomial's values at the n-point Gauss
    nodes x_g, int_0^1 P_i(2a - 1) times it (exact up to degree 2n - 1 - i); times 2i + 1, its
    Legendre coefficients."""
    x, w = npleg.leggauss(n)
    return (npleg.legvander(x, n - 1) * (w / 2.0)[:, None]).T


def continuation(n, ratio=None, subtract_end=False):
    """``shift_matrix`` for a next element ``ratio`` times as long as the series' own (ratio may
    be traced; None: 1, the exact static matrix): T[i, j] = (2i + 1) int_0^1 P_i(2a - 1)
    (P_j(1 + 2 ratio a) - s_j) da, a polynomial of degree n - 1 in ratio: the vector of its
    powers times the coefficient matrices (``_continuation_powers``), one small product, where
    the Legendre recurrence at shifted nodes is a chain of kernels in every element of a run."""
    if ratio is None:
        return shift_matrix(n, subtract_end)
    ratio = jnp.asarray(ratio)
    powers = ratio ** jnp.arange(n, dtype=ratio.dtype)
    return (powers @ jnp.asarray(_continuation_powers(n, subtract_end).reshape(n, n * n), ratio.dtype)).reshape(n, n)


@functools.lru_cache(maxsize=None)
def _continuation_powers(n, subtract_end):
    """T_m, shape ``(n, n, n)``, with ``continuation(n, r) = sum_m r^m T_m``: P_j(1 + 2 r a) at the
    n Gauss nodes a, expanded in powers of r, integrated against P_i by the n-point Gauss rule
    (exact: the products have degree at most 2n - 2 in a)."""
    x, _ = npleg.leggauss(n)
    a = (x + 1.0) / 2.0
    ahead = np.zeros((n, n, n))  # [power of r, node, j]
    for j in range(n):
        P_j = npleg.Legendre.basis(j).convert(kind=np.polynomial.Polynomial)
        for g in range(n):
            coefficients = P_j(np.polynomial.Polynomial([1.0, 2.0 * a[g]])).coef
            ahead[: coefficients.size, g, j] = coefficients
    if subtract_end:
        ahead[0] -= 1.0
    return test_scale(n)[None, :, None] * (_moments(n)[None] @ ahead)
