import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj


def legendre_errors(rule, max_degree):
    """|Q[P_j(2a - 1)] - delta_j0| for j = 0 .. max_degree: the error on a basis of P^max_degree."""
    points, weights = np.asarray(rule.points), np.asarray(rule.weights)
    values = np.polynomial.legendre.legvander(2 * points - 1, max_degree)
    return np.abs(weights @ values - np.eye(max_degree + 1)[0])


RULES = (
    [(f"gauss_legendre({n})", gj.gauss_legendre(n), 2 * n - 1) for n in range(1, 9)]
    + [(f"gauss_lobatto({n})", gj.gauss_lobatto(n), 2 * n - 3) for n in range(2, 9)]
    + [(f"gauss_radau({n})", gj.gauss_radau(n), 2 * n - 2) for n in range(1, 7)]
    + [(f"gauss_radau({n}, left)", gj.gauss_radau(n, right=False), 2 * n - 2) for n in range(1, 5)]
    + [("midpoint", gj.midpoint(), 1), ("trapezoid", gj.trapezoid(), 1)]
)


@pytest.mark.parametrize("name, rule, degree", RULES, ids=[r[0] for r in RULES])
def test_rule_is_exact_up_to_its_degree_and_not_beyond(name, rule, degree):
    errors = legendre_errors(rule, degree + 1)
    # 1e-14: round-off of a sum of at most 8 terms of size <= 1
    assert np.all(errors[: degree + 1] < 1e-14), errors
    # P_{degree+1} is integrated wrongly by O(1) (>= 0.1 for all these rules)
    assert errors[degree + 1] > 0.1, errors


def test_rules_have_the_documented_end_points():
    assert np.asarray(gj.gauss_lobatto(5).points)[[0, -1]].tolist() == [0.0, 1.0]
    assert np.asarray(gj.gauss_radau(3).points)[-1] == 1.0
    assert np.asarray(gj.gauss_radau(3, right=False).points)[0] == 0.0
    assert np.all((np.asarray(gj.gauss_legendre(6).points) > 0) & (np.asarray(gj.gauss_legendre(6).points) < 1))


@pytest.mark.parametrize("rule", [gj.gauss_legendre(4), gj.gauss_lobatto(5), gj.midpoint(), gj.trapezoid()])
def test_gauss_and_lobatto_rules_are_symmetric(rule):
    """Definition 4.1 [GBS]: points pair up around 1/2 with equal weights."""
    points, weights = np.asarray(rule.points), np.asarray(rule.weights)
    np.testing.assert_allclose(points + points[::-1], 1.0, atol=1e-15)
    np.testing.assert_allclose(weights, weights[::-1], atol=1e-15)


def test_rule_is_a_pytree_that_stacks_and_vmaps():
    rules = [gj.gauss_legendre(3), gj.gauss_lobatto(3), gj.gauss_radau(3)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *rules)
    integral = jax.vmap(lambda r: r.weights @ r.points**4)(stacked)
    np.testing.assert_allclose(integral, [np.asarray(r.weights) @ np.asarray(r.points) ** 4 for r in rules])
    assert isinstance(jax.tree.unflatten(jax.tree.structure(rules[0]), [0, 0]), gj.QuadratureRule)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: gj.gauss_legendre(0), "n >= 1"),
        (lambda: gj.gauss_lobatto(1), "n >= 2"),
        (lambda: gj.gauss_legendre(2.0), "integer"),
        (lambda: gj.QuadratureRule([0.5, 1.2], [0.5, 0.5]), r"\[0, 1\]"),
        (lambda: gj.QuadratureRule([-0.1], [1.0]), r"\[0, 1\]"),
        (lambda: gj.QuadratureRule([0.2, 0.8], [1.0]), "same non-empty shape"),
        (lambda: gj.QuadratureRule([np.nan], [1.0]), "finite"),
    ],
)
def test_bad_rules_raise_value_error(make, match):
    with pytest.raises(ValueError, match=match):
        make()
