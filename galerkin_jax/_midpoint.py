"""Energy-momentum schemes: the modified midpoint rule [GBS, eqs. (90)-(91)] and
Gonzalez's midpoint discrete gradient."""

import jax
import jax.numpy as jnp

from ._pytree import pytree_dataclass


def _split(Z):
    dq, dp = jnp.split(Z[0], 2)
    return dq, dp


def _increment_guess(q0, p0, previous):
    if previous is None:
        return jnp.zeros((1, 2 * q0.shape[0]), q0.dtype)
    return previous[2]  # the previous increment


def _end(q0, p0, Z):
    dq, dp = _split(Z)
    return q0 + dq, p0 + dp


@pytree_dataclass
class ModifiedMidpoint:
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

    def initial_guess(self, q0, p0, previous=None):
        return _increment_guess(q0, p0, previous)

    def residual(self, H, q0, p0, Z, h):
        dq, dp = _split(Z)
        q1, p1 = q0 + dq, p0 + dp
        V = lambda q: H(q, jnp.zeros_like(p0))
        slope = _radial_slope(V, q0, q1)
        r_q = dq - h * jax.grad(H, argnums=1)(q0 + 0.5 * dq, p0 + 0.5 * dp)
        r_p = dp + h * slope * (q0 + q1)
        return jnp.concatenate([r_q, r_p])[None, :]

    def end_state(self, H, q0, p0, Z, h):
        return _end(q0, p0, Z)


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
class DiscreteGradient:
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

    def initial_guess(self, q0, p0, previous=None):
        return _increment_guess(q0, p0, previous)

    def residual(self, H, q0, p0, Z, h):
        dz = Z[0]
        d = q0.shape[0]
        z0 = jnp.concatenate([q0, p0])
        Hz = lambda z: H(z[:d], z[d:])
        grad_mid = jax.grad(Hz)(z0 + 0.5 * dz)
        norm2 = dz @ dz
        degenerate = norm2 <= jnp.finfo(dz.dtype).tiny
        excess = Hz(z0 + dz) - Hz(z0) - grad_mid @ dz
        gradient = grad_mid + jnp.where(degenerate, 0.0, excess / jnp.where(degenerate, 1.0, norm2)) * dz
        field = jnp.concatenate([gradient[d:], -gradient[:d]])
        return (dz - h * field)[None, :]

    def end_state(self, H, q0, p0, Z, h):
        return _end(q0, p0, Z)
