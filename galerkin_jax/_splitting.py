"""Splitting methods for a separable H = T(p) + V(q) (``Splitting``): kicks and drifts.

The flows of V (a kick, p <- p - tau V'(q)) and of T (a drift, q <- q + tau T'(p)) are exact and
explicit; a splitting method chains them,

    Psi_h = K_{b_{m+1} h} o D_{a_m h} o K_{b_m h} o ... o D_{a_1 h} o K_{b_1 h},

sum a_i = sum b_i = 1 [Hairer, Lubich, Wanner, Geometric Numerical Integration (2nd ed.,
2006), Sec. III.5 and V.3.3]. Each kick and drift is a symplectic map, so Psi_h is symplectic;
palindromic coefficients (all below) make it symmetric. The schemes are Blanes and Moan's
optimised ones [Blanes & Moan 2002, J. Comput. Appl. Math. 142, 313-330]: their partitioned
Runge-Kutta (PRK) methods have their order on every separable H, their Runge-Kutta-Nystrom
(RKN) methods where moreover T is quadratic in p with a constant matrix (then [V, [V, [V, T]]]
= 0, which removes order conditions). An element starting and ending with a kick hands its
last force to the next element's first kick (first same as last).
"""

import dataclasses

import jax.numpy as jnp

from ._composition import ExplicitMap
from ._explicit import end_field, force, velocity
from ._pytree import pytree_dataclass
from ._structure import structure


def _palindrome(half, middle_count, total=1.0):
    """``half + (m,) * middle_count + reversed(half)``, m making the sum ``total``."""
    half = tuple(float(x) for x in half)
    middle = (total - 2.0 * sum(half)) / middle_count
    return half + (middle,) * middle_count + half[::-1]


def _drift_first(drifts_half, drifts_middle, kicks_half, kicks_middle):
    """A drift-kick-...-drift scheme (ABA, A the drift) as kicks and drifts: the first and last kick 0."""
    return (0.0,) + _palindrome(kicks_half, kicks_middle) + (0.0,), _palindrome(drifts_half, drifts_middle)


# name: (order, kicks b_1..b_{m+1}, drifts a_1..a_m, needs T quadratic for its order, source)
SCHEMES = {
    # kick-drift-kick: the Stormer-Verlet scheme [HLW, eq. (I.3.6)]
    "leapfrog": (2, (0.5, 0.5), (1.0,), False),
    # PRK, 6 stages, order 4: "S6" [Blanes & Moan 2002, Table 2], ABA, A = T (the drift)
    "blanes_moan4": (4, *_drift_first([0.0792036964311957, 0.353172906049774, -0.0420650803577195], 1,
                                      [0.209515106613362, -0.143851773179818], 2), False),
    # PRK, 10 stages, order 6: "S10" [Blanes & Moan 2002, Table 2], ABA, A = T
    "blanes_moan6": (6, *_drift_first([0.0502627644003922, 0.413514300428344, 0.0450798897943977,
                                       -0.188054853819569, 0.541960678450780], 1,
                                      [0.148816447901042, -0.132385865767784, 0.067307604692185,
                                       0.432666402578175], 2), False),
    # RKN, 6 stages, order 4: "SRKN_6^b" [Blanes & Moan 2002, Table 3], BAB, B = V (the kick)
    "blanes_moan_rkn4": (4, _palindrome([0.0829844064174052, 0.396309801498368, -0.0390563049223486], 1),
                         _palindrome([0.245298957184271, 0.604872665711080], 2), True),
    # RKN, 11 stages, order 6: "SRKN_11^b" [Blanes & Moan 2002, Table 3], BAB, B = V
    "blanes_moan_rkn6": (6, _palindrome([0.0414649985182624, 0.198128671918067, -0.0400061921041533,
                                         0.0752539843015807, -0.0115113874206879], 2),
                         _palindrome([0.123229775946271, 0.290553797799558, -0.127049212625417,
                                      -0.246331761062075, 0.357208872795928], 1), True),
}


@pytree_dataclass
class Splitting(ExplicitMap):
    """A splitting method for a separable H = T(p) + V(q): kicks of V, drifts of T (module
    docstring), explicit, symplectic and symmetric.

    Schemes (``SCHEMES``; coefficients in the source, cited there; "forces" are gradients of V
    per step, first same as last):
        "leapfrog": order 2, Stormer-Verlet (kick-drift-kick), 1 force.
        "blanes_moan4": order 4, the PRK method S6 [Blanes & Moan 2002], 6 forces.
        "blanes_moan6": order 6, the PRK method S10 [Blanes & Moan 2002], 10 forces.
        "blanes_moan_rkn4": order 4 where T is quadratic in p, SRKN_6^b [Blanes & Moan 2002], 6 forces.
        "blanes_moan_rkn6": order 6 where T is quadratic in p, SRKN_11^b [Blanes & Moan 2002], 11 forces.
    The RKN schemes are refused (a ValueError) where ``gj.structure`` does not read T as
    quadratic in p (``Structure.kinetic_quadratic``): on T = sum sqrt(1 + p^2) SRKN_11^b's order
    falls to 4.

    H must be separable as ``gj.structure`` reads it (a ValueError otherwise), and the steps
    fixed or saved at given times: a ``PIDController`` is refused (its estimate measures the
    interpolating cubic, not the splitting), and so is a ``TimeTransform`` (its K = s(q, p)
    (H + p_t) is not separable). Its unknowns are the increments Z = (dq | dp), the root of
    R(Z) = Z - Psi_h(z0) + z0, which a run whose elements the solver iterates (``save_at``,
    events, a sweep) finds in one update. The element polynomial (dense output, events) is
    the Hermite cubic through the end states (``_composition.hermite_polynomial``).

    Args:
        scheme: which kicks and drifts, a name above; default ``"blanes_moan4"`` (order 4 on
            every separable H). Take an RKN scheme where T is quadratic in p, ``"leapfrog"``
            for the cheapest step. Static.
    """

    scheme: str = dataclasses.field(default="blanes_moan4", metadata=dict(static=True))

    def __post_init__(self):
        if not isinstance(self.scheme, str) or self.scheme not in SCHEMES:
            raise ValueError(f"Splitting: unknown scheme {self.scheme!r}; known: {', '.join(SCHEMES)}.")

    @property
    def order(self):
        """The order on a separable H (an RKN scheme's: where T is quadratic in p)."""
        return SCHEMES[self.scheme][0]

    @property
    def kicks(self):
        return SCHEMES[self.scheme][1]

    @property
    def drifts(self):
        return SCHEMES[self.scheme][2]

    @property
    def forces_per_step(self):
        """Gradients of V per element in a run: the nonzero kicks, less one where the first
        and the last kick share theirs."""
        b = self.kicks
        return sum(x != 0.0 for x in b) - (b[0] != 0.0 and b[-1] != 0.0)

    def premise(self, H, q0, p0):
        """A ValueError where H (``H(q, p)``, args bound) does not read as separable, or, for an RKN
        scheme, its T as quadratic in p (``gj.structure``)."""
        found = structure(H, q0, p0)
        if not found.separable:
            raise ValueError(f"Splitting({self.scheme!r}) needs a separable H = T(p) + V(q), and this H reads as "
                             f"general ({found.reason}; gj.structure): use GalerkinVI, CG or a Composition of "
                             "them, which need no structure.")
        if SCHEMES[self.scheme][3] and not found.kinetic_quadratic:
            raise ValueError(f"Splitting({self.scheme!r}) is a Runge-Kutta-Nystrom scheme: it has its order where T "
                             "is quadratic in p with a constant matrix, and this H's d^2H/dp^2 reads p (gj.structure's "
                             "kinetic_quadratic is False): use 'blanes_moan4' or 'blanes_moan6', whose order holds "
                             "for any T.")

    def explicit_start(self, H, q0, p0):
        """The force at q0, which the first kick of the first element uses."""
        return force(H, q0, p0)

    def explicit(self, H, q0, p0, h, g0):
        """The element from the force ``g0`` at q0: ``(Z, (dq, dp), g)``, g the force at q1
        where the element ends with a kick (what the next one's first kick uses; else the
        next element's first kick is zero and g is not read)."""
        q, p, g, fresh = q0, p0, g0, True  # fresh: g is the force at the current q
        for i, b in enumerate(self.kicks):
            if b != 0.0:
                if not fresh:
                    g = force(H, q, p)
                p = p + (b * h) * g
                fresh = True
            if i < len(self.drifts):
                q = q + (self.drifts[i] * h) * velocity(H, q, p)
                fresh = False
        dq, dp = q - q0, p - p0
        return jnp.concatenate([dq, dp]), (dq, dp), g

    def explicit_field(self, H, q1, p1, memo):
        """Hamilton's field at the element's end (``_explicit.end_field``): from the memo where the
        element ends with a kick (the force at q1), else from a force evaluated anew."""
        ends_with_kick = len(self.kicks) > len(self.drifts) and self.kicks[-1] != 0.0
        return end_field(H, q1, p1, memo if ends_with_kick else force(H, q1, p1))

    def explicit_form(self, structure):
        """Itself: its element is explicit (``premise`` checked that H is separable)."""
        return self
