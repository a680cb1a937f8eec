"""The scan skeleton every run uses: one element after another, in blocks, for one run.

``march`` chains the elements of one run by a nested ``lax.scan`` (outer over blocks,
inner over the elements of a block); ``integrate`` calls it once and ``sweep`` vmaps it, so
a batch runs exactly the code of a single run (the root finder in ``_solve`` folds vmap
axes into its own batch axis). The carry holds the state with the compensation of its
summation (Kahan: the increments of many small elements are added without losing their
low bits, so round-off grows like sqrt(n)), the predictor's history, the iteration matrix,
the first failure's status, Newton counts and the largest local error estimate. An element
in closed form (``_explicit``) carries only what it needs: the state, summed plainly (one
element's rounding is the plain scheme's; notes/performance-studies.md, "Explicit elements"), the
force it hands the next element, and its counts (``explicit_start``).
"""

import dataclasses
import functools
import inspect
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from . import _output, _progress
from ._controllers import embedded_error
from ._explicit import cached_structure, is_explicit, shape_spec
from ._solve import (Options, SolverOptions, Status, accuracy_status, initial_matrix, keeps_state, relative_error,
                     solve, solver_from)


def bind_args(H, args):
    return H if args is None else (lambda q, p: H(q, p, args))


@functools.lru_cache(maxsize=None)
def time_reversed(H):
    """-H, one function per H (a run of it compiles once): its element of step h is H's of step
    -h, every residual holding H through h DH (a run backwards, ``_reversible``'s rebuild)."""
    return lambda q, p, *args: -H(q, p, *args)


@functools.lru_cache(maxsize=None)
def _time_directed(H):
    """sigma H, sigma carried in front of H's arguments: ``(q, p, (sigma, *args))``."""
    return lambda q, p, directed_args: directed_args[0] * H(q, p, *directed_args[1:])


@functools.lru_cache(maxsize=None)
def _directed_density(s):
    """A time transformation's s(q, p[, args]) with sigma carried in front of its arguments, as
    ``_time_directed``'s H has it: the density is the run's in either direction."""
    return lambda q, p, directed_args: s(q, p, *directed_args[1:])


def in_direction(H, args, sigma):
    """``(H~, args~)`` of the run in tau = sigma t, sigma = sign(t1 - t0): Hamilton's flow in
    tau is dz/dtau = sigma J DH(z) = J D(sigma H)(z), a run forwards of sigma H (H(q, p) or
    H(q, p, args)). A known sigma (a Python int, ``_output.Direction``) is a constant of
    H~: H itself, or ``time_reversed(H)``, with args as they are, so that a known direction
    compiles to the program it always did; a traced one travels in args~ = (sigma, *args)."""
    if isinstance(sigma, int):
        return (H if sigma == 1 else time_reversed(H)), args
    return _time_directed(H), (sigma,) if args is None else (sigma, args)


def density_in_direction(controller, sigma):
    """The controller of the run ``in_direction`` makes: a ``TimeTransform``'s own s reads the
    args~ = (sigma, *args) of a traced sigma as its H~ does (``_directed_density``)."""
    s = getattr(controller, "s", None)
    if s is None or isinstance(sigma, int):
        return controller
    return dataclasses.replace(controller, s=_directed_density(s))


def input_status(q0, p0, h):
    ok = jnp.isfinite(h) & (h > 0) & jnp.all(jnp.isfinite(q0)) & jnp.all(jnp.isfinite(p0))
    return jnp.where(ok, Status.SUCCESS, Status.INVALID_INPUT).astype(jnp.int32)


def nan_if_failed(x, status):
    """``x`` where ``status`` is SUCCESS (or INACCURATE, a run that went to its end:
    ``_solve.keeps_state``), NaN elsewhere; ``status`` has shape () or ``x.shape[:1]``."""
    failed = ~keeps_state(status).reshape(status.shape + (1,) * (jnp.ndim(x) - status.ndim))
    return jnp.where(failed, jnp.nan, x)


def element_residual(H, sweep_dimension=SolverOptions.sweep_dimension):
    """``(Z, params) -> R``, the element equations with everything they depend on in ``params``.

    A partitioned method (unknowns q | p along its ``partition_axis``, and a ``residual(...,
    part=)`` of either half) with a fixed point, on a separable H (``gj.structure``) of more
    than ``sweep_dimension`` degrees of freedom (``SolverOptions.sweep_dimension``), is solved
    through the residual of its Gauss-Seidel sweep, ``R~ = Z - G(Z)``: G first updates the p
    half from R_p(Z), then the q half from R_q at that update. R~ has R's roots, and its
    fixed-point iteration ``Z <- G(Z)`` contracts at the square of the rate of ``Z <- Z - R(Z)``:
    for H = T(p) + V(q) two of its updates in one, for the arithmetic of one, since each half
    reads one of T and V. Small states keep R: their cost is the loop's kernels, which the
    sweep's two half-residuals raise more than its rate saves. So does an H that is not
    separable (or whose structure cannot be read): the square rate is not its, and where each
    half's gradient runs through all of H an update of the sweep costs two plain ones.
    """
    separable = {}  # per state and args' shapes and dtypes: read once per trace

    def sweeps(method, q0, p0, args):
        partitioned = getattr(method, "partition_axis", None) is not None and method.fixed_point
        if not partitioned or q0.shape[0] <= sweep_dimension:
            return False
        key = shape_spec((q0, p0, args))
        if key not in separable:
            separable[key] = cached_structure(H, q0, p0, args).separable
        return separable[key]

    def fn(Z, params):
        method, q0, p0, h, args = params
        H_bound = bind_args(H, args)
        if not sweeps(method, q0, p0, args):
            return method.residual(H_bound, q0, p0, Z, h)
        axis = method.partition_axis
        r_p = method.residual(H_bound, q0, p0, Z, h, part="p")
        Z_q, Z_p = jnp.split(Z, 2, axis=axis)
        r_q = method.residual(H_bound, q0, p0, jnp.concatenate([Z_q, Z_p - r_p], axis=axis), h, part="q")
        return jnp.concatenate([r_q, r_p], axis=axis)

    def jacobian(Z, params):
        """dR/dZ flat, from the method's element structure (its optional ``jacobian``), or None:
        where it has none, where a subclass redefines ``residual`` and not ``jacobian``, or where
        ``fn`` is the sweep's R~. The root finder and the implicit function theorem then take
        R's Jacobian by its own tangents."""
        method, q0, p0, h, args = params
        if _defined_by(method, "jacobian") is not _defined_by(method, "residual") or sweeps(method, q0, p0, args):
            return None
        return method.jacobian(bind_args(H, args), q0, p0, Z, h)

    fn.jacobian = jacobian
    return fn


def _defined_by(method, name):
    """The class of ``method`` whose body defines ``name``, or None."""
    return next((cls for cls in type(method).__mro__ if name in vars(cls)), None)


def state_scale(z):
    """The size of a state z = (q, p) that the solver's round-off floor is relative to:
    max |z|, which propagates NaN and inf."""
    return jnp.max(jnp.abs(z))


def solver_options(method, max_iterations=None, krylov=None, solver=None):
    """The root finder's ``Options``: the ``SolverOptions`` of ``solver`` and its shorthands
    (``_solve.solver_from``), whether the method has a fixed point (a method without one,
    dG(k >= 1), has Newton at every size: ``Options.fixed_point``) and its ``settle``."""
    return Options(solver_from(solver, max_iterations, krylov), method.fixed_point,
                   settle=getattr(method, "settle", 0))


def reserved_to_t1(t0, t1, h, reserved):
    """A fixed-step run to a time t1 in ``reserved`` elements (a traced t1 or h): ``(n_active,
    h_last, t_end)``, the elements taken, the last one's size (shortened to land on t1) and the
    time the run ends at: t1, or where t1 lies beyond the reserve, the end of the last element
    reserved (``Status.MAX_STEPS``, with the state there)."""
    needed = jnp.ceil((t1 - t0) / h * (1 - 4 * jnp.finfo(jnp.result_type(h)).eps))
    short = needed > reserved
    n_active = jnp.clip(needed, 1, reserved).astype(jnp.int32)
    h_last = jnp.where(short, h, (t1 - t0) - (n_active - 1) * h)
    return n_active, h_last, jnp.where(short, t0 + reserved * h, t1)


def short_of_t1(status, t_end, t1):
    """``status``, or MAX_STEPS where a run of reserved fixed steps ended before t1."""
    return jnp.where((status == Status.SUCCESS) & (t_end != t1), Status.MAX_STEPS, status).astype(jnp.int32)


class Element(NamedTuple):
    """One element's result (``element``): its unknowns ``Z``, increment ``dz = z1 - z0`` (shape
    ``(2d,)``), the memo it hands the next element (``_explicit``; None for an iterated one), the
    root finder's ``matrix`` and counts, and its ``status`` (the solve's; for an element in closed
    form NONFINITE where its end is not finite)."""

    Z: jax.Array
    dz: jax.Array
    memo: object
    matrix: object
    iterations: jax.Array
    status: jax.Array
    trips: jax.Array
    lenient: jax.Array


@jax.named_scope("element")
def element(method, H, q, p, h, args, options, *, predicted=None, constant=None, matrix=None, scale=None,
            skip=False, first=True, memo=None, closed_form=None):
    """The element of step h from (q, p), the one computation every run, ``step`` and every
    derivative's element found again share. Where the method has a closed form (``_explicit``;
    ``closed_form`` False: not for this H, a time-transformed run's K) it is computed from
    ``memo`` (what the previous element handed on; a fresh start where None), without
    iteration; else the root finder (``_solve.solve``) solves its equations from
    ``predicted``, falling back on ``constant`` (both the method's constant guess where None),
    with ``matrix`` (a fresh one where None) and the round-off floor of ``scale`` (the state's
    where None), skipping where ``skip``; ``first``: its predictor has no history."""
    H_bound = bind_args(H, args)
    if is_explicit(method) if closed_form is None else closed_form:
        Z, (dq, dp), memo = method.explicit(H_bound, q, p, h, method.explicit_start(H_bound, q, p) if memo is None else memo)
        status = jnp.where(finite(q + dq, p + dp), Status.SUCCESS, Status.NONFINITE).astype(jnp.int32)
        zero = jnp.zeros((), jnp.int32)
        return Element(Z, jnp.concatenate([dq, dp]), memo, matrix, zero, status, zero, zero)
    constant = method.initial_guess(q, p) if constant is None else constant
    predicted = constant if predicted is None else predicted
    matrix = initial_matrix(predicted, options) if matrix is None else matrix
    scale = state_scale(jnp.concatenate([q, p])) if scale is None else scale
    Z, matrix, iterations, status, trips, lenient = solve(
        element_residual(H, options.solver.sweep_dimension), (method, q, p, h, args), predicted, constant, matrix,
        scale, skip, first, options)
    dz = jnp.concatenate(method.increment(H_bound, q, p, Z, h))
    return Element(Z, dz, None, matrix, iterations, status, trips, lenient)


def solve_element(method, H, q, p, h, args, options):
    """One element from the constant predictor, without history (``element``): ``(q1, p1, Z,
    iterations, status)``."""
    e = element(method, H, q, p, h, args, options)
    dq, dp = jnp.split(e.dz, 2)
    return q + dq, p + dp, e.Z, e.iterations, e.status


def compensated_add(x, dx, c):
    """Kahan summation: ``x + dx`` with ``c`` the low bits lost so far; returns ``(sum, c)``."""
    y = dx - c
    s = x + y
    return s, (s - x) - y


def continued(method, q, p, previous, ratio):
    """``method.initial_guess(q, p, previous, ratio=ratio)``, the previous element's polynomial
    continued over a next element ``ratio`` times as long; a method whose ``initial_guess``
    takes no ``ratio`` continues over its own length."""
    if "ratio" not in inspect.signature(method.initial_guess).parameters:
        return method.initial_guess(q, p, previous)
    return method.initial_guess(q, p, previous, ratio=ratio)


@jax.named_scope("predictor")
def predictor(method, q, p, previous, correction):
    """The previous element's polynomial continued one element ahead, plus the extrapolated
    error of that continuation (``miss_correction``). Returns ``(Z_pred, Z_continued, Z_constant)``."""
    continued = method.initial_guess(q, p, previous)
    return continued + correction, continued, method.initial_guess(q, p)


def _extrapolated(misses, m):
    """The next term of a sequence from its last m terms (``misses``, latest first), exact where the
    sequence is a polynomial of degree m - 1 (Newton's backward formula): weights
    ``(-1)^j binomial(m, j + 1)``."""
    return sum((-1.0) ** j * math.comb(m, j + 1) * misses[j] for j in range(m))


@jax.named_scope("predictor")
def miss_correction(misses, miss, n, orders=SolverOptions.miss_orders):
    """``(misses, correction)``: the history with element n's ``miss`` of its continued
    polynomial first, and the next element's correction of its continuation. The miss varies
    smoothly from element to element, so the correction extrapolates it from the last misses,
    by the one of the ``orders`` (``SolverOptions.miss_orders``) that would have come closer to this element's miss. For a
    mode of frequency omega, extrapolation of order m leaves |2 sin(h omega / 2)|^m of the
    miss, less the higher m while h omega is small; where the misses are not smooth in h
    (h omega ~ 1, a sharp turn of a nonlinear orbit) the low order does better. Element 0 has
    no real miss (nothing was continued), so an order competes once its test is made of real
    ones; before any does, the lowest order, and before that the last miss or nothing."""
    latest = jnp.concatenate([miss[None], misses[:-1]])  # shifted: cheaper than a ring written in place
    backtests = jnp.stack([miss - _extrapolated(misses, m) for m in orders])
    errors = jnp.sum(backtests.reshape(len(orders), -1) ** 2, axis=1)
    best = jnp.argmin(jnp.where(n > jnp.asarray(orders), errors, jnp.inf))  # the first, while none competes
    correction = sum(jnp.where(best == i, _extrapolated(latest, m), 0.0) for i, m in enumerate(orders))
    return latest, jnp.where(n >= 2, correction, jnp.where(n == 1, miss, 0.0))


# elements whose embedded estimates are the run's largest, on which the full estimate is taken
PEAKS = 4


def peak_start(q0, p0, Z0, h):
    """The carry of the ``PEAKS`` elements whose embedded estimates are the run's largest so far:
    each one's start, root, step and increment."""
    stack = lambda x: jnp.broadcast_to(x, (PEAKS,) + jnp.shape(x))
    return dict(size=jnp.full((PEAKS,), -jnp.inf, q0.dtype), q=stack(q0), p=stack(p0), Z=stack(Z0),
                h=stack(jnp.asarray(h, q0.dtype)), dz=stack(jnp.zeros(2 * q0.shape[0], q0.dtype)))


@jax.named_scope("estimate")
def embedded_size(method, H_bound, q, p, Z, h, increment, fields=None):
    """The largest entry of an element's embedded estimate (``embedded_error``, at the method's
    ``embedded_alpha``; one evaluation of Hamilton's field, or none where ``fields``, F at the
    element's start and end, are given and the end's is read), a number to rank elements by,
    not a function to differentiate."""
    q, p, Z, h, increment, fields = jax.lax.stop_gradient((q, p, Z, h, increment, fields))
    W = method.polynomial_with(H_bound, q, p, Z, h, increment, fields)
    end = None if fields is None else fields[1]
    return jnp.max(jnp.abs(embedded_error(H_bound, q, p, W, h, increment, end, embedded_alpha(method))))


def embedded_alpha(method):
    """Where in the element the embedded estimate takes the defect (``embedded_error``): the
    method's ``embedded_alpha``, 1 (the end) by default."""
    return float(getattr(method, "embedded_alpha", 1.0))


@jax.named_scope("estimate")
def peak_update(peak, size, q, p, Z, h, dz, ok):
    """``peak`` with element (q, p, Z, h, dz) in place of its smallest where its embedded estimate's
    ``size`` (``embedded_size``) is larger and ``ok``."""
    slot = jnp.argmin(peak["size"])
    bigger = ok & (size > peak["size"][slot])
    new = dict(size=size, **dict(zip(("q", "p", "Z", "h", "dz"), jax.lax.stop_gradient((q, p, Z, h, dz)))))
    return jax.tree.map(lambda a, b: jnp.where(bigger, a.at[slot].set(b), a), peak, new)


@jax.named_scope("estimate")
def peak_estimate(method, H_bound, peak):
    """The run's largest local error: the full a posteriori estimate (``local_error``) on the
    elements where the embedded one, of lower order, peaks (the full one peaks among them: one
    field evaluation per element instead of J + 1 and J Jacobian products). Returns ``(estimate,
    relative)``, the largest of the errors and of their ``relative_error``s."""
    frozen = jax.lax.stop_gradient(peak)
    local = jax.vmap(lambda q, p, Z, h, dz: method.local_error_with(H_bound, q, p, Z, h, dz))(
        frozen["q"], frozen["p"], frozen["Z"], frozen["h"], frozen["dz"])
    taken = frozen["size"] > -jnp.inf
    relative = jax.vmap(relative_error)(local, jnp.concatenate([frozen["q"], frozen["p"]], axis=1))
    return jax.lax.stop_gradient((jnp.max(jnp.where(taken, local, 0.0)), jnp.max(jnp.where(taken, relative, 0.0))))


def estimated_status(method, estimate, status, relative):
    """The run's status with its accuracy decided (``_solve.accuracy_status``) where the method
    computes its elements in closed form (``_explicit``: it has no solve whose failure the status
    would report, and a step too long for it blows up) and the run has an estimate (``estimate``
    True or "full"). An implicit method's status stays its solves' (a step of h omega = 1000 of
    Gauss collocation converges and keeps H: its ``error_estimate`` says it follows no trajectory)."""
    if estimate is False or not method.hamiltonian or not is_explicit(method):
        return status
    return accuracy_status(status, relative)


# the run's counters, carried as one int32 array (one fused kernel per element, not one each);
# the count of elements done stays apart: it depends on nothing a vmap maps over
COUNTERS = ("status", "total", "most", "trips", "lenient", "steps")
_AT = {name: i for i, name in enumerate(COUNTERS)}


def march(method, H, q0, p0, h, args, *, n_blocks, block_size, options, checkpoint=False, dense=False,
          observe=None, acc0=None, progress=False, estimate=True, h_last=None, n_active=None):
    """Chain ``n_blocks * block_size`` elements of one run.

    Args:
        h_last, n_active: a run to a time t1: its first ``n_active`` elements (traced; None:
            all) are taken, the last of them of size ``h_last``, and the rest leave the carry
            as it is (a sweep's members of different h reach the same t1).
        options: the root finder's ``Options`` (``solver_options``).
        observe: optional ``(acc, q, p) -> acc`` folded over the states after each element,
            starting from ``acc0`` (sweep diagnostics).
        dense: also return, per element, its start state and polynomial coefficients.
        progress: drive a progress bar from inside the loop (``_progress``).
        estimate: the run's largest local error estimate: "full" computes it on every element;
            True on the elements where the embedded estimate peaks (``peak_estimate``);
            False leaves it NaN.
    Returns:
        ``(final, saved, polynomials)``: ``final`` holds ``q, p, estimate, acc`` and the
        ``COUNTERS`` (``status``, ``total`` and ``most`` Newton iterations, ``trips`` of the
        batch, ``lenient``: elements accepted other than at round-off, ``_solve._converged``,
        ``steps``: elements solved);
        ``saved = (qs, ps)`` of shape ``(n_blocks, d)``, the state at the end of each
        block; ``polynomials`` is ``(Z_starts, W)`` per element or None. States and the
        estimate of a failed run are NaN.
    """
    solver = options.solver
    H_bound = bind_args(H, args)
    d = q0.shape[0]
    split = lambda z: (z[:d], z[d:])
    z0 = jnp.concatenate([q0, p0])
    guess = method.initial_guess(q0, p0)
    total = n_blocks * block_size
    explicit = is_explicit(method)
    if explicit:
        carry = explicit_start(method, H_bound, q0, p0, h)
    else:
        counters0 = jnp.zeros(len(COUNTERS), jnp.int32).at[_AT["status"]].set(input_status(q0, p0, h))
        # the state a failed run carries from then on (no NaN enters the linearisation, nor,
        # under vmap, the others' gradients), and whose scale starts a run
        start = dict(z=z0, z_prev=z0, Z_prev=guess, scale=state_scale(z0))
        carry = dict(start, comp=jnp.zeros_like(z0),
                     misses=jnp.zeros((max(solver.miss_orders),) + guess.shape, guess.dtype),
                     correction=jnp.zeros_like(guess), matrix=initial_matrix(guess, options), counters=counters0,
                     done=jnp.zeros((), jnp.int32))
    carry.update(estimate=jnp.zeros((), z0.dtype), relative=jnp.zeros((), z0.dtype), acc=acc0)
    if estimate is True:
        carry["peak"] = peak_start(q0, p0, guess, h)

    def step_size(done):
        """The element's h (``h_last`` for the last one of a run to t1) and whether it idles."""
        last = total - 1 if n_active is None else n_active - 1
        h_el = h if h_last is None else jnp.where(done == last, h_last, h)
        idle = jnp.zeros((), bool) if n_active is None else done >= n_active
        return h_el, idle

    def extras(c, new, q, p, Z, h_el, dz, z, z1, ok, idle, fields=None):
        """What a run asks for beyond the state: the estimate, the diagnostics, the idling of a
        member past t1, the progress bar and the dense output."""
        full = estimate == "full"
        if full:  # an estimate, not a function to differentiate (and no 0 * inf from a failed run's)
            frozen = jax.lax.stop_gradient((q, p, Z, h_el, args))
            local = jax.lax.stop_gradient(method.local_error(bind_args(H, frozen[4]), *frozen[:4]))
            new["estimate"] = jnp.maximum(c["estimate"], local)
            new["relative"] = jnp.maximum(c["relative"], relative_error(local, jnp.concatenate([q, p])))
        if observe is not None:
            new["acc"] = observe(c["acc"], *split(state(new)))
        if estimate is True:
            size = embedded_size(method, H_bound, q, p, Z, h_el, dz, None if fields is None else fields())
            new["peak"] = peak_update(c["peak"], size, q, p, Z, h_el, dz, ok & ~idle)
        if n_active is not None:
            new = jax.tree.map(lambda a, b: jnp.where(idle, a, b), dict(c, done=c["done"] + 1), new)
        if progress:
            _progress.report(new["done"], total, _progress.stride(total))
        # dense output: the element polynomial refined to the nodes' accuracy (``_output.refined``)
        kept = (z, _output.refined(method, H_bound, z, z1, method.polynomial_with(H_bound, q, p, Z, h_el, dz), h_el)
                ) if dense else None
        return new, kept

    def explicit_element(c):
        """The element in closed form (``_explicit``): no predictor, no iteration, the force
        carried; only the state, the memo and the counts are carried (``explicit_start``). A
        failed run goes on from its start values, read in place of the carried ones (the
        selection fuses into the element's first kernels)."""
        failed = c["status"] != Status.SUCCESS
        q, p, memo0 = (jnp.where(failed, c[k + "0"], c[k]) for k in ("q", "p", "memo"))
        h_el, idle = step_size(c["done"])
        e = element(method, H, q, p, h_el, args, options, memo=memo0)
        dq, dp = jnp.split(e.dz, 2)
        q1, p1 = q + dq, p + dp
        ok = ~failed & (e.status == Status.SUCCESS)
        new = dict(c, q=q1, p=p1, memo=e.memo, steps=c["steps"] + ok, done=c["done"] + 1,
                   status=jnp.where(ok | failed, c["status"], e.status).astype(jnp.int32))
        z = jnp.concatenate([q, p]) if dense else None
        return extras(c, new, q, p, e.Z, h_el, e.dz, z, jnp.concatenate([q1, p1]) if dense else None,
                      ok, idle, fields=lambda: (method.explicit_field(H_bound, q, p, memo0),
                                                method.explicit_field(H_bound, q1, p1, e.memo)))

    def iterated_element(c):
        z, counters = c["z"], c["counters"]
        (q, p), failed = split(z), counters[_AT["status"]] != Status.SUCCESS
        h_el, idle = step_size(c["done"])
        previous = (*split(c["z_prev"]), c["Z_prev"])
        Z_pred, continued, constant = predictor(method, q, p, previous, c["correction"])
        Z, dz, _, matrix, iterations, status, trips, lenient = element(
            method, H, q, p, h_el, args, options, predicted=Z_pred, constant=constant, matrix=c["matrix"],
            scale=c["scale"], skip=failed | idle, first=c["done"] == 0)
        z1, comp = compensated_add(z, dz, c["comp"])
        scale = state_scale(z1)  # the next element's (NaN or inf where z1 is not finite)
        status = jnp.where((status == Status.SUCCESS) & ~jnp.isfinite(scale), Status.NONFINITE, status)
        status = jnp.where(failed, counters[_AT["status"]], status)  # the first failure is kept
        ok = status == Status.SUCCESS
        now = jax.tree.map(lambda a, b: jnp.where(ok, b, a), start, dict(z=z1, z_prev=z, Z_prev=Z, scale=scale))
        misses, correction = miss_correction(c["misses"], Z - continued, c["done"], solver.miss_orders)
        counters = jnp.stack([status, counters[_AT["total"]] + iterations,
                              jnp.maximum(counters[_AT["most"]], iterations), counters[_AT["trips"]] + trips,
                              counters[_AT["lenient"]] + lenient, counters[_AT["steps"]] + ok])
        new = dict(c, **now, comp=comp, misses=misses, correction=correction, matrix=matrix,
                   counters=counters.astype(jnp.int32), done=c["done"] + 1)
        return extras(c, new, q, p, Z, h_el, dz, z, z1, ok, idle)

    def state(c):
        return jnp.concatenate([c["q"], c["p"]]) if explicit else c["z"]

    def status_of(c):
        return c["status"] if explicit else c["counters"][_AT["status"]]

    def reported(c):
        return split(nan_if_failed(state(c), status_of(c)))

    def block(c, _):
        c, kept = jax.lax.scan(lambda c, _: (explicit_element if explicit else iterated_element)(c), c, None,
                               length=block_size)
        return c, (reported(c), kept)

    if checkpoint:
        block = jax.checkpoint(block)
    final, (saved, kept) = jax.lax.scan(block, carry, None, length=n_blocks)
    q, p = reported(final)
    if explicit:  # no iteration: the solver's counters are zero
        counts = dict(status=final["status"], steps=final["steps"],
                      **{name: jnp.zeros((), jnp.int32) for name in ("total", "most", "trips", "lenient")})
    else:
        counts = {name: final["counters"][i] for i, name in enumerate(COUNTERS)}
    if estimate is True:
        final["estimate"], final["relative"] = peak_estimate(method, H_bound, final["peak"])
    elif estimate is False:
        final["estimate"] = jnp.full((), jnp.nan, z0.dtype)
    results = dict(q=q, p=p, estimate=nan_if_failed(final["estimate"], counts["status"]), acc=final["acc"], **counts)
    results["status"] = estimated_status(method, estimate, counts["status"], final["relative"])
    if kept is not None:
        kept = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), kept)
    return results, saved, kept


def finite(q, p):
    """Whether every entry of q and p is finite: ``sum(q * 0 + p * 0)`` is 0, or NaN where an entry
    is inf or NaN (one reduction, fused with the products; no overflow of a sum of finite values)."""
    return jnp.isfinite(jnp.sum(q * 0.0 + p * 0.0))


def explicit_start(method, H_bound, q0, p0, h):
    """The carry of a run of explicit elements (``_explicit``): the state q, p, the memo one
    element hands the next (the force), the start values a failed run carries from then on,
    the status, the elements solved and taken. The state is summed without compensation: one
    element's rounding is that of the plain scheme (notes/performance-studies.md, "Explicit elements")."""
    memo = method.explicit_start(H_bound, q0, p0)
    zero = jnp.zeros((), jnp.int32)
    return dict(q=q0, p=p0, memo=memo, q0=q0, p0=p0, memo0=memo, status=input_status(q0, p0, h), steps=zero,
                done=zero)
