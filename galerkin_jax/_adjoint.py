"""Derivatives of a run whose steps are chosen while it runs (``_adaptive``), paid for by the steps taken.

Such a run is a ``lax.while_loop``, which reverse mode cannot differentiate, and how many
elements it takes is known only when it ends. Its derivatives are those of the run that takes
the same steps (the step sizes are constants of the trajectory, as in diffrax): element n maps
its start z_n and the parameters theta = (method, args) to its end z_{n+1} and its polynomial
W_n, through the root of its equations, whose derivative is the implicit function theorem's
(``_solve.implicit``); what a run reads between nodes (``save_at``, events, dense output) is a
function of an element's z_n, W_n, z_{n+1}, its time t_n and its length h_n. ``run`` attaches
to the forward run the tangent map of all that, made of two sweeps over the elements the run
took, whatever ``max_steps``:

* forward (``jax.jvp``, ``_tangent_sweep``): element after element, each element's tangent by
  ``jax.jvp`` at its root, found again from z_n;
* reverse (``jax.grad``, ``jax.vjp``, ``_adjoint_sweep``): backwards, each element by
  ``jax.vjp``.

Neither sweep writes an output's derivative by hand: each output is defined once, as a
function of the element that writes it (``_kinds``), and the sweeps take its ``jax.jvp`` and
its ``jax.vjp`` (``_write_tangents``, ``_read_cotangents``). The forward run keeps z, t (and a sweep's diagnostics) at every ``every``-th
  node (checkpoints) and the roots of the elements since the last one (``Spec.stretch``:
  ``KEPT_ELEMENTS``, sqrt(max_steps) with ``checkpoint``); the adjoint takes that last
  stretch backwards from the kept roots, then each earlier stretch after solving it again
  from its checkpoint into the same buffer. A run of at most ``every`` elements is solved once.
  Under ``vmap`` on a CPU it takes the members one after another, each for its own elements
  (``_apart``).

``linear_map`` makes the forward sweep an operation that JAX transposes into the reverse one.
The times: a constant h's element n starts at t0 + n h; a controller's at t0 plus the steps
before it; the element that lands on t1 is t1 - t_n long, so t0, t1 and a constant h have
derivatives, a controller's steps none. A time-transformed run's time is a coordinate of its
state, and its last element's length in tau is fixed by landing on t1 (``_landing``). A save
time's place alpha in its element, and an event's, move with the inputs as the implicit
function theorem says (``_output.root``). A derivative that is not defined raises (``_tangents``);
second derivatives of such a run raise too (``_first_order``).
"""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from . import _adaptive, _output
from ._controllers import event_value, symbolic_zero as _symbolic_zero, user_args
from ._explicit import is_explicit
from ._march import bind_args, continued, element, element_residual, state_scale
from ._solve import Options, Status, implicit, initial_matrix, keeps_state

# the elements whose roots (z_n, t_n, Z_n) a gradient keeps (``Spec.stretch``), at most so many and
# so many bytes of them: a run that fits is not solved again
KEPT_ELEMENTS, KEPT_BYTES = 512, 2 ** 24

# the outputs of a run that have derivatives; the rest (counts, status, estimates, places) have none
DIFFERENTIABLE = ("z", "t", "saved", "ev_t", "ev_z", "node_t", "node_z", "W", "acc")
INPUTS = ("q0", "p0", "args", "method", "t0", "t1", "ts", "h")


@dataclasses.dataclass(frozen=True)
class Spec:
    """What a run is, apart from its inputs (static).

    Attributes:
        H: the user's Hamiltonian, unbound.
        transform: the ``TimeTransform`` (its s is static) or None.
        options: the root finder's ``Options``.
        max_steps, dense, events, estimate: as ``_adaptive.run`` takes them (events: a tuple;
            dense: True, or "nodes" for the node states alone).
        observe, acc0: a sweep's diagnostics, ``observe(acc, q, p)`` folded over the accepted
            nodes from ``acc0(q0, p0, args)``; or None.
        checkpoint: keep the fewest roots (``stretch``): memory for time.
    """

    H: object
    transform: object
    options: Options
    max_steps: int
    dense: bool = False
    events: object = None
    estimate: object = False
    observe: object = None
    acc0: object = None
    checkpoint: bool = False

    def stretch(self, root):
        """The elements between checkpoints, whose roots (``root``: one element's z, t, Z and
        acc, of which the sizes count) a gradient keeps: ``KEPT_ELEMENTS``, or as many as ``KEPT_BYTES`` hold,
        at most ``max_steps``, and at least sqrt(max_steps) (then the checkpoints and one
        stretch each take about sqrt(max_steps) elements of memory), which is all with
        ``checkpoint``."""
        fewest = max(1, math.isqrt(self.max_steps))
        if self.checkpoint:
            return fewest
        size = sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(root))
        return min(self.max_steps, max(fewest, min(KEPT_ELEMENTS, KEPT_BYTES // size)))


def run(spec, inputs):
    """The forward run of ``spec`` from ``inputs``, with derivatives (module docstring).

    Args:
        inputs: dict of ``q0``, ``p0`` (flat), ``args``, ``method``, ``controller`` (a
            ``PIDController`` or None), ``t0``, ``t1``, ``ts`` (or None) and ``h``, in the run's
            time tau, and optionally ``direction`` (``_output.Direction``: its events' g take
            t = sigma tau; none: forwards).
    Returns:
        dict: ``z``, ``t`` (where and when the run ended), ``saved`` (the states at ``ts``),
        ``places`` (their elements and alphas), the events, the dense buffers, ``acc``, and the
        counts of ``_adaptive.run``.
    """

    @jax.custom_jvp
    def outputs(inputs):
        return _forward(spec, inputs, keep=False)

    def outputs_jvp(primals, tangents):
        (inputs,), (d_inputs,) = primals, tangents
        leaves, full, pick, wanted = _tangents(spec, inputs, d_inputs)
        inputs = _first_order(inputs)
        c = _forward(spec, inputs, keep=True)
        out = {k: v for k, v in c.items() if k not in ("checkpoints", "kept")}
        differentiable = {k: out[k] for k in DIFFERENTIABLE if out.get(k) is not None}
        if not leaves:  # no input with a derivative moves
            return out, jax.tree.map(_zero_tangent, out)
        adjoint = _apart(lambda inputs, c, ct: _adjoint_sweep(spec, inputs, c, ct, wanted))
        d_out = linear_map(lambda leaves: _tangent_sweep(spec, inputs, c, full(leaves), wanted),
                           lambda ct: pick(adjoint(inputs, c, ct)), leaves, differentiable)
        zero = {k: jax.tree.map(_zero_tangent, v) for k, v in out.items() if k not in d_out}
        return out, {**zero, **d_out}

    outputs.defjvp(outputs_jvp, symbolic_zeros=True)
    if inputs["h"] is None:  # a PIDController's first step, picked here: a constant of the trajectory
        h = _adaptive.first_step(inputs["method"], spec.H, inputs["q0"], inputs["p0"], inputs["t0"], inputs["t1"],
                                 inputs["args"], inputs["controller"])
        inputs = dict(inputs, h=jax.lax.stop_gradient(h))
    return outputs(inputs)


def _apart(sweep):
    """``sweep(inputs, c, x)``, a sweep over the elements of the forward run ``c``, whose members,
    under ``vmap`` on a CPU, run one after another (``lax.map``), each for its own elements,
    where the forward run is batched (its members took their own steps), instead of all at once
    for the longest member's. There a batched element costs about its members' elements alone
    (their tangents are factorised and multiplied member by member), so a batch would only add
    the wait; an accelerator, where it costs about one member's, keeps the batch. So does a
    batch of cotangents of one run (``jacrev``), which shares its elements' roots and
    linearisations."""
    if jax.default_backend() != "cpu":
        return sweep

    def call(inputs, c, x):
        # the sweep's constants (the residuals of a vmapped vjp may batch them) as arguments too:
        # a rule may map every operand
        closed, shape = jax.make_jaxpr(sweep, return_shape=True)(inputs, c, x)
        structure = jax.tree.structure(shape)
        evaluate = lambda consts, *args: jax.tree.unflatten(structure, jax.core.eval_jaxpr(
            closed.jaxpr, consts, *jax.tree.leaves(args)))
        apart = jax.custom_batching.custom_vmap(evaluate)

        @apart.def_vmap
        def _(axis_size, in_batched, *args):
            _, _, c_batched, _ = in_batched  # (consts, inputs, c, x)
            if not any(jax.tree.leaves(c_batched)):  # one forward run: keep the batch
                out = jax.vmap(evaluate, in_axes=jax.tree.map(lambda b: 0 if b else None, in_batched))(*args)
            else:
                leaves, tree = jax.tree.flatten(args)
                batched = jax.tree.leaves(in_batched)

                def member(mapped):
                    mapped = iter(mapped)
                    return evaluate(*jax.tree.unflatten(tree, [next(mapped) if b else x for x, b in
                                                               zip(leaves, batched)]))

                out = jax.lax.map(member, [x for x, b in zip(leaves, batched) if b])
            return out, jax.tree.map(lambda _: True, out)

        return apart(list(closed.consts), inputs, c, x)

    return call


def linear_map(forward, transpose, x, y):
    """``forward(x)``, a linear map of the tangents ``x`` (a non-empty list of arrays, each a
    tangent, not a constant) to something of y's structure, as one operation whose transpose is
    ``transpose(ybar) -> xbar``: the map (x, y) -> (0, forward(x)) is handed to
    ``lax.custom_linear_solve`` as its ``solve``, and (xbar, ybar) -> (transpose(ybar), 0) as the
    solve of the transpose, so that reverse mode runs ``transpose`` and forward mode ``forward``.
    (Every operand of the solve must be a tangent: y's zeros are zeros times one of x.)"""
    zeros = lambda tree: jax.tree.map(jnp.zeros_like, tree)
    anchor = jnp.ravel(x[0])[0] if jnp.size(x[0]) else jnp.zeros((), jnp.result_type(x[0]))
    solve = lambda _, b: (zeros(b[0]), forward(b[0]))
    transpose_solve = lambda _, b: (transpose(b[1]), zeros(b[1]))
    y = jax.tree.map(lambda v: jnp.zeros_like(v) * anchor.astype(jnp.result_type(v)), y)
    return jax.lax.custom_linear_solve(lambda b: b, (x, y), solve, transpose_solve)[1]


def _zero_tangent(x):
    x = jnp.asarray(x)
    return jnp.zeros_like(x) if _inexact(x) else jnp.zeros(x.shape, jax.dtypes.float0)


def _inexact(x):
    dtype = getattr(x, "dtype", None)
    return dtype != jax.dtypes.float0 and jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def _add(a, b):
    """``a + b`` of two cotangent pytrees, where the leaves are numbers (float0 has none)."""
    return jax.tree.map(lambda x, y: x + y if _inexact(x) and _inexact(y) else x, a, b)


def _nonzero(tangent):
    return any(not _symbolic_zero(t) for t in jax.tree.leaves(tangent, is_leaf=_symbolic_zero))


def _tangents(spec, inputs, d_inputs):
    """``(leaves, full, pick, wanted)``: the tangents of the differentiable inputs (``INPUTS``)
    that are not symbolic zeros (floating leaves only), ``full(leaves)``, all the tangents as a
    dict of the inputs' structure with zeros elsewhere, ``pick(dict) -> leaves``, its inverse,
    and the names of the inputs that have such a tangent. A derivative the run does not have
    raises, naming the input."""
    if (inputs["controller"] is not None or spec.transform is not None) and _nonzero(d_inputs["h"]):
        raise ValueError("h has no derivative here: a controller's first step, or a time transformation's step "
                         "in tau, is a constant of the trajectory (fixed steps have a derivative in h).")
    if _nonzero(d_inputs["controller"]):
        raise ValueError("The controller's tolerances and bounds have no derivative: the steps are constants of "
                         "the trajectory.")
    primals, structure = jax.tree.flatten({k: inputs[k] for k in INPUTS})
    tangents = jax.tree.leaves({k: d_inputs[k] for k in INPUTS}, is_leaf=_symbolic_zero)
    where = [i for i, (x, t) in enumerate(zip(primals, tangents)) if _inexact(x) and not _symbolic_zero(t)]
    moving = lambda k: any(_inexact(x) and not _symbolic_zero(t) for x, t in
                           zip(jax.tree.leaves(inputs[k]), jax.tree.leaves(d_inputs[k], is_leaf=_symbolic_zero)))
    wanted = frozenset(filter(moving, INPUTS))

    def full(leaves):
        merged = [_zero_tangent(x) for x in primals]
        for i, t in zip(where, leaves):
            merged[i] = t
        return jax.tree.unflatten(structure, merged)

    def pick(bars):
        leaves = jax.tree.leaves(bars)
        return [leaves[i] for i in where]

    return [tangents[i] for i in where], full, pick, wanted


def _held(wanted):
    """``(theta, z, t0, t1, h) -> the same``, with the inputs that no derivative asks for held
    constant (``stop_gradient``), so that neither sweep computes their tangents or cotangents
    (a quadrature rule's, which cost as much as the state's). ``args~`` moves with the start."""
    keep = lambda key, x: x if key in wanted else jax.lax.stop_gradient(x)
    start_moves = bool(wanted & {"q0", "p0", "args", "t0"})

    def hold(theta, z, t0, t1, h):
        method, run_args = theta
        run_args = run_args if start_moves else jax.lax.stop_gradient(run_args)
        return (keep("method", method), run_args), z, keep("t0", t0), keep("t1", t1), keep("h", h)

    return hold


@jax.custom_jvp
def _no_second_derivative(x):
    return x


@_no_second_derivative.defjvp
def _no_second_derivative_jvp(primals, tangents):
    raise NotImplementedError(
        "Second derivatives of a run whose steps are chosen as it runs (a controller, save_at or events) are not "
        "supported: its derivative is a sweep over the steps taken. Differentiate a run of fixed steps (n_steps) "
        "twice instead.")


def _first_order(inputs):
    """The inputs, through an identity that raises where they are differentiated again."""
    return jax.tree.map(lambda x: _no_second_derivative(x) if _inexact(x) else x, inputs)


# ---------------------------------------------------------------------------------------------
# the forward run


def _start(spec, q0, p0, args, t0):
    """``(z~0, args~)``, the initial state and arguments of the problem the loop solves
    (``_adaptive.problem``), differentiable in the user's q0, p0, args and t0."""
    _, z_q0, z_p0, run_args, _, _ = _adaptive.problem(spec.H, spec.transform, q0, p0, t0, args)
    return jnp.concatenate([z_q0, z_p0]), run_args


def _sigma(inputs):
    """The run's direction sigma (``_output.Direction``), 1 where the inputs name none."""
    return inputs.get("direction", _output.FORWARDS).sigma


def _problem(spec, inputs):
    """``(H~, s~, clock)`` of the problem the loop solves."""
    fn, _, _, _, s, clock = _adaptive.problem(spec.H, spec.transform, inputs["q0"], inputs["p0"], inputs["t0"],
                                              inputs["args"])
    return fn, s, clock


def _forward(spec, inputs, keep):
    """The forward run; ``keep``: with the checkpoints and the kept roots a gradient reads."""
    fn, s, clock = _problem(spec, inputs)
    z0, run_args = _start(spec, inputs["q0"], inputs["p0"], inputs["args"], inputs["t0"])
    acc0 = None if spec.observe is None else spec.acc0(inputs["q0"], inputs["p0"], inputs["args"])
    every = None
    if keep:  # an element's root: its start z and t, its unknowns Z and the diagnostics there
        every = spec.stretch(dict(z=z0, Z=inputs["method"].initial_guess(*jnp.split(z0, 2)), t=z0[0], acc=acc0))
    controller = inputs["controller"] if spec.transform is None else spec.transform
    c = _adaptive.run(inputs["method"], fn, *jnp.split(z0, 2), inputs["t0"], inputs["t1"], inputs["h"], run_args,
                      controller, options=_options(spec, inputs), max_steps=spec.max_steps, ts=inputs["ts"], dense=spec.dense,
                      events=spec.events, estimate=spec.estimate, clock=clock, s=s, observe=spec.observe, acc0=acc0,
                      every=every, sigma=_sigma(inputs))
    return _outputs(c)


def _outputs(c):
    """The run's outputs (a dict) from the loop's final carry (``_adaptive.Carry``): where and
    when it ended (``z``, ``t``), its status, counts and record, and what it kept where asked:
    ``saved`` and ``places`` (the save times' states, and their elements and alphas), the
    events (``ev_t``, ``ev_z``, ``ev_n``, ``ev_alpha``, ``ev_count``, ``ended``), the dense
    output (``node_t``, ``node_z``, ``W``), ``acc``, and the ``checkpoints`` and ``kept`` roots."""
    out = dict(z=c.node.z, t=c.node.t, status=c.status, **c.counts._asdict(), h_min=c.record.h_min,
               h_max=c.record.h_max, estimate=c.record.estimate, hs=c.record.hs)
    if c.events is not None:
        e = c.events
        out.update(ev_t=e.t, ev_z=e.z, ev_n=e.n, ev_alpha=e.alpha, ev_count=e.count, ended=e.ended)
    if c.dense is not None:
        out.update(node_t=c.dense.node_t, node_z=c.dense.node_z)
        if c.dense.W is not None:
            out["W"] = c.dense.W
    if c.acc is not None:
        out["acc"] = c.acc
    if c.checkpoints is not None:
        out.update(checkpoints=c.checkpoints.nodes, kept=c.checkpoints.kept)
    if c.saves is not None:
        out["saved"], out["places"] = c.saves.states, (c.saves.elements, c.saves.alphas)
    return out


# ---------------------------------------------------------------------------------------------
# one element and what is read from it


def _element(spec, fn, theta, z, h, Z):
    """``(z_{n+1}, W_n)``: the element of length h from z with root ``Z`` (found beforehand),
    differentiable in theta = (method, args~), z and h (``_solve.implicit``)."""
    method, args = theta
    q, p = jnp.split(z, 2)
    H_bound = bind_args(fn, args)
    if explicit_here(method, spec):  # the closed form, differentiated as it is (``_explicit``)
        Z, dz, _ = method.explicit(H_bound, q, p, h, method.explicit_start(H_bound, q, p))
    else:
        residual = element_residual(fn, spec.options.solver.sweep_dimension)
        Z = implicit(residual, spec.options.solver.dense_limit, (method, q, p, h, args), Z, jnp.ones((), bool))
        dz = method.increment(H_bound, q, p, Z, h)
    dz = jnp.concatenate(dz)
    return z + dz, method.polynomial_with(H_bound, q, p, Z, h, dz)


def explicit_here(method, spec):
    """Whether the run's elements are computed in closed form: an explicit method (``_explicit``)
    on H itself, not on a time-transformed K (``_adaptive.run``)."""
    return is_explicit(method) and spec.transform is None


def _resolve(fn, theta, z, h, previous, matrix, options, explicit=False):
    """The root of the element of length h from z, found again from the previous element's
    polynomial continued (``previous = (z, Z, h, have)``; the constant state where not
    ``have``), ``matrix`` carried on (``_march.element``). Returns ``(Z, matrix, converged)``."""
    method, args = theta
    q, p = jnp.split(z, 2)
    z_prev, Z_prev, h_prev, have = previous
    guess = constant = None
    if not explicit:  # the closed form (``explicit_here``) takes no guess
        constant = method.initial_guess(q, p)
        guess = jnp.where(have, continued(method, q, p, (*jnp.split(z_prev, 2), Z_prev), h / h_prev), constant)
    e = element(method, fn, q, p, h, args, options, predicted=guess, constant=constant, matrix=matrix,
                scale=state_scale(z), skip=jnp.zeros((), bool), first=~have, closed_form=explicit)
    return jax.lax.stop_gradient(e.Z), e.matrix, e.status == Status.SUCCESS


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _landing(end_time, h, z, theta, t1, Z):
    """A time-transformed run's last element's length in tau, h, which lands it on t1,
    ``end_time(z, theta, h, Z) = t1``; its tangent by the implicit function theorem."""
    return h


@_landing.defjvp
def _landing_jvp(end_time, primals, tangents):
    h, z, theta, t1, Z = primals
    _, dz, dtheta, dt1, _ = tangents
    _, moved = jax.jvp(lambda z, theta: end_time(z, theta, h, Z), (z, theta), (dz, dtheta))
    _, rate = jax.jvp(lambda h: end_time(z, theta, h, Z), (h,), (jnp.ones_like(h),))
    return h, (dt1 - moved) / rate


def _save(clock, z, W, z1, t_n, h, ts, alpha, node):
    """The state at the save time ``ts`` in an element (``_output.state_at``), its alpha
    ``(ts - t_n) / h``, or on a time-transformed run's clock the root that the run located."""
    if clock is None:
        alpha = (ts - t_n) / h
    else:
        alpha = _output.root(lambda a, z, W, ts: _output.time_at(z, W, a, t_n, h, clock) - ts, alpha, (z, W, ts))
    return _output.state_at(z, W, z1, alpha, node)


def _event(g, sigma, clock, view, z, W, t_n, h, alpha, args):
    """``(t*, z*, alpha*)``: an event's time (in the run's tau), state and place in an element,
    alpha* the root of g(sigma tau(alpha), w(alpha)) that the forward run located. A traced
    sigma and the run's args~ (which a g may read, ``_controllers.event_value``) are arguments of
    the root's function (a value it closed over would be a constant of a transformation that has
    not traced it); a known sigma is a constant of it."""
    traced = () if isinstance(sigma, int) else (sigma,)

    def g_at(a, z, W, t_n, h, args, *traced):
        s = traced[0] if traced else sigma
        t = _output.directed(_output.time_at(z, W, a, t_n, h, clock), s)
        return event_value(g, t, *view(_output.on_polynomial(z, W, a[None])[0]), user_args(args, clock, s))

    alpha = _output.root(g_at, alpha, (z, W, t_n, h, args, *traced))
    return _output.time_at(z, W, alpha, t_n, h, clock), _output.on_polynomial(z, W, alpha[None])[0], alpha


# ---------------------------------------------------------------------------------------------
# the elements' times, lengths and places


def _timing(inputs, c, n, t_n, landed, t0, t1, h):
    """``(t_n, h_n)`` of element n, differentiable in (t0, t1, h) (module docstring); their values
    are the forward run's (``t_n``: the time it reached, for a controller's run)."""
    if inputs["controller"] is None:
        start = t0 + n * h
        return start, jnp.where(landed, t1 - start, h)
    start = t0 + jax.lax.stop_gradient(t_n - t0)
    return start, jnp.where(landed, t1 - start, jax.lax.stop_gradient(c["hs"][n]))


def _terminated(spec, c):
    """The run ended at a terminal event (row 0 of event ``c["ended"]``)."""
    if not _terminal(spec):
        return jnp.zeros((), bool)
    return c["ended"] >= 0


def _terminal(spec):
    return spec.events is not None and any(event.terminal for event in spec.events)


def _landed(spec, c, n):
    """Element n is the one that lands on t1: the last of a run that reached t1."""
    return keeps_state(c["status"]) & ~_terminated(spec, c) & (n == c["steps"] - 1)


def _options(spec, inputs):
    """The root finder's ``Options`` of the run: the spec's, with the tolerance's value where
    the inputs carry one (``integrate``'s ``RunOptions.planned``: an input, so that the
    derivative's sweeps, traced apart from the forward run, read it as theirs)."""
    tolerance = inputs.get("tolerance")
    return spec.options if tolerance is None else spec.options.with_tolerance(tolerance)


def _resolve_options(spec, inputs):
    """The root finder's options for elements found again: the forward run's, less a
    controller's cap on matrices (an element found again from another predictor must not fail
    where it converged)."""
    controlled = inputs["controller"] is not None or spec.transform is not None
    return dataclasses.replace(_options(spec, inputs), varying_steps=False, short_lived_matrices=controlled)


class _Element:
    """Element n of a run as the sweeps differentiate it: ``outputs(theta, z, t0, t1, h)``, its
    end z_{n+1}, its polynomial W (``_element``; refined where the run reads between the nodes,
    as the forward run does) and its start time and length (``_timing``)."""

    def __init__(self, spec, fn, inputs, c, clock, n, t_n, Z):
        self.spec, self.fn, self.inputs, self.c, self.clock, self.n, self.t_n, self.Z = (
            spec, fn, inputs, c, clock, n, t_n, Z)
        self.landed = _landed(spec, c, n)
        self.h_n = c["hs"][n]

    def outputs(self, theta, z, t0, t1, h):
        spec, fn, clock, Z = self.spec, self.fn, self.clock, self.Z
        if clock is None:
            start, length = _timing(self.inputs, self.c, self.n, self.t_n, self.landed, t0, t1, h)
        else:
            end_time = lambda z, theta, h, Z: _element(spec, fn, theta, z, h, Z)[0][clock]
            length = jnp.where(self.landed, _landing(end_time, self.h_n, z, theta, t1, Z), self.h_n)
            start = z[clock]
        z1, W = _element(spec, fn, theta, z, length, Z)
        if spec.dense is True or spec.events is not None or self.inputs["ts"] is not None:
            # what the run read between the nodes: the refined polynomial (``_adaptive.run``)
            W = _output.refined(theta[0], bind_args(fn, theta[1]), z, z1, W, length)
        return z1, W, start, length

    def local(self, hold):
        """``(theta, (z, acc), (t0, t1, h)) -> ((z1, acc1), local)``: the element as a map of the
        run's carry (its state and a sweep's diagnostics, ``Spec.observe``), and ``local``, what
        its outputs read (``_kinds``): its start z, polynomial W, end z1, start time and length."""
        spec = self.spec

        def local(theta, carry, times):
            z, acc = carry
            z1, W, start, h = self.outputs(*hold(theta, z, *times))
            acc1 = None if spec.observe is None else spec.observe(acc, *_output.user_view(z1, self.clock))
            # args~: an event's g may read H's args (``_controllers.event_value``)
            return (z1, acc1), dict(z=z, W=W, z1=z1, start=start, h=h, args=theta[1])

        return local


# ---------------------------------------------------------------------------------------------
# the outputs, each defined once as a function of the element that writes it; the sweeps take
# its tangent (``jax.jvp``) and its cotangent (``jax.vjp``) from that one definition

# the owner of a row that no element writes (sorted after every element)
_NOWHERE = 2 ** 31 - 1


@dataclasses.dataclass(frozen=True)
class _Rows:
    """Rows of the outputs ``keys`` written by the elements: row i is ``value(local, extra_i, i)``
    of the element ``owner[i]`` (sorted; ``_NOWHERE``: no element wrote it, and its value is NaN),
    ``local`` that element's ``_Element.local`` and ``extra`` a differentiable input read row by
    row (the save times) or None. ``each``: every element n writes at most row ``owner(n)``
    (a function; out of range: none), computed without a loop."""

    keys: tuple
    owner: object
    value: object
    extra: str = None
    each: bool = False
    written: object = None  # each: the rows some element writes (a boolean mask), None: all


def _kinds(spec, inputs, c, clock, view):
    """Every differentiable output of the run as ``_Rows``: the dense output's nodes and
    polynomials, where the run ended, the states at the save times, and the events."""
    steps, dtype = c["steps"], c["hs"].dtype
    sigma = _sigma(inputs)
    outside = spec.max_steps + 2  # a row index no output has
    terminal = _terminal(spec)
    ended_here = lambda n: _terminated(spec, c) & (n == steps - 1)

    def ended(local):
        """``(t*, z*, alpha*)`` of the terminal event that ended the run in this element."""
        rows = [(k, e) for k, e in enumerate(spec.events) if e.terminal]
        branch = lambda e, k: lambda: _event(e.g, sigma, clock, view, local["z"], local["W"], local["start"],
                                             local["h"], c["ev_alpha"][k][0], local["args"])
        index = sum(jnp.where(c["ended"] == k, i, 0) for i, (k, _) in enumerate(rows))
        return jax.lax.switch(index, [branch(e, k) for k, e in rows])

    def end(local, n):
        """Where element n ends: its end node, or where a terminal event ended the run in it."""
        t_b = local["start"] + local["h"] if clock is None else local["z1"][clock]
        if not terminal:
            return local["z1"], t_b
        return jax.lax.cond(ended_here(n), lambda: ended(local)[1::-1], lambda: (local["z1"], t_b))

    def polynomial(local, n):
        """Element n's polynomial; where a terminal event ended the run, on [t_n, t*]."""
        if not terminal:
            return local["W"]
        return jax.lax.cond(ended_here(n), lambda: _output.truncated(local["W"], ended(local)[2]), lambda: local["W"])

    start = lambda local: (local["z"], local["start"] if clock is None else local["z"][clock])
    nodes = jnp.arange(spec.max_steps + 1)
    kinds = [_Rows(("z", "t"), lambda n: jnp.where(n == steps - 1, 0, outside), lambda l, _, n: end(l, n), each=True)]
    if spec.dense:
        kinds.append(_Rows(("node_z", "node_t"), lambda n: jnp.where(n == 0, 0, outside), lambda l, _, n: start(l),
                           each=True))
        kinds.append(_Rows(("node_z", "node_t"), lambda n: n + 1, lambda l, _, n: end(l, n), each=True,
                           written=nodes <= steps))
    if spec.dense is True:
        kinds.append(_Rows(("W",), lambda n: n, lambda l, _, n: (polynomial(l, n),), each=True))
    if inputs["ts"] is not None:
        elements, alphas = c["places"]
        at_start = elements == _output.AT_START
        owner = jnp.where(at_start, 0, jnp.where(elements == _output.NOT_WRITTEN, _NOWHERE, elements))
        node = jnp.where(at_start, -1, jnp.where(alphas == 1.0, 1, 0))
        alphas = jnp.where(at_start, 0.0, alphas).astype(dtype)
        kinds.append(_Rows(("saved",), owner, lambda l, ts, i: (_save(clock, l["z"], l["W"], l["z1"], l["start"],
                                                                       l["h"], ts, alphas[i], node[i]),),
                           extra="ts"))
    for k, event in enumerate(spec.events or ()):
        owner = jnp.where(c["ev_n"][k] < 0, _NOWHERE, c["ev_n"][k])
        kinds.append(_Rows((f"ev_t/{k}", f"ev_z/{k}"), owner,
                           lambda l, _, i, k=k, g=event.g: _event(g, sigma, clock, view, l["z"], l["W"], l["start"],
                                                                  l["h"], c["ev_alpha"][k][i], l["args"])[:2]))
    return kinds


def _flat(tree):
    """The outputs keyed by their place: event k's rows under ``"ev_t/k"``; ``z`` and ``t``,
    which one element writes, as a row each."""
    flat = {}
    for key, value in tree.items():
        if key in ("ev_t", "ev_z"):
            flat.update({f"{key}/{k}": v for k, v in enumerate(value)})
        else:
            flat[key] = value[None] if key in ("z", "t") else value
    return flat


def _nested(flat):
    """``_flat``'s inverse."""
    tree = {}
    for key, value in flat.items():
        if "/" in key:
            name, k = key.split("/")
            tree.setdefault(name, {})[int(k)] = value
        else:
            tree[key] = value[0] if key in ("z", "t") else value
    return {k: tuple(v[i] for i in range(len(v))) if isinstance(v, dict) else v for k, v in tree.items()}


def _unwritten(kind, steps, size):
    """The rows of ``kind`` that no element of the run wrote (their values are NaN)."""
    if kind.each:
        return jnp.zeros((size,), bool) if kind.written is None else ~kind.written
    return kind.owner >= steps


def _each(kinds, n):
    """``local -> [rows]``: the rows element n writes of every output that each element writes
    once (``_Rows.each``), in one function (one linearisation for all of them)."""
    each = [kind for kind in kinds if kind.each]
    return each, lambda local: [kind.value(local, None, n) for kind in each]


def _write_tangents(kinds, n, local, d_local, extra, d_extra, out):
    """Element n's rows of every output: the tangents of their values (forward mode)."""
    each, rows = _each(kinds, n)
    _, d_rows = jax.jvp(rows, (local,), (d_local,))
    for kind, values in zip(each, d_rows):
        out = dict(out, **{key: out[key].at[kind.owner(n)].set(row, mode="drop") for key, row in
                           zip(kind.keys, values)})
    for kind in kinds:
        if kind.each:
            continue

        def one(i, out, kind=kind):
            x, dx = (None, None) if kind.extra is None else (extra[kind.extra][i], d_extra[kind.extra][i])
            _, rows = jax.jvp(lambda l, x: kind.value(l, x, i), (local, x), (d_local, dx))
            return dict(out, **{key: out[key].at[i].set(row) for key, row in zip(kind.keys, rows)})

        out = jax.lax.fori_loop(*_range(n, kind.owner), one, out)
    return out


def _read_cotangents(kinds, n, local, extra, ct, extra_bar):
    """Element n's rows of every output: their cotangents pulled back to the element's
    ``local`` values and the row-wise inputs (reverse mode), the transpose of
    ``_write_tangents``."""
    each, rows = _each(kinds, n)
    _, pull = jax.vjp(rows, local)
    (local_bar,) = pull([tuple(ct[key].at[kind.owner(n)].get(mode="fill", fill_value=0) for key in kind.keys)
                         for kind in each])
    for kind in kinds:
        if kind.each:
            continue

        def one(i, bars, kind=kind):
            local_bar, extra_bar = bars
            x = None if kind.extra is None else extra[kind.extra][i]
            _, pull = jax.vjp(lambda l, x: kind.value(l, x, i), local, x)
            bar, x_bar = pull(tuple(ct[key][i] for key in kind.keys))
            if kind.extra is not None:
                extra_bar = dict(extra_bar, **{kind.extra: extra_bar[kind.extra].at[i].add(x_bar)})
            return jax.tree.map(jnp.add, local_bar, bar), extra_bar

        local_bar, extra_bar = jax.lax.fori_loop(*_range(n, kind.owner), one, (local_bar, extra_bar))
    return local_bar, extra_bar


def _range(n, owner):
    """``[lo, hi)``, where the sorted ``owner`` equals n."""
    return jnp.searchsorted(owner, n, side="left"), jnp.searchsorted(owner, n, side="right")


def _sweep_setup(spec, inputs, c):
    fn, _, clock = _problem(spec, inputs)
    view = lambda z: _output.user_view(z, clock)
    return fn, clock, view, _kinds(spec, inputs, c, clock, view), _resolve_options(spec, inputs)


def _tangent_sweep(spec, inputs, c, d, wanted):
    """The tangents of the differentiable outputs for the inputs' tangents ``d`` (forward mode),
    ``wanted`` the inputs whose tangents are not zero (``_tangents``): element after element,
    each ``_Element.local`` and the rows it writes (``_write_tangents``) by ``jax.jvp``."""
    fn, clock, view, kinds, options = _sweep_setup(spec, inputs, c)
    primal = tuple(inputs[k] for k in ("q0", "p0", "args", "t0"))
    (z0, run_args), (dz0, d_run_args) = jax.jvp(lambda *a: _start(spec, *a), primal,
                                                tuple(d[k] for k in ("q0", "p0", "args", "t0")))
    theta, d_theta = (inputs["method"], run_args), (d["method"], d_run_args)
    times, d_times = tuple(inputs[k] for k in ("t0", "t1", "h")), tuple(d[k] for k in ("t0", "t1", "h"))
    extra, d_extra = {"ts": inputs["ts"]}, {"ts": d["ts"]}
    hold = _held(wanted)
    dtype = z0.dtype
    acc0 = d_acc0 = None
    if spec.observe is not None:
        acc0, d_acc0 = jax.jvp(spec.acc0, primal[:3], tuple(d[k] for k in ("q0", "p0", "args")))
    out = _flat({k: jax.tree.map(jnp.zeros_like, c[k]) for k in DIFFERENTIABLE if k in c and k != "acc"})

    def body(s):
        n, carry, d_carry, t_n, matrix, previous, ok, out = s
        element = _Element(spec, fn, inputs, c, clock, n, t_n, None)
        element.Z, matrix, solved = _resolve(fn, theta, carry[0], element.h_n, previous, matrix, options,
                                                    explicit_here(theta[0], spec))
        (carry1, local), (d_carry1, d_local) = jax.jvp(element.local(hold), (theta, carry, times),
                                                        (d_theta, d_carry, d_times))
        out = _write_tangents(kinds, n, local, d_local, extra, d_extra, out)
        t_next = t_n + element.h_n if clock is None else carry1[0][clock]
        previous = (carry[0], element.Z, element.h_n, jnp.ones((), bool))
        return n + 1, carry1, d_carry1, t_next, matrix, previous, ok & solved, out

    guess = inputs["method"].initial_guess(*jnp.split(z0, 2))
    previous = (z0, guess, jnp.ones((), dtype), jnp.zeros((), bool))
    s = (jnp.zeros((), jnp.int32), (z0, acc0), (dz0, d_acc0), jnp.asarray(inputs["t0"], dtype),
         initial_matrix(guess, options), previous, keeps_state(c["status"]), out)
    *_, d_carry, _, _, _, ok, out = jax.lax.while_loop(lambda s: s[0] < c["steps"], body, s)
    for kind in kinds:  # a row no element wrote has no tangent
        for key in kind.keys:
            unwritten = _unwritten(kind, c["steps"], out[key].shape[0])
            out[key] = jnp.where(unwritten.reshape((-1,) + (1,) * (out[key].ndim - 1)), jnp.nan, out[key])
    out = _nested(out)
    if spec.observe is not None:
        out["acc"] = d_carry[1]
    # a run that failed, or an element not found again, has no tangent: NaN, never a plausible one
    return jax.tree.map(lambda x: jnp.where(ok, x, jnp.nan) if _inexact(x) else x, out)


def _adjoint_sweep(spec, inputs, c, ct, wanted):
    """The cotangents of the inputs for the outputs' cotangents ``ct`` (reverse mode), the
    transpose of ``_tangent_sweep``: element after element backwards, each
    ``_Element.local`` and the rows it writes (``_read_cotangents``) by ``jax.vjp``; those of
    inputs not in ``wanted`` (``_tangents``) are zero."""
    fn, clock, view, kinds, options = _sweep_setup(spec, inputs, c)
    primal = tuple(inputs[k] for k in ("q0", "p0", "args", "t0"))
    (z0, run_args), start_vjp = jax.vjp(lambda *a: _start(spec, *a), *primal)
    theta = (inputs["method"], run_args)
    times = tuple(inputs[k] for k in ("t0", "t1", "h"))
    extra = {"ts": inputs["ts"]}
    hold = _held(wanted)
    dtype, steps, every = z0.dtype, c["steps"], c["kept"]["z"].shape[0]
    zeros = lambda tree: jax.tree.map(jnp.zeros_like, tree)
    ct = _flat({k: v for k, v in ct.items() if k != "acc"}) | {"acc": ct.get("acc")}
    # a cotangent on a row that no element wrote (a NaN value) makes every cotangent NaN
    poisoned = jnp.zeros((), bool)
    for kind in kinds:
        for key in kind.keys:
            unwritten = _unwritten(kind, steps, ct[key].shape[0])
            poisoned = poisoned | jnp.any(unwritten.reshape((-1,) + (1,) * (ct[key].ndim - 1)) & (ct[key] != 0))
    acc0 = None if spec.observe is None else spec.acc0(*primal[:3])
    guess = inputs["method"].initial_guess(*jnp.split(z0, 2))

    def again(k, first, count, kept, ok):
        """Stretch k's (from element ``first``) first ``count`` elements found again, forwards
        from its checkpoint, their roots in ``kept``."""
        start = jax.tree.map(lambda a: a[k], c["checkpoints"])

        def found(i, r):
            z, t, acc, matrix, previous, ok, kept = r
            h_n = c["hs"][first + i]
            Z, matrix, solved = _resolve(fn, theta, z, h_n, previous, matrix, options, explicit_here(theta[0], spec))
            z1 = _element(spec, fn, theta, z, h_n, Z)[0]
            kept = jax.tree.map(lambda b, x: b.at[i].set(x), kept, dict(z=z, Z=Z, t=t, acc=acc))
            acc1 = None if spec.observe is None else spec.observe(acc, *view(z1))
            t1 = t + h_n if clock is None else z1[clock]
            return z1, t1, acc1, matrix, (z, Z, h_n, jnp.ones((), bool)), ok & solved, kept

        previous = (z0, guess, jnp.ones((), dtype), jnp.zeros((), bool))
        r = (start["z"], start["t"], start["acc"], initial_matrix(guess, options), previous, ok, kept)
        *_, ok, kept = jax.lax.fori_loop(0, count, found, r)
        return kept, ok

    def backwards(first, length, kept, s):
        """The ``length`` elements from ``first`` taken backwards, from their roots in ``kept``."""

        def back(j, s):
            carry_bar, theta_bar, times_bar, extra_bar = s
            i = length - 1 - j
            n = first + i
            acc = None if spec.observe is None else jax.tree.map(lambda a: a[i], kept["acc"])
            element = _Element(spec, fn, inputs, c, clock, n, kept["t"][i], kept["Z"][i])
            (_, local), pull = jax.vjp(element.local(hold), theta, (kept["z"][i], acc), times)
            local_bar, extra_bar = _read_cotangents(kinds, n, local, extra, ct, extra_bar)
            theta_b, carry_bar, t_b = pull((carry_bar, local_bar))
            return carry_bar, _add(theta_bar, theta_b), tuple(a + b for a, b in zip(times_bar, t_b)), extra_bar

        return jax.lax.fori_loop(0, length, back, s)

    # the last stretch from the forward run's roots, then each earlier one found again over them
    # (one loop: the backward element compiles once)
    last = (steps + every - 1) // every - 1

    def segment(s):
        k, kept, ok, *bars = s
        first = k * every
        length = jnp.minimum(steps, first + every) - first
        kept, ok = again(k, first, jnp.where(k == last, 0, length), kept, ok)
        return k - 1, kept, ok, *backwards(first, length, kept, tuple(bars))

    carry_bar = (jnp.zeros_like(z0), ct["acc"])
    times_bar = tuple(jnp.zeros((), dtype) for _ in times)
    extra_bar = {"ts": None if inputs["ts"] is None else jnp.zeros_like(inputs["ts"])}
    s = (last, c["kept"], keeps_state(c["status"]), carry_bar, zeros(theta), times_bar, extra_bar)
    _, _, ok, (lam, acc_bar), (method_bar, run_args_bar), (t0_bar, t1_bar, h_bar), extra_bar = jax.lax.while_loop(
        lambda s: s[0] >= 0, segment, s)
    q0_bar, p0_bar, args_bar, t0_start_bar = start_vjp((lam, run_args_bar))
    if spec.observe is not None:
        q0_a, p0_a, args_a = jax.vjp(spec.acc0, *primal[:3])[1](acc_bar)
        q0_bar, p0_bar, args_bar = q0_bar + q0_a, p0_bar + p0_a, _add(args_bar, args_a)
    bar = dict(q0=q0_bar, p0=p0_bar, args=args_bar, method=method_bar, t0=t0_bar + t0_start_bar, t1=t1_bar,
               ts=extra_bar["ts"], h=h_bar)
    good = ok & ~poisoned
    return jax.tree.map(lambda x: jnp.where(good, x, jnp.nan) if _inexact(x) else x, bar)
