"""Tao's explicit map for any H, through an extended phase space (``Tao``).

Two copies (q, p) and (x, y) of phase space carry the extended Hamiltonian
[Tao 2016, Phys. Rev. E 94, 043303, eq. (2)]

    Hbar(q, p, x, y) = H_A + H_B + omega H_C,   H_A = H(q, y),   H_B = H(x, p),
    H_C = (|q - x|^2 + |p - y|^2) / 2,

whose three flows are exact and explicit [Tao 2016, eqs. (3)-(5)]:

    phi_A^d: p <- p - d dH/dq(q, y),  x <- x + d dH/dp(q, y)   (q, y held),
    phi_B^d: q <- q + d dH/dp(x, p),  y <- y - d dH/dq(x, p)   (x, p held),
    phi_C^d: (q - x, p - y) rotated by the angle 2 omega d, (q + x, p + y) held.

Psi_h = phi_A^{h/2} phi_B^{h/2} phi_C^h phi_B^{h/2} phi_A^{h/2} is symmetric and symplectic on
the extended space, of order 2 [Tao 2016, eq. (6)]; on the diagonal {x = q, y = p}, which the
exact flow of Hbar keeps, that flow is H's. One element here is a map of (q, p) alone:

    Phi_h(z) = P(Psi_h(z, z)),   P(q, p, x, y) = ((q + x) / 2, (p + y) / 2),

the start lifted to the diagonal, the copies' mean read at the end (the mean of the copies
is Pihajoki's projection [Pihajoki 2015, Celest. Mech. Dyn. Astr. 121, 211-231] and Tao's
output). Every run (fixed steps, save times, events, dense output, sweeps, derivatives)
computes this same map: nothing but (q, p) passes from one element to the next. The copies
part by O(h^3) over one element, which ``Tao.local_error`` reports.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ._composition import ExplicitMap
from ._defect import hamilton_field
from ._pytree import pytree_dataclass


def _gradient(H, q, p):
    """(dH/dq, dH/dp) at (q, p): one gradient of H."""
    return jax.grad(H, argnums=(0, 1))(q, p)


def flow_A(H, state, d):
    """phi_A^d [Tao 2016, eq. (3)]: the flow of H(q, y), which holds q and y."""
    q, p, x, y = state
    Hq, Hp = _gradient(H, q, y)
    return q, p - d * Hq, x + d * Hp, y


def flow_B(H, state, d):
    """phi_B^d [Tao 2016, eq. (4)]: the flow of H(x, p), which holds x and p."""
    q, p, x, y = state
    Hq, Hp = _gradient(H, x, p)
    return q + d * Hp, p, x, y - d * Hq


def flow_C(state, angle):
    """phi_C^d [Tao 2016, eq. (5)], ``angle = 2 omega d``: (q - x, p - y) rotated by it,
    (q + x, p + y) held (the flow of omega (|q - x|^2 + |p - y|^2) / 2)."""
    q, p, x, y = state
    c, s = jnp.cos(angle), jnp.sin(angle)
    u, v = q - x, p - y
    u, v = c * u + s * v, c * v - s * u
    return (q + x + u) / 2, (p + y + v) / 2, (q + x - u) / 2, (p + y - v) / 2


def extended_map(H, state, h, omega, stages=(1.0,)):
    """Psi on the extended space: for each stage gamma in turn Tao's second-order map of step
    gamma h, phi_A^{gamma h/2} phi_B^{gamma h/2} phi_C^{gamma h} phi_B^{gamma h/2} phi_A^{gamma h/2}
    [Tao 2016, eq. (6)]; two phi_A's that meet are one (the flows of one H_A commute), so m
    stages cost 3m + 1 gradients of H.

    Args:
        state: ``(q, p, x, y)``, each shape ``(d,)``.
        omega: the binding, a number.
        stages: the step fractions gamma_i (a composition's coefficients), static.
    Returns:
        ``(q, p, x, y)`` after the map.
    """
    a = stages[0] / 2  # the pending phi_A's step fraction
    for i, gamma in enumerate(stages):
        state = flow_A(H, state, a * h)
        state = flow_B(H, state, gamma * h / 2)
        state = flow_C(state, 2 * omega * gamma * h)
        state = flow_B(H, state, gamma * h / 2)
        a = gamma / 2 + (stages[i + 1] / 2 if i + 1 < len(stages) else 0.0)
    return flow_A(H, state, a * h)


def _check_stages(stages):
    gamma = np.asarray(stages, float)
    if not isinstance(stages, tuple) or gamma.ndim != 1 or gamma.size < 1:
        raise TypeError(f"Tao.stages must be a tuple of step fractions, got {stages!r}.")
    if abs(gamma.sum() - 1.0) > 1e-12 or not np.allclose(gamma, gamma[::-1], atol=1e-15, rtol=0):
        raise ValueError(f"Tao.stages must be symmetric and sum to 1, got {stages!r}.")


@pytree_dataclass
class Tao(ExplicitMap):
    """Tao's explicit map for any (non-separable) H, one element a map of (q, p) alone
    [Tao 2016, Phys. Rev. E 94, 043303] (module docstring).

    The start z0 = (q0, p0) is lifted to both copies of the extended phase space, Tao's map

        Psi_h = phi_A^{h/2} phi_B^{h/2} phi_C^h phi_B^{h/2} phi_A^{h/2}   [Tao 2016, eq. (6)]

    of Hbar = H(q, y) + H(x, p) + omega (|q - x|^2 + |p - y|^2) / 2 moves them, and the element
    ends at their mean: z1 = ((q + x) / 2, (p + y) / 2) [Pihajoki 2015]. Explicit for any H: 4
    gradients of H per step (3m + 1 for m stages), no iteration, no structure required.

    Properties: order 2. Not symplectic on (q, p) (the mean of the copies is not), and
    symmetric to high order, not exactly: Phi_{-h} o Phi_h = id + O(h^6) (the copies part by
    O(h^3) and their mean cancels the first terms; measured in ``tests/test_tao.py``), so a
    long run's energy error drifts slowly where a symplectic method's stays bounded (on the
    harmonic oscillator the one-step matrix has spectral radius 1 + h^6 / 128). In
    ``Composition(Tao(...), scheme)`` the stages compose on the extended space and the mean is
    read once per element (``composed``): order 4, 6 or 8, symmetric to O(h^{p+6}) at order p
    (order 4: measured 10).

    The binding omega: Tao binds the copies, carried from step to step, by omega, with h omega
    small and omega large enough that they stay together. Here they start together every
    element and part by O(h^3) over it whatever omega; the rotation phi_C adds an error
    proportional to omega h^{p+1} (the order-4 composition's error grows in proportion to
    omega), and an omega scaled as 1 / h (a fixed h omega) lowers a composition's order to 3.
    Hence the default omega = 0 (no binding: the extended map is then Pihajoki's leapfrog); a
    given omega should be a constant, below 1 / h.

    The element's unknowns are the increments and the copies' half difference at the
    element's end, Z = (dq | dp | (q - x) / 2 | (p - y) / 2), which a run whose elements the
    solver iterates finds in one update (``ExplicitMap``); the element
    polynomial is the Hermite cubic through the end states (``_composition.hermite_polynomial``).
    ``local_error`` is the larger of the defect estimate and half the copies' distance at the
    element's end (max-norm): where they part (a step too long for H) the run's estimate
    says so. A ``PIDController`` is refused (its estimate measures the cubic): use fixed steps
    (``save_at`` and events work with them) or a ``TimeTransform``.

    Args:
        omega: the binding, a number >= 0; default 0. Static: a new omega means a new
            compilation, and one sweep takes one omega.
        stages: the step fractions of the stages composed on the extended space, symmetric and
            summing to 1; default ``(1.0,)``, Tao's map of order 2. ``Composition`` sets them.
            Static.
    """

    omega: float = dataclasses.field(default=0.0, metadata=dict(static=True))
    stages: tuple = dataclasses.field(default=(1.0,), metadata=dict(static=True))

    symmetric = False  # to O(h^6), not to round-off: no checkpoint="reversible"
    unknowns = 4  # (dq | dp | (q - x) / 2 | (p - y) / 2)

    def __post_init__(self):
        omega = self.omega
        if isinstance(omega, bool) or not isinstance(omega, (int, float, np.integer, np.floating)):
            raise TypeError(f"Tao.omega must be a real number (static), got {omega!r}.")
        if not np.isfinite(omega) or omega < 0:
            raise ValueError(f"Tao.omega must be finite and >= 0, got {float(omega)}.")
        _check_stages(self.stages)

    def composed(self, coefficients):
        """This map composed on the extended space: the stages gamma_i s_j, each of this map's
        stages s_j within each coefficient gamma_i in turn (``Composition``'s elements)."""
        stages = tuple(float(g) * s for g in coefficients for s in self.stages)
        return Tao(self.omega, stages)

    def extended(self, H, q0, p0, h):
        """``(q, p, x, y)``: the copies at the element's end, from both at (q0, p0)."""
        return extended_map(H, (q0, p0, q0, p0), h, float(self.omega), self.stages)

    def explicit_start(self, H, q0, p0):
        """Nothing passes from element to element (a placeholder scalar)."""
        return jnp.zeros((), q0.dtype)

    def explicit(self, H, q0, p0, h, memo):
        """The element: ``(Z, (dq, dp), memo)``, the copies' mean less the start, and Z these
        increments with the copies' half difference ``((q - x) / 2 | (p - y) / 2)``."""
        q, p, x, y = self.extended(H, q0, p0, h)
        dq, dp = (q + x) / 2 - q0, (p + y) / 2 - p0
        return jnp.concatenate([dq, dp, (q - x) / 2, (p - y) / 2]), (dq, dp), memo

    def explicit_field(self, H, q1, p1, memo):
        """Hamilton's field at the element's end, evaluated there (one gradient)."""
        return hamilton_field(H)(q1, p1)

    def local_error_with(self, H, q0, p0, Z, h, increment):
        """The larger of the defect estimate (``ExplicitMap.local_error_with``) and half the
        copies' distance at the element's end, max-norm (|q - x| / 2, |p - y| / 2: the last
        blocks of Z)."""
        divergence = jnp.max(jnp.abs(Z[2 * q0.shape[0]:]))
        return jnp.maximum(super().local_error_with(H, q0, p0, Z, h, increment), divergence)

