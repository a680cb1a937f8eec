"""Energy-momentum schemes: the modified midpoint rule [GBS, eqs. (90)-(91)] and
Gonzalez's midpoint discrete gradient."""

import jax
import jax.numpy as jnp

from ._defect import local_error
from ._pytree import pytree_dataclass


def _split(Z):
    dq, dp = jnp.split(Z[0], 2)
    return dq, dp


class _Increment:
    """The members shared by schemes whose unknown is the increment ``dz = z1 - z0``, shape
    ``(1, 2d)``; their polynomial is the straight line z0 + alpha dz."""

    def initial_guess(self, q0, p0, previous=None):
        if previous is None:
            return jnp.zeros((1, 2 * q0.shape[0]), q0.dtype)
        return previous[2]  # the previous increment

    def increment(self, H, q0, p0, Z, h):
        return _split(Z)

    def polynomial(self, H, q0, p0, Z, h):
        return jnp.concatenate([0.5 * Z, 0.5 * Z])  # alpha = (P_0 + P_1) / 2

    def local_error(self, H, q0, p0, Z, h):
        return local_error(H, q0, p0, self.polynomial(H, q0, p0, Z, h), Z[0], h)


@pytree_dataclass
class ModifiedMidpoint(_Increment):
    """The energy-momentum "modified midpoint rule" [GBS, eqs. (90)-(91), Notation 4.2]:

        q2 - q1 = h dH/dp(qbar, pbar),
        p2 - p1 = -h (V2 - V1) / (r2^2 - r1^2) (q1 + q2),

    for H = |p|^2 / (2m) + V(|q|) (eq. (77)); with such H the first line is eq. (90).
    V(q) is read off the given H as H(q, 0). Energy and angular momentum q x p are
    conserved exactly (up to round-off) for every central potential (Prop. 4.6,
    Corollary 4.10). Not for other Hamiltonians: use ``DiscreteGradient`` there.

    When r2^2 - r1^2 is below eps^(1/3) (r1^2 + r2^2) the quotient, whose round-off grows
    like eps / (r2^2 - r1^2), is replaced by its limit dV/d(r^2) = V'(r) / (2r) at
    r^2 = (r1^2 + r2^2) / 2; that changes the energy by O((r2^2 - r1^2)^3) = O(eps).
    Unknowns: the increment ``(q2 - q1, p2 - p1)``, shape ``(1, 2d)``.
    """

    def residual(self, H, q0, p0, Z, h):
        dq, dp = _split(Z)
        q1 = q0 + dq
        V = lambda q: H(q, jnp.zeros_like(p0))
        slope = _radial_slope(V, q0, q1)
        r_q = dq - h * jax.grad(H, argnums=1)(q0 + 0.5 * dq, p0 + 0.5 * dp)
        r_p = dp + h * slope * (q0 + q1)
        return jnp.concatenate([r_q, r_p])[None, :]


def _radial_slope(V, q1, q2):
    """(V(q2) - V(q1)) / (r2^2 - r1^2), or its limit V'(r) / (2r), smoothly (double where)."""
    s1, s2 = q1 @ q1, q2 @ q2
    ds = s2 - s1
    eps = jnp.finfo(q1.dtype).eps
    near = jnp.abs(ds) <= eps ** (1.0 / 3.0) * (s1 + s2)
    quotient = (V(q2) - V(q1)) / jnp.where(near, 1.0, ds)
    mean = 0.5 * (q1 + q2)
    mean_sq = mean @ mean
    tiny = jnp.finfo(q1.dtype).tiny
    # a point of squared radius (s1 + s2) / 2 on the ray through the midpoint
    safe_mean = jnp.where(mean_sq > tiny, mean, jnp.ones_like(mean))
    point = safe_mean * jnp.sqrt(0.5 * (s1 + s2) / jnp.where(mean_sq > tiny, mean_sq, safe_mean @ safe_mean))
    limit = jax.grad(V)(point) @ point / (2.0 * (point @ point))
    return jnp.where(near, limit, quotient)


@pytree_dataclass
class DiscreteGradient(_Increment):
    """Gonzalez's midpoint discrete gradient method, energy-conserving for any H:

        z1 = z0 + h J DbarH(z0, z1),
        DbarH = DH(zbar) + [(H(z1) - H(z0) - DH(zbar) . dz) / |dz|^2] dz,   dz = z1 - z0,

    so DbarH . dz = H(z1) - H(z0) and, J being skew, H(z1) = H(z0) to round-off. Second
    order and symmetric, but neither symplectic nor angular-momentum conserving (on the
    quartic central-force scene of [GBS, Fig. 4.7] |L| changes by ~50 % over 10^4 steps).
    Prefer it to ``ModifiedMidpoint`` for Hamiltonians that are not |p|^2 / 2m + V(|q|);
    for central forces ``ModifiedMidpoint`` conserves both energy and L = q x p.
    Unknowns: the increment ``dz``, shape ``(1, 2d)``.
    """

    def residual(self, H, q0, p0, Z, h):
        """R(dz) = dz - h J DbarH(z0, z0 + dz).

        The excess H(z1) - H(z0) - DH(zbar) . dz is O(|dz|^3) but comes from values of size
        |H|: its round-off, eps |H|, divided by |dz|^2, makes the residual noisy at
        ~eps |H| / |DH| whatever h, and the energy random-walks with the step count (float32,
        Kepler e = 0.6 over one period: 1.5e-6 at h = 0.1, 1.4e-5 at h = 0.001). Below float64
        the excess is therefore taken from the line integral (``_excess``), which has no such
        cancellation (1.4e-6 at h = 0.001), where that integral is resolved to round-off.
        """
        dz = Z[0]
        d = q0.shape[0]
        z0 = jnp.concatenate([q0, p0])
        Hz = lambda z: H(z[:d], z[d:])
        grad_mid = jax.grad(Hz)(z0 + 0.5 * dz)
        norm2 = dz @ dz
        degenerate = norm2 <= jnp.finfo(dz.dtype).tiny
        excess = _excess(Hz, z0, dz, grad_mid)
        gradient = grad_mid + jnp.where(degenerate, 0.0, excess / jnp.where(degenerate, 1.0, norm2)) * dz
        field = jnp.concatenate([gradient[d:], -gradient[:d]])
        return (dz - h * field)[None, :]


def _gauss_line_integral(grad, z0, dz, grad_mid, nodes):
    """sum_l w_l (DH(z0 + alpha_l dz) - DH(zbar)) . dz over symmetric Gauss nodes
    ``(alpha_l, w_l)`` off the midpoint (the midpoint term is zero)."""
    return sum(w * ((grad(z0 + alpha * dz) - grad_mid) @ dz) for alpha, w in nodes)


_GAUSS2 = ((0.5 - 0.5 / 3.0**0.5, 0.5), (0.5 + 0.5 / 3.0**0.5, 0.5))
_GAUSS3 = ((0.5 - 0.5 * 0.6**0.5, 5.0 / 18.0), (0.5 + 0.5 * 0.6**0.5, 5.0 / 18.0))


def _excess(Hz, z0, dz, grad_mid):
    """H(z1) - H(z0) - DH(zbar) . dz, in the state's dtype.

    float64 and wider: from the H values, so DbarH . dz = H(z1) - H(z0) holds exactly up to
    round-off. Lower precision: int_0^1 (DH(z0 + s dz) - DH(zbar)) . dz ds by 3-point Gauss
    wherever it agrees with 2-point Gauss to eps |DH(zbar)| |dz|, so that its truncation error
    lies below the round-off of DH . dz itself (an O(eps) change, as in ``_radial_slope``),
    else from the H values.
    """
    dtype = dz.dtype
    excess = (Hz(z0 + dz) - Hz(z0)).astype(dtype) - grad_mid @ dz
    eps = jnp.finfo(dtype).eps
    if eps <= jnp.finfo(jnp.float64).eps:
        return excess
    grad = jax.grad(Hz)
    coarse = _gauss_line_integral(grad, z0, dz, grad_mid, _GAUSS2)
    fine = _gauss_line_integral(grad, z0, dz, grad_mid, _GAUSS3)
    resolved = jnp.abs(fine - coarse) <= eps * (jnp.abs(grad_mid) @ jnp.abs(dz))
    return jnp.where(resolved, fine, excess)
