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

Under ``vmap`` every member takes its own steps and finished members idle (their carry is
masked); the root finder folds the batch into one iteration as in ``march``. The loop is
forward-differentiable (``jax.jvp``); the step sizes are constants of the trajectory.
"""

import dataclasses

import jax
import jax.numpy as jnp

from . import _output
from ._controllers import PIDController, TimeTransform, embedded_error, poincare, scaled_error
from ._march import (bind_args, compensated_add, continued, element_residual, input_status, peak_estimate, peak_start,
                     peak_update, state_scale)
from ._solve import Status, initial_matrix, solve

_LANDING = 8  # shortened attempts of a time-transformed run's last element (Newton converges in 2-3)


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
    factor; a rejected step below dtmin (or the round-off of t) ends the run (DTMIN)."""

    def rule(c, step):
        err = jnp.where(step["solved"], scaled_error(step["embedded"], step["z"], step["z1"], controller), jnp.inf)
        accept = err <= 1
        # h_prev: the last accepted h
        h_ratio = jnp.where(c["steps"] > 0, step["h"] / c["h_prev"], jnp.nan) if controller.predictive else None
        h_next = jnp.minimum(step["h"] * controller.next_factor(err, c["err1"], c["err2"], order, accept, h_ratio),
                             controller.dtmax)
        at_floor = ~accept & ((step["h"] <= controller.dtmin) | (h_next <= tiny))
        memory = dict(err1=jnp.where(accept, err, c["err1"]), err2=jnp.where(accept, c["err1"], c["err2"]))
        return dict(accept=accept, finished=accept & step["last"], t_b=jnp.where(step["last"], step["t1"],
                    step["t"] + step["h"]), h_next=h_next, status=jnp.where(at_floor, Status.DTMIN, Status.SUCCESS),
                    rejected=~accept & ~at_floor, memory=memory)

    return rule, dict(err1=jnp.ones((), tiny.dtype), err2=jnp.ones((), tiny.dtype))


def _transform_rule(s, clock, view, tiny):
    """The time transformation: a constant step in tau; the element that passes t1 is shortened
    by Newton on its end time t_b(h), dt_b/dh = s(z1) (alpha beyond 1 extrapolates w)."""

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
                    rejected=jnp.zeros((), bool), memory=dict(landing=landing + shorten))

    return rule, dict(landing=jnp.zeros((), jnp.int32))


def _constant_rule(t0, h, count):
    """A constant h: element n spans [t0 + n h, t0 + (n + 1) h] (times by index, not by adding up
    steps, whose rounding would put t1 a sliver beyond the ``count`` elements), the last one
    (``count``, ``element_count``) shortened to land on t1."""

    def rule(c, step):
        return dict(accept=step["solved"], finished=step["solved"] & step["last"], h_next=c["h"],
                    status=step["status"], t_b=jnp.where(step["last"], step["t1"], t0 + (c["steps"] + 1) * h),
                    rejected=jnp.zeros((), bool), memory={})

    return rule


def element_count(t0, t1, h):
    """The elements of size h from t0 to t1, the last shortened (an end within 4 eps of t1 counts
    as t1: no sliver of an element); traced, as ``_span.fixed_step_count`` is for concrete times."""
    return jnp.maximum(1, jnp.ceil((t1 - t0) / h * (1 - 4 * jnp.finfo(jnp.result_type(h)).eps))).astype(jnp.int32)


def _event_update(event, g, c, step, accept, clock):
    """Locate a sign change of g on the accepted element's polynomial; returns the carry's event
    fields and the event ``(hit, t, z)``."""
    z, W, t, h = step["z"], step["W"], step["t"], step["h"]
    dtype = z.dtype
    g_b = g(step["t_b"], step["z1"])
    hit = accept & _crossing(event, c["g_a"], g_b)
    f = lambda a: g(_output.time_at(z, W, a, t, h, clock), _output.on_polynomial(z, W, a[None])[0])
    alpha = _output.locate(f, jnp.zeros((), dtype), jnp.ones((), dtype), c["g_a"])
    at = _output.on_polynomial(z, W, alpha[None])[0]
    t_ev = _output.time_at(z, W, alpha, t, h, clock)
    slot = jnp.where(hit & (c["ev_count"] < event.capacity), c["ev_count"], event.capacity)
    fields = dict(ev_t=c["ev_t"].at[slot].set(t_ev, mode="drop"), ev_z=c["ev_z"].at[slot].set(at, mode="drop"),
                  ev_n=c["ev_n"].at[slot].set(c["steps"], mode="drop"),
                  ev_alpha=c["ev_alpha"].at[slot].set(alpha, mode="drop"),
                  ev_count=c["ev_count"] + hit, g_a=jnp.where(accept, g_b, c["g_a"]))
    return fields, (hit, t_ev, at)


def _initial_carry(method, z0, t0, h0, guess, options, max_steps, m, ts, dense, event, g, observe, acc0, estimate,
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
        first = jnp.where(ts[:, None] == t0, z0[None, :], jnp.nan)
        nowhere = jnp.full(ts.shape, -1, jnp.int32)
        c["saved"], c["index"] = (first, nowhere, jnp.zeros_like(ts)), jnp.sum(ts <= t0).astype(jnp.int32)
    if dense:
        c["node_t"] = jnp.full((max_steps + 1,), jnp.inf, dtype).at[0].set(t0)
        c["node_z"] = jnp.full((max_steps + 1,) + z0.shape, jnp.nan, dtype).at[0].set(z0)
        c["W"] = jnp.zeros((max_steps, m) + z0.shape, dtype)
    if event is not None:
        shape = (event.capacity,)
        c.update(g_a=g(t0, z0), ev_t=jnp.full(shape, jnp.nan, dtype), ev_z=jnp.full(shape + z0.shape, jnp.nan, dtype),
                 ev_n=jnp.full(shape, -1, jnp.int32), ev_alpha=jnp.full(shape, jnp.nan, dtype),
                 ev_count=jnp.zeros((), jnp.int32))
    if estimate is True:
        c["peak"] = peak_start(q0, p0, guess, h0)
    if every:
        slots = max_steps // every + 1
        c["checkpoints"] = jax.tree.map(lambda x: jnp.zeros((slots,) + jnp.shape(x), jnp.result_type(x)).at[0].set(x),
                                        dict(z=z0, t=t0, acc=acc0))
    return c


def run(method, H, q0, p0, t0, t1, h0, args, controller, *, options, max_steps, ts=None, dense=False,
        event=None, estimate=False, clock=None, s=None, observe=None, acc0=None, every=None):
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
        every: keep ``checkpoints`` (z, t and acc at every ``every``-th accepted node, from the
            first), for the derivatives (``_adjoint``); None: none.
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
    m = method.polynomial(H_bound, q0, p0, guess, h0).shape[0]
    t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)
    tiny = 16 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(t0), jnp.abs(t1))
    pid = isinstance(controller, PIDController)
    if pid:
        rule, memory = _pid_rule(controller, m, tiny)
        h0 = jnp.minimum(h0, controller.dtmax)
        options = dataclasses.replace(options, varying_steps=True, short_lived_matrices=True)
    elif clock is not None:
        rule, memory = _transform_rule(s, clock, view, tiny)
        options = dataclasses.replace(options, short_lived_matrices=True)
    else:
        count = element_count(t0, t1, h0)
        rule, memory = _constant_rule(t0, h0, count), {}
    g = None if event is None else (lambda t, z: event.g(t, *view(z)))
    c = _initial_carry(method, z0, t0, h0, guess, options, max_steps, m, ts, dense, event, g, observe, acc0, estimate,
                       every)
    c.update(memory)
    if s is not None:
        s0 = s(*view(z0))
        c["status"] = jnp.where((s0 > 0) & jnp.isfinite(s0), c["status"], Status.TIME_TRANSFORM).astype(jnp.int32)
    c["done"] = c["status"] != Status.SUCCESS

    def body(c):
        active = ~c["done"]
        z, t = c["z"], c["t"]
        q, p = jnp.split(z, 2)
        if controller is None:  # a constant h: the last element by its index (``_constant_rule``)
            last = c["steps"] + 1 >= count
        else:
            last = t + c["h"] * (1 + 4 * jnp.finfo(dtype).eps) >= t1
        h = jnp.where(last & (clock is None), t1 - t, c["h"])
        # the last accepted element's polynomial continued over this one (the root finder
        # falls back on the constant state where that is worse)
        constant = method.initial_guess(q, p)
        previous = (*jnp.split(c["z_prev"], 2), c["Z_prev"])
        predicted = jnp.where(c["steps"] > 0, continued(method, q, p, previous, h / c["h_prev"]), constant)
        Z, matrix, iterations, status, trips, lenient = solve(
            fn, (method, q, p, h, args), predicted, constant, c["matrix"], state_scale(z), ~active, c["steps"] == 0,
            options)
        z1, comp = compensated_add(z, jnp.concatenate(method.increment(H_bound, q, p, Z, h)), c["comp"])
        W = method.polynomial(H_bound, q, p, Z, h)
        solved = (status == Status.SUCCESS) & jnp.all(jnp.isfinite(z1))
        status = jnp.where((status == Status.SUCCESS) & ~solved, Status.NONFINITE, status)
        # the embedded estimate, shared by the step rule and the run's estimate (``peak_update``)
        embedded = embedded_error(H_bound, q, p, W, h) if pid or estimate is True else None
        step = dict(z=z, z1=z1, W=W, h=h, t=t, t1=t1, last=last, solved=solved, status=status, embedded=embedded)
        verdict = rule(c, step)
        accept, finished = verdict["accept"] & active, verdict["finished"]
        fail = active & (verdict["status"] != Status.SUCCESS)
        new = dict(c, matrix=matrix, h=jnp.where(active, verdict["h_next"], c["h"]),
                   **jax.tree.map(lambda a, b: jnp.where(active, a, b), verdict["memory"], {k: c[k] for k in memory}))
        end = dict(z=z1, comp=comp, t=verdict["t_b"], z_prev=z, Z_prev=Z, h_prev=h)
        if event is not None:
            fields, (hit, t_ev, at) = _event_update(event, g, c, dict(step, t_b=verdict["t_b"]), accept, clock)
            new.update(fields)
            if event.terminal:
                stop = dict(end, z=at, comp=jnp.zeros_like(comp), t=t_ev)
                end = jax.tree.map(lambda a, b: jnp.where(hit, a, b), stop, end)
                finished = finished | hit
        if ts is not None:  # a rejected step writes nothing: its end time is -inf
            t_end = jnp.where(accept, end["t"], -jnp.inf)
            new["saved"], new["index"] = _output.fill_saves(c["saved"], c["index"], ts, (z, W, t, t_end, h, clock),
                                                            end["z"], c["steps"])
        # written in place; a rejected step's index lies past the buffers
        n = jnp.where(accept, c["steps"], max_steps + 1)
        new["hs"] = c["hs"].at[n].set(h, mode="drop")
        if dense:
            new["node_t"] = c["node_t"].at[n + 1].set(end["t"], mode="drop")
            new["node_z"] = c["node_z"].at[n + 1].set(end["z"], mode="drop")
            new["W"] = c["W"].at[n].set(W, mode="drop")
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
        if every:  # the accepted node whose index is a multiple of ``every``
            index = c["steps"] + 1
            slot = jnp.where(accept & (index % every == 0), index // every, max_steps + 1)
            node = dict(z=end["z"], t=end["t"], acc=new.get("acc"))
            new["checkpoints"] = jax.tree.map(lambda a, x: a.at[slot].set(x, mode="drop"), c["checkpoints"], node)
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

    c = jax.lax.while_loop(lambda c: ~c["done"], body, c)
    if estimate is True:
        c["estimate"] = peak_estimate(method, H_bound, c["peak"])
    return c
