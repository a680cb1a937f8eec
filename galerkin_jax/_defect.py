"""Hamilton's field, the defect of an element polynomial, and the a posteriori local error.

An element maps z0 to z1 and carries a polynomial w(alpha), alpha in [0, 1] (its dense
output). In master time Hamilton's equations read z' = h F(z), F = J DH. The local error
e = z1 - z(1; z0) of the element, z the exact flow from z0, follows from the nonlinear
variation-of-constants (Alekseev-Groebner) formula with the defect
delta(alpha) = w'(alpha) - h F(w(alpha)) and the jumps of w at both ends:

    e = Phi(1, 0) (w(0) - z0) + int_0^1 Phi(1, alpha) delta(alpha) dalpha + (z1 - w(1)),

Phi(1, alpha) the derivative of the exact flow from alpha to 1. Expanding Phi(1, alpha) =
sum_j (h A)^j (1 - alpha)^j / j! with A = DF(w(1/2)) gives

    e ~ sum_{j=0}^{J} (h A)^j / j! m_j,
    m_j = (w(0) - z0) + int_0^1 (1 - alpha)^j delta(alpha) dalpha + [j = 0] (z1 - w(1)).

The Galerkin equations make the first moments vanish: with exact quadrature m_j = 0 for
j < k in cG(k) (the defect is orthogonal to the test space P^{k-1}) and for j <= k in dG(k)
(eq. (18): jump and defect together are orthogonal to P^k). The first term that survives is
the leading term of the local error, so the estimate has the method's true local order
(2k + 1 for cG(k), 2k + 2 for dG(k)) and is asymptotically exact, not a bound; with inexact
quadrature the lower moments no longer vanish and the estimate follows the lower order.
It costs J + 1 evaluations of F and J Jacobian-vector products per element, no implicit
solve; J is the number of Legendre coefficients of w, one more than the first surviving
term needs for cG and the midpoint schemes.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial import legendre as npleg

from . import _basis


def hamilton_field(H, part=None):
    """(q, p) -> J DH(q, p) = (dH/dp, -dH/dq) stacked, with DH from ``jax.grad`` [GBS, eq. (6)];
    ``part`` "q" or "p": that half alone, q' = dH/dp or p' = -dH/dq, from the one partial
    gradient it needs."""
    if part == "q":
        return jax.grad(H, argnums=1)
    if part == "p":
        return lambda q, p: -jax.grad(H, argnums=0)(q, p)
    dH = jax.grad(H, argnums=(0, 1))

    def field(q, p):
        dHdq, dHdp = dH(q, p)
        return jnp.concatenate([dHdp, -dHdq])

    return field


def symplectic_field(H):
    """z -> J DH(z) for z = (q, p) stacked (``hamilton_field``)."""
    field = hamilton_field(H)
    return lambda z: field(*jnp.split(z, 2))


@functools.lru_cache(maxsize=None)
def _collocation(J):
    """Gauss points alpha_l (J + 1 of them), weights b_l, and the integration matrix
    S[l, m] = int_0^{alpha_l} L_m, L_m the Lagrange polynomials on the points (exact to degree J)."""
    x, w = npleg.leggauss(J + 1)
    alpha = (x + 1.0) / 2.0
    V = npleg.legvander(x, J)  # P_j(x_l)
    coefficients = np.linalg.inv(V)  # column m: Legendre coefficients of L_m
    integrals = npleg.legval(x, npleg.legint(coefficients, lbnd=-1.0)) / 2.0  # [m, l]
    return alpha, w / 2.0, integrals.T


def local_error(H, q0, p0, W, increment, h):
    """The estimated local error of one element, max-norm over (q, p) (module docstring).

    The linear error equation y' = h A(alpha) y + delta(alpha), y(0) = w(0) - z0, is solved by
    J Picard sweeps on J + 1 Gauss points (each adds one power of h A, with A = DF along w),
    and e = y(1) + (z1 - w(1)).

    Args:
        H: ``H(q, p)``.
        q0, p0: the element's initial state, shape ``(d,)``.
        W: Legendre coefficients of ``w(alpha) - z0``, shape ``(J, 2d)``.
        increment: ``z1 - z0``, shape ``(2d,)``.
        h: step size.
    Returns:
        A scalar.
    """
    J, dtype = W.shape[0], W.dtype
    z0 = jnp.concatenate([q0, p0])
    alpha, weights, S = _collocation(J)
    alpha = jnp.asarray(alpha, dtype)
    field = jax.vmap(symplectic_field(H))
    on_w = z0[None, :] + _basis.combine(_basis.legendre_values(alpha, J), W)
    F, tangent = jax.linearize(field, on_w)  # A = DF along w, traced once for the J + 1 sweeps
    defect = _basis.combine(_basis.legendre_derivatives(alpha, J), W) - h * F
    start_jump = _basis.combine((-1.0) ** np.arange(J), W)

    sweep = lambda y: start_jump[None, :] + _basis.combine(S, h * tangent(y) + defect)
    y = jax.lax.fori_loop(0, J, lambda _, y: sweep(y), start_jump[None, :] + _basis.combine(S, defect))
    e = start_jump + _basis.combine(weights, h * tangent(y) + defect) + increment - jnp.sum(W, axis=0)
    return jnp.max(jnp.abs(e))
