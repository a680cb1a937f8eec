"""The user's functions and ``args`` as the compiled programs take them: every input explicit.

Two things a user writes would otherwise not reach the programs as inputs:

* ``args`` with leaves that are not arrays (an activation function of an ``eqx.nn.MLP``, an int
  that sizes a loop, a string): they are static, as equinox and diffrax treat them. ``args``
  is split into its array leaves, which the programs take (traced, differentiated, vmapped),
  and the rest, which the wrapped function puts back (``WithArgs``; hashed with it, so a new
  static value is a new program, the same one the same program).
* arrays that ``H``, an event's ``g`` or a ``TimeTransform``'s ``s`` close over while JAX traces
  them (a parameter of ``jax.grad``, ``jax.jit`` or ``jax.vmap`` captured in a lambda): each
  function is closure-converted (``closure_convert``) and its constants travel in ``args``
  beside the user's (``Explicit``, ``EventG``), so they differentiate exactly as ``args`` does,
  by the one definition of every derivative. A function that closes over no traced value is
  handed down as it is.

Arrays are JAX and NumPy arrays, NumPy scalars and Python floats and complex numbers (a float
in ``args`` stays an input, as it always was); every other leaf is static.
"""

import dataclasses
import functools
import inspect
from typing import Any, Callable

import jax
import numpy as np
from jax._src import core as _core

from ._controllers import Event, TimeTransform


def is_array(x):
    """Whether a leaf of ``args`` is an input of the programs (module docstring)."""
    return isinstance(x, (jax.Array, np.ndarray, np.generic, float, complex)) and not isinstance(x, bool)


@dataclasses.dataclass(frozen=True)
class _Static:
    """A static leaf, hashed by its value where it has one, else by its identity."""

    value: Any

    def _key(self):
        try:
            hash(self.value)
            return (0, self.value)
        except TypeError:
            return (1, id(self.value))

    def __hash__(self):
        return hash(self._key())

    def __eq__(self, other):
        return isinstance(other, _Static) and type(self.value) is type(other.value) and self._key() == other._key()


@dataclasses.dataclass(frozen=True)
class Split:
    """The static part of ``args``: its tree structure and, per leaf, the static value or None
    where the leaf is an array (which comes from the arrays the programs take)."""

    treedef: Any
    static: tuple

    def combine(self, arrays):
        arrays = iter(arrays)
        return self.treedef.unflatten([next(arrays) if s is None else s.value for s in self.static])


def split(args):
    """``(arrays, spec)``: ``args``'s array leaves (a tuple) and its ``Split``; ``spec`` None
    where every leaf is an array (then ``arrays`` is ``args`` itself)."""
    leaves, treedef = jax.tree.flatten(args)
    if all(is_array(x) or isinstance(x, _core.Tracer) for x in leaves):
        return args, None
    static = tuple(None if is_array(x) or isinstance(x, _core.Tracer) else _Static(x) for x in leaves)
    return tuple(x for x, s in zip(leaves, static) if s is None), Split(treedef, static)


@dataclasses.dataclass(frozen=True)
class WithArgs:
    """``fn(*xs, args)`` from ``(*xs, arrays)``: the user's function called with args rebuilt from
    its arrays (``Split.combine``), or ``fn(*xs)`` where it takes none (``takes_args``). Hashed by
    ``(fn, spec, takes_args)``: one user function and one static part compile once."""

    fn: Callable
    spec: Any = None
    takes_args: bool = True

    def __call__(self, *xs):
        *xs, arrays = xs
        if not self.takes_args:
            return self.fn(*xs)
        return self.fn(*xs, arrays if self.spec is None else self.spec.combine(arrays))


@dataclasses.dataclass(frozen=True)
class Explicit:
    """A user's function as the library calls it, ``f(*xs, bundle)`` with the leading arguments
    ``xs`` (``(q, p)`` of H and s) and ``bundle = (arrays, constants)``: ``fn(*xs, arrays,
    *constants[key])``, ``fn`` a ``WithArgs`` or its closure-converted form (whose constants are
    those at ``key``; None: it has none)."""

    fn: Callable
    key: Any = None

    def __call__(self, *xs):
        *xs, (arrays, consts) = xs
        return self.fn(*xs, arrays, *(() if self.key is None else consts[self.key]))


@dataclasses.dataclass(frozen=True)
class EventG:
    """An event's g closure-converted: the library calls it ``g(t, q, p, bundle)`` (``reads_args``:
    ``_controllers.event_value``), and it calls ``fn(t, q, p, *constants[key])``."""

    fn: Callable
    key: str
    reads_args = True

    def __call__(self, t, q, p, bundle):
        return self.fn(t, q, p, *bundle[1][self.key])


def tracing():
    """Whether a JAX transformation is tracing now (only then can a function close over a traced
    value)."""
    try:
        return not _core.trace_state_clean()
    except AttributeError:  # a JAX without it: assume so
        return True


def closure_convert(f, *example):
    """``(f~, constants)`` with ``f~(*xs, *constants) = f(*xs)``: the traced values ``f`` closes over
    (of any transformation: ``jax.closure_convert`` keeps those of ``vmap``, which a compiled
    program cannot close over) hoisted into arguments; ``(f, [])`` where it closes over none."""
    closed, shape = jax.make_jaxpr(f, return_shape=True)(*example)
    traced = [isinstance(c, _core.Tracer) for c in closed.consts]
    if not any(traced):
        return f, []
    kept = [c for c, t in zip(closed.consts, traced) if not t]
    out_tree = jax.tree.structure(shape)

    def converted(*xs_and_consts):
        xs, hoisted = xs_and_consts[:len(example)], iter(xs_and_consts[len(example):])
        kept_ = iter(kept)
        consts = [next(hoisted) if t else next(kept_) for t in traced]
        return jax.tree.unflatten(out_tree, _core.eval_jaxpr(closed.jaxpr, consts, *jax.tree.leaves(xs)))

    return converted, [c for c, t in zip(closed.consts, traced) if t]


def explicit_inputs(H, q0, p0, args, *, controller=None, events=None, t0=0.0):
    """``(H, args, controller, events)`` with every input of the user's functions explicit
    (module docstring): the given objects where nothing needs converting, else ``Explicit``
    functions (events: ``EventG``) and ``args = (arrays, constants)``.

    Args:
        q0, p0: the initial state in the user's shape, for tracing the functions.
        controller: a ``TimeTransform`` whose s is converted too; any other controller passes.
        events: an ``Event`` or a list of them (their g converted), or None.
        t0: the start time, for tracing the events' g.
    """
    arrays, spec = split(args)
    has_args = args is not None
    s = controller.s if isinstance(controller, TimeTransform) else None
    event_list = [events] if isinstance(events, Event) else list(events or [])
    functions = {"H": WithArgs(H, spec, has_args)}
    if callable(s):
        functions["s"] = WithArgs(s, spec, has_args)
    consts, converted_gs = {}, {}
    if tracing():
        for key, f in functions.items():
            converted, found = closure_convert(f, q0, p0, arrays)
            if found:
                functions[key], consts[key] = converted, list(found)
        t = jax.numpy.asarray(t0, q0.dtype)
        for k, event in enumerate(event_list):
            if isinstance(event, Event) and callable(event.g):
                converted, found = closure_convert(event.g, t, q0, p0)
                if found:
                    converted_gs[k], consts[f"g{k}"] = converted, list(found)
    if spec is None and not consts:
        return H, args, controller, events
    explicit = {k: Explicit(f, k if k in consts else None) for k, f in functions.items()}
    if "s" in explicit:
        controller = dataclasses.replace(controller, s=explicit["s"])
    if converted_gs:
        event_list = [dataclasses.replace(e, g=EventG(converted_gs[k], f"g{k}")) if k in converted_gs else e
                      for k, e in enumerate(event_list)]
        events = event_list[0] if isinstance(events, Event) else event_list
    return explicit["H"], (arrays, consts), controller, events


def on_entry(fn):
    """Decorate a public function ``f(H, q, p, ..., args=, controller=, events=)`` so that its
    H, args and a ``TimeTransform``'s s reach it with every input explicit (``explicit_inputs``);
    the state is read in the user's own shape. Where the inputs cannot be traced (bad input) they
    pass as given, for the function's checks to name."""
    signature = inspect.signature(fn)
    names = list(signature.parameters)[:3]

    @functools.wraps(fn)
    def public(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        given = bound.arguments
        H, q0, p0 = (given.get(name) for name in names)
        try:
            q0, p0 = jax.tree.map(jax.numpy.asarray, (q0, p0))
            H, run_args, controller, events = explicit_inputs(
                H, q0, p0, given.get("args"), controller=given.get("controller"), events=given.get("events"),
                t0=given.get("t0", 0.0))
        except Exception:  # noqa: BLE001 -- bad input: the function's own checks name it
            return fn(*args, **kwargs)
        given[names[0]] = H
        if "args" in signature.parameters:
            given["args"] = run_args
        if given.get("controller") is not None:
            given["controller"] = controller
        if given.get("events") is not None:
            given["events"] = events
        return fn(*bound.args, **bound.kwargs)

    return public
