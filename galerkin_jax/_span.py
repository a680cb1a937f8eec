"""Checks of a run's time span, step rule, save times and events, before anything is traced.

Values are checked where they are concrete; traced ones are reported through the status.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._controllers import Event, PIDController, TimeTransform, check_values, concrete_values, event_value
from ._method import layers


def concrete(*xs):
    return all(not isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(xs))


def as_value(x, dtype):
    """``x`` as an array of ``dtype`` that stays concrete where x is (a NumPy array: under ``jit``
    a ``jnp`` conversion of a Python number is traced), so that a run under ``jit`` with a
    Python ``t1`` or ``h`` plans its elements as the same run outside it does."""
    return jnp.asarray(x, dtype) if isinstance(x, jax.core.Tracer) else np.asarray(x, dtype)


def known(x):
    """``float(x)`` where x's value is known while tracing (concrete, or a JVP tracer of a concrete
    value, as under ``jax.grad`` outside ``jit``), else None."""
    if isinstance(x, jax.core.Tracer):
        try:
            x = x.to_concrete_value()
        except AttributeError:  # a JAX without it: traced means unknown
            return None
    return None if x is None or jnp.ndim(x) != 0 else float(x)


def direction(t0, t1, dtype):
    """sigma = sign(t1 - t0), the run's direction (1 without a t1): a Python int where t0 and
    t1 are known while tracing (``known``), else traced, -1 where t1 < t0 and 1 elsewhere (under
    ``jit`` or ``vmap`` over t1: the run's order is known only when it runs)."""
    if t1 is None:
        return 1
    a, b = known(t0), known(t1)
    if a is not None and b is not None:
        return -1 if b < a else 1
    return jnp.where(jnp.asarray(t1, dtype) < jnp.asarray(t0, dtype), -1.0, 1.0).astype(dtype)


def _scalar(name, x):
    if jnp.ndim(x) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(x)}.")
    if concrete(x) and not np.isfinite(float(x)):
        raise ValueError(f"{name} must be finite, got {float(x)}.")


def check_span(n_steps, t0, t1, controller, events=None, max_steps=None, sweep=False):
    """Exactly one of ``n_steps`` and ``t1`` (t1 < t0 runs backwards; t1 = t0 returns the initial
    state); a controller needs ``t1``; an infinite t1 runs until a terminal event (``events``):
    with fixed steps at most ``max_steps`` elements."""
    if (n_steps is None) == (t1 is None):
        raise ValueError("Give exactly one of n_steps and t1 (the end time).")
    _scalar("t0", t0)
    if controller is not None:
        if not isinstance(controller, (PIDController, TimeTransform)):
            raise TypeError(f"controller must be gj.PIDController or gj.TimeTransform, got {type(controller).__name__}.")
        if n_steps is not None:
            raise ValueError("A controller chooses the steps: give t1 (the end time), not n_steps.")
    if t1 is not None:
        if concrete(t1) and jnp.ndim(t1) == 0 and np.isinf(float(t1)):
            _check_unbounded(float(t1), controller, events, max_steps, sweep)
        else:
            _scalar("t1", t1)


def _check_unbounded(t1, controller, events, max_steps, sweep):
    """An infinite t1: a run (not a sweep) that a terminal event ends, of at most max_steps."""
    terminal = [events] if isinstance(events, Event) else list(events or [])
    if sweep:
        raise ValueError(f"sweep needs a finite t1, got {t1}: every configuration reaches it.")
    if not any(isinstance(e, Event) and e.terminal for e in terminal):
        raise ValueError(f"t1 = {t1} runs until a terminal event: pass events=gj.Event(g, terminal=True), or a finite "
                         "t1.")
    if controller is None and max_steps is None:
        raise ValueError(f"Fixed steps to t1 = {t1} need max_steps: the most elements before the terminal event.")


def check_controller(controller, method, batch=None):
    """Tolerances > 0 and the bounds of a ``PIDController`` (each field a scalar, or in a sweep
    of ``batch`` configurations also of shape (batch,)); methods a controller can drive."""
    if controller is None:
        return
    if type(method).__name__ == "LagrangianVI":
        raise ValueError(
            "LagrangianVI is given L(q, qdot), which has no Hamilton's field for the embedded "
            "estimate or the time transformation: use GalerkinVI on the matching H, or fixed steps."
        )
    if any(type(m).__name__ == "Splitting" for m in layers(method)):
        why = ("its error estimate measures the interpolating cubic, not the splitting" if isinstance(
            controller, PIDController) else "the time-transformed K = s(q, p) (H + p_t) is not separable")
        raise ValueError(f"Splitting with a {type(controller).__name__}: {why}; use fixed steps (save_at and "
                         "events work with them).")
    if isinstance(controller, PIDController) and any(type(m).__name__ == "Tao" for m in layers(method)):
        raise ValueError("Tao with a PIDController: its error estimate measures the interpolating cubic, not Tao's "
                         "map; use fixed steps (save_at and events work with them) or a TimeTransform.")
    if type(method).__name__ == "Composition" and not isinstance(controller, TimeTransform):
        raise ValueError(
            "Composition with a PIDController: the error estimate measures the composition's "
            "interpolating cubic, not its steps; use fixed steps or a TimeTransform."
        )
    if isinstance(controller, TimeTransform):
        if type(method).__name__ == "ModifiedMidpoint":
            raise ValueError(
                "ModifiedMidpoint needs H = |p|^2 / 2m + V(|q|) (a central force), and the time "
                "transformation hands it K = s(q, p) (H + p_t) on (q, t | p, p_t), which is not of that "
                "form: use fixed steps or a PIDController, whose steps of any length keep its conservation of H."
            )
        if controller.s is not None and not callable(controller.s):
            raise TypeError(f"TimeTransform.s must be a callable s(q, p), got {type(controller.s).__name__}.")
        return
    for name in ("predictive", "force_dtmin"):
        if not isinstance(getattr(controller, name), bool):
            raise TypeError(f"controller.{name} must be a bool, got {getattr(controller, name)!r}.")
    shapes = [()] if batch is None else [(), (batch,)]
    for field in dataclasses.fields(controller):
        x = getattr(controller, field.name)
        if jnp.shape(x) not in shapes:
            allowed = "a scalar" if batch is None else f"a scalar or of shape ({batch},)"
            raise ValueError(f"controller.{field.name} must be {allowed}, got shape {jnp.shape(x)}.")
    # a controller built by the user was checked at construction; one rebuilt by JAX (a tree
    # map, a stacked sweep's) is checked here
    check_values(concrete_values(controller), "controller.")


def check_max_steps(max_steps):
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps must be an integer >= 1, got {max_steps!r}.")


def check_nodes(save_at, save_every):
    """``save_at="steps"`` (every node): True; a time array or None: False."""
    if isinstance(save_at, str):
        if save_at != "steps":
            raise ValueError(f'save_at must be "steps" or an array of times, got {save_at!r}.')
        if save_every != 1:
            raise ValueError('save_at="steps" saves every node: leave save_every at 1.')
        return True
    if isinstance(save_at, (list, tuple)) and any(isinstance(x, str) for x in save_at):
        raise ValueError('save_at is "steps" (every node) or an array of times, not both.')
    return False


def check_save_at(save_at, t0, t1, dtype, sigma=1):
    """``save_at`` as a 1-D array, sorted in the run's direction ``sigma`` (``direction``:
    non-decreasing; non-increasing in a run backwards, t1 < t0), between t0 and t1, where these
    are known while tracing (else the run checks them, ``_adaptive.run``); None stays None."""
    if save_at is None:
        return None
    ts = jnp.asarray(save_at, dtype)
    if ts.ndim != 1 or ts.shape[0] == 0:
        raise ValueError(f"save_at must be a non-empty 1-D array of times, got shape {ts.shape}.")
    if concrete(ts):
        values = np.asarray(ts)
        if not np.all(np.isfinite(values)):
            raise ValueError("save_at must hold finite times.")
        if not isinstance(sigma, int):  # the direction is known when the run runs
            return ts
        backwards = sigma == -1
        _check_order(values, backwards)
        if known(t0) is not None and known(t1) is not None:
            lo, hi = sorted((known(t0), known(t1)))
            if values.min() < lo or values.max() > hi:
                span = "[t1, t0]" if backwards else "[t0, t1]"
                raise ValueError(f"save_at must lie in {span} = [{lo}, {hi}], got [{values.min()}, {values.max()}].")
    return ts


def _check_order(values, backwards):
    """Raise ``ValueError`` where the save times ``values`` (concrete) go against the run's
    direction, naming the direction and the first pair out of order."""
    steps = -np.diff(values) if backwards else np.diff(values)
    if np.any(steps < 0):
        i = int(np.argmax(steps < 0))
        order, run = ("non-increasing", "a run backwards (t1 < t0)") if backwards else \
            ("non-decreasing", "a run forwards (t1 > t0)")
        raise ValueError(f"save_at must be sorted in the run's direction: {order} in {run}, got "
                         f"{values[i]} before {values[i + 1]}.")


def check_events(events, q0, p0, t0, args=None):
    """``events`` (an ``Event`` or a list of them) as a tuple, each checked (g called with H's
    ``args`` where it reads them); None stays None."""
    if events is None:
        return None
    if isinstance(events, Event):
        events = (events,)
    if not isinstance(events, (list, tuple)) or not events:
        raise TypeError(f"events must be a gj.Event or a non-empty list of them, got {type(events).__name__}.")
    for event in events:
        check_event(event, q0, p0, t0, args)
    return tuple(events)


def check_event(event, q0, p0, t0, args=None):
    if not isinstance(event, Event):
        raise TypeError(f"events must be a gj.Event or a list of them, got {type(event).__name__}.")
    # its fields were checked when it was built (``Event.__post_init__``); here g's output
    try:
        out = jax.eval_shape(lambda t, q, p: event_value(event.g, t, q, p, args), jnp.asarray(t0, q0.dtype), q0, p0)
    except TypeError as error:
        raise TypeError(f"Event.g could not be called as g(t, q, p): {error}") from error
    shape = getattr(out, "shape", None)
    if shape == () and getattr(out, "dtype", None) == bool:
        raise TypeError(f"Event.g ({_name(event.g)}) returns a boolean: an event is located where g changes "
                        "sign, to round-off, which a condition cannot tell. Return a number whose sign changes "
                        "there instead, e.g. q[0] - 1.0 for the condition q[0] > 1.0.")
    if shape != ():
        got = f"an array of shape {shape}" if shape is not None else f"{type(out).__name__}"
        raise ValueError(f"Event.g ({_name(event.g)}) must return a scalar, got {got} (q0 of shape "
                         f"{tuple(q0.shape)}): one number whose sign changes at the event, e.g. q[0] rather than q.")


def _name(f):
    """A function's name for a message, e.g. ``section`` or ``<lambda>``."""
    return getattr(f, "__name__", None) or repr(f)


def fixed_step_count(t0, t1, h):
    """``(n, h_last)``: the elements of size h from t0 to t1, the last shortened to land on t1
    (an end within 4 eps of t1 counts as t1: no sliver of an element)."""
    span = float(t1) - float(t0)
    n = max(1, math.ceil(span / float(h) * (1 - 4 * np.finfo(float).eps)))
    return n, span - (n - 1) * float(h)


def check_estimate(error_estimate):
    """``error_estimate`` as the march takes it: True, False or "full"."""
    if isinstance(error_estimate, str):
        if error_estimate != "full":
            raise ValueError(f'error_estimate must be True, False or "full", got {error_estimate!r}.')
        return "full"
    if not isinstance(error_estimate, (bool, np.bool_)):
        raise TypeError(f'error_estimate must be True, False or "full", got {type(error_estimate).__name__}.')
    return bool(error_estimate)
