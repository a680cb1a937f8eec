"""States of any shape: flattened once at the public functions, so the solver sees vectors.

A state is an array of any shape (N bodies in space: ``(N, 3)``) or a pytree of arrays (a
dict of positions), q and p of one structure and shapes. The public functions (``step``,
``integrate``, ``amplification_matrix``, ``sweep``) flatten it into vectors of length d,
the number of elements of q: the leaves in pytree order, each in C order, in one float
dtype. The user's functions (H, an event's g(t, q, p), a time transformation's s(q, p), a
sweep's invariants I(q, p)) are wrapped (``Unflattened``) to take those vectors and call
the function with the state in its own shape; saved states, which carry leading axes (time,
batch, events), are unflattened on the way out. A state that is one 1-D array passes
through untouched, so the flat path is the one that runs.
"""

import dataclasses
import functools
import inspect
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import _state


@dataclasses.dataclass(frozen=True)
class Layout:
    """The shape of a state: its tree structure and the shape of each leaf (hashable)."""

    treedef: Any
    shapes: tuple

    @property
    def sizes(self):
        return tuple(math.prod(s) for s in self.shapes)

    def flatten(self, tree, lead=()):
        """The state ``tree`` (leaves of shape ``lead + shape``) as an array ``lead + (d,)``."""
        leaves = self.treedef.flatten_up_to(tree)
        return jnp.concatenate([jnp.reshape(x, tuple(lead) + (-1,)) for x in leaves], axis=-1)

    def unflatten(self, z):
        """The flat states ``z`` (``(..., d)``) in the user's layout: leaves ``(...,) + shape``."""
        lead = jnp.shape(z)[:-1]
        parts = jnp.split(z, np.cumsum(self.sizes)[:-1], axis=-1)
        return self.treedef.unflatten([jnp.reshape(x, lead + s) for x, s in zip(parts, self.shapes)])


@dataclasses.dataclass(frozen=True)
class Unflattened:
    """``fn`` with the flat state at arguments ``position`` (q) and ``position + 1`` (p):
    ``Unflattened(H, layout)(q, p, *rest) = H(layout.unflatten(q), layout.unflatten(p), *rest)``.

    Hash and equality come from ``(fn, layout, position)``, so that the compiled programs,
    which take H as a static argument, are reused for one user function and one layout.
    """

    fn: Callable
    layout: Layout
    position: int = 0

    @property
    def reads_args(self):
        """An event's g that takes H's args (``_controllers.event_value``)."""
        return getattr(self.fn, "reads_args", False)

    def __call__(self, *args):
        i = self.position
        q, p = (self.layout.unflatten(x) for x in args[i : i + 2])
        return self.fn(*args[:i], q, p, *args[i + 2 :])


def flatten_state(q0, p0):
    """``(layout, q0, p0)``: the checked state flattened to vectors; ``layout`` None where it
    is one 1-D array (then q0, p0 are returned as given, for ``prepare`` to check)."""
    if all(isinstance(x, (jax.Array, np.ndarray)) and x.ndim == 1 for x in (q0, p0)):
        return None, q0, p0
    q, p = _state.check_state(q0, p0)
    leaves, treedef = jax.tree.flatten(q)
    if treedef == jax.tree.structure(0.0) and leaves[0].ndim == 1:
        return None, q0, p0
    layout = Layout(treedef, tuple(x.shape for x in leaves))
    return layout, layout.flatten(q), layout.flatten(p)


def wrap(fn, layout, position=0):
    """``fn`` taking flat states; a non-callable is returned as is, for the checks to name."""
    return Unflattened(fn, layout, position) if callable(fn) else fn


def wrap_controller(controller, layout):
    """A ``TimeTransform``'s own s(q, p) taking flat states; other controllers as they are."""
    if getattr(controller, "s", None) is None or not dataclasses.is_dataclass(controller):
        return controller
    return dataclasses.replace(controller, s=wrap(controller.s, layout))


def wrap_event(event, layout):
    """An ``Event`` whose g(t, q, p) takes flat states."""
    if not (dataclasses.is_dataclass(event) and hasattr(event, "g")):
        return event
    return dataclasses.replace(event, g=wrap(event.g, layout, 1))


def unflatten_solution(layout, solution):
    """A ``Solution`` (one run or batched) with q, p and the events' q, p in the user's layout."""
    events = solution.events
    if events is not None:
        events = dataclasses.replace(events, q=layout.unflatten(events.q), p=layout.unflatten(events.p))
    return dataclasses.replace(solution, q=layout.unflatten(solution.q), p=layout.unflatten(solution.p),
                               events=events, layout=layout)


def _unflatten_pair(layout, pair):
    return tuple(layout.unflatten(x) for x in pair)


def _keep(layout, out):
    return out


def any_shape(output):
    """Decorate a public function ``f(H, q, p, ...)`` so that it takes states of any shape:
    q and p flattened, H, ``events`` and ``controller`` wrapped, the result passed through
    ``output(layout, result)``."""

    def decorate(fn):
        signature = inspect.signature(fn)
        names = list(signature.parameters)[:3]

        @functools.wraps(fn)
        def public(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            given = bound.arguments
            layout, q, p = flatten_state(given[names[1]], given[names[2]])
            if layout is None:
                return fn(*args, **kwargs)
            given.update({names[0]: wrap(given[names[0]], layout), names[1]: q, names[2]: p})
            if given.get("events") is not None:
                given["events"] = wrap_event(given["events"], layout)
            if given.get("controller") is not None:
                given["controller"] = wrap_controller(given["controller"], layout)
            return output(layout, fn(*bound.args, **bound.kwargs))

        return public

    return decorate


on_step = any_shape(_unflatten_pair)
on_integrate = any_shape(unflatten_solution)
on_amplification = any_shape(_keep)


def flatten_batch(q0, p0, names=("configs.q0", "configs.p0")):
    """``(layout, q0, p0)`` of states with a leading batch axis B: ``(B, *shape)`` arrays or
    pytrees whose leaves all lead with B, flattened to ``(B, d)``. ``layout`` is None, and
    q0, p0 are returned as given, where they are ``(B, d)`` arrays or where two single
    arrays of rank <= 2 differ (the checks of ``(B, d)`` then name the problem)."""
    (qs, q_tree, paths), (ps, p_tree, _) = (_state.state_leaves(x, name) for x, name in zip((q0, p0), names))
    single = q_tree == p_tree == jax.tree.structure(0.0)
    if single and ((qs[0].ndim == 2 and ps[0].ndim == 2) or (qs[0].shape != ps[0].shape and max(qs[0].ndim, ps[0].ndim) <= 2)):
        return None, q0, p0
    if q_tree != p_tree:
        raise ValueError(f"{names[0]} and {names[1]} must have the same structure, got {q_tree} and {p_tree}.")
    B = qs[0].shape[0] if qs[0].ndim else None
    for path, q, p in zip(paths, qs, ps):
        if q.shape != p.shape:
            raise ValueError(f"{names[0]}{path} and {names[1]}{path} must have the same shape (B, ...), got "
                             f"{q.shape} and {p.shape}.")
        if q.ndim == 0 or q.shape[0] != B:
            raise ValueError(f"{names[0]}{path} needs a leading batch axis of size B = {B} (every leaf), got shape "
                             f"{q.shape}.")
    layout = Layout(q_tree, tuple(x.shape[1:] for x in qs))
    if sum(layout.sizes) == 0:
        raise ValueError(f"{names[0]}: a state needs at least one element, got shapes {list(layout.shapes)}.")
    dtype = _state.state_dtype(*qs, *ps)
    flat = lambda xs: layout.flatten(q_tree.unflatten([x.astype(dtype) for x in xs]), lead=(B,))
    return layout, flat(qs), flat(ps)


def _flatten_reference(layout, reference, B):
    if not (isinstance(reference, (tuple, list)) and len(reference) == 2):
        return reference
    want = (layout.treedef, [(B,) + s for s in layout.shapes])
    for r in reference:
        leaves, treedef = jax.tree.flatten(r)
        got = (treedef, [jnp.shape(x) for x in leaves])
        if got != want:
            raise ValueError(f"reference must be (q_ref, p_ref), each like configs.q0 (structure and shapes "
                             f"{want[0]}, {want[1]}), got {got[0]}, {got[1]}.")
    return tuple(layout.flatten(jax.tree.map(jnp.asarray, r), lead=(B,)) for r in reference)


def unflatten_sweep(layout, result):
    """A ``SweepResult`` with q, p (and its solution's) in the user's layout."""
    runs = result.solution
    runs = None if runs is None else unflatten_solution(layout, runs)
    return dataclasses.replace(result, q=layout.unflatten(result.q), p=layout.unflatten(result.p), solution=runs)


def on_sweep(fn):
    """Decorate ``sweep(H, configs, ...)``: ``configs.q0``, ``configs.p0`` of shape
    ``(B, *shape)`` or pytrees with a leading axis B; H, ``invariants``, ``reference`` and a
    ``TimeTransform``'s s follow the state's layout."""
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def public(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        given = bound.arguments
        configs = given.get("configs")
        if not all(hasattr(configs, name) for name in ("q0", "p0", "h")):
            return fn(*args, **kwargs)
        layout, q0, p0 = flatten_batch(configs.q0, configs.p0)
        if layout is None:
            return fn(*args, **kwargs)
        B = q0.shape[0]
        given.update(H=wrap(given["H"], layout), configs=dataclasses.replace(configs, q0=q0, p0=p0))
        if isinstance(given.get("invariants"), dict):
            given["invariants"] = {name: wrap(I, layout) for name, I in given["invariants"].items()}
        if given.get("reference") is not None:
            given["reference"] = _flatten_reference(layout, given["reference"], B)
        if given.get("controller") is not None:
            given["controller"] = wrap_controller(given["controller"], layout)
        return unflatten_sweep(layout, fn(*bound.args, **bound.kwargs))

    return public
