"""Energy-momentum schemes: the modified midpoint rule [GBS, eqs. (90)-(91)] and
Gonzalez's midpoint discrete gradient."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._method import AbstractMethod
from ._pytree import pytree_dataclass

LINE_POINTS = 6  # Gauss points of the energy-momentum schemes' line integrals (m, with m - 1 to check)


def _split(Z):
    dq, dp = jnp.split(Z[0], 2)
    return dq, dp


class _Increment(AbstractMethod):
    """The members shared by schemes whose unknown is the increment ``dz = z1 - z0``, shape
    ``(1, 2d)``; their polynomial is the straight line z0 + alpha dz."""

    fixed_point = True  # R = dz - h (...): dR/dz = I at h = 0

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        if previous is None:
            return jnp.zeros((1, 2 * q0.shape[0]), q0.dtype)
        return previous[2] if ratio is None else ratio * previous[2]  # the previous increment

    def increment(self, H, q0, p0, Z, h):
        return _split(Z)

    def polynomial(self, H, q0, p0, Z, h):
        return jnp.concatenate([0.5 * Z, 0.5 * Z])  # alpha = (P_0 + P_1) / 2


@pytree_dataclass
class ModifiedMidpoint(_Increment):
    """The energy-momentum "modified midpoint rule" [GBS, eqs. (90)-(91), Notation 4.2]:

        q2 - q1 = h dH/dp(qbar, pbar),
        p2 - p1 = -h (V2 - V1) / (r2^2 - r1^2) (q1 + q2),

    for H = |p|^2 / (2m) + V(|q|) (eq. (77)); with such H the first line is eq. (90).
    V(q) is read off the given H as H(q, 0). Energy and angular momentum q x p are
    conserved exactly (up to round-off) for every central potential (Prop. 4.6,
    Corollary 4.10). Not for other Hamiltonians: use ``DiscreteGradient`` there.

    The quotient's round-off grows like eps / (r2^2 - r1^2) as the radii approach each other
    (near an apsis, in every orbit): where it resolves, the quotient is taken as the mean of
    dV/d(r^2) over [r1^2, r2^2] instead (``_radial_slope``), which has no such round-off.
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


def _radial_slope(V, q1, q2, m=LINE_POINTS):
    """(V(q2) - V(q1)) / (s2 - s1), s = r^2, without the round-off of the quotient.

    The quotient equals int_0^1 V_s(s1 + a (s2 - s1)) da with V_s = dV/ds = V'(r) / (2r), taken
    on the ray through the midpoint (V is radial). Where the radii are close this integral is
    taken by m-point Gauss: where it agrees with (m-1)-point Gauss to 64 eps |V_s| (the
    round-off of the values), its truncation error, far below the (m-1)-point rule's, lies
    below the round-off; it is smooth in q1 and q2 and tends to V_s as s2 -> s1. The quotient's
    round-off, ~eps |V| / |s2 - s1|, grows without bound there, at every apsis: noise in the
    residual that the root finder cannot iterate below. Elsewhere (a large change of radius)
    the quotient, whose round-off is small there.
    """
    s1, s2 = q1 @ q1, q2 @ q2
    ds = s2 - s1
    dtype = q1.dtype
    mean = 0.5 * (q1 + q2)
    direction = jnp.where(mean @ mean > jnp.finfo(dtype).tiny, mean, jnp.ones_like(mean))
    direction = direction / jnp.sqrt(direction @ direction)

    def slope_at(s):  # V_s at squared radius s
        point = direction * jnp.sqrt(s)
        return jax.grad(V)(point) @ point / (2.0 * s)

    # the rules integrate V_s - V_s(mid), which vanishes with s2 - s1, so that their
    # round-off is relative to that difference, not to V_s (and the midpoint node adds nothing)
    fine_x, fine_w = _off_midpoint_gauss(m, dtype)
    coarse_x, coarse_w = _off_midpoint_gauss(m - 1, dtype)
    middle = slope_at(s1 + 0.5 * ds)
    fine = jax.vmap(slope_at)(s1 + jnp.asarray(fine_x, dtype) * ds) - middle
    coarse = jax.vmap(slope_at)(s1 + jnp.asarray(coarse_x, dtype) * ds) - middle
    fine, coarse = jnp.asarray(fine_w, dtype) @ fine, jnp.asarray(coarse_w, dtype) @ coarse
    # each value of V_s carries a few eps |V_s| of round-off: a closer test would flip with it
    resolved = jnp.abs(fine - coarse) <= 64 * jnp.finfo(dtype).eps * jnp.abs(middle)
    quotient = (V(q2) - V(q1)) / jnp.where(resolved, 1.0, ds)
    return jnp.where(resolved, middle + fine, quotient)


@pytree_dataclass
class DiscreteGradient(_Increment):
    """Gonzalez's midpoint discrete gradient method, energy-conserving for any H:

        z1 = z0 + h J DbarH(z0, z1),
        DbarH = DH(zbar) + [(H(z1) - H(z0) - DH(zbar) . dz) / |dz|^2] dz,   dz = z1 - z0,

    so DbarH . dz = H(z1) - H(z0) and, J being skew, H(z1) = H(z0) to round-off. Second
    order and symmetric, but neither symplectic nor angular-momentum conserving (|L| drifts
    on the quartic central-force scene of [GBS, Fig. 4.7]).
    Prefer it to ``ModifiedMidpoint`` for Hamiltonians that are not |p|^2 / 2m + V(|q|);
    for central forces ``ModifiedMidpoint`` conserves both energy and L = q x p.
    Unknowns: the increment ``dz``, shape ``(1, 2d)``.

    Args:
        line_points: the number m of Gauss points of the line integral that gives the excess
            H(z1) - H(z0) - DH(zbar) . dz (``_excess``), m >= 2; default 6. 0 takes it from H
            values alone, cheaper, but its round-off grows faster over long runs. Static: a
            new value means a new compilation.
    """

    line_points: int = dataclasses.field(default=LINE_POINTS, metadata=dict(static=True))
    # An element's energy error holds its iteration error's component along DH(z1). After the
    # stop and the polish that error is below eps |dz|, but it follows the predictor's smooth
    # miss: on Kepler (e = 0.6, h = 0.01) it changed H by -1.8e-4 eps a step through the
    # perihelion passages (r < 0.7), -3e-5 eps a step on average, a drift that outgrows the
    # round-off's random walk from 10^6 steps on. One more fixed-point update
    # (``AbstractMethod.settle``), one residual an element, leaves -1.5e-5, +0.2e-6, +3.1e-6
    # (+- 9e-6) eps a step in three runs (notes/performance-studies.md, "How the energy error was
    # brought to sqrt(n) eps").
    settle = 1

    def __post_init__(self):
        m = self.line_points
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 0 or m == 1:
            raise ValueError(f"DiscreteGradient needs line_points = 0 or an integer >= 2, got {m!r}.")

    def residual(self, H, q0, p0, Z, h):
        """R(dz) = dz - h J DbarH(z0, z0 + dz)."""
        dz = Z[0]
        d = q0.shape[0]
        z0 = jnp.concatenate([q0, p0])
        Hz = lambda z: H(z[:d], z[d:])
        grad_mid = jax.grad(Hz)(z0 + 0.5 * dz)
        norm2 = dz @ dz
        degenerate = norm2 <= jnp.finfo(dz.dtype).tiny
        excess = _excess(Hz, z0, dz, grad_mid, self.line_points)
        gradient = grad_mid + jnp.where(degenerate, 0.0, excess / jnp.where(degenerate, 1.0, norm2)) * dz
        field = jnp.concatenate([gradient[d:], -gradient[:d]])
        return (dz - h * field)[None, :]


def _two_sum(a, b):
    """``(s, e)`` with s = fl(a + b) and s + e = a + b exactly (Knuth)."""
    s = a + b
    b_virtual = s - a
    return s, (a - (s - b_virtual)) + (b - b_virtual)


def _off_midpoint_gauss(m, dtype=np.float64):
    """The m-point Gauss rule on [0, 1] without its midpoint node (whose term is zero):
    ``(points, weights)`` in ``dtype``, its points in pairs alpha, 1 - alpha whose sum is 1
    exactly and whose weights are equal.

    Rounded one by one, 1/2 + x/2 and 1/2 - x/2 miss symmetry by an ulp (for m = 6 two pairs
    did, and the rounded rule's first moment about 1/2 was 8.2e-18 instead of 0): the rule's
    error then holds 8.2e-18 f'(1/2), of one sign wherever f' keeps its sign. In the discrete
    gradient's excess f = DH(z0 + alpha dz) . dz has the slope dz . D^2H dz, positive through
    every perihelion passage of Kepler: -2.5e-5 eps a step of the energy's drift of -4.5e-5
    (2.1e-13 after 10^7 steps, e = 0.6, h = 0.01). With exact pairs the odd moments vanish;
    the even moments' rounding (an eps of theirs) meets odd derivatives of the integrand,
    which change sign where the orbit turns."""
    return _symmetric_gauss(m, np.dtype(dtype))


@functools.cache
def _symmetric_gauss(m, dtype):
    x, w = np.polynomial.legendre.leggauss(m)
    upper = x > 1e-12  # leggauss's nodes are symmetric about 0
    high = (0.5 + 0.5 * x[upper]).astype(dtype)  # in [1/2, 1): 1 - high is exact (Sterbenz)
    low = dtype.type(1) - high
    weights = (0.5 * w[upper]).astype(dtype)
    return np.concatenate([low[::-1], high]), np.concatenate([weights[::-1], weights])


def _line_integrals(grad, z0, dz, grad_mid, m):
    """int_0^1 (DH(z0 + s dz) - DH(zbar)) . dz ds by m-point and by (m-1)-point Gauss, from one
    batched evaluation of DH at the nodes of both rules (one traced gradient, not 2m - 1)."""
    fine_x, fine_w = _off_midpoint_gauss(m, dz.dtype)
    coarse_x, coarse_w = _off_midpoint_gauss(m - 1, dz.dtype)
    alpha = jnp.asarray(np.concatenate([fine_x, coarse_x]), dz.dtype)
    slopes = (jax.vmap(grad)(z0[None, :] + alpha[:, None] * dz[None, :]) - grad_mid[None, :]) @ dz
    fine, coarse = slopes[: len(fine_x)], slopes[len(fine_x) :]
    return jnp.asarray(fine_w, dz.dtype) @ fine, jnp.asarray(coarse_w, dz.dtype) @ coarse


def _excess(Hz, z0, dz, grad_mid, m):
    """H(z0 + dz) - H(z0) - DH(zbar) . dz, without bias and with as little round-off as the
    element allows.

    From H values: H(z1) - H(z0) with z1 = fl(z0 + dz), plus DH . rho for the rounding
    rho = z0 + dz - z1 of z1 (exact by ``_two_sum``). Divided by |dz|^2 in DbarH, the round-off
    of each H value, ~eps |H|, changes the energy by ~eps |H| per element, and it does not
    cancel from one element to the next (the next element starts from the compensated sum of
    the increments, not from z1): a random walk of eps |H| a step.

    From the line integral int_0^1 (DH(z0 + s dz) - DH(zbar)) . dz ds by m-point Gauss, where
    it agrees with (m-1)-point Gauss to eps |DH(zbar)| |dz|, so that its truncation error lies
    below the round-off of DH . dz itself and leaves no bias: a random walk of eps |DH| |dz|
    a step, h times smaller. Elsewhere (a large step, near a singularity of H) from H values.
    """
    dtype = dz.dtype
    z1, rho = _two_sum(z0, dz)
    from_values = (Hz(z1) - Hz(z0)).astype(dtype) + grad_mid @ rho - grad_mid @ dz
    if m == 0:
        return from_values
    fine, coarse = _line_integrals(jax.grad(Hz), z0, dz, grad_mid, m)
    resolved = jnp.abs(fine - coarse) <= jnp.finfo(dtype).eps * (jnp.abs(grad_mid) @ jnp.abs(dz))
    return jnp.where(resolved, fine, from_values)
