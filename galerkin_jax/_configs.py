"""Configurations of a sweep: stacked methods, states, step sizes and args (``Configs``, ``grid``)."""

import itertools
from typing import Any

import jax
import jax.numpy as jnp

from ._pytree import pytree_dataclass
from ._quadrature import QuadratureRule


@pytree_dataclass
class Configs:
    """Configurations of a sweep: every leaf has a leading batch axis of size B.

    Attributes:
        method: a method pytree with stacked quadrature arrays (see ``stack_methods``).
        q0, p0: shape ``(B, d)``.
        h: shape ``(B,)``.
        args: ``None`` or a pytree whose leaves have a leading axis B.
    """

    method: Any
    q0: jax.Array
    p0: jax.Array
    h: jax.Array
    args: Any = None

    @property
    def size(self):
        return self.h.shape[0]


def pad_rule(rule, n):
    """The rule with zero-weight points at 1/2 appended up to ``n`` points; integrates the same."""
    extra = n - rule.num_points
    if extra < 0:
        raise ValueError(f"pad_rule: the rule has {rule.num_points} points, more than n = {n}.")
    points = jnp.concatenate([jnp.asarray(rule.points), jnp.full(extra, 0.5, jnp.result_type(rule.points))])
    weights = jnp.concatenate([jnp.asarray(rule.weights), jnp.zeros(extra, jnp.result_type(rule.weights))])
    return QuadratureRule(points, weights)


def _is_rule(x):
    return isinstance(x, QuadratureRule)


def stack_methods(methods):
    """Stack methods of one kind and degree along a new leading axis, padding their rules
    to a common point count with ``pad_rule`` so that rules of any size share one batch."""
    methods = list(methods)
    rules = [r for m in methods for r in jax.tree_util.tree_leaves(m, is_leaf=_is_rule) if _is_rule(r)]
    n = max((r.num_points for r in rules), default=0)
    padded = [jax.tree.map(lambda x: pad_rule(x, n) if _is_rule(x) else x, m, is_leaf=_is_rule) for m in methods]
    structures = {jax.tree.structure(m) for m in padded}
    if len(structures) != 1:
        raise ValueError("stack_methods: methods must be of one kind and degree (static fields equal).")
    return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *padded)


def grid(*, method, h, state, args=None):
    """The cartesian product of the given axes as ``Configs`` (order: method, h, state, args).

    Args:
        method: sequence of methods (rules of any size; see ``stack_methods``).
        h: sequence of step sizes.
        state: sequence of ``(q0, p0)`` pairs.
        args: None, or a sequence of ``args`` pytrees.
    """
    args_axis = [None] if args is None else list(args)
    rows = list(itertools.product(range(len(method)), list(h), list(state), range(len(args_axis))))
    stacked_args = None
    if args is not None:
        stacked_args = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *[args_axis[r[3]] for r in rows])
    return Configs(
        method=stack_methods([method[r[0]] for r in rows]),
        q0=jnp.stack([jnp.asarray(r[2][0]) for r in rows]),
        p0=jnp.stack([jnp.asarray(r[2][1]) for r in rows]),
        h=jnp.asarray([r[1] for r in rows]),
        args=stacked_args,
    )
