"""Tuning quadrature rules by gradient descent (optax), through the implicit solves.

A rule is parametrised without constraints: points = sigmoid(x) lie in (0, 1) and
weights = softmax(y) are positive and sum to one (the rule integrates constants exactly,
so the methods stay consistent). Gradients of any loss built from ``integrate``, ``step``,
``sweep`` or ``amplification_matrix`` reach (x, y) by the implicit function theorem.
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._quadrature import QuadratureRule


def rule_from_params(params) -> QuadratureRule:
    """QuadratureRule(sigmoid(x), softmax(y)) from ``params = (x, y)``, each shape ``(n_q,)``."""
    x, y = params
    return QuadratureRule(jax.nn.sigmoid(x), jax.nn.softmax(y))


def params_from_rule(rule) -> tuple[jax.Array, jax.Array]:
    """The inverse of ``rule_from_params``; needs points strictly inside (0, 1) and positive weights."""
    points, weights = np.asarray(rule.points, dtype=float), np.asarray(rule.weights, dtype=float)
    if np.any(points <= 0) or np.any(points >= 1) or np.any(weights <= 0):
        raise ValueError("params_from_rule: points must lie in (0, 1) and weights be > 0.")
    weights = weights / weights.sum()
    return jnp.asarray(np.log(points / (1 - points))), jnp.asarray(np.log(weights))


def asymmetry(rule) -> jax.Array:
    """|sum_l (1 - 2 alpha_l) w_l| [GBS, eq. (61)]: zero for rules symmetric about 1/2."""
    return jnp.abs(jnp.sum((1.0 - 2.0 * rule.points) * rule.weights))


def tune_rule(loss, rule, *, optimizer=None, iterations=100) -> tuple[QuadratureRule, np.ndarray]:
    """Minimise ``loss(rule)`` over the rule's points and weights with optax.

    Args:
        loss: the function to minimise, ``QuadratureRule -> scalar``, differentiable (e.g.
            built on ``gj.integrate``); required.
        rule: the starting rule, points in (0, 1) and weights > 0; required.
        optimizer: the optimiser, an ``optax.GradientTransformation``; default None,
            ``optax.adam(0.05)``.
        iterations: the number of optimiser steps; default 100.
    Returns:
        ``(best_rule, history)`` with the loss before each step in ``history`` (NumPy array);
        the best rule seen is returned, not the last.
    """
    optimizer = optimizer or optax.adam(0.05)
    params = params_from_rule(rule)
    value_and_grad = jax.jit(jax.value_and_grad(lambda p: loss(rule_from_params(p))))
    state = optimizer.init(params)
    history, best = [], (np.inf, params)
    for _ in range(iterations):
        value, grad = value_and_grad(params)
        value = float(value)
        history.append(value)
        if value < best[0]:
            best = (value, params)
        updates, state = optimizer.update(grad, state, params)
        params = optax.apply_updates(params, updates)
    return rule_from_params(best[1]), np.asarray(history)
