"""Configurations of a sweep: stacked methods, states, step sizes and args (``Configs``, ``grid``)."""

import itertools
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._method import AbstractMethod, check_method, describe_method
from ._state import check_state, non_finite, state_dtype
from ._pytree import pytree_dataclass
from ._quadrature import QuadratureRule


@pytree_dataclass
class Configs:
    """Configurations of a sweep: every leaf has a leading batch axis of size B.

    Attributes:
        method: the methods, one method pytree with stacked quadrature arrays (see
            ``stack_methods``).
        q0: the initial positions, shape ``(B, d)``, or ``(B,) + shape`` for states of any shape, or pytrees of
            arrays whose leaves lead with B (``sweep`` flattens them; H sees each member's
            state in its shape).
        p0: the initial momenta, of q0's shape (structure).
        h: the step sizes, shape ``(B,)``.
        args: the extra inputs of H, ``None`` or a pytree whose leaves have a leading axis B.
    """

    method: Any
    q0: jax.Array
    p0: jax.Array
    h: jax.Array
    args: Any = None

    @property
    def size(self):
        return self.h.shape[0]


def pad_rule(rule, n) -> QuadratureRule:
    """The rule with zero-weight points at 1/2 appended up to ``n`` points; integrates the same.

    Args:
        rule: the rule to pad, a ``QuadratureRule`` with shape ``(n_q,)``; required.
        n: the point count wanted, an integer >= n_q; required.
    Returns:
        ``QuadratureRule`` with shape ``(n,)``; its weights have the same sum.
    """
    if not isinstance(rule, QuadratureRule):
        raise TypeError(f"pad_rule: rule must be a QuadratureRule, got {type(rule).__name__}.")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < rule.num_points:
        raise ValueError(f"pad_rule: n must be an integer >= the rule's {rule.num_points} points, got {n!r}.")
    extra = n - rule.num_points
    points = jnp.concatenate([jnp.asarray(rule.points), jnp.full(extra, 0.5, jnp.result_type(rule.points))])
    weights = jnp.concatenate([jnp.asarray(rule.weights), jnp.zeros(extra, jnp.result_type(rule.weights))])
    return QuadratureRule(points, weights)


def _is_rule(x):
    return isinstance(x, QuadratureRule)


def _check_methods(methods, name):
    """One kind and degree (equal static fields): one compiled program serves the batch."""
    if not methods:
        raise ValueError(f"{name}: no methods given; give at least one, e.g. [gj.CG(2, gj.gauss_legendre(3))].")
    for i, m in enumerate(methods):
        try:
            check_method(m)
        except (TypeError, ValueError) as error:
            raise type(error)(f"{name}[{i}]: {error}") from None
    kinds = [describe_method(m) for m in methods]
    for i, kind in enumerate(kinds):
        if kind != kinds[0]:
            raise ValueError(
                f"{name}: all methods of one sweep must be of one kind and degree (they share one "
                f"compiled program), got {kinds[0]} ({name}[0]) and {kind} ({name}[{i}]); rules may "
                "differ in size. Run one sweep per kind."
            )


def stack_methods(methods) -> AbstractMethod:
    """Stack methods of one kind and degree along a new leading axis, padding their rules
    to a common point count with ``pad_rule`` so that rules of any size share one batch.

    Args:
        methods: the methods to stack, a sequence of one kind and degree, e.g.
            ``[gj.CG(2, r) for r in rules]``; required.
    Returns:
        one method whose quadrature arrays have shape ``(B, n_q)``.
    """
    methods = list(methods)
    _check_methods(methods, "methods")
    rules = [r for m in methods for r in jax.tree_util.tree_leaves(m, is_leaf=_is_rule) if _is_rule(r)]
    n = max((r.num_points for r in rules), default=0)
    padded = [jax.tree.map(lambda x: pad_rule(x, n) if _is_rule(x) else x, m, is_leaf=_is_rule) for m in methods]
    if len({jax.tree.structure(m) for m in padded}) != 1:
        raise ValueError("stack_methods: methods must be of one kind and degree (static fields equal).")
    return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *padded)


def _ndim(x):
    """Array rank of x, nested lists and tuples included; None for ragged or non-numeric x."""
    if isinstance(x, (list, tuple)):
        inner = {_ndim(v) for v in x}
        return 1 if not x else (1 + inner.pop() if len(inner) == 1 and None not in inner else None)
    if isinstance(x, (bool, str, bytes)) or x is None:
        return None
    if isinstance(x, (int, float, np.number, np.ndarray, jax.Array)):
        return jnp.ndim(x)
    return None


def _method_axis(method):
    """A single method is one point of the axis; otherwise a sequence of methods."""
    if all(callable(getattr(method, m, None)) for m in ("initial_guess", "residual")):
        return [method]
    if isinstance(method, (str, bytes)) or not isinstance(method, (list, tuple)):
        raise TypeError(
            "method must be a galerkin_jax method such as gj.CG(2, gj.gauss_legendre(3)), or a list of "
            f"them, got {type(method).__name__}."
        )
    methods = list(method)
    _check_methods(methods, "method")
    return methods


def _step_axis(h):
    """A number is one step size; a list, tuple or 1-D array is the axis. Values > 0 where concrete."""
    if _ndim(h) is None or _ndim(h) > 1:
        got = f"shape {np.shape(h)}" if _ndim(h) is not None else type(h).__name__
        raise TypeError(f"h must be a step size > 0 or a list (1-D array) of them, got {got}.")
    hs = list(h) if _ndim(h) == 1 else [h]
    if not hs:
        raise ValueError("h: no step sizes given; give at least one, e.g. h=0.01 or h=[0.01, 0.02].")
    for i, value in enumerate(hs):
        if not isinstance(value, jax.core.Tracer) and not (np.isfinite(float(value)) and float(value) > 0):
            raise ValueError(f"h must be finite and > 0, got h[{i}] = {float(value)!r}.")
    return hs


def _is_part(x):
    """One of q0, p0: a 1-D sequence or array, an array of any rank >= 1, or a dict of arrays."""
    return _ndim(x) == 1 or (isinstance(x, (np.ndarray, jax.Array)) and x.ndim >= 1) or isinstance(x, Mapping)


def _is_state(x):
    return isinstance(x, (tuple, list, np.ndarray, jax.Array)) and len(x) == 2 and _is_part(x[0]) and _is_part(x[1])


def _flat_vector(x):
    return isinstance(x, jax.Array) and x.ndim == 1


def _state_axis(state):
    """A pair (q0, p0) of 1-D arrays is one state; a list of such pairs is the axis."""
    if _is_state(state):
        states, names = [state], ["state"]
    elif isinstance(state, (tuple, list)) and state and all(_is_state(s) for s in state):
        states, names = list(state), [f"state[{i}]" for i in range(len(state))]
    elif isinstance(state, (tuple, list)) and not state:
        raise ValueError("state: no states given; give one state (q0, p0) or a list of them.")
    else:
        items = list(state) if isinstance(state, (tuple, list)) else []
        wrong = [i for i, s in enumerate(items) if not _is_state(s)]
        some = items and len(wrong) < len(items)  # a list of states with some wrong items
        bad = f"state[{wrong[0]}] is {_describe(items[wrong[0]])}" if some else f"got {_describe(state)}"
        raise ValueError(
            "state must be one state (q0, p0), a pair of 1-D arrays of one length d, or a list of such "
            f"pairs (all of one d); {bad}."
        )
    as_part = lambda x: jnp.asarray(x) if _ndim(x) is not None else jax.tree.map(jnp.asarray, x)
    states = [tuple(as_part(x) for x in s) for s in states]
    for name, (q0, p0) in zip(names, states):
        if _flat_vector(q0) and _flat_vector(p0) and (q0.shape != p0.shape or q0.shape[0] == 0):
            raise ValueError(f"{name}: q0 and p0 need one length d >= 1, got {q0.shape[0]} and {p0.shape[0]}.")
        if not all(isinstance(x, jax.core.Tracer) or np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves((q0, p0))):
            parts = [f"{part}: {non_finite(x)}" for part, tree in (("q0", q0), ("p0", p0))
                     for x in jax.tree.leaves(tree) if not np.all(np.isfinite(np.asarray(x)))]
            raise ValueError(f"{name} must be finite, got {'; '.join(parts)}.")
        try:
            check_state(q0, p0)
        except ValueError as error:
            raise ValueError(f"{name}: {error}") from None
    layout = lambda x: (jax.tree.structure(x), [jnp.shape(v) for v in jax.tree.leaves(x)])
    for name, (q0, _) in zip(names, states):
        if not (_flat_vector(q0) and _flat_vector(states[0][0])) and layout(q0) != layout(states[0][0]):
            raise ValueError(f"state: all states of one sweep need one shape; {names[0]} has "
                             f"{layout(states[0][0])}, {name} has {layout(q0)}. Run one sweep per shape.")
        if _flat_vector(q0) and q0.shape != states[0][0].shape:
            raise ValueError(
                f"state: all states of one sweep need one dimension d; {names[0]} has d = "
                f"{states[0][0].shape[0]}, {name} has d = {q0.shape[0]}. Run one sweep per dimension."
            )
    return states


def _describe(x):
    if isinstance(x, (np.ndarray, jax.Array)):
        return f"an array of shape {x.shape}"
    if isinstance(x, (tuple, list)):
        return f"a {type(x).__name__} of {len(x)} items of ranks {[_ndim(v) for v in x]}"
    return f"a {type(x).__name__}"


def _args_axis(args):
    """None: no args. A list is the axis; anything else is one args pytree for every configuration."""
    if not isinstance(args, list):
        return [args]
    if not args:
        raise ValueError("args: an empty list; give None, one args pytree, or a list of them (the axis).")
    shapes = [jax.tree.map(jnp.shape, a) for a in args]
    structures = [jax.tree.structure(a) for a in args]
    for i in range(1, len(args)):
        if structures[i] != structures[0] or shapes[i] != shapes[0]:
            raise ValueError(
                "args: every entry of the args axis (a list) needs the same structure and shapes, got "
                f"{shapes[0]} (args[0]) and {shapes[i]} (args[{i}]). To pass one list as args, wrap it: "
                "args=[[a, b]]."
            )
    return args


def grid(*, method, h, state, args=None) -> Configs:
    """The cartesian product of the given axes as ``Configs`` (order: method, h, state, args).

    Each axis takes a list of values or a single value, which is one point of its axis.

    Args:
        method: the method axis: a method, or a list of methods of one kind and degree (e.g.
            all ``CG(2, rule)``; rules of any size, see ``stack_methods``); required.
        h: the step-size axis: a step size > 0, or a list (tuple, 1-D array) of them; required.
        state: the initial-state axis: one state ``(q0, p0)``, a pair of 1-D arrays of one
            length d (or of arrays of any one shape, e.g. ``(N, 3)``, or of dicts of arrays of
            one structure), or a list of such pairs, all of one shape; required.
        args: the axis of H's extra input; default None. A list is the axis (one args pytree
            per entry, all of one structure and shape); anything else (a number, an array, a
            tuple, a dict) is one args pytree shared by every configuration. One list as args:
            ``args=[[a, b]]``.
    Returns:
        ``Configs`` with B = the product of the axes' lengths, q0, p0 and h in the states' dtype.
    Raises:
        ValueError or TypeError naming the argument: an empty axis, a non-positive h, methods of
            different kinds or degrees, states of different dimensions or with len(q0) != len(p0).
    """
    methods, hs, states = _method_axis(method), _step_axis(h), _state_axis(state)
    args_axis = _args_axis(args)
    rows = list(itertools.product(range(len(methods)), range(len(hs)), range(len(states)), range(len(args_axis))))
    dtype = state_dtype(*jax.tree.leaves(states))
    stack = lambda i: jax.tree.map(lambda *x: jnp.stack(x).astype(dtype), *[states[r[2]][i] for r in rows])
    stacked_args = None
    if args is not None:
        stacked_args = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *[args_axis[r[3]] for r in rows])
    return Configs(
        method=stack_methods([methods[r[0]] for r in rows]),
        q0=stack(0),
        p0=stack(1),
        h=jnp.stack([jnp.asarray(hs[r[1]]) for r in rows]).astype(dtype),
        args=stacked_args,
    )
