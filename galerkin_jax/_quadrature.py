"""Quadrature rules on the master element [0, 1] [GBS, eq. (29)]."""

import jax
import numpy as np
from numpy.polynomial import legendre as npleg

from ._pytree import pytree_dataclass


def _is_concrete_array(x):
    return isinstance(x, (np.ndarray, jax.Array)) and not isinstance(x, jax.core.Tracer)


@pytree_dataclass
class QuadratureRule:
    """Points ``alpha_l`` in [0, 1] and weights ``w_l``: int_0^1 f ~ sum_l w_l f(alpha_l).

    A pytree with leaves ``points`` and ``weights`` (shape ``(n_q,)``), so rules with
    equal point counts can be stacked and vmapped, and both arrays can be differentiated.
    A zero weight is allowed: it pads a rule to a common point count without changing it.

    Args:
        points: shape ``(n_q,)``, in [0, 1].
        weights: shape ``(n_q,)``.
    """

    points: jax.Array
    weights: jax.Array

    def __post_init__(self):
        # Runs again on every unflatten (jit, vmap, in_axes specs): check concrete values only.
        for name in ("points", "weights"):
            value = getattr(self, name)
            if isinstance(value, (list, tuple, float, int)):
                object.__setattr__(self, name, np.atleast_1d(np.asarray(value, dtype=float)))
        points, weights = self.points, self.weights
        if not (_is_concrete_array(points) and _is_concrete_array(weights)):
            return
        if points.shape != weights.shape or points.ndim < 1 or points.shape[-1] == 0:
            raise ValueError(
                "quadrature: points and weights need the same non-empty shape (n_q,), got "
                f"{points.shape} and {weights.shape}."
            )
        pts, wts = np.asarray(points), np.asarray(weights)
        if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(wts))):
            raise ValueError("quadrature: points and weights must be finite.")
        if np.any(pts < 0.0) or np.any(pts > 1.0):
            raise ValueError(f"quadrature: points must lie in [0, 1], got {pts}.")

    @property
    def num_points(self):
        return self.points.shape[-1]


def _check_count(n, least, name):
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < least:
        raise ValueError(f"{name} needs an integer number of points n >= {least}, got {n!r}.")


def _from_reference(x, w):
    """Map a rule on [-1, 1] to [0, 1]."""
    return QuadratureRule(points=(np.asarray(x) + 1.0) / 2.0, weights=np.asarray(w) / 2.0)


def gauss_legendre(n):
    """n-point Gauss-Legendre rule on [0, 1]; exact for polynomials of degree 2n - 1."""
    _check_count(n, 1, "gauss_legendre")
    return _from_reference(*npleg.leggauss(int(n)))


def gauss_lobatto(n):
    """n-point Gauss-Lobatto rule on [0, 1] (both end points); exact to degree 2n - 3.

    Interior nodes are the roots of P'_{n-1}; the weights are 2 / (n (n - 1) P_{n-1}(x)^2).
    """
    _check_count(n, 2, "gauss_lobatto")
    n = int(n)
    p_last = np.zeros(n)
    p_last[-1] = 1.0  # Legendre coefficients of P_{n-1}
    interior = np.sort(np.real(npleg.legroots(npleg.legder(p_last)))) if n > 2 else np.array([])
    x = np.concatenate([[-1.0], interior, [1.0]])
    w = 2.0 / (n * (n - 1) * npleg.legval(x, p_last) ** 2)
    return _from_reference(x, w)


def gauss_radau(n, *, right=True):
    """n-point Gauss-Radau rule on [0, 1]; exact to degree 2n - 2.

    The right rule contains alpha = 1 (its nodes are those of Radau IIA); the left rule
    contains alpha = 0. Left nodes on [-1, 1]: roots of P_{n-1} + P_n; weights
    2 / n^2 at -1 and (1 - x) / (n^2 P_{n-1}(x)^2) elsewhere.
    """
    _check_count(n, 1, "gauss_radau")
    n = int(n)
    p_prev, p_n = np.zeros(n + 1), np.zeros(n + 1)
    p_prev[n - 1], p_n[n] = 1.0, 1.0
    x = np.sort(np.real(npleg.legroots(p_prev + p_n)))
    x[0] = -1.0
    w = (1.0 - x) / (n**2 * npleg.legval(x, p_prev) ** 2)
    w[0] = 2.0 / n**2
    if right:
        x, w = -x[::-1], w[::-1]
    return _from_reference(x, w)


def midpoint():
    """The one-point rule at alpha = 1/2 (= gauss_legendre(1)) [GBS, Remark 4.8]."""
    return QuadratureRule(points=np.array([0.5]), weights=np.array([1.0]))


def trapezoid():
    """The trapezoidal rule: points 0 and 1, weights 1/2 [GBS, Remark 4.7]."""
    return QuadratureRule(points=np.array([0.0, 1.0]), weights=np.array([0.5, 0.5]))
