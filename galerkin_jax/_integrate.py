"""One time element (``step``), many (``integrate``), and the one-step Jacobian (``amplification_matrix``)."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from . import _adjoint, _checks, _inputs, _output, _reversible, _shape, _span
from ._controllers import Event, Events, PIDController, TimeTransform
from ._explicit import explicit_form

from ._march import (bind_args, density_in_direction, input_status, march, nan_if_failed, reserved_to_t1, short_of_t1, solve_element,
                     solver_options, in_direction)
from ._output import DenseOutput
from ._pytree import pytree_dataclass
from ._solve import SolverOptions, Status, throw_if_failed

DEFAULT_MAX_NEWTON_ITERATIONS = SolverOptions.max_iterations


DEFAULT_MAX_STEPS = 4096  # attempts of a run whose steps a controller chooses (diffrax's default)


_STATIC = dict(metadata=dict(static=True))


@pytree_dataclass
class Problem:
    """What is integrated: Hamilton's equations of ``H`` (static) from ``(q0, p0)`` (flat), by
    ``method`` with ``args`` (H's third argument, or None), the steps chosen by ``controller``
    (a ``PIDController`` or ``TimeTransform``; None: fixed steps)."""

    H: object = dataclasses.field(**_STATIC)
    q0: jax.Array = None
    p0: jax.Array = None
    method: object = None
    args: object = None
    controller: object = None


@pytree_dataclass
class Span:
    """Where the run goes: from ``t0`` to ``t1`` (None: ``n_steps`` elements) in the direction
    ``direction`` (``_output.Direction``: a known sigma is static), by the step ``h`` (a
    controller's first; None: picked, ``_adaptive.first_step``). ``h_last``: the last element's
    length where fixed steps land on a concrete t1, else None. ``n_steps`` (the elements of fixed
    steps) and ``max_steps`` (a loop's attempts, or the elements a scan to a traced t1 reserves)
    are static; ``count``: the elements taken of ``n_steps`` reserved (``integrate``'s n_steps
    given with max_steps, a value), else None."""

    t0: jax.Array = 0.0
    t1: jax.Array = None
    h: jax.Array = None
    direction: object = _output.FORWARDS
    h_last: jax.Array = None
    count: jax.Array = None
    n_steps: int = dataclasses.field(default=None, **_STATIC)
    max_steps: int = dataclasses.field(default=None, **_STATIC)


@pytree_dataclass
class Outputs:
    """What the run keeps: the states at the save times ``ts`` (None: the ends, or fixed steps'
    every ``save_every``-th node) or at every node (``nodes``, ``save_at="steps"``), the
    ``events`` (a tuple of ``Event``, or None), every element's polynomial (``dense``) and the
    largest local error (``estimate``, as ``integrate``'s ``error_estimate``). All but ``ts`` and
    the events' leaves are static."""

    ts: jax.Array = None
    events: tuple = None
    nodes: bool = dataclasses.field(default=False, **_STATIC)
    save_every: int = dataclasses.field(default=1, **_STATIC)
    dense: bool = dataclasses.field(default=False, **_STATIC)
    estimate: object = dataclasses.field(default=True, **_STATIC)


@pytree_dataclass
class RunOptions:
    """How the run computes: the root finder's ``Options``, the gradient's storage
    (``checkpoint``, as ``integrate``'s) and the progress bar (static); ``tolerance``: the
    stopping rule's ``SolverOptions.tolerance`` as a value (``planned``), or None where the
    options hold it."""

    solver: object = dataclasses.field(default=None, **_STATIC)
    checkpoint: object = dataclasses.field(default=False, **_STATIC)
    progress: bool = dataclasses.field(default=False, **_STATIC)
    tolerance: jax.Array = None

    @classmethod
    def planned(cls, options, dtype, checkpoint=False, progress=False):
        """The run's options with ``SolverOptions.tolerance`` a value of the program, so that
        another tolerance compiles nothing new; the reversible gradient (whose steps back are a
        ``jax.custom_vjp`` with the options static) keeps it in the options."""
        if checkpoint == _reversible.REVERSIBLE:
            return cls(options, checkpoint, progress)
        static = dataclasses.replace(options, solver=dataclasses.replace(options.solver, tolerance=0.0))
        return cls(static, checkpoint, progress, tolerance=np.asarray(options.solver.tolerance, dtype))

    def root_finder(self):
        """The root finder's ``Options``, holding the tolerance's value where it is one."""
        return self.solver if self.tolerance is None else self.solver.with_tolerance(self.tolerance)


@pytree_dataclass
class Run:
    """One frozen description of a run of ``integrate``, built once from its checked arguments
    and handed down (``_directed``, ``_dispatch``) to the compiled program (``_integrate``,
    ``_integrate_adaptive``), whose argument it is: its static parts are the program's, its
    leaves the values it runs on."""

    problem: Problem
    span: Span
    outputs: Outputs
    options: RunOptions


def _replace(run, **parts):
    """``run`` with the fields ``parts[name]`` (a dict) of its part ``name`` replaced."""
    return dataclasses.replace(run, **{name: dataclasses.replace(getattr(run, name), **fields)
                                       for name, fields in parts.items()})


@pytree_dataclass
class Solution:
    """The result of ``integrate``: the saved states, the run's status and its counts.

    Attributes:
        t: the save times, shape ``(m,)``: ``save_at`` where given; for fixed steps every
            ``save_every``-th node from ``t0`` (``m = n_steps // save_every + 1``); for a run
            with a controller or events and no ``save_at``, ``[t0, t_end]``.
        q: the positions at ``t``, of shape ``(m,) + shape`` for states of that shape (``(m, d)``
            for 1-D states; a pytree state: its leaves with the leading axis m). After the first
            failure the states are NaN; a run stopped by ``max_steps`` or ``dtmin`` (status
            MAX_STEPS, DTMIN) keeps the time and state where it stopped, its later save times NaN.
        p: the momenta at ``t``, likewise.
        status: the run's int32 ``Status`` code, 0 when every implicit solve converged (an
            explicit method, which has none: when it ran to its end with no step that lost all
            accuracy, ``Status.INACCURATE``). Status 0 promises converged solves, not accurate
            steps: read ``error_estimate`` for that.
        stats: the run's counts, a dict of arrays:

            - ``num_newton_iterations``: the iterations of the implicit solves, in total;
            - ``max_newton_iterations``: the largest count in one element;
            - ``batch_newton_iterations``: the iterations the batch ran (under ``vmap`` each
              element waits for the batch's slowest member);
            - ``num_accepted_stalled``: elements accepted other than at round-off (their updates
              stopped shrinking with the residual below sqrt(eps) of the state, see ``Status``);
            - ``num_steps``: every attempt, as in diffrax, the sum of the two below;
            - ``num_accepted_steps``: the elements of the run;
            - ``num_rejected_steps``: the attempts not accepted (a time-transformed run's are its
              tries at the last element; fixed steps reject none);
            - ``min_step``, ``max_step``: the smallest and largest accepted h (of a
              time-transformed run, in tau; of fixed steps h, where the last element to t1 may
              be shorter).
        error_estimate: the largest estimated local (one-element) error of the run, max-norm
            over (q, p), shape (); NaN for a failed run and for ``LagrangianVI``.
        dense: the element polynomials, a ``DenseOutput``, with ``integrate(..., dense=True)``;
            else None.
        events: the located events, an ``Events`` with ``integrate(..., events=Event(...))`` (a
            list of them for a list of events); else None.
        layout: the layout of a state that is not one 1-D array (``_shape.Layout``), else None.
            Static.
    """

    t: jax.Array
    q: jax.Array
    p: jax.Array
    status: jax.Array
    stats: dict
    error_estimate: jax.Array
    dense: object = None
    events: object = None
    layout: object = dataclasses.field(default=None, metadata=dict(static=True))

    def evaluate(self, t) -> tuple:
        """``(q, p)`` at the times ``t`` (scalar or 1-D) in ``[t0, t1]``: the states at the nodes,
        each element's polynomial in between (one run, ``dense=True``). A time outside
        [t0, t1] raises a ValueError where t is concrete and gives NaN under jit; every time
        after a failed element (or a terminal event) gives NaN.

        Returns:
            ``(q, p)``, each shape ``t.shape + shape`` (states of that shape; a pytree: each leaf).
        """
        dense = self.dense
        if dense is None:
            raise ValueError("evaluate needs the element polynomials: integrate(..., dense=True).")
        if jnp.ndim(dense.t) != 1:
            raise ValueError("evaluate works on one run; index a batched Solution first.")
        t = jnp.asarray(t, dense.z.dtype)
        if t.ndim > 1:
            raise ValueError(f"t must be a scalar or 1-D, got shape {t.shape}.")
        bounds = (dense.t[0], dense.t1)
        if not any(isinstance(x, jax.core.Tracer) for x in (t, *bounds)):
            lo, hi = sorted(float(b) for b in bounds)
            if not bool(jnp.all((t >= lo) & (t <= hi))):
                raise ValueError(f"t must lie in [t0, t1] = [{lo}, {hi}], got values outside.")
        q, p = dense.view(_evaluate(dense, jnp.atleast_1d(t)))
        q, p = q.reshape(t.shape + q.shape[-1:]), p.reshape(t.shape + p.shape[-1:])
        return (q, p) if self.layout is None else (self.layout.unflatten(q), self.layout.unflatten(p))


@jax.jit
def _evaluate(dense, t):
    return _output.evaluate(dense, t)


def prepare(H, q0, p0, method, h, args):
    _checks.check_function(H)
    _checks.check_method(method)
    q0, p0 = _checks.check_state(q0, p0)
    if h is not None:
        _checks.check_step_size(h)
    fn = bind_args(H, args)
    _checks.check_scalar_output(fn, q0, p0)
    _checks.check_premise(method, fn, q0, p0)
    return q0, p0, None if h is None else _span.as_value(h, q0.dtype)


@_inputs.on_entry
@_shape.on_step
def step(H, q, p, *, method, h, args=None, max_newton_iterations=None, krylov=None, solver=None, throw=False,
         return_status=False) -> tuple:
    """One time element: ``(q, p) -> (q1, p1)``.

    A failed solve returns NaN states (never a plausible one).

    Args:
        H: the Hamiltonian, ``H(q, p)`` or ``H(q, p, args)`` returning a scalar; required. For
            ``LagrangianVI`` it is the Lagrangian ``L(q, qdot)``.
        q: the position at the element's start, an array of any shape (``(d,)``, ``(N, 3)``, ...)
            or a pytree of arrays; required. H receives it so.
        p: the momentum at the element's start, of q's shape (pytree structure); required.
        method: the time-stepping scheme, e.g. ``CG(k, rule)``, ``DG(k, rule)``; required.
        h: the step size, a scalar > 0; required.
        args: the extra input of ``H``, passed as its third argument; default None.
        max_newton_iterations: the iteration cap of the implicit solve; default None (48), as in
            ``integrate``. Static.
        krylov: solve by Newton-Krylov; default None (False), as in ``integrate``. Static.
        solver: the implicit solve's options, a ``SolverOptions``; default None
            (``SolverOptions()``), as in ``integrate``. Static.
        throw: raise ``SolverError`` when the solve failed; default False. Outside ``jit`` only,
            as in ``integrate``.
        return_status: also return the int32 ``Status`` code; default False. Works under jit.

    Returns:
        ``(q1, p1)``, in the shape (structure) of q and p; ``(q1, p1, status)`` with ``return_status``.
    """
    q, p, h = prepare(H, q, p, method, h, args)
    options = solver_options(method, max_newton_iterations, krylov, solver)
    method = explicit_form(method, H, q, p, args, options.solver)
    q1, p1, status = _step(H, q, p, method, h, args, options)
    if throw:
        throw_if_failed(status)
    q1, p1 = nan_if_failed(q1, status), nan_if_failed(p1, status)
    return (q1, p1, status) if return_status else (q1, p1)


@functools.partial(jax.jit, static_argnums=(0, 6))
def _step(H, q, p, method, h, args, options):
    q1, p1, _, _, status = solve_element(method, H, q, p, h, args, options)
    return q1, p1, jnp.maximum(status, input_status(q, p, h))


@_inputs.on_entry
@_shape.on_integrate
def integrate(
    H,
    q0,
    p0,
    *,
    method,
    h=None,
    n_steps=None,
    t0=0.0,
    t1=None,
    controller=None,
    max_steps=None,
    save_at=None,
    events=None,
    args=None,
    save_every=1,
    max_newton_iterations=None,
    krylov=None,
    solver=None,
    throw=False,
    checkpoint=False,
    dense=False,
    progress=False,
    error_estimate=True,
) -> Solution:
    """Integrate Hamilton's equations from ``t0``, over ``n_steps`` elements of size ``h`` or to ``t1``.

    Give ``n_steps`` for that many equal steps, or ``t1`` to end at a time. With ``t1`` a
    ``controller`` may choose the steps: error per step (``PIDController``) or a time
    transformation that keeps the method's structure (``TimeTransform``). Fixed steps are
    chained by a nested ``lax.scan`` (outer over saves, inner over ``save_every`` elements), so
    memory is O(n_steps / save_every); to a ``t1`` the last element is shortened to land on it.

    Args:
        H: the Hamiltonian, a function ``H(q, p)`` or ``H(q, p, args)`` that returns a scalar;
            required. For ``LagrangianVI`` it is the Lagrangian ``L(q, qdot)``.
        q0: the initial position, an array of any shape (``(d,)``, ``(N, 3)``, ...) or a pytree
            of arrays; required. H, an event's g and a time transformation's s receive states in
            this shape; the solver works on the flattened vectors of length d, the number of
            elements of q0.
        p0: the initial momentum, of q0's shape (pytree structure); required, for
            ``LagrangianVI`` too.
        method: the time-stepping scheme, a method object such as ``CG(2, gauss_legendre(2))``,
            ``DG``, ``GalerkinVI``; required.
        h: the step size, > 0; default None, which only a ``PIDController``'s run accepts: it
            picks the first step by Hairer, Norsett and Wanner's starting step algorithm (Solving
            ODEs I, Sec. II.4), as diffrax does. Under a controller h is the first step (a
            ``TimeTransform``'s: the step in its fictive time tau); it may be traced (vmap over
            step sizes).
        n_steps: the number of elements of size h; default None, then give ``t1``. Static; a
            multiple of ``save_every``. Given with ``max_steps`` it is a value (it may be traced),
            so another n_steps reuses the compiled program: see ``max_steps``.
        t0: the start time; default 0.0.
        t1: the end time; default None, then give ``n_steps``. t1 < t0 runs backwards in time
            (not with ``LagrangianVI``), also where t0 or t1 is traced (``jit``, ``vmap`` over t1
            with members of both directions); t1 = t0 returns the initial state. An infinite t1
            (``jnp.inf``, ``-jnp.inf``) runs until a terminal event ends it: at most ``max_steps``
            attempts, which fixed steps then need.
        controller: what chooses the steps; default None, fixed steps of size h. Pass a
            ``PIDController`` for a short accurate run or a ``TimeTransform`` for a long one;
            either needs ``t1``.
        max_steps: the most step attempts, accepted and rejected, of a controller's run; default
            None (4096). Raise it when a run ends with status MAX_STEPS. With fixed steps it is
            the elements the scan reserves, required to a traced ``t1`` or with a traced ``h``: a
            run of any ``n_steps`` or to any ``t1`` within the reserve reuses one program. Its
            saves are every ``save_every``-th node of the reserve (a multiple of it), those past
            the end repeat the end state at the end time; an end beyond the reserve stops there
            with status MAX_STEPS. Static.
        save_at: the times at which to save the state; default None: every ``save_every``-th
            node of fixed steps, ``[t0, t_end]`` of a run with a controller or events. Times
            between t0 and t1, sorted in the run's direction, are read off the element
            polynomials and become ``Solution.t``; ``"steps"`` saves every accepted node, in the
            user's shapes (a controller's run: ``max_steps + 1`` rows, t = inf and NaN states past
            the last node; ``num_accepted_steps + 1`` of them hold nodes).
        events: the sign changes of functions g(t, q, p) to locate; default None. An ``Event``
            or a list of them, each located on the element polynomials and reported in
            ``Solution.events`` (an ``Events``, or a list of them).
        args: the extra input of ``H``, passed as its third argument; default None. It may be
            traced (differentiated, vmapped) without a new compilation.
        save_every: the stride of the saved states of a fixed-step run of ``n_steps``; default 1,
            every node. Raise it to store fewer states on a long run. Static.
        max_newton_iterations: the implicit solve's iteration cap per element; default None
            (``SolverOptions.max_iterations``, 48). A shorthand for that field of ``solver``; the
            fixed-point iteration counts in blocks of two (an element of more than 32 unknowns
            starting with four), so a cap is rounded up to a block's end there. Static.
        krylov: solve by Newton-Krylov (GMRES on Hessian-vector products); default None
            (``SolverOptions.krylov``, False). Turn it on for stiff systems (h omega >~ 1) of more
            than 256 unknowns per element (k * 2d for cG(k), (k + 1) * 2d for dG(k)), which
            without it have the fixed-point iteration only; dG(k >= 1) has no fixed point and
            always uses it. Static.
        solver: the implicit solve's options, a ``SolverOptions``; default None
            (``SolverOptions()``). The two shorthands above replace their fields. Static.
        throw: raise ``SolverError`` with the status's message when the status is nonzero;
            default False (read ``Solution.status``). Only outside ``jit``/``vmap``/``grad``:
            there the status is traced, and ``throw=True`` raises a ``TypeError`` before anything
            runs.
        checkpoint: what a reverse-mode gradient stores of the run; default False, every
            element's residuals. True rematerialises each saved block, so a gradient stores one
            state per save; ``"reversible"`` stores the saves only (see Notes). Static.
        dense: keep every element's polynomial, for ``Solution.evaluate``; default False. Memory
            O(n_steps), or O(max_steps) for a controller's run. Static.
        progress: show a progress bar, ticked from inside the compiled loop (fixed steps);
            default False. tqdm if installed, else lines on stderr. Static.
        error_estimate: how ``Solution.error_estimate``, the largest local error (``_defect``),
            is computed; default True, the full estimate on the four elements where the embedded
            one (``embedded_error``, one field evaluation per element) peaks. ``"full"``: on every
            element (the exact maximum, at J + 1 field evaluations and J Jacobian products per
            element); False leaves it NaN. Static.

    Returns:
        ``Solution``.

    Notes:
        Gradients of a run whose steps are chosen as it runs (a controller, ``save_at``, events)
        keep the roots of its last 512 elements (at most 16 MiB) and solve the elements before
        them again; ``checkpoint=True`` keeps sqrt(max_steps) of them
        ([Derivatives](derivatives.md#what-a-gradient-costs)). ``checkpoint="reversible"``
        rebuilds each state in the backward pass by an element of step -h,
        z_n = Phi_{-h}(z_{n+1}) (``_reversible``): memory O(1) in n_steps at twice the element
        solves. It needs a symmetric method (cG(k), GalerkinVI with a symmetric rule,
        ModifiedMidpoint, compositions) and fixed steps of ``n_steps`` or to a concrete t1;
        elsewhere it raises a ValueError.
    """
    q0, p0, h = prepare(H, q0, p0, method, h, args)
    _span.check_span(n_steps, t0, t1, controller, events, max_steps)
    _span.check_controller(controller, method)
    if h is None and not isinstance(controller, PIDController):
        raise ValueError("h=None picks the first step of a PIDController's run; fixed steps and a TimeTransform "
                         "need h.")
    options = solver_options(method, max_newton_iterations, krylov, solver)
    method = explicit_form(method, H, q0, p0, args, options.solver)
    estimate = _span.check_estimate(error_estimate)
    checkpoint = _reversible.check_checkpoint(checkpoint)
    if checkpoint == _reversible.REVERSIBLE:
        _reversible.check_reversible(method, controller=controller, save_at=save_at, events=events, dense=dense,
                                     traced_end=max_steps is not None and controller is None
                                     or n_steps is None and not _span.concrete(h, t0, t1))
    single = isinstance(events, Event)
    events = _span.check_events(events, q0, p0, t0, args)
    sigma = _span.direction(t0, t1, q0.dtype)
    nodes = _span.check_nodes(save_at, save_every)
    ts = None if nodes else _span.check_save_at(save_at, t0, t1, q0.dtype, sigma)
    run = Run(Problem(H, q0, p0, method, args, controller),
              Span(t0, t1, h, _output.Direction(sigma), n_steps=n_steps, max_steps=max_steps),
              Outputs(ts, events, nodes=nodes, save_every=save_every, dense=bool(dense), estimate=estimate),
              RunOptions.planned(options, q0.dtype, checkpoint=checkpoint, progress=bool(progress)))
    sol = _reversible.reverse_mode_only(_directed)(run) if checkpoint == _reversible.REVERSIBLE else _directed(run)
    if single:
        sol = dataclasses.replace(sol, events=sol.events[0])
    if throw:
        throw_if_failed(sol.status)
    return sol


def _directed(run):
    """The run from t0 to t1 in the direction sigma = sign(t1 - t0) (``_span.direction``): with
    tau = sigma t, Hamilton's flow is dz/dtau = J D(sigma H)(z), so it is the run forwards of
    sigma H (``_march.in_direction``) from sigma t0 to sigma t1, its save times sigma ts, its
    events' g evaluated at t = sigma tau (``_output.directed``; ``Event.direction`` counts in
    run order), its times mapped back by t = sigma tau and its dense output mapping t <-> tau
    (``DenseOutput.direction``). A known sigma is a Python int (1: the run as it is; -1: -H,
    times negated); a traced one (``jit``, ``vmap`` over t1) is carried as a value, so one
    program runs either way."""
    problem, span = run.problem, run.span
    sigma, dtype = span.direction.sigma, problem.q0.dtype
    known = isinstance(sigma, int)
    if (known and sigma == 1) or (not known and not problem.method.hamiltonian):
        # forwards; or a Lagrangian, which has no sigma H: a traced t1 < t0 is INVALID_INPUT in the run
        return _dispatch(_replace(run, span=dict(t0=_span.as_value(span.t0, dtype), direction=_output.FORWARDS)))
    if not problem.method.hamiltonian:
        raise ValueError("t1 < t0 (a run backwards in time) needs a Hamiltonian method; LagrangianVI is given L.")
    H, args = in_direction(problem.H, problem.args, sigma)
    controller = density_in_direction(problem.controller, sigma)
    into = lambda x: None if x is None else _output.directed(_span.as_value(x, dtype), sigma)
    sol = _dispatch(_replace(run, problem=dict(H=H, args=args, controller=controller), span=dict(t0=into(span.t0), t1=into(span.t1)),
                             outputs=dict(ts=into(run.outputs.ts))))
    back = lambda x: _output.directed(x, sigma)
    dense = None if sol.dense is None else dataclasses.replace(
        sol.dense, t=back(sol.dense.t), t_end=back(sol.dense.t_end), t1=back(sol.dense.t1), direction=span.direction)
    events = None if sol.events is None else [dataclasses.replace(e, t=back(e.t)) for e in sol.events]
    return dataclasses.replace(sol, t=back(sol.t), dense=dense, events=events)


def _dispatch(run):
    """The compiled run that ``run`` asks for, forwards in its time (``_directed``): fixed steps
    (a scan, ``_integrate``), or a loop whose steps are not known in advance
    (``_integrate_adaptive``, whose events read the run's ``direction``)."""
    problem, span, outputs = run.problem, run.span, run.outputs
    h, t0, n_steps, max_steps, dtype = span.h, span.t0, span.n_steps, span.max_steps, problem.q0.dtype
    if outputs.nodes:  # fixed steps save every node anyway
        outputs = dataclasses.replace(outputs, save_every=1)
    # the scan's run; every node is its save_every=1
    fixed = lambda span: _integrate(dataclasses.replace(run, span=span, outputs=dataclasses.replace(outputs,
                                                                                                    nodes=False)))
    if n_steps is not None and outputs.ts is None and outputs.events is None:
        if max_steps is None:
            _checks.check_counts(n_steps, outputs.save_every)
            return fixed(span)
        # n_steps of max_steps reserved: the count is a value, so a new one reuses the program
        _checks.check_counts(max_steps, outputs.save_every, name="max_steps")  # the reserve
        return fixed(dataclasses.replace(span, count=_checks.check_count(n_steps), n_steps=max_steps,
                                         max_steps=None))
    if n_steps is not None:
        _checks.check_count(n_steps)
        span = dataclasses.replace(span, t1=t0 + n_steps * h, n_steps=None)
    span = dataclasses.replace(span, t1=_span.as_value(span.t1, dtype))
    # where h, t0 and t1 are known while tracing (concrete, or differentiated outside jit) the
    # elements are counted now; the last one's length stays a function of them (its derivatives)
    known = all(_span.known(x) is not None for x in (h, t0, span.t1))
    if max_steps is not None:
        _span.check_max_steps(max_steps)
    if problem.controller is None and outputs.ts is None and outputs.events is None:
        if outputs.save_every != 1:
            raise ValueError("save_every needs n_steps; with t1, pass save_at=times to save at chosen times.")
        if known and max_steps is None:
            n, _ = _span.fixed_step_count(*(_span.known(x) for x in (t0, span.t1, h)))
            return fixed(dataclasses.replace(span, h_last=(span.t1 - t0) - (n - 1) * h, n_steps=n))
        if max_steps is None:
            raise ValueError("Fixed steps to a traced t1 (or with a traced h) need max_steps: the elements reserved.")
        return fixed(dataclasses.replace(span, n_steps=max_steps))
    if max_steps is None:
        max_steps = (_span.fixed_step_count(*(_span.known(x) for x in (t0, span.t1, h)))[0]
                     if problem.controller is None and known else DEFAULT_MAX_STEPS)
    # a loop saves at ts or every node, and shows no progress bar: those options are not its program's
    return _integrate_adaptive(dataclasses.replace(run, span=dataclasses.replace(span, max_steps=max_steps),
                                                   outputs=dataclasses.replace(outputs, save_every=1),
                                                   options=dataclasses.replace(run.options, progress=False)))


def solution(final, saved, kept, q0, p0, h, block_size, t0=0.0, t1=None):
    """The ``Solution`` of one run from ``march``'s outputs (of a run to ``t1``: its saves
    are clipped to t1, where a member that reached it early repeats its last state)."""
    qs, ps = saved
    n_saves = qs.shape[0]
    t = t0 + jnp.arange(n_saves + 1, dtype=q0.dtype) * (block_size * h)
    if t1 is not None:
        t = jnp.minimum(t, t1).at[-1].set(t1)
    dense = None
    status = final["status"]
    if kept is not None:
        starts, W = kept
        z_end = jnp.concatenate([final["q"], final["p"]])
        nodes = t0 + jnp.arange(W.shape[0] + 1, dtype=q0.dtype) * h
        nodes = nodes if t1 is None else jnp.minimum(nodes, t1).at[-1].set(t1)
        t_end = jnp.where(status == Status.SUCCESS, nodes[-1], nodes[final["steps"]])
        dense = DenseOutput(t=nodes, z=jnp.concatenate([starts, z_end[None]]), W=W, t_end=t_end, t1=nodes[-1])
    return Solution(
        t=t,
        q=jnp.concatenate([q0[None], qs]),
        p=jnp.concatenate([p0[None], ps]),
        status=status,
        stats={"num_newton_iterations": final["total"], "max_newton_iterations": final["most"],
               "batch_newton_iterations": final["trips"], "num_accepted_stalled": final["lenient"],
               "num_steps": final["steps"], "num_accepted_steps": final["steps"],
               "num_rejected_steps": jnp.zeros_like(final["steps"]),
               "min_step": h, "max_step": h},
        error_estimate=final["estimate"],
        dense=dense,
    )


@jax.jit
def _integrate(run):
    """Fixed steps: ``n_steps`` of size h, or to ``t1`` (the last of size ``h_last``; None: ``n_steps``
    elements are reserved and the first that reach t1 taken, ``reserved_to_t1``)."""
    problem, span, outputs, options = run.problem, run.span, run.outputs, run.options
    H, q0, p0, method, args = problem.H, problem.q0, problem.p0, problem.method, problem.args
    h, t0, t1, h_last, n_steps, save_every = span.h, span.t0, span.t1, span.h_last, span.n_steps, outputs.save_every
    n_active, t_end = None, t1
    if span.count is not None:  # the count's end; a count beyond the reserve ends short of it
        n_active = jnp.clip(span.count, 0, n_steps)
        t1, t_end = t0 + span.count * h, t0 + n_active * h
    elif t1 is not None and h_last is None:
        n_active, h_last, t_end = reserved_to_t1(t0, t1, h, n_steps)
    if options.checkpoint == _reversible.REVERSIBLE:  # n_active is None: the caller refused a reserve
        final, saved = _reversible.reversible_march(
            H, method, q0, p0, h, h_last, args,
            (options.solver, n_steps // save_every, save_every, outputs.estimate, options.progress))
        return solution(final, saved, None, q0, p0, h, save_every, t0, t_end)
    final, saved, kept = march(
        method, H, q0, p0, h, args, n_blocks=n_steps // save_every, block_size=save_every,
        options=options.root_finder(), checkpoint=options.checkpoint, dense=outputs.dense, progress=options.progress,
        estimate=outputs.estimate, h_last=h_last, n_active=n_active,
    )
    if n_active is not None:
        final["status"] = short_of_t1(final["status"], t_end, t1)
        if span.count is not None:
            final, saved, kept = _invalid(span.count < 0, final, saved, kept)
        elif not method.hamiltonian:  # a traced t1 < t0: a Lagrangian has no run backwards (``_directed``)
            final, saved, kept = _invalid(t1 < t0, final, saved, kept)
    return solution(final, saved, kept, q0, p0, h, save_every, t0, t_end)


def _invalid(wrong, final, saved, kept):
    """Bad input found in the run (a traced value): status INVALID_INPUT, NaN states."""
    final = dict(final, status=jnp.where(wrong, Status.INVALID_INPUT, final["status"]).astype(jnp.int32))
    nan = lambda tree: jax.tree.map(lambda x: jnp.where(wrong, jnp.nan, x), tree)
    return final, nan(saved), nan(kept)


@jax.jit
def _integrate_adaptive(run):
    """A run whose steps are not known in advance (``_adaptive.run``), with the derivatives of the
    run that takes the same steps (``_adjoint``); ``nodes``: its saves are every accepted node
    (``save_at="steps"``), padded with t = inf and NaN states to ``max_steps + 1``. Its times are
    the run's tau, forwards; its events read the user's t = sigma tau (``direction``)."""
    problem, span, outputs, options = run.problem, run.span, run.outputs, run.options
    q0, p0, controller, t0, t1, ts, events = (problem.q0, problem.p0, problem.controller, span.t0, span.t1, outputs.ts,
                                              outputs.events)
    transform = controller if isinstance(controller, TimeTransform) else None
    spec = _adjoint.Spec(problem.H, transform, options.solver, span.max_steps,
                         dense=True if outputs.dense else ("nodes" if outputs.nodes else False), events=events,
                         estimate=outputs.estimate, checkpoint=options.checkpoint)
    inputs = dict(q0=q0, p0=p0, args=problem.args, method=problem.method, controller=None if transform else controller,
                  t0=t0, t1=t1, ts=ts, h=span.h, direction=span.direction, tolerance=options.tolerance)
    c = _adjoint.run(spec, inputs)
    clock = None if transform is None else q0.shape[0]
    view = lambda z: _output.user_view(z, clock)
    status = c["status"]
    # a run stopped by max_steps or dtmin keeps its state and time where it stopped
    failed = jnp.where((status == Status.MAX_STEPS) | (status == Status.DTMIN), Status.SUCCESS, status)
    if ts is not None:
        t, (q, p) = ts, view(c["saved"])
    elif outputs.nodes:
        t, (q, p) = c["node_t"], view(c["node_z"])
    else:
        q_end, p_end = view(nan_if_failed(c["z"], failed))
        t, q, p = jnp.stack([t0, c["t"]]), jnp.stack([q0, q_end]), jnp.stack([p0, p_end])
    dense_output = None
    if outputs.dense:
        dense_output = DenseOutput(t=c["node_t"], z=c["node_z"], W=c["W"], t_end=c["t"], t1=t1, clock=clock)
    found = None
    if events is not None:
        found = [Events(t=t, q=view(z)[0], p=view(z)[1], count=c["ev_count"][k], ended=c["ended"] == k)
                 for k, (t, z) in enumerate(zip(c["ev_t"], c["ev_z"]))]
    stats = {"num_newton_iterations": c["total"], "max_newton_iterations": c["most"],
             "batch_newton_iterations": c["trips"], "num_accepted_stalled": c["lenient"], "num_steps": c["attempts"],
             "num_accepted_steps": c["steps"], "num_rejected_steps": c["rejected"], "min_step": c["h_min"], "max_step": c["h_max"]}
    return Solution(t=t, q=q, p=p, status=status, stats=stats, error_estimate=nan_if_failed(c["estimate"], failed),
                    dense=dense_output, events=found)


@_inputs.on_entry
@_shape.on_amplification
def amplification_matrix(H, q, p, *, method, h, args=None, solver=None) -> jax.Array:
    """A = d z_1 / d z_0 of one element, by ``jax.jacfwd`` through the implicit solve [GBS, eq. (48)].

    For a quadratic H this is the amplification matrix of the two-level scheme
    ``z_{k+1} = A z_0``; in general it is the Jacobian of the one-step map. A failed solve
    gives a matrix of NaN.

    Args:
        H: the Hamiltonian, ``H(q, p)`` or ``H(q, p, args)``; required.
        q: the position at which the one-step map is differentiated, an array of any shape or a
            pytree of arrays; required.
        p: the momentum there, of q's shape (pytree structure); required.
        method: the time-stepping scheme, e.g. ``CG(k, rule)``; required.
        h: the step size, a scalar > 0; required.
        args: the extra input of ``H``, passed as its third argument; default None.
        solver: the implicit solve's options, a ``SolverOptions``; default None
            (``SolverOptions()``), as in ``integrate``.

    Returns:
        shape ``(2d, 2d)`` in the ordering ``z = (q, p)``. A state of another shape or a
        pytree enters flattened: d is its number of elements and q's entries are its leaves in
        pytree order, each in C (row-major) order, e.g. ``q.ravel()`` for an ``(N, 3)`` array.
    """
    q, p, h = prepare(H, q, p, method, h, args)
    d = q.shape[0]
    options = solver_options(method, solver=solver)
    method = explicit_form(method, H, q, p, args, options.solver)

    def one_step(z):
        q1, p1, status = _step(H, z[:d], z[d:], method, h, args, options)
        return jnp.concatenate([q1, p1]), status

    A, status = jax.jacfwd(one_step, has_aux=True)(jnp.concatenate([q, p]))
    return nan_if_failed(A, status)
