"""States between two nodes with the nodes' accuracy: the element polynomial refined by Picard sweeps.

An element's polynomial w (``_output``) is accurate to O(h^m) between its nodes, m = its
number of Legendre coefficients (k + 1 for cG(k) and dG(k)), where the nodes of cG(k) with k
Gauss points are accurate to a local O(h^(2k + 1)). ``refine`` builds from w a polynomial
w~ in the same form, ``z0 + sum_j W~_j P_j(2 alpha - 1)``, whose error between the nodes is
of the local order ``order``:

1. Picard sweeps on N = ``order`` - 1 Gauss points alpha_l of [0, 1]:

       Z_l <- z0 + h sum_i S[l, i] F(Z_i),   S[l, i] = int_0^{alpha_l} L_i,

   L_i the Lagrange polynomials on the points, F = J DH (master time: z' = h F(z)), from
   Z_l = w(alpha_l). Each sweep gains one power of h on the error of Z (the sweep's map
   has Lipschitz constant O(h)); the interpolation of F on N points errs by O(h^(N + 1)),
   the uniform error of N-stage Gauss collocation to which the sweeps converge (Hairer,
   Norsett, Wanner, Solving ODEs I, Sec. II.7). ``order`` - m - 1 sweeps take the error from
   O(h^m) to O(h^(order - 1)) at the points.
2. w~(alpha) = z0 + h int_0^alpha (the interpolant of F(Z) on the points): one evaluation
   more, error O(h^order), degree N (``order`` Legendre coefficients).
3. + alpha (z1 - w~(1)): w~ passes through both nodes (w~(0) = z0 by construction); the gap
   is itself O(h^order) where the node z1 is as accurate.

Cost: ``order`` - m evaluations of F on N points, no implicit solve; F from ``jax.grad`` of
H, so any H the run accepts works. Differentiable (``jax.jvp``, ``jax.vjp``) in z0, z1, W,
h and alpha. For cG(k), ``order`` = 2k + 1: k evaluations on 2k points. Measured: the error
inside is 0.82 to 1.00 times z1's local error, of its order (cG(2), cG(4), cG(6) on Kepler,
a non-polynomial H, a time-transformed Kepler: ``tests/test_interpolate.py``); over 100
orbits of a time-transformed Kepler e = 0.99 the energy error between the nodes is 1.01 to
1.25 times the nodes' per orbit (the one-off ``interpolate`` study of notes/README.md;
docs/accuracy.md, "States between the nodes").

A time-transformed run (``TimeTransform``) passes the Hamiltonian it solves, the Poincare
K on the extended state z = (q, t, p, p_t), its step h in tau and its alpha in tau: w~ has
the same form as w, so ``_output.time_at`` and ``_output.alpha_at_time`` with ``clock``
invert its time coordinate as they do w's.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial import legendre as npleg

from . import _basis
from ._defect import symplectic_field


@functools.lru_cache(maxsize=None)
def _sweep_matrices(N):
    """The N Gauss points alpha_l on [0, 1]; M, shape ``(N, N)``: Legendre coefficients of the
    interpolant from its values at the points ((2j + 1) w_l P_j(x_l) / 2, the N-point Gauss rule,
    exact for these products of degree <= 2N - 2); S = A M, shape ``(N, N)``: the values at the
    points of its antiderivative from 0 (A[l, j] = int_0^{alpha_l} P_j(2t - 1) dt)."""
    x, _ = npleg.leggauss(N)
    alpha = (x + 1.0) / 2.0
    M = _basis.test_scale(N)[:, None] * _basis._moments(N)
    P = npleg.legvander(x, N)  # P_j(x_l), j <= N
    A = np.column_stack([alpha] + [(P[:, j + 1] - P[:, j - 1]) / (2 * (2 * j + 1)) for j in range(1, N)])
    return alpha, M, A @ M


def refine(H, z0, z1, W, h, *, order):
    """Legendre coefficients ``W~`` of the refined polynomial minus z0 (module docstring).

    Args:
        H: the Hamiltonian the run solves, bound: ``H(q, p)`` (a time-transformed run's K).
        z0, z1: the element's nodes, ``(2d,)`` each, z = (q, p).
        W: its polynomial's Legendre coefficients, ``(m, 2d)`` (``DenseOutput.W``), accurate
            to O(h^m) between the nodes.
        h: its step (in tau for a time-transformed run).
        order: the local order of w~'s error, an int > m (static); cG(k): 2k + 1, the
            order of its nodes' local error (measured for cG; for another method, its
            nodes' local order, not measured).
    Returns:
        ``(order, 2d)``: w~(alpha) = ``_output.on_polynomial(z0, W~, alpha)``.
    """
    m = W.shape[0]
    if order <= m:
        raise ValueError(f"refine: order {order} must exceed the polynomial's {m} coefficients.")
    alpha, M, S = (jnp.asarray(a, z0.dtype) for a in _sweep_matrices(order - 1))
    field = lambda Z: h * jax.vmap(symplectic_field(H))(Z)
    Z = z0[None, :] + _basis.combine(_basis.legendre_values(alpha, m), W)
    for _ in range(order - m - 1):
        Z = z0[None, :] + _basis.combine(S, field(Z))
    refined = _basis.combine(_basis.antiderivative_matrix(order - 1), _basis.combine(M, field(Z)))
    gap = z1 - z0 - jnp.sum(refined, axis=0)  # P_j(1) = 1; alpha = (P_0 + P_1) / 2
    return refined.at[:2].add(0.5 * gap[None, :])


def interpolate(H, z0, z1, W, h, alpha, *, order):
    """States at ``alpha`` (scalar or ``(n,)``, in [0, 1]) of one element from ``refine``:
    ``(2d,)`` or ``(n, 2d)``."""
    refined = refine(H, z0, z1, W, h, order=order)
    values = z0[None, :] + _basis.combine(_basis.legendre_values(jnp.atleast_1d(alpha), order), refined)
    return values[0] if jnp.ndim(alpha) == 0 else values
