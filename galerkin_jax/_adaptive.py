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

Under ``vmap`` every member takes its own steps and finished members idle: the body leaves
their outputs as they are, and the loop goes on while any member does (``_any_member``); the
root finder folds the batch into one iteration as in ``march``. The loop is
forward-differentiable (``jax.jvp``); the step sizes are constants of the trajectory.
"""

import dataclasses

import jax
import jax.numpy as jnp

from . import _output
from ._controllers import PIDController, TimeTransform, embedded_error, poincare, scaled_error
from ._defect import symplectic_field
from ._explicit import is_explicit
from ._march import (bind_args, compensated_add, continued, element_residual, input_status, peak_estimate, peak_start,
                     peak_update, state_scale)
from ._solve import Status, initial_matrix, solve

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


def _pid_rule(controller, order, tiny):
    """Error-per-step control: accept where the scaled embedded estimate is <= 1; h by the PID
    factor, clipped to [dtmin, dtmax] (as diffrax does); a step rejected at dtmin (or at the
    round-off of t) ends the run there (DTMIN): a step whose error exceeds the tolerance is not
    passed off as a result, unless ``force_dtmin`` asks for diffrax's rule, which accepts a
    solved step of h <= dtmin whatever its error. Every attempt not accepted counts as rejected,
    the last one of a run ended by DTMIN included."""

    def rule(c, step):
        err = jnp.where(step["solved"], scaled_error(step["embedded"], step["z"], step["z1"], controller), jnp.inf)
        accept = err <= 1
        if controller.force_dtmin:
            accept = accept | (step["solved"] & (step["h"] <= controller.dtmin))
        # h_prev: the last accepted h
        h_ratio = jnp.where(c["steps"] > 0, step["h"] / c["h_prev"], jnp.nan) if controller.predictive else None
        h_next = jnp.clip(step["h"] * controller.next_factor(err, c["err1"], c["err2"], order, accept, h_ratio),
                          controller.dtmin, controller.dtmax)
        at_floor = ~accept & ((step["h"] <= controller.dtmin) | (h_next <= tiny))
        memory = dict(err1=jnp.where(accept, err, c["err1"]), err2=jnp.where(accept, c["err1"], c["err2"]))
        return dict(accept=accept, finished=accept & step["last"], t_b=jnp.where(step["last"], step["t1"],
                    step["t"] + step["h"]), h_next=h_next, status=jnp.where(at_floor, Status.DTMIN, Status.SUCCESS),
                    rejected=~accept, memory=memory)

    return rule, dict(err1=jnp.ones((), tiny.dtype), err2=jnp.ones((), tiny.dtype))


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


def _transform_rule(s, clock, view, tiny):
    """The time transformation: a constant step in tau; the element that passes t1 is shortened
    by Newton on its end time t_b(h), dt_b/dh = s(z1) (alpha beyond 1 extrapolates w). The
    attempts not accepted (the shortened ones before the landing, a failed one) count as
    rejected."""

    def rule(c, step):
        z1, h, t1 = step["z1"], step["h"], step["t1"]
        t_b = z1[clock]
        s1 = s(*view(z1))
        positive = (s1 > 0) & jnp.isfinite(s1)
        status = jnp.where(step["solved"] & ~positive, Status.TIME_TRANSFORM, step["status"])
        solved = step["solved"] & positive
        near = jnp.abs(t_b - t1) <= tiny
        landing = c["landing"]
        shorten = solved & ~near & ((t_b > t1) | (landing > 0)) & (landing < _LANDING)
        accept = solved & ~shorten
        finished = accept & (near | (t_b > t1))
        return dict(accept=accept, finished=finished, t_b=jnp.where(finished, t1, t_b),
                    h_next=jnp.where(shorten, h * (1 + (t1 - t_b) / (h * s1)), h), status=status,
                    rejected=~accept, memory=dict(landing=landing + shorten))

    return rule, dict(landing=jnp.zeros((), jnp.int32))


def _constant_rule(t0, h):
    """A constant h: element n spans [t0 + n h, t0 + (n + 1) h] (times by index, not by adding up
    steps, whose rounding would put t1 a sliver beyond the last element), the last one (by its
    index, ``element_count``, in ``run``) shortened to land on t1."""

    def rule(c, step):
        return dict(accept=step["solved"], finished=step["solved"] & step["last"], h_next=c["h"],
                    status=step["status"], t_b=jnp.where(step["last"], step["t1"], t0 + (c["steps"] + 1) * h),
                    rejected=jnp.zeros((), bool), memory={})

    return rule


def element_count(t0, t1, h):
    """The elements of size h from t0 to t1, the last shortened (an end within 4 eps of t1 counts
    as t1: no sliver of an element); traced, as ``_span.fixed_step_count`` is for concrete times."""
    return jnp.maximum(1, jnp.ceil((t1 - t0) / h * (1 - 4 * jnp.finfo(jnp.result_type(h)).eps))).astype(jnp.int32)


# the sub-intervals of an element on which each event's g is sampled: every sign change of g
# between samples is located (crossings closer together than 1/16 of an element are missed)
EVENT_SAMPLES = 16


def _event_crossings(events, gs, c, step, accept, clock, W):
    """Each event's g sampled at ``EVENT_SAMPLES`` sub-intervals of the accepted element's
    polynomial ``W`` (its ends: the nodes): ``[(values, crossing, g_b)]``, ``crossing`` the
    sub-intervals where g changes sign in the event's direction."""
    z, t, h = step["z"], step["t"], step["h"]
    alphas = jnp.linspace(0.0, 1.0, EVENT_SAMPLES + 1, dtype=z.dtype)
    inner = _output.on_polynomial(z, W, alphas[1:-1])
    inner_t = jax.vmap(lambda a: _output.time_at(z, W, a, t, h, clock))(alphas[1:-1])
    samples = []
    for event, g, g_a in zip(events, gs, c["g_a"]):
        g_b = g(step["t_b"], step["z1"])
        values = jnp.concatenate([g_a[None], jax.vmap(g)(inner_t, inner), g_b[None]])
        samples.append((values, accept & _crossing(event, values[:-1], values[1:]), g_b))
    return samples


def _events_update(events, gs, c, step, accept, clock, samples, W):
    """Locate every sign change of g on the element's refined polynomial ``W``
    (``_output.refined``), in order, by ``_output.locate``: where the samples of the element's
    own polynomial (``samples``, ``_event_crossings``) change sign, g is sampled again on ``W``,
    whose brackets the roots are located in (a root beside a sample point may lie on the other
    side of it on W). A terminal event's first crossing ends the run there; no later crossing of
    any event in the element counts. Returns the carry's event fields and ``(alpha_stop, ended)``: where a terminal event
    ended the run (inf: none did) and which (-1: none)."""
    z, t, h = step["z"], step["t"], step["h"]
    dtype = z.dtype
    alphas = jnp.linspace(0.0, 1.0, EVENT_SAMPLES + 1, dtype=dtype)
    found = []
    for k, (event, g, (_, crossing, g_b)) in enumerate(zip(events, gs, samples)):
        f = lambda a, g=g: g(_output.time_at(z, W, a, t, h, clock), _output.on_polynomial(z, W, a[None])[0])

        def located(_, f=f, k=k, event=event, g_b=g_b):
            inner = jax.vmap(f)(alphas[1:-1])  # g on W, between the nodes' own values
            values = jnp.concatenate([c["g_a"][k][None], inner, g_b[None]])
            crossing = accept & _crossing(event, values[:-1], values[1:])
            f_lo = jnp.concatenate([f(alphas[0])[None], inner])
            roots = jax.vmap(lambda lo, hi, f_lo: _output.locate(f, lo, hi, f_lo))(alphas[:-1], alphas[1:], f_lo)
            return jnp.where(crossing, roots, jnp.inf)

        roots = jax.lax.cond(jnp.any(crossing), located, lambda _: jnp.full(crossing.shape, jnp.inf, dtype), None)
        found.append((roots, g_b))
    firsts = jnp.stack([jnp.min(roots) if event.terminal else jnp.inf for event, (roots, _) in zip(events, found)])
    alpha_stop, ended = jnp.min(firsts), jnp.where(jnp.isfinite(jnp.min(firsts)), jnp.argmin(firsts), -1)
    fields = {k: [] for k in ("g_a", "ev_t", "ev_z", "ev_n", "ev_alpha", "ev_count")}
    for k, (event, (roots, g_b)) in enumerate(zip(events, found)):
        valid = jnp.isfinite(roots) & (roots <= alpha_stop) & ((ended == k) | ~event.terminal | (roots < alpha_stop))
        slot = jnp.where(valid, c["ev_count"][k] + jnp.cumsum(valid) - 1, event.capacity)
        at = _output.on_polynomial(z, W, jnp.where(valid, roots, 0.0))
        times = jax.vmap(lambda a: _output.time_at(z, W, a, t, h, clock))(jnp.where(valid, roots, 0.0))
        write = lambda buffer, values: buffer.at[slot].set(values, mode="drop")
        fields["ev_t"].append(write(c["ev_t"][k], times))
        fields["ev_z"].append(write(c["ev_z"][k], at))
        fields["ev_n"].append(write(c["ev_n"][k], jnp.broadcast_to(c["steps"], slot.shape)))
        fields["ev_alpha"].append(write(c["ev_alpha"][k], roots))
        fields["ev_count"].append(c["ev_count"][k] + jnp.sum(valid).astype(jnp.int32))
        fields["g_a"].append(jnp.where(accept, g_b, c["g_a"][k]))
    fields = {k: tuple(v) for k, v in fields.items()}
    fields["ev_count"] = jnp.stack(fields["ev_count"])
    return fields, (alpha_stop, ended.astype(jnp.int32))


def _initial_carry(method, z0, t0, h0, guess, options, max_steps, m, ts, dense, events, gs, observe, acc0, estimate,
                   every):
    dtype = z0.dtype
    q0, p0 = jnp.split(z0, 2)
    c = dict(z=z0, comp=jnp.zeros_like(z0), t=t0, z_prev=z0, Z_prev=guess, hs=jnp.zeros((max_steps,), dtype),
             h=jnp.asarray(h0, dtype), h_prev=jnp.asarray(h0, dtype), matrix=initial_matrix(guess, options),
             status=input_status(q0, p0, h0), h_min=jnp.full((), jnp.inf, dtype), h_max=jnp.zeros((), dtype),
             estimate=jnp.zeros((), dtype),
             **{k: jnp.zeros((), jnp.int32) for k in ("steps", "rejected", "attempts", "total", "most", "trips",
                                                      "lenient")})
    if observe is not None:
        c["acc"] = acc0
    if ts is not None:
        at_start = ts == t0
        first = jnp.where(at_start[:, None], z0[None, :], jnp.nan)
        places = jnp.where(at_start, _output.AT_START, _output.NOT_WRITTEN).astype(jnp.int32)
        c["saved"], c["index"] = (first, places, jnp.zeros_like(ts)), jnp.sum(ts <= t0).astype(jnp.int32)
    if dense:
        c["node_t"] = jnp.full((max_steps + 1,), jnp.inf, dtype).at[0].set(t0)
        c["node_z"] = jnp.full((max_steps + 1,) + z0.shape, jnp.nan, dtype).at[0].set(z0)
    if dense is True:
        c["W"] = jnp.zeros((max_steps, _output.refined_size(m)) + z0.shape, dtype)
    if events is not None:
        shapes = [(event.capacity,) for event in events]
        c.update(g_a=tuple(g(t0, z0) for g in gs), ev_t=tuple(jnp.full(s, jnp.nan, dtype) for s in shapes),
                 ev_z=tuple(jnp.full(s + z0.shape, jnp.nan, dtype) for s in shapes),
                 ev_n=tuple(jnp.full(s, -1, jnp.int32) for s in shapes),
                 ev_alpha=tuple(jnp.full(s, jnp.nan, dtype) for s in shapes),
                 ev_count=jnp.zeros((len(events),), jnp.int32), ended=jnp.full((), -1, jnp.int32))
    if estimate is True:
        c["peak"] = peak_start(q0, p0, guess, h0)
    if every:
        slots = max_steps // every + 1
        c["checkpoints"] = jax.tree.map(lambda x: jnp.zeros((slots,) + jnp.shape(x), jnp.result_type(x)).at[0].set(x),
                                        dict(z=z0, t=t0, acc=acc0))
        c["kept"] = jax.tree.map(lambda x: jnp.zeros((every,) + jnp.shape(x), jnp.result_type(x)),
                                 dict(z=z0, Z=guess, t=t0, acc=acc0))
    return c


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
        dense: keep every accepted node's time and state (``node_t``, ``node_z``) and, True,
            every element's polynomial (``W``); "nodes": the nodes alone (``save_at="steps"``).
        sigma: the run's direction: it runs forwards in tau = sigma t (``_integrate._directed``),
            and its events' g take t (``_output.directed``).
        every: keep ``checkpoints`` (z, t and acc at every ``every``-th accepted node, from the
            first) and ``kept``, the start z, t, acc and root Z of the accepted elements since
            the last checkpoint (element n in row n mod every), for the derivatives
            (``_adjoint``); None: neither.
    Returns:
        the final carry, a dict: ``t``, ``z``, ``status``, counts, ``hs`` (the accepted steps),
        ``h_min``, ``h_max``, ``estimate``, and ``saved``, the dense buffers, the events (with
        each row's element ``ev_n`` and place ``ev_alpha``) and the checkpoints where asked.
    """
    fn = element_residual(H, options.solver.sweep_dimension)
    H_bound = bind_args(H, args)
    view = lambda z: _output.user_view(z, clock)
    z0 = jnp.concatenate([q0, p0])
    dtype = z0.dtype
    guess = method.initial_guess(q0, p0)
    m = polynomial_size(method, H_bound, q0, p0)
    t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)
    tiny = 16 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(t0), jnp.abs(t1))
    pid = isinstance(controller, PIDController)
    if pid:
        rule, memory = _pid_rule(controller, m, tiny)
        h0 = jnp.clip(h0, controller.dtmin, controller.dtmax)
        options = dataclasses.replace(options, varying_steps=True, short_lived_matrices=True)
    elif clock is not None:
        rule, memory = _transform_rule(s, clock, view, tiny)
        options = dataclasses.replace(options, short_lived_matrices=True)
    else:
        count = element_count(t0, t1, h0)
        rule, memory = _constant_rule(t0, h0), {}
    gs = None if events is None else tuple(lambda t, z, g=event.g: g(_output.directed(t, sigma), *view(z))
                                           for event in events)
    c = _initial_carry(method, z0, t0, h0, guess, options, max_steps, m, ts, dense, events, gs, observe, acc0,
                       estimate, every)
    c.update(memory)
    # a run arrives forwards in its time (``_integrate._directed``): a traced t1 < t0 that did not (a
    # Lagrangian's) is bad input, and so is a traced save time outside [t0, t1], or out of the run's
    # order where that was not known before it ran (concrete ones raise before)
    valid = (t1 > t0) if ts is None else (t1 > t0) & jnp.all((ts >= t0) & (ts <= t1))
    if ts is not None and not isinstance(sigma, int):
        valid = valid & jnp.all(ts[1:] >= ts[:-1])
    c["status"] = jnp.where(valid, c["status"], Status.INVALID_INPUT).astype(jnp.int32)
    if s is not None:
        s0 = s(*view(z0))
        c["status"] = jnp.where((s0 > 0) & jnp.isfinite(s0), c["status"], Status.TIME_TRANSFORM).astype(jnp.int32)
    c["done"] = c["status"] != Status.SUCCESS
    # the closed form where the method has one for H (``_explicit``); a time-transformed run
    # solves K = s (H + p_t), whose structure is not H's: it iterates
    explicit = is_explicit(method) and clock is None
    if explicit:
        c["memo"] = method.explicit_start(H_bound, q0, p0)

    def body(c):
        active = ~c["done"]
        z, t = c["z"], c["t"]
        q, p = jnp.split(z, 2)
        if controller is None:  # a constant h: the last element by its index (``_constant_rule``)
            last = c["steps"] + 1 >= count
        else:
            last = t + c["h"] * (1 + 4 * jnp.finfo(dtype).eps) >= t1
        h = jnp.where(last & (clock is None), t1 - t, c["h"])
        if explicit:  # closed form (``_explicit``), from the force at z, carried from the last accepted element
            Z, dz, memo = method.explicit(H_bound, q, p, h, c["memo"])
            z1, comp = z + jnp.concatenate(dz), c["comp"]
            matrix, iterations, trips, lenient = c["matrix"], 0, 0, 0
            status = jnp.int32(Status.SUCCESS)
        else:
            # the last accepted element's polynomial continued over this one (the root finder
            # falls back on the constant state where that is worse)
            constant = method.initial_guess(q, p)
            previous = (*jnp.split(c["z_prev"], 2), c["Z_prev"])
            predicted = jnp.where(c["steps"] > 0, continued(method, q, p, previous, h / c["h_prev"]), constant)
            Z, matrix, iterations, status, trips, lenient = solve(
                fn, (method, q, p, h, args), predicted, constant, c["matrix"], state_scale(z), ~active,
                c["steps"] == 0, options)
            z1, comp = compensated_add(z, jnp.concatenate(method.increment(H_bound, q, p, Z, h)), c["comp"])
        W = method.polynomial(H_bound, q, p, Z, h)
        solved = (status == Status.SUCCESS) & jnp.all(jnp.isfinite(z1))
        status = jnp.where((status == Status.SUCCESS) & ~solved, Status.NONFINITE, status)
        # the embedded estimate, shared by the step rule and the run's estimate (``peak_update``)
        # an explicit element's force at its end (``_explicit``) where the estimate only ranks
        # elements; a controller's steps take the field evaluated anew, as an iterated run's
        field = method.explicit_field(H_bound, *jnp.split(z1, 2), memo) if explicit and not pid else None
        embedded = embedded_error(H_bound, q, p, W, h, field) if pid or estimate is True else None
        step = dict(z=z, z1=z1, W=W, h=h, t=t, t1=t1, last=last, solved=solved, status=status, embedded=embedded)
        verdict = rule(c, step)
        accept, finished = verdict["accept"] & active, verdict["finished"]
        fail = active & (verdict["status"] != Status.SUCCESS)
        new = dict(c, matrix=matrix, h=jnp.where(active, verdict["h_next"], c["h"]),
                   **jax.tree.map(lambda a, b: jnp.where(active, a, b), verdict["memory"], {k: c[k] for k in memory}))
        end = dict(z=z1, comp=comp, t=verdict["t_b"], z_prev=z, Z_prev=Z, h_prev=h)
        if explicit:
            end["memo"] = memo
        # between the nodes the element's polynomial refined to the nodes' accuracy, where a
        # save time or an event lies in the element (every element for dense output)
        step = dict(step, t_b=verdict["t_b"])
        samples = None if events is None else _event_crossings(events, gs, c, step, accept, clock, W)
        W_fine = None
        if dense is True or ts is not None or events is not None:
            refine = lambda W: _output.refined(method, H_bound, z, z1, W, h)
            if dense is True:
                W_fine = refine(W)
            else:
                wanted = jnp.zeros((), bool)
                if ts is not None:  # the next save time falls in the element
                    next_save = ts[jnp.minimum(c["index"], ts.shape[0] - 1)]
                    wanted = (c["index"] < ts.shape[0]) & (next_save <= verdict["t_b"])
                if events is not None:
                    wanted = wanted | jnp.any(jnp.stack([jnp.any(crossing) for _, crossing, _ in samples]))
                W_fine = jax.lax.cond(accept & wanted, refine, _output.padded, W)
        if events is not None:
            fields, (alpha_stop, ended) = _events_update(events, gs, c, step, accept, clock, samples, W_fine)
            new.update(fields, ended=jnp.where(accept, ended, c["ended"]))
            if any(event.terminal for event in events):
                hit = accept & (ended >= 0)
                at = jnp.where(hit, alpha_stop, 0.0)
                stop = dict(end, z=_output.on_polynomial(z, W_fine, at[None])[0], comp=jnp.zeros_like(comp),
                            t=_output.time_at(z, W_fine, at, t, h, clock))
                end = jax.tree.map(lambda a, b: jnp.where(hit, a, b), stop, end)
                finished = finished | hit
        if ts is not None:  # a rejected step writes nothing: its end time is -inf
            t_end = jnp.where(accept, end["t"], -jnp.inf)
            new["saved"], new["index"] = _output.fill_saves(c["saved"], c["index"], ts,
                                                            (z, W_fine, t, t_end, h, clock), end["z"], c["steps"])
        # written in place; a rejected step's index lies past the buffers
        n = jnp.where(accept, c["steps"], max_steps + 1)
        new["hs"] = c["hs"].at[n].set(h, mode="drop")
        if dense:
            new["node_t"] = c["node_t"].at[n + 1].set(end["t"], mode="drop")
            new["node_z"] = c["node_z"].at[n + 1].set(end["z"], mode="drop")
        if dense is True:
            if events is not None and any(event.terminal for event in events):
                W_fine = jax.lax.cond(hit, _output.truncated, lambda W, _: W, W_fine, at)  # the element that ends
            new["W"] = c["W"].at[n].set(W_fine, mode="drop")
        local = jnp.nan
        if estimate == "full":
            frozen = jax.lax.stop_gradient((q, p, Z, h, args))
            local = jax.lax.stop_gradient(method.local_error(bind_args(H, frozen[4]), *frozen[:4]))
        elif estimate:
            size = jax.lax.stop_gradient(jnp.max(jnp.abs(embedded)))
            new["peak"] = peak_update(c["peak"], size, q, p, Z, h, accept)
        for key in end:
            new[key] = jnp.where(accept, end[key], c[key])
        if observe is not None:
            new["acc"] = jax.tree.map(lambda a, b: jnp.where(accept, b, a), c["acc"], observe(c["acc"], *view(end["z"])))
        if every:  # the accepted node whose index is a multiple of ``every``, and the element's root
            index = c["steps"] + 1
            slot = jnp.where(accept & (index % every == 0), index // every, max_steps + 1)
            node = dict(z=end["z"], t=end["t"], acc=new.get("acc"))
            new["checkpoints"] = jax.tree.map(lambda a, x: a.at[slot].set(x, mode="drop"), c["checkpoints"], node)
            row = jnp.where(accept, c["steps"] % every, every)
            root = dict(z=z, Z=jax.lax.stop_gradient(Z), t=t, acc=c.get("acc"))
            new["kept"] = jax.tree.map(lambda a, x: a.at[row].set(x, mode="drop"), c["kept"], root)
        attempts = c["attempts"] + active
        out_of_steps = active & ~finished & (attempts >= max_steps) & ~fail
        new.update(
            status=jnp.where(fail, verdict["status"], jnp.where(out_of_steps, Status.MAX_STEPS, c["status"])
                             ).astype(jnp.int32),
            done=c["done"] | fail | (active & finished) | out_of_steps,
            steps=c["steps"] + accept, rejected=c["rejected"] + (active & verdict["rejected"]), attempts=attempts,
            total=c["total"] + iterations * active, most=jnp.maximum(c["most"], iterations * active),
            trips=c["trips"] + trips * active, lenient=c["lenient"] + (accept & (lenient > 0)),
            h_min=jnp.where(accept, jnp.minimum(c["h_min"], h), c["h_min"]),
            h_max=jnp.where(accept, jnp.maximum(c["h_max"], h), c["h_max"]),
            estimate=jnp.where(accept, jnp.fmax(c["estimate"], local), c["estimate"]),
        )
        return new

    c = jax.lax.while_loop(lambda c: _any_member(~c["done"]), body, c)
    if estimate is True:
        c["estimate"] = peak_estimate(method, H_bound, c["peak"])
    return c
