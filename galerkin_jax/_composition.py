"""Symmetric compositions of a symmetric one-step method (``Composition``).

Psi_h = Phi_{gamma_m h} o ... o Phi_{gamma_1 h} with sum gamma_i = 1 and gamma_i = gamma_{m+1-i}
[Hairer, Lubich, Wanner, Geometric Numerical Integration (2nd ed., 2006), Sec. V.3.2]: for a
symmetric Phi of order 2 the coefficients below give the stated order; the composition is
symmetric, and symplectic where Phi is. One element of the composition is m elements of Phi,
one after another from the state the previous one ends at; its unknowns are theirs, stacked,
so a run iterates them as one system (or, where Phi has a closed form, ``_explicit``, computes
them without iteration: a composition of Stormer-Verlet is explicit).
"""

import numpy as np
import jax.numpy as jnp
import dataclasses

from ._defect import hamilton_field, local_error
from ._method import AbstractMethod
from ._pytree import pytree_dataclass
from ._quadrature import QuadratureRule


def _symmetric(half, middle=None):
    """The coefficients ``half + (middle,) + reversed(half)``; the middle one, where not given,
    makes the sum 1."""
    half = tuple(float(x) for x in half)
    middle = 1.0 - 2.0 * sum(half) if middle is None else float(middle)
    return half + (middle,) + half[::-1]


# name: (order on a symmetric method of order 2, coefficients, source)
SCHEMES = {
    # the triple jump: gamma_1 = gamma_3 = 1 / (2 - 2^(1/3)) [Yoshida 1990, Phys. Lett. A 150,
    # 262-268, eq. (5.4); Creutz & Gocksch 1989; Suzuki 1990]; HLW eq. (V.3.5)
    "yoshida4": (4, _symmetric([1.0 / (2.0 - 2.0 ** (1.0 / 3.0))])),
    # Suzuki's fractal: gamma_1 = gamma_2 = gamma_4 = gamma_5 = 1 / (4 - 4^(1/3)) [Suzuki 1990,
    # Phys. Lett. A 146, 319-323]; HLW eq. (V.3.6)
    "suzuki4": (4, _symmetric([1.0 / (4.0 - 4.0 ** (1.0 / 3.0))] * 2)),
    # five stages, gamma_1 = 0.28 near the least error constant [McLachlan 1995, SIAM J. Sci.
    # Comput. 16, 151-168, the method of order 4 with s = 5]
    "mclachlan4": (4, _symmetric([0.28, 0.62546642846767004501])),
    # seven stages [Yoshida 1990, Table 1, solution A]; HLW Sec. V.3.2, "p6 s7"
    "yoshida6": (6, _symmetric([0.78451361047755726381949763, 0.23557321335935813368479318,
                                -1.17767998417887100694641568])),
    # nine stages, s9odr6a [Kahan & Li 1997, Math. Comp. 66, 1089-1099]; HLW eq. (V.3.11), "p6 s9"
    "kahan_li6": (6, _symmetric([0.39216144400731413927925056, 0.33259913678935943859974864,
                                 -0.70624617255763935980996482, 0.08221359629355080023149045])),
    # nine stages, gamma_1 = 0.1867 [McLachlan 1995, SIAM J. Sci. Comput. 16, 151-168, order 6, m = 9]
    "mclachlan6": (6, _symmetric([0.1867, 0.55549702371247839916, 0.12946694891347535806,
                                  -0.84326562338773460855])),
    # fifteen stages, s15odr8 [Kahan & Li 1997]; HLW eq. (V.3.12), "p8 s15"
    "kahan_li8_s15": (8, _symmetric([0.74167036435061295344822780, -0.40910082580003159399730010,
                                 0.19075471029623837995387626, -0.57386247111608226665638773,
                                 0.29906418130365592384446354, 0.33462491824529818378495798,
                                 0.31529309239676659663205666])),
    # seventeen stages, s17odr8b [Kahan & Li 1997]; HLW eq. (V.3.13), "p8 s17"
    "kahan_li8_s17": (8, _symmetric([0.13020248308889008087881763, 0.56116298177510838456196441,
                                     -0.38947496264484728640807860, 0.15884190655515560089621075,
                                     -0.39590389413323757733623154, 0.18453964097831570709183254,
                                     0.25837438768632204729397911, 0.29501172360931029887096624])),
    # seventeen stages [McLachlan 1995, order 8, m = 17] (his m = 15 one is Kahan and Li's s15odr8)
    "mclachlan8": (8, _symmetric([0.12886597938144329897, 0.5815140871052509624, -0.41017537146985013753,
                                  0.1851469357165877327, -0.40955234342085141934, 0.14440594108001204106,
                                  0.27833550039367965131, 0.31495668391629485789])),
}

# older names of schemes: name -> the name in SCHEMES
ALIASES = {"kahan_li8": "kahan_li8_s15"}

# a Hermite cubic on [0, 1] in the Legendre basis: rows the coefficients of P_0 .. P_3 of
# alpha -> H10(alpha), H01(alpha), H11(alpha), the weights of h f(z0), dz, h f(z1)
_HERMITE = np.stack([np.polynomial.legendre.poly2leg(np.polynomial.Polynomial(c)(
    np.polynomial.Polynomial([0.5, 0.5])).coef) for c in ([0, 1, -2, 1], [0, 0, 3, -2], [0, 0, -1, 1])], axis=1)


def hermite_polynomial(H, q0, p0, increment, h, fields=None):
    """The Hermite cubic through (z0, h f(z0)) and (z1, h f(z1)), z1 = z0 + increment, f
    Hamilton's field (evaluated at both ends, or ``fields = (f(z0), f(z1))`` where the run has
    them): Legendre coefficients, shape ``(4, 2d)`` (the element polynomial of a method whose
    stages are not polynomials: compositions, splittings)."""
    if fields is None:
        field = hamilton_field(H)
        dq, dp = jnp.split(increment, 2)
        fields = field(q0, p0), field(q0 + dq, p0 + dp)
    columns = jnp.stack([h * fields[0], increment, h * fields[1]])
    return jnp.asarray(_HERMITE, q0.dtype) @ columns


def hermite_error(H, q0, p0, increment, h):
    """The local error (``_defect.local_error``) of an element whose polynomial is the Hermite
    cubic of its ends (``hermite_polynomial``)."""
    return local_error(H, q0, p0, hermite_polynomial(H, q0, p0, increment, h), increment, h)


class ExplicitMap(AbstractMethod):
    """A method whose element is an explicit map z0 -> z1, computed from a fresh start
    (``explicit(H, q0, p0, h, explicit_start(H, q0, p0))``): a splitting, Tao's map. Its
    unknowns Z begin with the increments (dq | dp), and hold ``unknowns - 2`` more blocks of d
    numbers the map hands its error estimate (Tao's copies' distance); Z is the root of
    R(Z) = Z - explicit(...)[0], which a run whose elements the solver iterates (``save_at``,
    events, a sweep) finds in one update. Its element polynomial is the Hermite cubic through
    the end states (``hermite_polynomial``), which matches Hamilton's field at both ends, so the
    embedded estimate reads its defect inside, at alpha = 1/4 (``embedded_error``)."""

    fixed_point = True  # dR/dZ = I
    partition_axis = None
    embedded_alpha = 0.25
    settle = 0
    hamiltonian = True
    unknowns = 2  # blocks of d numbers in Z

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        if previous is not None and ratio is None:
            return previous[2]  # the previous element's unknowns
        return jnp.zeros(self.unknowns * q0.shape[0], q0.dtype)

    def residual(self, H, q0, p0, Z, h, part=None):
        """Z less the unknowns the map computes (its root: those)."""
        return Z - self.explicit(H, q0, p0, h, self.explicit_start(H, q0, p0))[0]

    @staticmethod
    def _increment(q0, Z):
        """z1 - z0, the first two blocks of Z."""
        return Z[:2 * q0.shape[0]]

    def increment(self, H, q0, p0, Z, h):
        return jnp.split(self._increment(q0, Z), 2)

    def polynomial(self, H, q0, p0, Z, h):
        return hermite_polynomial(H, q0, p0, self._increment(q0, Z), h)

    def polynomial_with(self, H, q0, p0, Z, h, increment, fields=None):
        return hermite_polynomial(H, q0, p0, increment, h, fields)

    def local_error(self, H, q0, p0, Z, h):
        return self.local_error_with(H, q0, p0, Z, h, self._increment(q0, Z))

    def local_error_with(self, H, q0, p0, Z, h, increment):
        return hermite_error(H, q0, p0, increment, h)

    def explicit_form(self, structure):
        """Itself: its element is explicit."""
        return self


def _is_symmetric_rule(rule):
    points, weights = np.asarray(rule.points, float), np.asarray(rule.weights, float)
    order = np.argsort(points)
    tol = 1e-12
    return bool(np.allclose(points[order], 1.0 - points[order][::-1], atol=tol)
                and np.allclose(weights[order], weights[order][::-1], atol=tol))


def _check_symmetric(method):
    """A ValueError where ``method`` is known not to be symmetric (dG(k), a given Lagrangian,
    a concrete asymmetric rule)."""
    name = type(method).__name__
    if name == "DG":
        raise ValueError("Composition needs a symmetric method; DG(k) is not (its upwind flux): use CG(k, "
                         "gauss_legendre(k)) or GalerkinVI(s, rule) with a symmetric rule.")
    if not getattr(method, "hamiltonian", True):
        raise ValueError(f"Composition needs a method given a Hamiltonian; {name} is given a Lagrangian: "
                         "use GalerkinVI on the matching H.")
    rule = getattr(method, "quadrature", None)
    if isinstance(rule, QuadratureRule) and not any(hasattr(x, "aval") for x in (rule.points, rule.weights)):
        if np.ndim(rule.points) == 1 and not _is_symmetric_rule(rule):
            raise ValueError(f"Composition needs a symmetric method; {name}'s rule is not symmetric about "
                             "alpha = 1/2 (points and weights), so neither is the method.")


@pytree_dataclass
class Composition(AbstractMethod):
    """A symmetric composition of a symmetric one-step method [HLW, Sec. V.3.2]:
    Psi_h = Phi_{gamma_m h} o ... o Phi_{gamma_1 h}.

    On a symmetric method of order 2 (cG(1), ``GalerkinVI(1, rule)`` with a symmetric rule,
    Stormer-Verlet, ``ModifiedMidpoint``) the scheme gives its stated order; on a symmetric
    method of order p > 2 at least min(p, order) (the coefficients solve the conditions for
    order 2 only). Symmetric, and symplectic where the method is. Where the method has a
    closed form for H (``gj.structure``: Stormer-Verlet on a separable H) every stage is
    computed without iteration, the force carried from stage to stage and step to step.
    Where the method composes on a space of its own (``Tao``: its ``composed``) the stages
    compose there and the element reads the state once at its end (``lifted``).

    Schemes (``SCHEMES``; the coefficients in the source, cited there):
        "yoshida4": order 4, 3 stages, the triple jump [Yoshida 1990, eq. (5.4)].
        "suzuki4": order 4, 5 stages [Suzuki 1990].
        "mclachlan4": order 4, 5 stages, gamma_1 = 0.28 [McLachlan 1995].
        "yoshida6": order 6, 7 stages [Yoshida 1990, Table 1, A].
        "kahan_li6": order 6, 9 stages, s9odr6a [Kahan & Li 1997].
        "mclachlan6": order 6, 9 stages, gamma_1 = 0.1867 [McLachlan 1995].
        "kahan_li8_s15": order 8, 15 stages, s15odr8 [Kahan & Li 1997]; "kahan_li8" names it too.
        "kahan_li8_s17": order 8, 17 stages, s17odr8b [Kahan & Li 1997].
        "mclachlan8": order 8, 17 stages [McLachlan 1995].
    Kahan and Li's as listed in Hairer, Lubich, Wanner, Geometric Numerical Integration (2006),
    Sec. V.3.2; McLachlan's as tabulated in Principia's integrators (McLachlan1995SS9, SS17), checked by the
    measured order.

    The element polynomial (dense output, ``save_at``, events, the error estimate) is the
    Hermite cubic through the end states with Hamilton's field there (local order 4; the
    refinement of ``_output.refined`` raises it). A ``PIDController`` is refused: the
    estimate measures that cubic, not the composition.

    Args:
        method: the symmetric one-step method composed, e.g. ``CG(1, gauss_legendre(1))`` or
            another ``Composition``; required.
        scheme: the stage coefficients gamma_i, a name above or a tuple of numbers (symmetric,
            summing to 1); default ``"yoshida4"``, order 4 in 3 stages. Static.
    """

    method: AbstractMethod
    scheme: object = dataclasses.field(default="yoshida4", metadata=dict(static=True))

    partition_axis = None
    embedded_alpha = 0.25  # the Hermite cubic matches the field at the ends (``embedded_error``)

    def __post_init__(self):
        if isinstance(self.scheme, str):
            if self.scheme in ALIASES:  # one name per scheme: one compilation
                object.__setattr__(self, "scheme", ALIASES[self.scheme])
            if self.scheme not in SCHEMES:
                raise ValueError(f"Composition: unknown scheme {self.scheme!r}; known: {', '.join(SCHEMES)}.")
            return
        gamma = np.asarray(self.scheme, float)
        if not isinstance(self.scheme, tuple) or gamma.ndim != 1 or gamma.size < 1:
            raise TypeError(f"Composition.scheme must be a scheme's name or a tuple of coefficients, got "
                            f"{self.scheme!r}.")
        if abs(gamma.sum() - 1.0) > 1e-12 or not np.allclose(gamma, gamma[::-1], atol=1e-15, rtol=0):
            raise ValueError(f"Composition coefficients must be symmetric and sum to 1, got {self.scheme!r}.")

    def _check_on_construction(self):
        _check_symmetric(self.method)

    @property
    def coefficients(self):
        """The coefficients gamma_i, a tuple of floats."""
        return SCHEMES[self.scheme][1] if isinstance(self.scheme, str) else tuple(float(x) for x in self.scheme)

    @property
    def lifted(self):
        """Where the method composes on a space of its own (``Tao``: the extended phase space,
        its ``composed(coefficients)``), that method with this scheme's stages, which every
        member below hands the element to; else None."""
        composed = getattr(self.method, "composed", None)
        return None if composed is None else composed(self.coefficients)

    def composed(self, coefficients):
        """Where the method composes on a space of its own (``lifted``): this composition
        composed again with ``coefficients`` (a composition of a composition); else None."""
        return None if self.lifted is None else self.lifted.composed(coefficients)

    @property
    def forces_per_step(self):
        """Gradients of V per element of a run where the method is explicit (``_explicit``): the
        stages times the method's own count (its force is carried from stage to stage, first
        same as last); None where the method has no count (it iterates, or its closed form
        depends on H: ``GalerkinVI(1, rule)`` counts 1, its explicit form on a separable H)."""
        inner = getattr(self.method, "forces_per_step", None)
        return None if inner is None else len(self.coefficients) * inner

    @property
    def fixed_point(self):
        return self.method.fixed_point  # dR/dZ at h = 0 is block diagonal, of the method's blocks

    @property
    def settle(self):
        return getattr(self.method, "settle", 0)

    @property
    def hamiltonian(self):
        return self.method.hamiltonian

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        """The previous element's stage unknowns (they change by O(h^2) from element to
        element), or the method's constant guess for every stage."""
        if self.lifted is not None:
            return self.lifted.initial_guess(q0, p0, previous, ratio)
        if previous is not None and ratio is None:
            return previous[2]
        return jnp.concatenate([self.method.initial_guess(q0, p0)] * len(self.coefficients))

    def _stages(self, Z):
        return jnp.split(Z, len(self.coefficients))

    def residual(self, H, q0, p0, Z, h):
        """Each stage's equations at the state the stages before it end at."""
        if self.lifted is not None:
            return self.lifted.residual(H, q0, p0, Z, h)
        q, p, out = q0, p0, []
        for gamma, Z_i in zip(self.coefficients, self._stages(Z)):
            out.append(self.method.residual(H, q, p, Z_i, gamma * h))
            dq, dp = self.method.increment(H, q, p, Z_i, gamma * h)
            q, p = q + dq, p + dp
        return jnp.concatenate(out)

    def increment(self, H, q0, p0, Z, h):
        if self.lifted is not None:
            return self.lifted.increment(H, q0, p0, Z, h)
        q, p = q0, p0
        for gamma, Z_i in zip(self.coefficients, self._stages(Z)):
            dq, dp = self.method.increment(H, q, p, Z_i, gamma * h)
            q, p = q + dq, p + dp
        return q - q0, p - p0

    def polynomial(self, H, q0, p0, Z, h):
        """The Hermite cubic through the end states (``hermite_polynomial``)."""
        return self.polynomial_with(H, q0, p0, Z, h, jnp.concatenate(self.increment(H, q0, p0, Z, h)))

    def polynomial_with(self, H, q0, p0, Z, h, increment, fields=None):
        """``polynomial`` from the element's increment (and the field at its ends where given):
        the stages are not computed again."""
        if self.lifted is not None:
            return self.lifted.polynomial_with(H, q0, p0, Z, h, increment, fields)
        return hermite_polynomial(H, q0, p0, increment, h, fields)

    @property
    def explicit(self):
        """Where the method is explicit (``_explicit``): ``(H, q0, p0, h, g0) -> (Z, (dq, dp), g1)``,
        its stages in closed form one after another, the force carried; else None."""
        if self.lifted is not None:
            return self.lifted.explicit
        if not callable(getattr(self.method, "explicit", None)):
            return None

        def explicit(H, q0, p0, h, g):
            q, p, Zs = q0, p0, []
            for gamma in self.coefficients:
                Z_i, (dq, dp), g = self.method.explicit(H, q, p, gamma * h, g)
                q, p = q + dq, p + dp
                Zs.append(Z_i)
            return jnp.concatenate(Zs), (q - q0, p - p0), g

        return explicit

    def local_error(self, H, q0, p0, Z, h):
        return self.local_error_with(H, q0, p0, Z, h, jnp.concatenate(self.increment(H, q0, p0, Z, h)))

    def local_error_with(self, H, q0, p0, Z, h, increment):
        """``local_error`` from the element's increment: the stages are not computed again."""
        if self.lifted is not None:
            return self.lifted.local_error_with(H, q0, p0, Z, h, increment)
        return hermite_error(H, q0, p0, increment, h)

    def explicit_start(self, H, q0, p0):
        if self.lifted is not None:
            return self.lifted.explicit_start(H, q0, p0)
        return self.method.explicit_start(H, q0, p0)

    def explicit_field(self, H, q1, p1, memo):
        if self.lifted is not None:
            return self.lifted.explicit_field(H, q1, p1, memo)
        return self.method.explicit_field(H, q1, p1, memo)

    def explicit_form(self, structure):
        """The composition of the method's explicit form for H's structure, or None (``lifted``:
        the method composed on its own space)."""
        if self.lifted is not None:
            return self.lifted
        form = getattr(self.method, "explicit_form", None)
        inner = None if form is None else form(structure)
        return None if inner is None else Composition(inner, self.scheme)
