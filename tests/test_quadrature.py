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
        (lambda: gj.QuadratureRule([0.25, 0.75], [0.5, 1.0]), r"weights must sum to 1 .* weights \[0.5 1. \] sum to 1.5"),
        (lambda: gj.QuadratureRule([0.5], [0.0]), "weights must sum to 1"),
        (lambda: gj.QuadratureRule([[0.5], [0.5]], [[1.0], [0.9]]), r"weights \[0.9\] \(row 1\) sum to 0.9"),
    ],
)
def test_bad_rules_raise_value_error(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_weight_sum_tolerance_is_1e_12_in_float64():
    """Rules found by root finding carry up to ~2000 eps in their sum (gauss_radau(40): 1800 eps
    = 4e-13), and must pass; a sum off by 1e-11 changes the scheme above round-off."""
    for n in (13, 25, 34, 40):
        gj.gauss_radau(n)
    gj.QuadratureRule([0.3, 0.7], [0.5, 0.5 + 5e-13])
    with pytest.raises(ValueError, match="sum to 1"):
        gj.QuadratureRule([0.3, 0.7], [0.5, 0.5 + 1e-11])


def test_stacked_and_padded_rules_are_checked_row_by_row():
    stacked = gj.QuadratureRule(np.array([[0.2, 0.8], [0.5, 0.5]]), np.array([[0.5, 0.5], [1.0, 0.0]]))
    assert stacked.points.shape == (2, 2)
    padded = gj.pad_rule(gj.gauss_legendre(2), 5)  # zero weights: the sum is unchanged
    assert float(np.sum(padded.weights)) == pytest.approx(1.0, abs=1e-15)
    method = gj.stack_methods([gj.CG(1, gj.midpoint()), gj.CG(1, gj.gauss_lobatto(4))])
    np.testing.assert_allclose(np.sum(method.quadrature.weights, axis=1), 1.0, atol=1e-15)


def test_traced_rules_and_rebuilt_pytrees_are_not_checked():
    """Leaves rebuilt by jit, grad and tree maps (cotangents, zeros) are not rules: no check."""
    params = (jnp.array([-1.0, 1.0]), jnp.array([0.0, 0.3]))
    loss = lambda p: jnp.sum(gj.rule_from_params(p).weights * gj.rule_from_params(p).points ** 2)
    assert np.all(np.isfinite(jax.grad(loss)(params)[1]))
    assert float(jnp.sum(gj.rule_from_params(params).weights)) == pytest.approx(1.0, abs=1e-15)
    grad = jax.grad(lambda r: -jnp.sum(r.points * r.weights))(gj.gauss_legendre(2))
    assert isinstance(grad, gj.QuadratureRule)  # points -w < 0, weights summing to -1: no error
    np.testing.assert_allclose(grad.weights, -np.asarray(gj.gauss_legendre(2).points))
    zeros = jax.tree.map(jnp.zeros_like, gj.gauss_legendre(3))
    assert float(jnp.sum(zeros.weights)) == 0.0
    jax.jit(lambda w: gj.QuadratureRule(jnp.array([0.2, 0.8]), w).weights * 2)(jnp.array([0.5, 1.0]))
