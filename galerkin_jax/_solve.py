"""The one root finder for the element equations ``R(Z) = 0``, and its status codes.

Every path (``step``, ``integrate``, ``jax.vmap(integrate)``, ``sweep``,
``amplification_matrix``) solves its elements here. The iteration is written over an
explicit batch axis B: a ``custom_vmap`` rule folds any ``vmap`` axes into it, so a vmapped
run pays for a Jacobian only in the iterations where some member asks for one (under a
plain ``vmap`` a ``lax.cond`` becomes a ``select`` that runs both branches every time).

Iteration (per member): ``Z <- Z - K R(Z)``, in two phases per element. The thresholds are
the fields of ``SolverOptions`` (named in parentheses), each with its unit and reason.

* The fixed-point phase: ``K = I``, the fixed-point iteration of ``Z = h Phi(Z)`` (every method
  whose residual has Jacobian I at h = 0), in blocks of ``fixed_point_block`` updates checked
  once at the block's end; a system of more than ``small`` unknowns starts each element with a
  block of ``first_block``. Its loop carries no matrix, so a run that never needs Newton never
  pays for one. A member leaves it for Newton when it contracts at a rate above
  ``theta_fixed_point``, or when its patience is used up (``fixed_point_patience``, at most
  half the cap, so that Newton is always reached).
  A large batch iterates its stragglers (``stragglers``) gathered apart.
  Partitioned methods on a separable H of more than ``sweep_dimension`` degrees of freedom hand
  this solver the residual of their Gauss-Seidel sweep (``_march.element_residual``), whose
  fixed point contracts at the square of the plain one's rate.
  A method whose residual's Jacobian at h = 0 is not I (dG(k >= 1)) has no fixed point and
  solves every element by Newton.
* The Newton phase: ``K`` the inverse of a Jacobian ``dR/dZ`` taken at an earlier iterate and
  kept across elements (the simplified Newton method, as in Hairer and Wanner's Radau5), one
  checked update at a time. The Jacobian comes from the element's structure where the method
  has one (cG, dG: Hamilton's field's Jacobian at the quadrature points,
  ``_galerkin.galerkin_jacobian``), else from one tangent of R per unknown. A member refreshes
  its matrix when it contracts slower than ``theta_newton``, when it has iterated ``patience``
  times with it in one element, or when an update goes astray (the update is rejected). Far
  from the root (a first element, a large h omega) the steps follow Newton with a fresh matrix:
  a full step that does not lower the residual is taken anyway, and so are the fresh steps after it while the residual comes
  back below where it started (the watchdog, ``watch``, in an element whose predictor is the
  constant guess, a run's first: plain Newton's first step can raise the residual and still
  reach the root in a few more); if it does not, and in the other elements, the member goes back there and halves its steps (damped Newton, down to
  ``min_damping``), each taken damped step with a fresh matrix. A system too large for a dense matrix (more than ``dense_limit`` unknowns)
  has Newton only with ``krylov``: every update a fresh Newton direction, by GMRES on
  Jacobian-vector products (Newton-Krylov; its cost follows the Hessian's sparsity, not n^3).
  A small system that switched stays with Newton (its Newton update costs two to three
  fixed-point ones); a large one, whose update costs a product with an n x n matrix or a
  Krylov solve, for ``newton_stretch`` elements, then tries the fixed point again, and so
  does a small one whose matrix serves few elements (``Options.short_lived_matrices``: a
  controller's varying h, a time-transformed run); there a stretch ends at the first of its
  elements that needs a fresh matrix (the kept one no longer serves: Newton from the
  continued polynomial costs a matrix an element and often ends at another root, where the
  fixed point, at the next h, may converge).
  Under a controller an element of any size that asks for more than ``attempt_matrices``
  dense matrices fails, and the controller retries it with a shorter h.
  Small systems solve a run's first element by Newton: the predictor has no history yet.

The loop's cost is mostly per check, not per update: the decisions, the sizes and the loop's
trip are each a kernel that XLA's CPU runtime launches on its own. A block of two fixed-point
updates costs little more than one; a rejected block is undone as a whole.

Stopping rule (``_converged``, correctness; the policy above is ``_policy``, speed): a member
stops when the error left after its update, ``|dZ| theta / (1 - theta)`` (theta the
contraction rate: a block's last two updates' ratio, or in Newton's one update per check the
largest ratio of the element), is below the round-off ``eps |Z|`` of the unknowns (or
``SolverOptions.tolerance`` of them, where asked), or when its
updates stop shrinking: at the round-off of the state (``noise``) whatever K (there also when
they still shrink, by less than half, past the member's patience), below ``sqrt(eps)`` of the
state only with a fresh Newton matrix (the floor of an ill-conditioned system). The last two
accept an element short of the round-off criterion; ``stats["num_accepted_stalled"]`` counts
them. A growing update is never applied, and the residual at the accepted iterate must be
below ``sqrt(eps)`` of the state. An accepted iterate gets one more update from its residual,
which is already known (a product, no residual). Iterating to the floor, not to a tolerance,
and that last update leave no systematic iteration error in the states, so round-off grows
like sqrt(n) (Brouwer's law), not like n. Sizes are root-mean-square norms over a member's
unknowns (a sum of squares is one cheap reduction; NaN and inf propagate through it).

Derivatives come from the implicit function theorem (``implicit``), never from the iterations.
"""

import dataclasses
import enum
import functools

import jax
import jax.numpy as jnp
import numpy as np

from . import _tangent
from ._contraction import error_left_below
from ._pytree import pytree_dataclass
from ._solver_options import SolverOptions, solver_from


class Status(enum.IntEnum):
    """Codes of ``Solution.status``; the first failure of a run is kept, and every state after it
    is NaN (a run stopped by MAX_STEPS or DTMIN keeps its time and state where it stopped; an
    INACCURATE one, which ran to its end, keeps every state and its estimate).
    ``status_message(code)`` says what went wrong and what to try.

    Attributes:
        SUCCESS: 0, every implicit solve converged to round-off (or to
            ``SolverOptions.tolerance``, where set); an explicit method, which has none, ran to
            its end with no step that lost all accuracy (``INACCURATE``). How accurate the steps
            are, ``error_estimate`` says.
        NEWTON_MAX_ITERATIONS: 1, an iteration hit ``max_newton_iterations`` (the element
            equations may have no real solution).
        NONFINITE: 2, NaN or inf in the element unknowns.
        INVALID_INPUT: 3, a traced ``h <= 0``, a non-finite initial state, a traced save time outside
            [t0, t1] (or, in a run whose direction is traced, out of the run's order), or a traced
            t1 < t0 of ``LagrangianVI``, which has no run backwards.
        MAX_STEPS: 4, a controller's run used ``max_steps`` attempts before ``t1`` (fixed steps:
            ``t1`` lies beyond the ``max_steps`` elements reserved).
        DTMIN: 5, a step was rejected at ``dtmin`` (or at the round-off of t).
        TIME_TRANSFORM: 6, the time transformation's ``s(q, p)`` was not positive and finite.
        INACCURATE: 7, the run went to its end, and its error estimate says that a step means
            nothing: an element's estimated local error (``Solution.error_estimate``'s, the largest
            of those the estimate is taken on: the four where the embedded one peaks, or every one
            with ``error_estimate="full"``) is at least ``NO_ACCURACY`` (0.1) times the size
            ``max |z|`` of the state it starts from, or is not finite (``relative_error``,
            ``accuracy_status``). Unlike the failures above, the states, the estimate and
            their derivatives are kept, as computed: look at them. Decided for a method that
            computes its elements in closed form (a splitting, a composition of Störmer-Verlet,
            ``Tao``: it has no solve to fail, and a step too long for it blows up) where the run
            has an estimate (not with ``error_estimate=False``), for fixed steps, controllers
            and sweeps alike. An implicit method's status stays its solves': at h omega = 1000
            Gauss collocation converges and keeps H, and its ``error_estimate`` says that it
            follows no trajectory.
    """

    SUCCESS = 0
    NEWTON_MAX_ITERATIONS = 1
    NONFINITE = 2
    INVALID_INPUT = 3
    MAX_STEPS = 4
    DTMIN = 5
    TIME_TRANSFORM = 6
    INACCURATE = 7


# an element whose estimated local error is this fraction of its state's size means nothing
# (API contract: the estimate "is large (>= 0.1 for an O(1) state) when a step means nothing")
NO_ACCURACY = 0.1


def relative_error(local, z):
    """An element's estimated local error ``local`` over the size ``max |z|`` of its start state z
    (0 where the error is 0, inf where only the state is; NaN where either is NaN)."""
    scale = jnp.max(jnp.abs(z))
    return jnp.where(local == 0, 0.0, local / scale)


def accuracy_status(status, relative):
    """``status``, or INACCURATE where it is SUCCESS and the run's largest ``relative_error``
    ``relative`` is not below ``NO_ACCURACY`` (NaN and inf included). The one place that decides
    (``march``, ``_adaptive.run``)."""
    lost = (status == Status.SUCCESS) & ~(relative < NO_ACCURACY)
    return jnp.where(lost, Status.INACCURATE, status).astype(jnp.int32)


def keeps_state(status):
    """Whether a run of this status keeps its states and estimate as computed: SUCCESS, and
    INACCURATE, which ran to the end."""
    return (status == Status.SUCCESS) | (status == Status.INACCURATE)


MESSAGES = {
    Status.SUCCESS: (
        "The run reached its end with finite states. An implicit method's solves converged: to round-off (or to "
        "SolverOptions.tolerance, where set), except the steps counted in stats['num_accepted_stalled'], whose "
        "updates stopped shrinking with the residual below sqrt(eps) of the state (the floor of an "
        "ill-conditioned system); an explicit one (a Splitting, Stormer-Verlet and its compositions on a "
        "separable H, Tao's map) has no solve to fail, and every estimated local error of its run is below 0.1 "
        "of its state (else status INACCURATE); see error_estimate for how accurate the steps are."
    ),
    Status.NEWTON_MAX_ITERATIONS: (
        "An implicit solve did not converge within max_newton_iterations; reduce h or raise the "
        "cap. The element equations may have no real solution for this h. A system of more "
        "than 256 unknowns per element (k * 2d for cG(k)) has only the fixed-point iteration "
        "unless krylov=True, which a stiff one (h omega >~ 1) needs."
    ),
    Status.NONFINITE: "NaN or inf in the element unknowns; check H, args and the initial state.",
    Status.INVALID_INPUT: ("Invalid traced input: h <= 0, a non-finite initial state, a save time outside [t0, t1] "
                           "or out of the run's order, or t1 < t0 with LagrangianVI (which has no run backwards)."),
    Status.MAX_STEPS: (
        "The run reached max_steps (accepted and rejected steps together) before t1; raise "
        "max_steps or loosen the tolerance."
    ),
    Status.DTMIN: (
        "The step size fell below dtmin (or to the round-off of t) with the step still rejected: "
        "the solution may be singular there, or the tolerance below what the precision allows."
    ),
    Status.TIME_TRANSFORM: (
        "The time transformation's step density s(q, p) was not positive and finite at a state of "
        "the run. The default s (TimeTransform()) fails only where Hamilton's field overflows, at a "
        "collision, or with s_max=inf where the field vanishes on the way: pass a TimeTransform(s=...) "
        "of your own there, or use fixed steps or a PIDController. A TimeTransform(s=...) of your own "
        "must stay positive and finite at every state the orbit reaches: look where your s vanishes, changes sign or "
        "divides by zero."
    ),
    Status.INACCURATE: (
        "The explicit method's run went to its end, but its error estimate says it has lost all accuracy: an "
        "element's estimated "
        "local error is at least 0.1 of its state's size, or not finite (error_estimate holds the largest; the "
        "states are as computed). The step is beyond the method's stability or accuracy for this problem: "
        "reduce h, or use a PIDController with a method that admits one (CG, DG, GalerkinVI)."
    ),
}


def status_message(status) -> str:
    """The message of a status code (an int or a concrete array)."""
    return MESSAGES[Status(int(status))]


class SolverError(RuntimeError):
    """A nonzero status with ``throw=True``; ``status`` holds the codes (one per member)."""

    def __init__(self, message, status):
        super().__init__(message)
        self.status = status


def throw_if_failed(status):
    """``throw=True``: raise ``SolverError`` with the message of the first nonzero code of
    ``status`` (a concrete code, or one per member). A traced status (under ``jit``, ``vmap``
    or ``grad``) cannot raise: a ``TypeError`` says so, before anything runs."""
    if isinstance(status, jax.core.Tracer):
        raise TypeError("throw=True needs a concrete status: it works outside jit, vmap and grad. Inside them, "
                        "read the status (Solution.status, SweepResult.status, step(..., return_status=True)).")
    codes = np.atleast_1d(np.asarray(status))
    failed = np.flatnonzero(codes != Status.SUCCESS)
    if failed.size:
        code = int(codes[failed[0]])
        where = f" (configurations {failed.tolist()})" if codes.size > 1 else ""
        raise SolverError(f"status {code} ({Status(code).name}){where}: {status_message(code)}", status)


ALWAYS = 2**30  # elements of Newton: for good


@dataclasses.dataclass(frozen=True)
class Options:
    """The root finder's static options: the user's ``SolverOptions`` and what the method adds.

    Attributes:
        solver: ``SolverOptions``.
        fixed_point: the method has a fixed-point iteration; else every element is Newton's,
            by Newton-Krylov where no dense matrix is kept, whatever ``solver.krylov`` says.
        varying_steps: h changes from element to element (a ``PIDController``'s run): an
            element that asks for more than ``SolverOptions.attempt_matrices`` dense matrices
            fails, and the controller retries it shorter.
        short_lived_matrices: a Newton matrix serves few later elements, so a small system
            follows the Newton policy of a large one (``SolverOptions``: the fixed point's
            patience, the refresh rate, ``newton_stretch``): a small system's policy (Newton
            early, kept for good) would take a fresh matrix in nearly every element. Set under
            a ``PIDController``, whose h changes in every element, and in a time-transformed
            run, whose constant step in tau is as long against the local time scale all along
            the orbit (a matrix is out of date a few elements on) and whose Jacobian holds the
            derivatives of the step density s (the default s: H's third). A stretch of Newton
            ends at the first of its elements that needs a fresh matrix (where the method has
            a fixed point to go back to).
        settle: fixed-point updates, each from a fresh residual, that an element accepted by
            the fixed-point phase takes after its polish (the method's ``settle``, ``_settle``).
        tolerance: ``SolverOptions.tolerance`` as a value of the program (``integrate``'s runs,
            so that another tolerance compiles nothing new), or None: ``solver.tolerance``. Not
            compared nor hashed: a value stands in for the solver's, which the program's key
            holds as 0 (``_integrate.RunOptions.planned``).
    """

    solver: SolverOptions
    fixed_point: bool = True
    varying_steps: bool = False
    short_lived_matrices: bool = False
    settle: int = 0
    tolerance: object = dataclasses.field(default=None, compare=False)

    def with_tolerance(self, value):
        """These options with the tolerance ``value`` (traced) in place of ``solver.tolerance``."""
        return dataclasses.replace(self, tolerance=value)

    def tolerance_value(self):
        """The stopping rule's tolerance: the value given (``with_tolerance``), else ``solver.tolerance``."""
        return self.solver.tolerance if self.tolerance is None else self.tolerance

    @property
    def max_iterations(self):
        return self.solver.max_iterations

    @property
    def krylov(self):
        return self.solver.krylov


@pytree_dataclass
class Matrix:
    """The iteration matrix ``K`` of each member, kept across elements.

    Attributes:
        state: int32, shape ``(B, 2)`` (or ``(2,)`` for one run): ``newton`` and ``pending``
            in one array (one kernel and one copy per element, not two).
        inverse: ``(B, n, n)`` inverse Jacobians, or None when n > ``SolverOptions.dense_limit``
            (then Newton is Newton-Krylov, with ``SolverOptions.krylov``, or there is none).
        reference: the watchdog's reference iterate and residual (``_rewind``), each Z's shape:
            buffers of the Newton phase, written before they are read in every element, and
            kept across elements so that no element copies them in.

    ``newton``: the elements, this one included, that the member still solves by Newton; 0 for
    the fixed point (module docstring). ``pending``: ``inverse`` is yet to be computed.
    """

    state: jax.Array
    inverse: object
    reference: object

    @classmethod
    def of(cls, newton, pending, inverse, reference):
        state = jnp.stack([jnp.asarray(newton, jnp.int32), jnp.asarray(pending, jnp.int32)], axis=-1)
        return cls(state, inverse, reference)

    @property
    def newton(self):
        return self.state[..., 0]

    @property
    def pending(self):
        return self.state[..., 1] != 0


def initial_matrix(Z, options):
    """``Matrix`` for the first element of one run (``options``: ``Options``); a method whose
    fixed-point iteration cannot contract solves every element by Newton."""
    n, solver = Z.size, options.solver
    dense = n <= solver.dense_limit
    newton = 1 if dense and n <= solver.small else 0
    inverse = jnp.zeros((n, n), Z.dtype) if dense else None
    reference = (jnp.zeros_like(Z), jnp.zeros_like(Z)) if dense or _krylov(options) else None
    return Matrix.of(newton if options.fixed_point else ALWAYS, True, inverse, reference)


def _krylov(options):
    """Without a dense matrix, the Newton phase is Newton-Krylov where it exists: with
    ``krylov=True``, or for a method without a fixed point."""
    return options.krylov or not options.fixed_point


def _matvec(K, r):
    """K @ r per member, ``(B, n, n) x (B, n)``, unrolled over the columns: one fused loop,
    where a batched dot or a broadcast-and-reduce of a small size is several times slower."""
    total = K[:, :, 0] * r[:, :1]
    for j in range(1, r.shape[1]):
        total = total + K[:, :, j] * r[:, j : j + 1]
    return total


def sizes(unit, *arrays):
    """The root-mean-square of each member of each array (leading axis B), in one reduction:
    an array of shape ``(len(arrays), B)``. With ``unit`` (B,), the state's size
    (``_Problem.unit``), the squares are taken of the arrays over it, so that they neither
    overflow nor underflow where the numbers are far from 1 (float32: |x| > 1e19 or < 1e-19)."""
    x = jnp.stack([a.reshape(a.shape[0], -1) for a in arrays])
    if unit is None:
        return jnp.sqrt(jnp.mean(x * x, axis=-1))
    x = x / unit[None, :, None]
    return unit[None, :] * jnp.sqrt(jnp.mean(x * x, axis=-1))


def _select(mask, x, y):
    return jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y)


def block_jacobians(residual, Z):
    """dR_b / dZ_b for every member b, shape ``(B, n, n)``: the batched residual is block
    diagonal, so n JVPs with the same unit direction in every member give every block."""
    B, n = Z.shape[0], Z[0].size
    _, jvp = jax.linearize(residual, Z)
    units = jnp.eye(n, dtype=Z.dtype).reshape((n,) + Z.shape[1:])
    columns = jax.vmap(lambda e: jvp(jnp.broadcast_to(e, Z.shape)))(units)
    return jnp.moveaxis(columns.reshape(n, B, n), 0, -1)


@dataclasses.dataclass(frozen=True)
class _Problem:
    """The element equations of a batch and what every phase of the iteration reads."""

    fn: object  # (Z, params) -> R for one member
    params: object  # leading axis B
    scale: jax.Array  # (B,): the size of the state the unknowns are increments of
    tolerance: jax.Array  # (B,): ``SolverOptions.tolerance`` (``Options.tolerance_value``)
    solver: SolverOptions
    newton: bool  # a Newton phase is there to ask for
    large: bool  # the Newton policy of a large system: n > ``small``, or ``Options.short_lived_matrices``
    # the fresh dense Newton matrices a member may take in one element before it fails, or None
    # (no cap): ``SolverOptions.attempt_matrices`` under a controller (``Options.varying_steps``)
    matrix_cap: object = None
    unit: object = dataclasses.field(init=False)  # (B,): the scale of the ``sizes``, or None
    # the batched residual, jitted: its call sites (start, blocks, Newton matrix) reuse one trace
    _residual: object = dataclasses.field(init=False, repr=False)

    def __post_init__(self):
        # ``scale`` (1 where that is 0), computed once, outside the loops. None in float64,
        # where a square overflows only past 1e154 (a kinetic energy |p|^2 / 2 in H does too).
        float64 = jnp.finfo(self.scale.dtype).bits == 64
        object.__setattr__(self, "unit", None if float64 else jnp.where(self.scale > 0, self.scale, 1.0))
        object.__setattr__(self, "_residual", jax.jit(jax.vmap(self.fn)))

    @property
    def max_iterations(self):
        return self.solver.max_iterations

    def residual(self, Z):
        return self._residual(Z, self.params)

    def jacobians(self, Z):
        """dR/dZ of every member, ``(B, n, n)``: from the element's structure where the
        equations carry one (``_tangent.structured_jacobian``), else ``block_jacobians``."""
        J = jax.vmap(functools.partial(_tangent.structured_jacobian, self.fn))(self.params, Z)
        return block_jacobians(self.residual, Z) if J is None else J

    def newton_krylov(self, Z, r):
        """``dR/dZ(Z)^{-1} r`` per member, by restarted GMRES on Jacobian-vector products: the
        Newton direction of a system too large for a dense matrix, at the cost of a few
        residual linearisations per Krylov iteration (H's Hessian-vector products), however
        sparse H's Hessian. Each member solves alone (vmap), as it would in a run of its own."""
        solver = self.solver
        tolerance = max(solver.krylov_tolerance, 10 * float(jnp.finfo(r.dtype).eps))

        def direction(Z, r, params):
            _, jvp = jax.linearize(lambda Z: self.fn(Z, params), Z)
            return jax.scipy.sparse.linalg.gmres(jvp, r, tol=tolerance, restart=solver.krylov_restart,
                                                 maxiter=solver.krylov_restarts)[0]

        return jax.vmap(direction)(Z, r, self.params)


# The scalars of each member travel as two stacked arrays for one run, the flags as 0/1 among
# the int32 counts: XLA then computes each group in one fused kernel, and copies it once per
# loop trip, not once per scalar (the loop's cost is mostly kernel launches). A batch keeps
# them apart: a packed group is a concatenate, whose per-element indexing XLA does not vectorise.
_GROUPS = {"floats": ("damping", "step", "rate", "r_size", "ref_size", "watch", "lenient", "matrices"),
           "ints": ("newton", "fresh", "current", "asked", "active", "iterations", "status", "since")}
_FLAGS = ("newton", "fresh", "current", "asked", "active", "lenient")
# at most 8 a group: XLA's CPU compiler fuses a concatenate of up to 8 operands into one kernel,
# so the small integers past that travel among the floats (exactly: they are far below 2^24)
_COUNTS = ("watch", "matrices")


def _pack(c):
    if c["Z"].shape[0] > 1:
        return c
    packed = {k: v for k, v in c.items() if not any(k in names for names in _GROUPS.values())}
    dtypes = {"floats": c["r_size"].dtype, "ints": jnp.int32}
    return dict(packed, **{group: jnp.stack([c[k].astype(dtypes[group]) for k in names])
                           for group, names in _GROUPS.items()})


def _unpack(c):
    if "ints" not in c:
        return c
    values = {k: v for k, v in c.items() if k not in _GROUPS}
    return dict(values, **{k: _get(c, k) for names in _GROUPS.values() for k in names})


def _get(c, name):
    """A member scalar of the carry, packed (one run) or not."""
    for group, names in _GROUPS.items():
        if group in c and name in names:
            value = c[group][names.index(name)]
            return value != 0 if name in _FLAGS else value.astype(jnp.int32) if name in _COUNTS else value
    return c[name]


def _live(problem, c):
    """Members still iterating: active and under their own iteration cap (in a batch the
    phases run one after the other, so the batch's count of updates is no member's)."""
    return _get(c, "active") & (_get(c, "iterations") < problem.max_iterations)


KRYLOV = "newton-krylov"  # the Newton phase's K where no dense matrix is kept


def _update(problem, K, Z, r, damping):
    """``damping K r`` per member, flat: K = I (``None``), a dense inverse, or ``KRYLOV``."""
    if K is KRYLOV:
        r = problem.newton_krylov(Z, r)
    r = r.reshape(r.shape[0], -1)
    if K is not None and K is not KRYLOV:
        r = _matvec(K, r) if r.shape[1] <= problem.solver.small else jnp.einsum("bij,bj->bi", K, r)
    return damping[:, None] * r


def _converged(problem, c, m):
    """The stopping rule (correctness; module docstring): ``(done, accepted, lenient, noisy)``
    per moving member, from the block's measurements ``m``, and ``small``: an update small
    enough to stop on. ``accepted``: the last iterate is
    kept (else the block's start is); ``lenient``: accepted by a rule other than the error
    left being below round-off (a stall at the sqrt(eps) floor with a fresh Newton matrix, or
    round-off-sized updates that still shrink past the member's patience)."""
    eps = jnp.finfo(m["step"].dtype).eps
    step, theta, z_size, r_size = m["step"], m["theta"], m["z_size"], m["r_size"]
    floor = jnp.sqrt(eps) * (problem.scale + z_size + jnp.finfo(step.dtype).tiny)
    noisy = step <= problem.solver.noise * eps * (problem.scale + z_size)  # round-off, not a slow K
    grown = (step >= m["before"]) | (step >= c["step"])  # within the block, or since the last one
    # the error left after this update is below the round-off of the unknowns (or the tolerance)
    limit = jnp.maximum(eps, problem.tolerance)
    strict = (step == 0) | error_left_below(step, theta, limit * z_size)
    # round-off that still shrinks, by less than half an update, past the member's patience
    settled = noisy & ~grown & (theta > 0.5) & m["patience"]
    accept_here = (strict | settled) & ~m["bad"] & (r_size <= floor)
    # the updates stopped shrinking at the floor: keep the block's start, never the growing
    # update. Below sqrt(eps) only with a fresh Newton K (a stale K can stall far from the
    # root; it is refreshed instead); at the round-off of the state whatever the K.
    at_floor = ~m["stale"] & (m["rate"] >= 1.0) & (step <= floor) & ~noisy
    stalled = (at_floor | (noisy & grown)) & (c["r_size"] <= floor)
    done = accept_here | stalled
    lenient = jnp.where(accept_here, ~strict, at_floor & ~(noisy & grown))
    return done, accept_here, lenient, noisy, strict | settled


def _policy(problem, c, m, going, noisy, watchdog):
    """The switching, refresh and damping policy (speed; module docstring): for the members
    ``going`` on, ``(backtrack, rejected, failed, asks, watch, tentative)``. ``watchdog``: the Newton
    phase, where a full step with a fresh matrix may raise the residual (``SolverOptions.watch``)."""
    solver, newton, current, damping = problem.solver, c["newton"], c["current"], c["damping"]
    bad, rate, stale, r_size = m["bad"], m["rate"], m["stale"], m["r_size"]
    lowered = ~bad & (r_size < c["r_size"])
    # a Newton step that does not lower the residual is halved with a K taken at its start,
    # else undone for such a K. ``current`` implies a fresh Newton K (``_served`` sets all
    # three), so not ``stale``.
    backtrack = going & current & ~lowered & ~noisy & (damping > solver.min_damping)
    rejected = going & ((stale & (bad | (rate > 1.0))) | (~stale & ~current & ~lowered & ~noisy))
    failed = going & current & bad & ~backtrack
    watch = c["watch"]
    if watchdog and solver.watch > 0:
        # the watchdog: a full fresh step that raises the residual is taken, and so are the
        # fresh steps after it until the residual is below where it started; those that lower
        # the residual are free, ``watch`` that raise it are not: at the last the member goes
        # back to where the first started, and halves its steps for the rest of the element
        tentative = backtrack & ~bad & (damping == 1.0) & (watch == 0)
        watching = going & (watch > 0)
        recovered = watching & ~bad & (r_size < c["ref_size"])
        onward = watching & ~recovered & ~bad & (lowered | (watch > 1))
        back = watching & ~recovered & ~onward  # to the reference, at the refresh (``_rewind``)
        backtrack = backtrack & ~tentative & ~watching
        rejected = (rejected & ~tentative & ~onward) | back
        failed = failed & ~watching
        watch = jnp.where(tentative, solver.watch, jnp.where(recovered, 0, jnp.where(
            back, BACK, jnp.where(onward & ~lowered, watch - 1, watch))))
        watched = tentative | onward | back  # each of these steps asks for a fresh matrix
    else:
        tentative = watched = jnp.zeros_like(going)
    # a damped step is taken far from the root, where a matrix from an earlier iterate is no
    # guide: the next step has a fresh one (damped Newton, not damped simplified Newton)
    watched = watched | (going & ~backtrack & ~rejected & ~failed & (damping < 1.0) & current)
    large = m["large"]
    slow = m["theta"] > jnp.where(newton, solver.theta_newton[large], solver.theta_fixed_point)
    unsure = m["small"] & ~bad & stale  # a small update but a large residual: K is off
    asks = rejected | ((slow | m["patience"]) & ~noisy) | unsure | watched
    return backtrack, rejected, failed, asks, watch, tentative


def _block(problem, c, inverse, size):
    """``size`` updates of the moving members, checked once at the end by the stopping rule
    (``_converged``), then the policy (``_policy``). ``inverse`` is the Newton phase's
    matrices, None in the fixed-point phase."""
    c = _unpack(c)
    n, dtype = c["Z"][0].size, c["Z"].dtype
    solver = problem.solver
    Z0, r0, newton, fresh, current, damping = c["Z"], c["r"], c["newton"], c["fresh"], c["current"], c["damping"]
    mode = newton if inverse is not None else ~newton
    moving = _live(problem, c) & ~c["asked"] & mode  # members that asked wait for their matrix
    Z, r, steps = Z0, r0, []
    for _ in range(size):
        steps.append(_update(problem, inverse, Z, r, damping))
        Z = Z - steps[-1].reshape(Z.shape)
        r = problem.residual(Z)
    measured = sizes(problem.unit, *steps[-2:], Z, r)
    step, z_size, r_size = measured[-3], measured[-2], measured[-1]
    before = measured[0] if size > 1 else c["step"]  # the update before the last, with this K
    rate = step / before  # NaN until a member has two updates with one K
    # the contraction rate: a block's last two updates' (an element's first ratio is its
    # largest and would hold it back a block), one update per check (Newton): the largest
    # of the element's ratios, as one ratio alone is noisy
    theta = rate if size > 1 else jnp.fmax(rate, c["rate"])
    iterations, large = c["iterations"] + size * moving, problem.large
    # a Newton member's patience counts from its matrix, a fixed-point member's from the start
    left = jnp.where(newton, solver.patience, solver.fixed_point_patience_for(large)) - jnp.where(
        newton, iterations - c["since"], iterations)
    m = dict(step=step, before=before, rate=rate, theta=theta, z_size=z_size, r_size=r_size,
             bad=~jnp.isfinite(step + r_size), patience=left <= 0, large=large,
             stale=~(newton & fresh))  # a fixed-point K, or a Newton K from an earlier iterate
    done, accept_here, lenient, noisy, m["small"] = _converged(problem, c, m)
    done = moving & done
    going = moving & ~done
    backtrack, rejected, failed, asks, watch, tentative = _policy(problem, c, m, going, noisy, inverse is not None)
    take = (done & accept_here) | (going & ~rejected & ~failed & ~backtrack)
    # computed once: without the barrier XLA repeats the decisions above in every fusion
    # that reads them (the selects below, the packed carries), which costs more than the rest
    take, going, failed, backtrack, rejected, accepted, watch, tentative = jax.lax.optimization_barrier(
        (take, going, failed, backtrack, rejected, done & accept_here, watch, tentative))
    status = jnp.where(failed, Status.NONFINITE, c["status"])
    if problem.matrix_cap is not None and inverse is not KRYLOV:
        # under a controller, a member that asks for one matrix too many fails: the controller
        # retries the element shorter, which costs less than more matrices at this h
        spent = going & ~failed & ~backtrack & asks & (c["matrices"] >= problem.matrix_cap)
        going, failed = going & ~spent, failed | spent
        status = jnp.where(spent, Status.NEWTON_MAX_ITERATIONS, status)
    asked = c["asked"] | (going & ~failed & ~backtrack & asks & problem.newton)
    restart = asked | backtrack
    # An accepted iterate gets one more update from its residual, already known: a product, no
    # residual. It leaves theta times less of the iteration error, which is systematic (it
    # follows the predictor's smooth miss) and would add up over the elements. (Not with
    # Newton-Krylov: a Krylov solve is no product, and exact Newton leaves no such error.)
    polished = Z if inverse is KRYLOV else Z - _update(problem, inverse, Z, r, damping).reshape(Z.shape)
    # a batch counts the updates it ran (``trips``); a run alone's are its iterations
    counted = {"trips": c["trips"] + size} if "trips" in c else {}
    return _pack(dict(
        c, **counted, Z=_select(accepted, polished, _select(take, Z, Z0)), r=_select(take, r, r0),
        asked=asked, active=(c["active"] & ~moving) | (going & ~failed),
        lenient=jnp.where(done, lenient, c["lenient"]),
        current=current if inverse is KRYLOV else current & ~take,  # a Krylov direction is always new
        damping=jnp.where(backtrack, 0.5 * damping, jnp.where(take, jnp.minimum(1.0, 2.0 * damping), damping)),
        step=jnp.where(moving, jnp.where(restart, jnp.nan, step), c["step"]),
        rate=jnp.where(moving, jnp.where(restart, jnp.nan, rate), c["rate"]),
        r_size=jnp.where(take, r_size, c["r_size"]), iterations=iterations, watch=watch,
        ref_size=jnp.where(tentative, c["r_size"], c["ref_size"]),
        status=status,
    ))


@jax.named_scope("fixed_point")
def _fixed_point(problem, c):
    """The fixed-point phase: members not in Newton mode iterate ``Z <- Z - R(Z)`` in blocks
    until they converge, fail or ask for a Newton matrix. Its loop carries no matrix.

    A batch of at least ``8 * stragglers`` runs as a whole while more than one member in
    ``stragglers`` moves, then gathers those left (the stragglers: a larger h, a harder
    stretch of orbit) and iterates them alone, so that the batch does not pay for its
    slowest members' last updates. (The Newton phase does not: gathering the matrices of its
    few members costs more than it saves.)"""
    solver = problem.solver

    def moving(problem, c):
        return _live(problem, c) & ~_get(c, "asked") & ~_get(c, "newton")

    def blocks(problem, c, going):
        return jax.lax.while_loop(going, lambda c: _block(problem, c, None, solver.fixed_point_block), c)

    def loop(problem, c):
        return blocks(problem, c, lambda c: jnp.any(moving(problem, c)))

    B, n = c["Z"].shape[0], c["Z"][0].size
    if n > solver.small:
        c = _block(problem, c, None, solver.first_block)  # unconditional: a conditional costs more
    if B < 8 * solver.stragglers:
        return loop(problem, c)
    capacity = B // solver.stragglers
    c = blocks(problem, c, lambda c: jnp.sum(moving(problem, c)) > capacity)
    stragglers = lambda c: _gathered(problem, c, moving(problem, c), capacity, loop)
    return jax.lax.cond(jnp.any(moving(problem, c)), stragglers, lambda c: c, c)


@jax.named_scope("settle")
def _settle(problem, c, skip, updates):
    """``updates`` more fixed-point updates, each from a fresh residual, for the members the
    fixed-point phase accepted (``Options.settle``; not counted in ``iterations``, as the polish
    is not). The stopping rule leaves an error below the round-off of the unknowns, and the
    polish shrinks it by the rate; what is left still follows the predictor's smooth miss, so
    that its part in a conserved quantity adds up over the elements (``DiscreteGradient`` on
    Kepler: -3e-5 eps a step). One more update shrinks it by the rate again."""
    c = _unpack(c)
    settled = ~c["active"] & ~c["newton"] & ~skip & (c["status"] == Status.SUCCESS)

    def updated(Z):
        for _ in range(updates):
            Z = _select(settled, Z - problem.residual(Z), Z)
        return Z

    Z = jax.lax.cond(jnp.any(settled), updated, lambda Z: Z, c["Z"])
    return _pack(dict(c, Z=Z))


def _members(problem, which, capacity):
    """The members ``which`` (at most ``capacity`` of them) as a batch of ``capacity``:
    ``(index, take, sub)``, ``take`` gathering a per-member array, ``sub`` their problem. The
    slots left over hold a copy of member B - 1 and index B, which ``.at[index]`` drops."""
    B = which.shape[0]
    index = jnp.nonzero(which, size=capacity, fill_value=B)[0]
    take = lambda x: x[jnp.minimum(index, B - 1)]
    return index, take, dataclasses.replace(problem, params=jax.tree.map(take, problem.params), scale=take(problem.scale),
                                            tolerance=take(problem.tolerance))


def _gathered(problem, c, which, capacity, solve):
    """``solve(problem, c)`` for the members ``which`` alone, gathered (``_members``) and
    scattered back; the rest are unchanged, the slots left over inactive."""
    index, take, sub_problem = _members(problem, which, capacity)
    sub = jax.tree.map(lambda x: take(x) if jnp.ndim(x) else x, c)  # scalars are the batch's
    sub["active"] = sub["active"] & (index < which.shape[0])
    sub = solve(sub_problem, sub)
    return jax.tree.map(lambda x, y: x.at[index].set(y, mode="drop") if jnp.ndim(x) else y, c, sub)


def _served(c, served, dense=True):
    """The members ``served`` a fresh Newton matrix (``dense``; else a Krylov direction, which
    ``_Problem.matrix_cap`` does not count): Newton mode, a new rate, the patience counted
    from here, and full steps again: a damping that outlived the matrix it was halved for
    keeps every later step short, and the modified midpoint rule's 2e5-step Kepler run
    stalled on it (``test_energy_round_off_grows_no_faster_than_sqrt_n``)."""
    return dict(c, newton=c["newton"] | served, fresh=c["fresh"] | served, current=c["current"] | served,
                asked=c["asked"] & ~served, damping=jnp.where(served, 1.0, c["damping"]),
                step=jnp.where(served, jnp.nan, c["step"]), rate=jnp.where(served, jnp.nan, c["rate"]),
                since=jnp.where(served, c["iterations"], c["since"]), matrices=c["matrices"] + (served & dense))


def _refresh(problem, c, inverse, reference):
    """A batch: fresh Newton matrices at the current iterates for the members that asked, at
    most ``capacity`` of them, gathered so that the work follows the askers, not the batch;
    those beyond it keep asking. Returns ``(c, inverse, reference)`` (``_rewind``)."""
    B = c["Z"].shape[0]
    capacity = min(B, max(8, B // problem.solver.refresh_share))

    def refreshed(c, inverse, reference):
        c, reference = _rewind(c, reference)
        index, take, sub = _members(problem, c["asked"], capacity)
        inverse = inverse.at[index].set(jnp.linalg.inv(sub.jacobians(take(c["Z"]))), mode="drop")
        return _served(c, jnp.zeros(B, bool).at[index].set(True, mode="drop")), inverse, reference

    return jax.lax.cond(jnp.any(c["asked"]), refreshed, lambda *s: s, c, inverse, reference)


BACK, DONE_WATCHING = -2, -1  # ``watch``: back to the reference pending; no more watchdog this element


def _rewind(c, reference):
    """At a refresh, before the matrix is taken: members whose watchdog gave up go back to its reference with half a
    step, the rest that are not watching take their iterate as the reference (a watchdog's
    first step is a refresh's first, so the reference is where it started; no member goes
    back before a refresh has written its reference: ``Matrix.reference``)."""
    c = _unpack(c)
    back, idle = c["watch"] == BACK, c["watch"] == 0
    Z, r = _select(back, reference[0], c["Z"]), _select(back, reference[1], c["r"])
    c = dict(c, Z=Z, r=r, r_size=jnp.where(back, c["ref_size"], c["r_size"]),
             damping=jnp.where(back, 0.5, c["damping"]), watch=jnp.where(back, DONE_WATCHING, c["watch"]))
    return _pack(c), (_select(idle, Z, reference[0]), _select(idle, r, reference[1]))


@jax.named_scope("newton")
def _newton(problem, c, inverse, reference):
    """The Newton phase: members in Newton mode, and those that asked for it, iterate with
    their matrices, one checked update at a time (damping needs each).

    One run refreshes once per round (a conditional costs as much as an iteration of a small
    system, and one that passes the matrix through copies it), then iterates until it
    converges, fails or asks again. A batch serves its askers every iteration, so that nobody
    waits for the others' rounds to end.
    """
    moving = lambda s: jnp.any(_live(problem, s[0]) & (_get(s[0], "newton") | _get(s[0], "asked")))
    if c["Z"].shape[0] > 1:
        def step(state):
            c, inverse, reference = _refresh(problem, *state)
            return _block(problem, c, inverse, 1), inverse, reference

        return jax.lax.while_loop(moving, step, (c, inverse, reference))

    def round(state):
        def fresh(c, _, reference):
            c, reference = _rewind(c, reference)
            inverse = jnp.linalg.inv(problem.jacobians(c["Z"]))
            return _pack(_served(_unpack(c), jnp.ones(1, bool))), inverse, reference

        c, inverse, reference = jax.lax.cond(_get(state[0], "asked")[0], fresh, lambda *s: s, *state)
        going = lambda c: jnp.any(_live(problem, c) & ~_get(c, "asked"))
        return jax.lax.while_loop(going, lambda c: _block(problem, c, inverse, 1), c), inverse, reference

    return jax.lax.while_loop(moving, round, (c, inverse, reference))


@jax.named_scope("krylov")
def _newton_krylov(problem, c, reference):
    """The Newton phase of a system without a dense matrix: every update a fresh Newton
    direction, by GMRES (``_Problem.newton_krylov``). There is no matrix to wait for: every
    member that asks is served at once."""
    serve = lambda c: _pack(_served(_unpack(c), _get(c, "asked"), dense=False))
    moving = lambda s: jnp.any(_live(problem, s[0]) & (_get(s[0], "newton") | _get(s[0], "asked")))

    def step(state):
        c, reference = _rewind(*state)
        return _block(problem, serve(c), KRYLOV, 1), reference

    return jax.lax.while_loop(moving, step, (serve(c), reference))


@jax.named_scope("start")
def _start(problem, Z_pred, Z_alt, skip):
    """The first iterate and its residual: ``Z_pred``, or the constant ``Z_alt`` where that has
    the smaller residual and ``Z_pred``'s residual is not small against ``Z_pred`` (a continued
    polynomial can overshoot at large h omega). Returns ``(Z, r, r_size, ok)``; a non-finite Z
    has a non-finite residual."""
    r_pred = problem.residual(Z_pred)
    z_size, r_size = sizes(problem.unit, Z_pred, r_pred)

    def rival(Z, r, r_size):
        r_alt = problem.residual(Z_alt)
        r_alt_size = sizes(problem.unit, r_alt)[0]
        better = doubtful & ((r_alt_size < r_size) | ~jnp.isfinite(r_size))  # as in a run alone
        return _select(better, Z_alt, Z), _select(better, r_alt, r), jnp.where(better, r_alt_size, r_size)

    doubtful = ~(r_size < problem.solver.doubtful_start * z_size) & ~skip
    Z, r, r_size = jax.lax.cond(jnp.any(doubtful), rival, lambda *a: a, Z_pred, r_pred, r_size)
    return Z, r, r_size, jnp.isfinite(r_size)


def _iterate(fn, options, params, Z_pred, Z_alt, matrix, scale, tolerance, skip, first):
    """The iteration for a batch (every argument has a leading axis B); see the module docstring.

    Returns ``(Z, matrix, iterations, status, trips, lenient)``; ``trips`` counts the batch's
    updates, ``lenient`` marks an element accepted other than at round-off (``_converged``).
    """
    B, n, dtype = Z_pred.shape[0], Z_pred[0].size, Z_pred.dtype
    solver = options.solver
    krylov = matrix.inverse is None and _krylov(options)
    problem = _Problem(fn, params, scale, tolerance, solver, matrix.inverse is not None or krylov,
                       n > solver.small or options.short_lived_matrices,
                       solver.attempt_matrices if options.varying_steps else None)
    Z, r, r_size, ok = _start(problem, Z_pred, Z_alt, skip)
    # the watchdog watches an element whose predictor is the constant guess (``first``):
    # elsewhere the predictor has the previous elements' history
    watch = jnp.where(first, 0, DONE_WATCHING).astype(jnp.int32)
    nan, false = jnp.full(B, jnp.nan, dtype), jnp.zeros(B, bool)
    newton = matrix.newton > 0
    asked = newton & matrix.pending & ok & ~skip
    zero = jnp.zeros(B, jnp.int32)
    c = dict(Z=Z, r=r, newton=newton, fresh=newton if krylov else false, current=newton if krylov else false,
             asked=asked, damping=jnp.ones(B, dtype), step=nan, rate=nan, r_size=r_size, ref_size=nan, matrices=zero,
             active=ok & ~skip, lenient=false, iterations=zero, since=zero, watch=watch,
             status=jnp.where(ok | skip, Status.SUCCESS, Status.NONFINITE).astype(jnp.int32))
    if B > 1:
        c["trips"] = jnp.int32(0)  # the batch's updates; a run alone's are its iterations
    c = _pack(c)
    if options.fixed_point:
        c = _fixed_point(problem, c)
        if options.settle:
            c = _settle(problem, c, skip, options.settle)
    inverse, reference = matrix.inverse, matrix.reference
    if inverse is not None:
        c, inverse, reference = _newton(problem, c, inverse, reference)
    elif krylov:
        c, reference = _newton_krylov(problem, c, reference)
    c = _unpack(c)
    status = jnp.where(c["active"], Status.NEWTON_MAX_ITERATIONS, c["status"]).astype(jnp.int32)
    # a failed member's unknowns become its constant predictor: a finite point for the
    # linearisation, so no NaN reaches the others' gradients (its outputs are masked)
    Z = _select(status == Status.SUCCESS, c["Z"], Z_alt)
    # elements of Newton left: one fewer for a member in Newton mode, a stretch for one that switched
    switched = solver.newton_stretch if problem.large else ALWAYS
    left = jnp.where(newton, matrix.newton, jnp.where(c["newton"], switched, 0)) - c["newton"]
    if options.short_lived_matrices and options.fixed_point:
        # a stretch goes on while its matrix serves: an element of it that needs a fresh one ends it
        left = jnp.where(newton & (c["matrices"] > 0), 0, left)
    matrix = Matrix.of(left, matrix.pending & ~c["fresh"], inverse, reference)
    lenient = c["lenient"] & (status == Status.SUCCESS)
    return Z, matrix, c["iterations"], status, jnp.broadcast_to(c.get("trips", c["iterations"]), (B,)), lenient


def _fold(x, batched, axis_size):
    """Leading vmap axis of size ``axis_size`` folded into the batch axis B."""
    if not batched:
        x = jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
    return x.reshape((-1,) + x.shape[2:])


def _batched(fn, options):
    # jitted so that its trace is cached: under vmap, scan's batching fixpoint calls the rule
    # below twice with the same shapes, and each call would trace the whole iteration again
    traced = jax.jit(functools.partial(_iterate, fn, options))

    @jax.custom_batching.custom_vmap
    def iterate(*args):
        return traced(*args)

    @iterate.def_vmap
    def rule(axis_size, in_batched, *args):
        leaves, tree = jax.tree.flatten(args, is_leaf=lambda x: x is None)
        flags = jax.tree.leaves(in_batched, is_leaf=lambda x: x is None)
        folded = [x if x is None else _fold(x, b, axis_size) for x, b in zip(leaves, flags)]
        out = iterate(*jax.tree.unflatten(tree, folded))
        out = jax.tree.map(lambda x: x.reshape((axis_size, -1) + x.shape[1:]), out)
        return out, jax.tree.map(lambda _: True, out)

    return iterate


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def implicit(fn, dense_limit, params, Z, ok):
    """``Z``, a root of ``fn(., params)``, with the tangent of the implicit function theorem:
    ``dZ = -(dR/dZ)^{-1} dR/dparams dparams`` where ``ok``, zero elsewhere (a failed solve
    has no derivative; its states are NaN). The linear solve follows the forward solve's:
    dense up to ``dense_limit`` unknowns (``SolverOptions.dense_limit``), matrix-free GMRES
    above (``_tangent``)."""
    return Z


@implicit.defjvp
def _implicit_jvp(fn, dense_limit, primals, tangents):
    params, Z, ok = primals
    Z = implicit(fn, dense_limit, params, Z, ok)  # Z moves with params where the rule is differentiated again
    return Z, _tangent.tangent(fn, params, Z, ok, tangents[0], dense_limit=dense_limit)


def solve(fn, params, Z_pred, Z_alt, matrix, scale, skip, first, options):
    """The root of ``fn(Z, params) = 0`` for one run (vmappable: vmap axes join the batch).

    Args:
        fn: ``(Z, params) -> R``, same shape as Z; static.
        params: pytree of everything R depends on (method, state, h, args).
        Z_pred, Z_alt: the predictor and the constant-state fallback.
        matrix: the ``Matrix`` carried from the previous element.
        scale: size of the state the unknowns are increments of.
        skip: do not iterate (an earlier element failed).
        first: ``Z_pred`` is the constant guess (a run's first element, ``step``), which the
            watchdog watches (``SolverOptions.watch``).
        options: ``Options``; static.
    Returns:
        ``(Z, matrix, iterations, status, trips, lenient)``: ``trips`` counts the updates the
        batch ran (its slowest member's), ``iterations`` this member's; ``lenient``: accepted
        other than at round-off (``_converged``).
    """
    iterate = _batched(fn, options.with_tolerance(None))  # the value is an argument, not a closure
    tolerance = jnp.asarray(options.tolerance_value(), jnp.result_type(scale))
    args = jax.lax.stop_gradient((params, Z_pred, Z_alt, matrix, scale, tolerance, skip, jnp.asarray(first)))
    expanded = jax.tree.map(lambda x: jnp.asarray(x)[None], args)
    Z, matrix, iterations, status, trips, lenient = jax.tree.map(lambda x: x[0], iterate(*expanded))
    Z = implicit(fn, options.solver.dense_limit, params, Z, (status == Status.SUCCESS) & ~skip)  # skipped: no root
    return Z, jax.lax.stop_gradient(matrix), iterations, status, trips, lenient
