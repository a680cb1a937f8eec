"""The loop of a run whose steps are not known in advance: one ``lax.while_loop`` over attempts.

Three step rules share it:

* ``PIDController``: each attempt solves one element of size h, estimates its error
  (``embedded_error``) and is accepted or rejected; h changes by the controller's factor
  either way. A failed solve or a non-finite state rejects the step, and ends the run only
  below ``dtmin``. The root finder is told that h varies (``Options.varying_steps``) and that
  its matrices serve few elements (``Options.short_lived_matrices``).
* ``TimeTransform``: the run integrates the Poincare-transformed K (``poincare``) in tau with
  the constant step h; the time is the state's coordinate ``clock``. The element that passes
  t1 is shortened in tau until it lands on t1 (Newton on its end time, whose tau-derivative
  is s), so the last step alone differs from h.
* a constant h (``save_at`` or ``events`` on a run of fixed steps): every attempt is accepted,
  the last one shortened to land on t1.

Each attempt (``_body``) solves an element (``_attempt``), has the step rule judge it (a
``Verdict``), records what the accepted element writes (saves, events, dense output, the
estimate, checkpoints) and counts. The carry is a ``Carry`` of named parts, each None where
the run does not ask for it; what stays fixed while the loop runs is a ``_Loop``.

Under ``vmap`` every member takes its own steps and finished members idle: the body leaves
their outputs as they are, and the loop goes on while any member does (``_any_member``); the
root finder folds the batch into one iteration as in ``march``. The loop is
forward-differentiable (``jax.jvp``); the step sizes are constants of the trajectory.
"""

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from . import _output
from ._controllers import (PIDController, TimeTransform, embedded_error, event_value, poincare, scaled_error,
                           user_args)
from ._defect import symplectic_field
from ._explicit import is_explicit
from ._march import (bind_args, compensated_add, continued, element, embedded_alpha, estimated_status, input_status,
                     peak_estimate, peak_start, peak_update, state_scale)
from ._solve import Status, initial_matrix, relative_error

_LANDING = 8  # shortened attempts of a time-transformed run's last element (Newton converges in 2-3)


@jax.custom_batching.custom_vmap
def _any_member(going):
    """``going``; under ``vmap``, whether any member is: the loop's condition stays unbatched, so
    that JAX does not select every carried buffer between a finished member's old and new values
    at every attempt (the body leaves a finished member's outputs as they are itself)."""
    return going


@_any_member.def_vmap
def _(axis_size, in_batched, going):
    return (jnp.any(going) if in_batched[0] else going), False


def problem(H, controller, q0, p0, t0, args):
    """``(H, q0, p0, args, s, clock)`` the loop solves: the user's, or with a ``TimeTransform``
    the Poincare-transformed problem on the extended state (``poincare``)."""
    if not isinstance(controller, TimeTransform):
        return H, q0, p0, args, None, None
    K, q0, p0, args, s = poincare(H, controller, q0, p0, t0, args)
    return K, q0, p0, args, s, q0.shape[0] - 1


def _crossing(event, g_a, g_b):
    up, down = (g_a < 0) & (g_b >= 0), (g_a > 0) & (g_b <= 0)
    return {0: up | down, 1: up, -1: down}[event.direction]


def polynomial_size(method, H_bound, q0, p0):
    """The coefficients m of the method's element polynomial (the embedded estimate's order)."""
    guess = method.initial_guess(q0, p0)
    return jax.eval_shape(lambda: method.polynomial(H_bound, q0, p0, guess, jnp.ones((), q0.dtype))).shape[0]


def first_step(method, H, q0, p0, t0, t1, args, controller):
    """A ``PIDController``'s first step where ``h=None``: ``initial_step`` for the method's
    embedded order, a constant of the trajectory (no derivative)."""
    H_bound = bind_args(H, args)
    z0 = jnp.concatenate([q0, p0])
    order = polynomial_size(method, H_bound, q0, p0)
    return initial_step(symplectic_field(H_bound), z0, order, controller, jnp.abs(t1 - t0))


def initial_step(field, z0, order, controller, span):
    """The first step of a controlled run where none is given: the starting step algorithm of
    Hairer, Norsett and Wanner (Solving ODEs I, Sec. II.4, as diffrax's), with the tolerances'
    scale ``atol + rtol |z0|`` and the embedded estimate's ``order``: h0 = 0.01 |z0| / |f(z0)|,
    one explicit Euler step to measure the field's change, then the h whose local error of
    that order meets 0.01, at most 100 h0 and the span."""
    rms = lambda x: jnp.sqrt(jnp.mean(x * x))
    scale = controller.atol + controller.rtol * jnp.abs(z0)
    f0 = field(z0)
    d0, d1 = rms(z0 / scale), rms(f0 / scale)
    h0 = jnp.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / jnp.where(d1 > 0, d1, 1.0))
    d2 = rms((field(z0 + h0 * f0) - f0) / scale) / h0
    largest = jnp.maximum(d1, d2)
    h1 = jnp.where(largest <= 1e-15, jnp.maximum(1e-6, 1e-3 * h0), (0.01 / jnp.where(largest > 0, largest, 1.0))
                   ** (1.0 / order))
    return jax.lax.stop_gradient(jnp.minimum(jnp.minimum(100 * h0, h1), span))




def element_count(t0, t1, h):
    """The elements of size h from t0 to t1, the last shortened (an end within 4 eps of t1 counts
    as t1: no sliver of an element); traced, as ``_span.fixed_step_count`` is for concrete times."""
    return jnp.maximum(1, jnp.ceil((t1 - t0) / h * (1 - 4 * jnp.finfo(jnp.result_type(h)).eps))).astype(jnp.int32)



# ---------------------------------------------------------------------------------------------
# the loop's carry: named parts, each None where the run does not ask for it


class Node(NamedTuple):
    """Where the run stands: the last accepted node's state ``z`` (``comp``: its compensated
    sum's remainder, ``_march.compensated_add``) and time ``t``, and what the next element
    continues from: the element before it (its start ``z_prev``, root ``Z_prev`` and length
    ``h_prev``, ``_march.continued``) and an explicit method's ``memo`` (the force at z,
    ``_explicit``; else None)."""

    z: jax.Array
    comp: jax.Array
    t: jax.Array
    z_prev: jax.Array
    Z_prev: jax.Array
    h_prev: jax.Array
    memo: object = None


class Control(NamedTuple):
    """The step rule's state: the next attempt's ``h``, the root finder's ``matrix`` and the
    rule's ``memory`` (a dict: the PID's last two errors, a landing's shortened attempts)."""

    h: jax.Array
    matrix: object
    memory: dict


class Counts(NamedTuple):
    """The run's counts (``Solution.stats``): accepted ``steps``, ``rejected`` ones and all
    ``attempts``; Newton iterations in ``total``, the ``most`` in one element and the ``trips``
    the batch ran; elements accepted ``lenient`` (stalled, ``Status``)."""

    steps: jax.Array
    rejected: jax.Array
    attempts: jax.Array
    total: jax.Array
    most: jax.Array
    trips: jax.Array
    lenient: jax.Array


class Record(NamedTuple):
    """The accepted elements: each one's length ``hs`` (row n: element n), the smallest and
    largest (``h_min``, ``h_max``), the largest local error ``estimate`` and ``relative`` error
    (``_solve.relative_error``; with
    ``estimate=True``, the ``peak`` elements where the embedded one peaks, ``_march.peak_update``;
    else None)."""

    hs: jax.Array
    h_min: jax.Array
    h_max: jax.Array
    estimate: jax.Array
    peak: dict = None
    relative: jax.Array = None


class Saves(NamedTuple):
    """The states at the save times (``_output.fill_saves``): ``states``, each one's element
    and alpha (``elements``, ``alphas``), and ``index``, the first time not yet written."""

    states: jax.Array
    elements: jax.Array
    alphas: jax.Array
    index: jax.Array


class Dense(NamedTuple):
    """Every accepted node's time and state (``node_t``, ``node_z``: inf and NaN past the last)
    and every element's refined polynomial ``W`` (None: the nodes alone, ``save_at="steps"``)."""

    node_t: jax.Array
    node_z: jax.Array
    W: jax.Array = None


class EventState(NamedTuple):
    """The events' (tuples, one entry per event): g at the last node ``g_a``; the crossings
    located, each event's buffer of times ``t``, states ``z``, elements ``n`` and places
    ``alpha`` in them; their ``count`` (one array) and the event that ``ended`` the run
    (-1: none)."""

    g_a: tuple
    t: tuple
    z: tuple
    n: tuple
    alpha: tuple
    count: jax.Array
    ended: jax.Array


class Checkpoints(NamedTuple):
    """What the derivatives read (``_adjoint``): ``nodes``, z, t and acc at every ``every``-th
    accepted node from the first, and ``kept``, the start z, t, acc and root Z of the accepted
    elements since the last of them (element n in row n mod every)."""

    nodes: dict
    kept: dict


class Carry(NamedTuple):
    """The loop's carry: where the run stands (``node``), the step rule's state (``control``),
    the ``status`` and whether the run is ``done``, its ``counts`` and ``record``, a sweep's
    diagnostics ``acc`` (``observe``), and what it keeps where asked (else None): the
    ``saves``, the ``dense`` output, the ``events`` and the ``checkpoints``."""

    node: Node
    control: Control
    status: jax.Array
    done: jax.Array
    counts: Counts
    record: Record
    acc: object = None
    saves: Saves = None
    dense: Dense = None
    events: EventState = None
    checkpoints: Checkpoints = None


class Attempt(NamedTuple):
    """One attempt at an element (``_attempt``): from the node ``z`` = (q, p) at ``t``, of length
    ``h`` (``last``: the element meant to end the run), its root ``Z``, increment ``dz``, end ``z1`` (``comp``),
    polynomial ``W``, whether it was ``solved`` and its ``status``, the embedded estimate (or
    None), the root finder's ``matrix`` and counts, the explicit ``memo``, and ``t_b``, where
    the element ends (the step rule's, ``Verdict``; None before it)."""

    q: jax.Array
    p: jax.Array
    z: jax.Array
    t: jax.Array
    h: jax.Array
    last: jax.Array
    Z: jax.Array
    dz: jax.Array
    z1: jax.Array
    comp: jax.Array
    W: jax.Array
    solved: jax.Array
    status: jax.Array
    embedded: jax.Array
    matrix: object
    iterations: jax.Array
    trips: jax.Array
    lenient: jax.Array
    memo: object = None
    t_b: jax.Array = None


class Verdict(NamedTuple):
    """A step rule's judgement of an attempt: ``accept`` it, whether that ``finished`` the run,
    where the element ends (``t_b``), the next attempt's ``h_next``, the ``status`` (nonzero:
    the run fails), whether the attempt counts as ``rejected``, and the rule's new ``memory``."""

    accept: jax.Array
    finished: jax.Array
    t_b: jax.Array
    h_next: jax.Array
    status: jax.Array
    rejected: jax.Array
    memory: dict


# ---------------------------------------------------------------------------------------------
# the step rules: ``rule(c, step) -> Verdict`` and the initial memory


def _pid_rule(controller, order, tiny, t1):
    """Error-per-step control: accept where the scaled embedded estimate is <= 1; h by the PID
    factor, clipped to [dtmin, dtmax] (as diffrax does); a step rejected at dtmin (or at the
    round-off of t) ends the run there (DTMIN): a step whose error exceeds the tolerance is not
    passed off as a result, unless ``force_dtmin`` asks for diffrax's rule, which accepts a
    solved step of h <= dtmin whatever its error. Every attempt not accepted counts as rejected,
    the last one of a run ended by DTMIN included."""

    @jax.named_scope("step_rule")
    def rule(c, step):
        memory = c.control.memory
        err = jnp.where(step.solved, scaled_error(step.embedded, step.z, step.z1, controller), jnp.inf)
        accept = err <= 1
        if controller.force_dtmin:
            accept = accept | (step.solved & (step.h <= controller.dtmin))
        # h_prev: the last accepted h
        h_ratio = jnp.where(c.counts.steps > 0, step.h / c.node.h_prev, jnp.nan) if controller.predictive else None
        h_next = jnp.clip(step.h * controller.next_factor(err, memory["err1"], memory["err2"], order, accept, h_ratio),
                          controller.dtmin, controller.dtmax)
        at_floor = ~accept & ((step.h <= controller.dtmin) | (h_next <= tiny))
        memory = dict(err1=jnp.where(accept, err, memory["err1"]), err2=jnp.where(accept, memory["err1"],
                                                                                   memory["err2"]))
        return Verdict(accept=accept, finished=accept & step.last, t_b=jnp.where(step.last, t1, step.t + step.h),
                       h_next=h_next, status=jnp.where(at_floor, Status.DTMIN, Status.SUCCESS), rejected=~accept,
                       memory=memory)

    return rule, dict(err1=jnp.ones((), tiny.dtype), err2=jnp.ones((), tiny.dtype))


def _transform_rule(s, clock, view, tiny, t1):
    """The time transformation: a constant step in tau; the element that passes t1 is shortened
    by Newton on its end time t_b(h), dt_b/dh = s(z1) (alpha beyond 1 extrapolates w). The
    attempts not accepted (the shortened ones before the landing, a failed one) count as
    rejected."""

    @jax.named_scope("step_rule")
    def rule(c, step):
        z1, h = step.z1, step.h
        t_b = z1[clock]
        s1 = s(*view(z1))
        positive = (s1 > 0) & jnp.isfinite(s1)
        status = jnp.where(step.solved & ~positive, Status.TIME_TRANSFORM, step.status)
        solved = step.solved & positive
        near = jnp.abs(t_b - t1) <= tiny
        landing = c.control.memory["landing"]
        shorten = solved & ~near & ((t_b > t1) | (landing > 0)) & (landing < _LANDING)
        accept = solved & ~shorten
        finished = accept & (near | (t_b > t1))
        return Verdict(accept=accept, finished=finished, t_b=jnp.where(finished, t1, t_b),
                       h_next=jnp.where(shorten, h * (1 + (t1 - t_b) / (h * s1)), h), status=status,
                       rejected=~accept, memory=dict(landing=landing + shorten))

    return rule, dict(landing=jnp.zeros((), jnp.int32))


def _constant_rule(t0, h, t1):
    """A constant h: element n spans [t0 + n h, t0 + (n + 1) h] (times by index, not by adding up
    steps, whose rounding would put t1 a sliver beyond the last element), the last one (by its
    index, ``element_count``, in ``_attempt``) shortened to land on t1."""

    @jax.named_scope("step_rule")
    def rule(c, step):
        return Verdict(accept=step.solved, finished=step.solved & step.last, h_next=c.control.h, status=step.status,
                       t_b=jnp.where(step.last, t1, t0 + (c.counts.steps + 1) * h), rejected=jnp.zeros((), bool),
                       memory={})

    return rule, {}


# the sub-intervals of an element on which each event's g is sampled: every sign change of g
# between samples is located (crossings closer together than 1/16 of an element are missed)
EVENT_SAMPLES = 16


def _event_crossings(events, gs, g_a, step, accept, clock, W):
    """Each event's g sampled at ``EVENT_SAMPLES`` sub-intervals of the accepted element's
    polynomial ``W`` (its ends: the nodes, g there ``g_a`` and at ``step.t_b``):
    ``[(values, crossing, g_b)]``, ``crossing`` the sub-intervals where g changes sign in the
    event's direction."""
    z, t, h = step.z, step.t, step.h
    alphas = jnp.linspace(0.0, 1.0, EVENT_SAMPLES + 1, dtype=z.dtype)
    inner = _output.on_polynomial(z, W, alphas[1:-1])
    inner_t = jax.vmap(lambda a: _output.time_at(z, W, a, t, h, clock))(alphas[1:-1])
    samples = []
    for event, g, g_a_k in zip(events, gs, g_a):
        g_b = g(step.t_b, step.z1)
        values = jnp.concatenate([g_a_k[None], jax.vmap(g)(inner_t, inner), g_b[None]])
        samples.append((values, accept & _crossing(event, values[:-1], values[1:]), g_b))
    return samples


def _events_update(events, gs, state, n, step, accept, clock, samples, W):
    """Locate every sign change of g on the element's refined polynomial ``W``
    (``_output.refined``), in order, by ``_output.locate``: where the samples of the element's
    own polynomial (``samples``, ``_event_crossings``) change sign, g is sampled again on ``W``,
    whose brackets the roots are located in (a root beside a sample point may lie on the other
    side of it on W). A terminal event's first crossing ends the run there; no later crossing of
    any event in the element counts. ``state``: the ``EventState`` before the element, ``n`` its
    index. Returns the new ``EventState`` (``ended`` as it was) and ``(alpha_stop, ended)``: where
    a terminal event ended the run (inf: none did) and which (-1: none)."""
    z, t, h = step.z, step.t, step.h
    dtype = z.dtype
    alphas = jnp.linspace(0.0, 1.0, EVENT_SAMPLES + 1, dtype=dtype)
    found = []
    for k, (event, g, (_, crossing, g_b)) in enumerate(zip(events, gs, samples)):
        f = lambda a, g=g: g(_output.time_at(z, W, a, t, h, clock), _output.on_polynomial(z, W, a[None])[0])

        def located(_, f=f, k=k, event=event, g_b=g_b):
            inner = jax.vmap(f)(alphas[1:-1])  # g on W, between the nodes' own values
            values = jnp.concatenate([state.g_a[k][None], inner, g_b[None]])
            crossing = accept & _crossing(event, values[:-1], values[1:])
            f_lo = jnp.concatenate([f(alphas[0])[None], inner])
            roots = jax.vmap(lambda lo, hi, f_lo: _output.locate(f, lo, hi, f_lo))(alphas[:-1], alphas[1:], f_lo)
            return jnp.where(crossing, roots, jnp.inf)

        roots = jax.lax.cond(jnp.any(crossing), located, lambda _: jnp.full(crossing.shape, jnp.inf, dtype), None)
        found.append((roots, g_b))
    firsts = jnp.stack([jnp.min(roots) if event.terminal else jnp.inf for event, (roots, _) in zip(events, found)])
    alpha_stop, ended = jnp.min(firsts), jnp.where(jnp.isfinite(jnp.min(firsts)), jnp.argmin(firsts), -1)
    fields = {k: [] for k in ("g_a", "t", "z", "n", "alpha", "count")}
    for k, (event, (roots, g_b)) in enumerate(zip(events, found)):
        valid = jnp.isfinite(roots) & (roots <= alpha_stop) & ((ended == k) | ~event.terminal | (roots < alpha_stop))
        slot = jnp.where(valid, state.count[k] + jnp.cumsum(valid) - 1, event.capacity)
        at = _output.on_polynomial(z, W, jnp.where(valid, roots, 0.0))
        times = jax.vmap(lambda a: _output.time_at(z, W, a, t, h, clock))(jnp.where(valid, roots, 0.0))
        write = lambda buffer, values: buffer.at[slot].set(values, mode="drop")
        fields["t"].append(write(state.t[k], times))
        fields["z"].append(write(state.z[k], at))
        fields["n"].append(write(state.n[k], jnp.broadcast_to(n, slot.shape)))
        fields["alpha"].append(write(state.alpha[k], roots))
        fields["count"].append(state.count[k] + jnp.sum(valid).astype(jnp.int32))
        fields["g_a"].append(jnp.where(accept, g_b, state.g_a[k]))
    fields = {k: tuple(v) for k, v in fields.items()}
    fields["count"] = jnp.stack(fields["count"])
    return state._replace(**fields), (alpha_stop, ended.astype(jnp.int32))


# ---------------------------------------------------------------------------------------------
# the carry at the start


def _start_saves(ts, t0, z0):
    """The save times at t0 written (``_output.AT_START``), the others not yet."""
    at_start = ts == t0
    first = jnp.where(at_start[:, None], z0[None, :], jnp.nan)
    places = jnp.where(at_start, _output.AT_START, _output.NOT_WRITTEN).astype(jnp.int32)
    return Saves(first, places, jnp.zeros_like(ts), jnp.sum(ts <= t0).astype(jnp.int32))


def _start_dense(dense, max_steps, m, t0, z0):
    """The node buffers from (t0, z0); with ``dense=True`` the polynomials' (``m``: their size)."""
    dtype = z0.dtype
    node_t = jnp.full((max_steps + 1,), jnp.inf, dtype).at[0].set(t0)
    node_z = jnp.full((max_steps + 1,) + z0.shape, jnp.nan, dtype).at[0].set(z0)
    W = jnp.zeros((max_steps, _output.refined_size(m)) + z0.shape, dtype) if dense is True else None
    return Dense(node_t, node_z, W)


def _start_events(events, gs, t0, z0):
    """Empty buffers of each event's ``capacity``; g at the start."""
    dtype = z0.dtype
    shapes = [(event.capacity,) for event in events]
    return EventState(g_a=tuple(g(t0, z0) for g in gs), t=tuple(jnp.full(s, jnp.nan, dtype) for s in shapes),
                      z=tuple(jnp.full(s + z0.shape, jnp.nan, dtype) for s in shapes),
                      n=tuple(jnp.full(s, -1, jnp.int32) for s in shapes),
                      alpha=tuple(jnp.full(s, jnp.nan, dtype) for s in shapes),
                      count=jnp.zeros((len(events),), jnp.int32), ended=jnp.full((), -1, jnp.int32))


def _start_checkpoints(every, max_steps, z0, guess, t0, acc0):
    """The first checkpoint, (z0, t0, acc0), and ``every`` rows for the elements' roots."""
    slots = max_steps // every + 1
    nodes = jax.tree.map(lambda x: jnp.zeros((slots,) + jnp.shape(x), jnp.result_type(x)).at[0].set(x),
                         dict(z=z0, t=t0, acc=acc0))
    kept = jax.tree.map(lambda x: jnp.zeros((every,) + jnp.shape(x), jnp.result_type(x)),
                        dict(z=z0, Z=guess, t=t0, acc=acc0))
    return Checkpoints(nodes, kept)


def _initial_carry(loop, z0, t0, h0, guess, acc0, memory, memo):
    """The carry before the first attempt (status: the input's, ``input_status``)."""
    dtype = z0.dtype
    q0, p0 = jnp.split(z0, 2)
    return Carry(
        node=Node(z=z0, comp=jnp.zeros_like(z0), t=t0, z_prev=z0, Z_prev=guess, h_prev=jnp.asarray(h0, dtype),
                  memo=memo),
        control=Control(h=jnp.asarray(h0, dtype), matrix=initial_matrix(guess, loop.options), memory=memory),
        status=input_status(q0, p0, h0), done=None, counts=Counts(*(jnp.zeros((), jnp.int32) for _ in Counts._fields)),
        record=Record(hs=jnp.zeros((loop.max_steps,), dtype), h_min=jnp.full((), jnp.inf, dtype),
                      h_max=jnp.zeros((), dtype), estimate=jnp.zeros((), dtype),
                      peak=peak_start(q0, p0, guess, h0) if loop.estimate is True else None,
                      relative=jnp.zeros((), dtype)),
        acc=None if loop.observe is None else acc0,
        saves=None if loop.ts is None else _start_saves(loop.ts, t0, z0),
        dense=_start_dense(loop.dense, loop.max_steps, loop.m, t0, z0) if loop.dense else None,
        events=None if loop.events is None else _start_events(loop.events, loop.gs, t0, z0),
        checkpoints=_start_checkpoints(loop.every, loop.max_steps, z0, guess, t0, acc0) if loop.every else None)


@dataclasses.dataclass(frozen=True)
class _Loop:
    """What stays as it is while the loop runs (``run`` builds it): the problem (``method``, the
    unbound ``H``, ``H_bound``, ``args``; ``m``: the size of
    its element polynomial), the root finder's ``options``, the step ``rule`` (``pid``: a
    ``PIDController``'s; ``count``: a constant h's elements, else None), ``explicit``: the
    elements in closed form (``_explicit``), the ``clock`` and the user's ``view`` of a state,
    ``t1``, ``max_steps``, and the outputs asked for (``run``'s ``ts``, ``events`` with their
    ``gs``, g(t, z) in the user's t, ``dense``, ``estimate``, ``observe`` and ``every``)."""

    method: object
    H: object
    H_bound: object
    args: object
    m: int
    options: object
    rule: object
    pid: bool
    count: object
    explicit: bool
    clock: object
    view: object
    t1: jax.Array
    max_steps: int
    ts: object
    events: object
    gs: object
    dense: object
    estimate: object
    observe: object
    every: object

    @property
    def terminal(self):
        return self.events is not None and any(event.terminal for event in self.events)


# ---------------------------------------------------------------------------------------------
# the loop's body: an attempt, the rule's verdict on it, what it records, the counts


def _attempt(loop, c, active):
    """Solve the element from the run's node: of the rule's h, the last one shortened to land on
    t1 (a time-transformed run's lands in ``_transform_rule``); its root from the last accepted
    element's polynomial continued over it (the root finder falls back on the constant state
    where that is worse), or in closed form (``_explicit``, from the force at the node, carried
    from the last accepted element), and its embedded estimate where the rule or the run's
    estimate reads it."""
    method, H_bound, node = loop.method, loop.H_bound, c.node
    z, t = node.z, node.t
    q, p = jnp.split(z, 2)
    if loop.count is not None:  # a constant h: the last element by its index (``_constant_rule``)
        last = c.counts.steps + 1 >= loop.count
    else:
        last = t + c.control.h * (1 + 4 * jnp.finfo(z.dtype).eps) >= loop.t1
    h = jnp.where(last & (loop.clock is None), loop.t1 - t, c.control.h)
    if loop.explicit:
        predicted = constant = None
    else:
        constant = method.initial_guess(q, p)
        previous = (*jnp.split(node.z_prev, 2), node.Z_prev)
        predicted = jnp.where(c.counts.steps > 0, continued(method, q, p, previous, h / node.h_prev), constant)
    Z, dz, memo, matrix, iterations, status, trips, lenient = element(
        method, loop.H, q, p, h, loop.args, loop.options, predicted=predicted, constant=constant,
        matrix=c.control.matrix, scale=state_scale(z), skip=~active, first=c.counts.steps == 0, memo=node.memo,
        closed_form=loop.explicit)
    # an explicit element's state is summed plainly (``_march.explicit_start``)
    z1, comp = (z + dz, node.comp) if loop.explicit else compensated_add(z, dz, node.comp)
    W = method.polynomial_with(H_bound, q, p, Z, h, dz)
    solved = (status == Status.SUCCESS) & jnp.all(jnp.isfinite(z1))
    status = jnp.where((status == Status.SUCCESS) & ~solved, Status.NONFINITE, status)
    # the embedded estimate, shared by the step rule and the run's estimate (``peak_update``)
    # an explicit element's force at its end (``_explicit``) where the estimate only ranks
    # elements; a controller's steps take the field evaluated anew, as an iterated run's
    field = method.explicit_field(H_bound, *jnp.split(z1, 2), memo) if loop.explicit and not loop.pid else None
    embedded = (embedded_error(H_bound, q, p, W, h, dz, field, embedded_alpha(method))
                if loop.pid or loop.estimate is True else None)
    return Attempt(q=q, p=p, z=z, t=t, h=h, last=last, Z=Z, dz=dz, z1=z1, comp=comp, W=W, solved=solved, status=status,
                   embedded=embedded, matrix=matrix, iterations=iterations, trips=trips, lenient=lenient, memo=memo)


def _control(c, step, verdict, active):
    """The step rule's state after the attempt (a finished member's as it was)."""
    keep = lambda new, old: jnp.where(active, new, old)
    return Control(h=keep(verdict.h_next, c.control.h), matrix=step.matrix,
                   memory=jax.tree.map(keep, verdict.memory, c.control.memory))


@jax.named_scope("dense")
def _refined(loop, c, step, accept, samples):
    """Between the nodes, the element's polynomial refined to the nodes' accuracy
    (``_output.refined``) where a save time or an event lies in the accepted element (every
    element for dense output; elsewhere padded to its size); None where nothing reads it."""
    if not (loop.dense is True or loop.ts is not None or loop.events is not None):
        return None
    refine = lambda W: _output.refined(loop.method, loop.H_bound, step.z, step.z1, W, step.h)
    if loop.dense is True:
        return refine(step.W)
    wanted = jnp.zeros((), bool)
    if loop.ts is not None:  # the next save time falls in the element
        ts, index = loop.ts, c.saves.index
        next_save = ts[jnp.minimum(index, ts.shape[0] - 1)]
        wanted = (index < ts.shape[0]) & (next_save <= step.t_b)
    if loop.events is not None:
        wanted = wanted | jnp.any(jnp.stack([jnp.any(crossing) for _, crossing, _ in samples]))
    return jax.lax.cond(accept & wanted, refine, _output.padded, step.W)


@jax.named_scope("events")
def _events(loop, c, step, accept, samples, W, end):
    """The events located in the accepted element (``_events_update``) and where a terminal one
    ended the run: ``(events, end, stop)``, ``end`` the node the element ends at (where a
    terminal event ended the run, there), ``stop`` = ``(hit, alpha)``: whether one did, and where
    (None without a terminal event)."""
    events, (alpha_stop, ended) = _events_update(loop.events, loop.gs, c.events, c.counts.steps, step, accept,
                                                 loop.clock, samples, W)
    events = events._replace(ended=jnp.where(accept, ended, c.events.ended))
    if not loop.terminal:
        return events, end, None
    hit = accept & (ended >= 0)
    at = jnp.where(hit, alpha_stop, 0.0)
    stop = end._replace(z=_output.on_polynomial(step.z, W, at[None])[0], comp=jnp.zeros_like(step.comp),
                        t=_output.time_at(step.z, W, at, step.t, step.h, loop.clock))
    return events, jax.tree.map(lambda a, b: jnp.where(hit, a, b), stop, end), (hit, at)


@jax.named_scope("save_at")
def _saves(loop, c, step, accept, end, W):
    """The save times in the accepted element written (``_output.fill_saves``); a rejected step
    writes nothing: its end time is -inf."""
    saves = c.saves
    t_end = jnp.where(accept, end.t, -jnp.inf)
    (states, elements, alphas), index = _output.fill_saves(
        saves[:3], saves.index, loop.ts, (step.z, W, step.t, t_end, step.h, loop.clock), end.z, c.counts.steps)
    return Saves(states, elements, alphas, index)


def _dense(loop, c, n, end, W, stop):
    """The accepted element's end node in row n + 1 and, with ``dense=True``, its polynomial in
    row n (where a terminal event ended the run in it, on [t_n, t*], ``_output.truncated``)."""
    dense = c.dense
    node_t = dense.node_t.at[n + 1].set(end.t, mode="drop")
    node_z = dense.node_z.at[n + 1].set(end.z, mode="drop")
    if loop.dense is not True:
        return Dense(node_t, node_z)
    if stop is not None:
        W = jax.lax.cond(stop[0], _output.truncated, lambda W, _: W, W, stop[1])
    return Dense(node_t, node_z, dense.W.at[n].set(W, mode="drop"))


@jax.named_scope("estimate")
def _local_error(loop, c, step, accept):
    """``(local, peak)``: with ``estimate="full"`` the element's local error (``local_error``);
    with True the ``peak`` elements updated by its embedded estimate (``peak_update``)."""
    local, peak = jnp.nan, c.record.peak
    if loop.estimate == "full":
        frozen = jax.lax.stop_gradient((step.q, step.p, step.Z, step.h, loop.args))
        local = jax.lax.stop_gradient(loop.method.local_error(bind_args(loop.H, frozen[4]), *frozen[:4]))
    elif loop.estimate:
        size = jax.lax.stop_gradient(jnp.max(jnp.abs(step.embedded)))
        peak = peak_update(peak, size, step.q, step.p, step.Z, step.h, step.dz, accept)
    return local, peak


@jax.named_scope("checkpoints")
def _checkpoints(loop, c, step, accept, end, acc):
    """The accepted node whose index is a multiple of ``every`` (z, t and the new ``acc``), and the
    element's root (start z, Z, t and acc) in row n mod every."""
    every, steps = loop.every, c.counts.steps
    index = steps + 1
    slot = jnp.where(accept & (index % every == 0), index // every, loop.max_steps + 1)
    node = dict(z=end.z, t=end.t, acc=acc)
    nodes = jax.tree.map(lambda a, x: a.at[slot].set(x, mode="drop"), c.checkpoints.nodes, node)
    row = jnp.where(accept, steps % every, every)
    root = dict(z=step.z, Z=jax.lax.stop_gradient(step.Z), t=step.t, acc=c.acc)
    return Checkpoints(nodes, jax.tree.map(lambda a, x: a.at[row].set(x, mode="drop"), c.checkpoints.kept, root))


def _counts(c, step, verdict, active, accept):
    counts, on = c.counts, lambda x: x * active
    return Counts(steps=counts.steps + accept, rejected=counts.rejected + (active & verdict.rejected),
                  attempts=counts.attempts + active, total=counts.total + on(step.iterations),
                  most=jnp.maximum(counts.most, on(step.iterations)), trips=counts.trips + on(step.trips),
                  lenient=counts.lenient + (accept & (step.lenient > 0)))


def _body(loop, c):
    """One attempt: solve the element (``_attempt``), the step rule's verdict on it, what the
    accepted element records (events, saves, dense output, the estimate, checkpoints; a
    rejected one writes past the buffers), and the run's counts and status. A finished member
    (under ``vmap``) attempts on and leaves everything as it was."""
    active = ~c.done
    step = _attempt(loop, c, active)
    verdict = loop.rule(c, step)
    accept, finished = verdict.accept & active, verdict.finished
    fail = active & (verdict.status != Status.SUCCESS)
    step = step._replace(t_b=verdict.t_b)
    end = Node(z=step.z1, comp=step.comp, t=verdict.t_b, z_prev=step.z, Z_prev=step.Z, h_prev=step.h,
               memo=step.memo)
    samples = None if loop.events is None else _event_crossings(loop.events, loop.gs, c.events.g_a, step, accept,
                                                                loop.clock, step.W)
    W = _refined(loop, c, step, accept, samples)
    events, stop = c.events, None
    if loop.events is not None:
        events, end, stop = _events(loop, c, step, accept, samples, W, end)
        if stop is not None:
            finished = finished | stop[0]
    saves = None if loop.ts is None else _saves(loop, c, step, accept, end, W)
    # written in place; a rejected step's index lies past the buffers
    n = jnp.where(accept, c.counts.steps, loop.max_steps + 1)
    hs = c.record.hs.at[n].set(step.h, mode="drop")
    dense = _dense(loop, c, n, end, W, stop) if loop.dense else None
    local, peak = _local_error(loop, c, step, accept)
    node = jax.tree.map(lambda a, b: jnp.where(accept, a, b), end, c.node)
    acc = None
    if loop.observe is not None:
        acc = jax.tree.map(lambda a, b: jnp.where(accept, b, a), c.acc, loop.observe(c.acc, *loop.view(end.z)))
    checkpoints = _checkpoints(loop, c, step, accept, end, acc) if loop.every else None
    counts = _counts(c, step, verdict, active, accept)
    out_of_steps = active & ~finished & (counts.attempts >= loop.max_steps) & ~fail
    status = jnp.where(fail, verdict.status, jnp.where(out_of_steps, Status.MAX_STEPS, c.status)).astype(jnp.int32)
    record = c.record
    record = Record(hs=hs, h_min=jnp.where(accept, jnp.minimum(record.h_min, step.h), record.h_min),
                    h_max=jnp.where(accept, jnp.maximum(record.h_max, step.h), record.h_max),
                    estimate=jnp.where(accept, jnp.fmax(record.estimate, local), record.estimate), peak=peak,
                    relative=jnp.where(accept, jnp.maximum(record.relative, relative_error(local, step.z)),
                                       record.relative))
    return Carry(node=node, control=_control(c, step, verdict, active), status=status,
                 done=c.done | fail | (active & finished) | out_of_steps, counts=counts, record=record, acc=acc,
                 saves=saves, dense=dense, events=events, checkpoints=checkpoints)


def run(method, H, q0, p0, t0, t1, h0, args, controller, *, options, max_steps, ts=None, dense=False,
        events=None, estimate=False, clock=None, s=None, observe=None, acc0=None, every=None, sigma=1):
    """Integrate from t0 to t1 with the step rule ``controller`` (None: the constant h0).

    Args:
        H: the Hamiltonian the method solves (K for a time-transformed run), unbound.
        q0, p0: its initial state (extended by (t, p_t) for a time-transformed run).
        clock: index of the time coordinate in z = (q, p), or None (time is t0 + sum h).
        s: the bound step density of a time-transformed run (checked at every node).
        ts: sorted save times, or None.
        estimate: the largest local error of the accepted elements, as in ``march``: "full",
            True (the full estimate where the embedded one peaks) or False (NaN).
        observe, acc0: ``(acc, q, p) -> acc`` folded over the accepted states (``march``).
        dense: keep every accepted node's time and state (``Dense``) and, True, every
            element's polynomial; "nodes": the nodes alone (``save_at="steps"``).
        sigma: the run's direction: it runs forwards in tau = sigma t (``_integrate._directed``),
            and its events' g take t (``_output.directed``).
        every: keep the ``Checkpoints`` for the derivatives (``_adjoint``) every ``every``
            accepted nodes; None: none.
    Returns:
        the final ``Carry``: where the run ended (``node``), its ``status``, ``counts`` and
        ``record`` (the accepted steps, the estimate), and the saves, the dense output, the
        events (with each crossing's element and place) and the checkpoints where asked.
    """
    H_bound = bind_args(H, args)
    view = lambda z: _output.user_view(z, clock)
    z0 = jnp.concatenate([q0, p0])
    dtype = z0.dtype
    guess = method.initial_guess(q0, p0)
    m = polynomial_size(method, H_bound, q0, p0)
    t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)
    # a step below tiny does not move t (an infinite t1: run until a terminal event, at most max_steps)
    tiny = 16 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(t0), jnp.where(jnp.isfinite(t1), jnp.abs(t1), 0.0))
    pid, count = isinstance(controller, PIDController), None
    if pid:
        rule, memory = _pid_rule(controller, m, tiny, t1)
        h0 = jnp.clip(h0, controller.dtmin, controller.dtmax)
        options = dataclasses.replace(options, varying_steps=True, short_lived_matrices=True)
    elif clock is not None:
        rule, memory = _transform_rule(s, clock, view, tiny, t1)
        options = dataclasses.replace(options, short_lived_matrices=True)
    else:
        count = element_count(t0, t1, h0)
        rule, memory = _constant_rule(t0, h0, t1)
    reads = user_args(args, clock, sigma) if events is not None else None
    gs = None if events is None else tuple(
        lambda t, z, g=event.g: event_value(g, _output.directed(t, sigma), *view(z), reads) for event in events)
    # the closed form where the method has one for H (``_explicit``); a time-transformed run
    # solves K = s (H + p_t), whose structure is not H's: it iterates
    explicit = is_explicit(method) and clock is None
    loop = _Loop(method=method, H=H, H_bound=H_bound, args=args, m=m, options=options, rule=rule, pid=pid,
                 count=count, explicit=explicit, clock=clock, view=view, t1=t1, max_steps=max_steps, ts=ts,
                 events=events, gs=gs, dense=dense, estimate=estimate, observe=observe, every=every)
    memo = method.explicit_start(H_bound, q0, p0) if explicit else None
    c = _initial_carry(loop, z0, t0, h0, guess, acc0, memory, memo)
    # a run arrives forwards in its time (``_integrate._directed``): a traced t1 < t0 that did not (a
    # Lagrangian's) is bad input, and so is a traced save time outside [t0, t1], or out of the run's
    # order where that was not known before it ran (concrete ones raise before)
    valid = (t1 >= t0) if ts is None else (t1 >= t0) & jnp.all((ts >= t0) & (ts <= t1))
    if ts is not None and not isinstance(sigma, int):
        valid = valid & jnp.all(ts[1:] >= ts[:-1])
    status = jnp.where(valid, c.status, Status.INVALID_INPUT).astype(jnp.int32)
    if s is not None:
        s0 = s(*view(z0))
        status = jnp.where((s0 > 0) & jnp.isfinite(s0), status, Status.TIME_TRANSFORM).astype(jnp.int32)
    c = c._replace(status=status, done=status != Status.SUCCESS)
    c = jax.lax.while_loop(lambda c: _any_member(~c.done), functools.partial(_body, loop), c)
    if estimate is True:
        largest, relative = peak_estimate(method, H_bound, c.record.peak)
        c = c._replace(record=c.record._replace(estimate=largest, relative=relative))
    return c._replace(status=estimated_status(method, estimate, c.status, c.record.relative))
