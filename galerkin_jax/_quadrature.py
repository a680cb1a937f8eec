"""Quadrature rules on the master element [0, 1] [GBS, eq. (29)]."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial import legendre as npleg

# |sum w - 1| allowed, relative to max(1, sum |w|). float64: 1e-12, because rules computed
# by root finding carry that much (gauss_radau(40) is off by 1800 eps = 4e-13) while a sum
# off by more changes the scheme by more than round-off. Lower precisions: 32 eps, since
# rounding the weights to the dtype and softmax (rule_from_params) leave at most 4 eps.
WEIGHT_SUM_RTOL_FLOAT64 = 1e-12


def weight_sum_tolerance(dtype):
    """The tolerance on |sum_l w_l - 1| for weights stored in ``dtype``."""
    eps = float(jnp.finfo(dtype).eps) if jnp.issubdtype(dtype, jnp.floating) else 0.0
    return max(WEIGHT_SUM_RTOL_FLOAT64, 32.0 * eps)


def _is_concrete_array(x):
    return isinstance(x, (np.ndarray, jax.Array)) and not isinstance(x, jax.core.Tracer)


@dataclasses.dataclass(frozen=True)
class QuadratureRule:
    """Points ``alpha_l`` in [0, 1] and weights ``w_l``: int_0^1 f ~ sum_l w_l f(alpha_l) [GBS, eq. (29)].

    A pytree with leaves ``points`` and ``weights`` (shape ``(n_q,)``), so rules with
    equal point counts can be stacked (shape ``(B, n_q)``) and vmapped, and both arrays
    can be differentiated. The weights sum to 1 (constants are integrated exactly); a
    zero weight is allowed: it pads a rule to a common point count without changing it.

    Concrete arrays are checked when a rule is constructed, row by row for stacked rules;
    traced ones are not. Rebuilding a rule from its leaves (``jax.tree.unflatten``, as jit,
    vmap, grad and tree maps do) checks nothing: those leaves may be cotangents, tangents
    or zeros, which are not rules.

    Args:
        points: the quadrature points alpha_l in [0, 1], shape ``(n_q,)`` or ``(B, n_q)``;
            required.
        weights: the weights w_l, of the points' shape, each row summing to 1 (to
            ``weight_sum_tolerance``); required.
    Raises:
        ValueError: shapes differ or are empty, values not finite, points outside [0, 1],
            or weights that do not sum to 1.
    """

    points: jax.Array
    weights: jax.Array

    def __post_init__(self):
        for name in ("points", "weights"):
            value = getattr(self, name)
            if isinstance(value, (list, tuple, float, int)):
                object.__setattr__(self, name, np.atleast_1d(np.asarray(value, dtype=float)))
        if _is_concrete_array(self.points) and _is_concrete_array(self.weights):
            _check_rule_values(self.points, self.weights)

    @property
    def num_points(self):
        return self.points.shape[-1]


def _check_rule_values(points, weights):
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
    sums = wts.sum(axis=-1, dtype=np.float64)
    tol = weight_sum_tolerance(wts.dtype) * np.maximum(1.0, np.abs(wts).sum(axis=-1, dtype=np.float64))
    bad = np.flatnonzero(np.abs(sums - 1.0) > tol)
    if bad.size:
        index = np.unravel_index(bad[0], sums.shape)
        where = "" if wts.ndim == 1 else f" (row {index[0] if len(index) == 1 else index})"
        raise ValueError(
            f"quadrature: weights must sum to 1 (to {weight_sum_tolerance(wts.dtype):.0e}), so that "
            f"constants are integrated exactly; weights {wts[index]}{where} sum to {float(sums[index])!r}. "
            "Normalise them: weights / sum(weights)."
        )


def _rule_flatten(rule):
    return (rule.points, rule.weights), None


def _rule_unflatten(_, leaves):
    # no __post_init__: rebuilt leaves may be tangents, cotangents or tree-map results
    rule = object.__new__(QuadratureRule)
    object.__setattr__(rule, "points", leaves[0])
    object.__setattr__(rule, "weights", leaves[1])
    return rule


_KEYS = (jax.tree_util.GetAttrKey("points"), jax.tree_util.GetAttrKey("weights"))
# register_pytree_with_keys: its structures compare the class (see _pytree)
jax.tree_util.register_pytree_with_keys(
    QuadratureRule,
    lambda rule: (tuple(zip(_KEYS, _rule_flatten(rule)[0])), None),
    _rule_unflatten,
    _rule_flatten,
)


def _check_count(n, least, name):
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < least:
        raise ValueError(f"{name} needs an integer number of points n >= {least}, got {n!r}.")


def _from_reference(x, w):
    """Map a rule on [-1, 1] to [0, 1]."""
    return QuadratureRule(points=(np.asarray(x) + 1.0) / 2.0, weights=np.asarray(w) / 2.0)


def gauss_legendre(n) -> QuadratureRule:
    """n-point Gauss-Legendre rule on [0, 1]; exact for polynomials of degree 2n - 1.

    Args:
        n: the number of points, an integer >= 1; required.
    """
    _check_count(n, 1, "gauss_legendre")
    return _from_reference(*npleg.leggauss(int(n)))


def gauss_lobatto(n) -> QuadratureRule:
    """n-point Gauss-Lobatto rule on [0, 1] (both end points); exact to degree 2n - 3.

    Interior nodes are the roots of P'_{n-1}; the weights are 2 / (n (n - 1) P_{n-1}(x)^2).

    Args:
        n: the number of points, end points included, an integer >= 2; required.
    """
    _check_count(n, 2, "gauss_lobatto")
    n = int(n)
    p_last = np.zeros(n)
    p_last[-1] = 1.0  # Legendre coefficients of P_{n-1}
    interior = np.sort(np.real(npleg.legroots(npleg.legder(p_last)))) if n > 2 else np.array([])
    x = np.concatenate([[-1.0], interior, [1.0]])
    w = 2.0 / (n * (n - 1) * npleg.legval(x, p_last) ** 2)
    return _from_reference(x, w)


def gauss_radau(n, *, right=True) -> QuadratureRule:
    """n-point Gauss-Radau rule on [0, 1]; exact to degree 2n - 2.

    The right rule contains alpha = 1 (its nodes are those of Radau IIA); the left rule
    contains alpha = 0. Left nodes on [-1, 1]: roots of P_{n-1} + P_n; weights
    2 / n^2 at -1 and (1 - x) / (n^2 P_{n-1}(x)^2) elsewhere.

    Args:
        n: the number of points, an integer >= 1; required.
        right: which end point the rule contains; default True, alpha = 1 (Radau IIA's
            nodes). False: the left rule, with alpha = 0.
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


def midpoint() -> QuadratureRule:
    """The one-point rule at alpha = 1/2 (= gauss_legendre(1)) [GBS, Remark 4.8]."""
    return QuadratureRule(points=np.array([0.5]), weights=np.array([1.0]))


def trapezoid() -> QuadratureRule:
    """The trapezoidal rule: points 0 and 1, weights 1/2 [GBS, Remark 4.7]."""
    return QuadratureRule(points=np.array([0.0, 1.0]), weights=np.array([0.5, 0.5]))
