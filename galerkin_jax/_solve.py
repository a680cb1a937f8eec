"""The one root finder for the element equations ``R(Z) = 0``, and its status codes.

Every path (``step``, ``integrate``, ``jax.vmap(integrate)``, ``sweep``,
``amplification_matrix``) solves its elements here. The iteration is written over an
explicit batch axis B: a ``custom_vmap`` rule folds any ``vmap`` axes into it, so a vmapped
run pays for a Jacobian only in the iterations where some member asks for one (under a
plain ``vmap`` a ``lax.cond`` becomes a ``select`` that runs both branches every time).

Iteration (per member): ``Z <- Z - K R(Z)``, in two phases per element.

* The fixed-point phase: ``K = I``, the fixed-point iteration of ``Z = h Phi(Z)`` (every method
  whose residual has Jacobian I at h = 0), in blocks of ``FIXED_POINT_BLOCK`` updates checked
  once at the block's end; a system of more than ``SMALL`` unknowns starts each element with a
  block of ``FIRST_BLOCK`` (it needs four to six updates, and a check costs several kernels).
  Its loop carries no matrix, so a run that never needs Newton never pays for one. A member
  leaves it when it contracts at a rate above 1/2 or takes too many iterations in one element
  (the predictor's error and the rate together decide the cost).
  A large batch iterates its stragglers, its last eighth to converge, gathered apart.
  Partitioned methods on states of more than ``_march.SWEEP_DIMENSION`` degrees of freedom
  hand this solver the residual of their Gauss-Seidel sweep (``_march.element_residual``),
  whose fixed point contracts at the square of the plain one's rate.
  A method whose residual's Jacobian at h = 0 is not I (dG(k >= 1)) has no fixed point and
  solves every element by Newton.
* The Newton phase: ``K`` the inverse of a Jacobian ``dR/dZ`` taken at an earlier iterate and
  kept across elements (the simplified Newton method, as in Hairer and Wanner's Radau5), one
  checked update at a time. A member refreshes its matrix when it contracts too slowly or an
  update goes astray (the update is rejected). A Newton step that does not lower the residual
  is halved if the matrix was taken at the step's start (``current``), else undone and the
  matrix refreshed there (damped Newton far from the root, simplified Newton near it). A
  system too large for a dense matrix (more than ``DENSE_LIMIT`` unknowns) has Newton only
  with ``Options.krylov``: every update a fresh Newton direction, by GMRES on Jacobian-vector
  products (Newton-Krylov; its cost follows the Hessian's sparsity, not n^3). A small system
  that switched stays with Newton (its Newton update costs two to three fixed-point ones); a
  large one, whose update costs a product with an n x n matrix or a Krylov solve, for
  ``NEWTON_STRETCH`` elements, then tries the fixed point again (one hard element does not
  cost it the run). Small systems solve a run's first element by Newton: the predictor has no
  history yet.

The loop's cost is mostly per check, not per update: the decisions, the sizes and the loop's
trip are each a kernel that XLA's CPU runtime launches on its own. A block of two fixed-point
updates costs little more than one; a rejected block is undone as a whole.

Stopping rule: a member stops when the error left after its update, ``|dZ| theta / (1 - theta)``
(theta the contraction rate: a block's last two updates' ratio, or in Newton's one update per
check the largest ratio of the element), is below the round-off ``eps |Z|`` of the unknowns, or
when its updates stop shrinking: at the round-off of the state whatever K (there also when
they still shrink, by less than half, past the member's patience), below ``sqrt(eps)`` of the
state only with a fresh Newton matrix (the floor of an ill-conditioned system). A growing
update is never applied, and the residual at the accepted iterate must be below ``sqrt(eps)``
of the state. An accepted iterate gets one more update from its residual, which is already
known (a product, no residual). Iterating to the floor, not to a tolerance, and that last
update leave no systematic iteration error in the states, so round-off grows like sqrt(n)
(Brouwer's law), not like n. Sizes are root-mean-square norms over a member's unknowns (a
sum of squares is one cheap reduction; NaN and inf propagate through it).

Derivatives come from the implicit function theorem (``implicit``), never from the iterations.
"""

import dataclasses
import enum
import functools

import jax
import jax.numpy as jnp

from ._pytree import pytree_dataclass


class Status(enum.IntEnum):
    """Codes of ``Solution.status``; the first failure of a run is kept."""

    SUCCESS = 0
    NEWTON_MAX_ITERATIONS = 1
    NONFINITE = 2
    INVALID_INPUT = 3
    MAX_STEPS = 4
    DTMIN = 5
    TIME_TRANSFORM = 6


MESSAGES = {
    Status.SUCCESS: (
        "Every implicit solve converged to round-off. This says nothing about accuracy: "
        "see error_estimate for the local error of the steps."
    ),
    Status.NEWTON_MAX_ITERATIONS: (
        "An implicit solve did not converge within max_newton_iterations; reduce h or raise the "
        "cap. The element equations may have no real solution for this h. A system of more "
        "than 256 unknowns per element (k * 2d for cG(k)) has only the fixed-point iteration "
        "unless krylov=True, which a stiff one (h omega >~ 1) needs."
    ),
    Status.NONFINITE: "NaN or inf in the element unknowns; check H, args and the initial state.",
    Status.INVALID_INPUT: "Invalid traced input: h <= 0 or a non-finite initial state.",
    Status.MAX_STEPS: (
        "The run reached max_steps (accepted and rejected steps together) before t1; raise "
        "max_steps or loosen the tolerance."
    ),
    Status.DTMIN: (
        "The step size fell below dtmin (or to the round-off of t) with the step still rejected: "
        "the solution may be singular there, or the tolerance below what the precision allows."
    ),
    Status.TIME_TRANSFORM: (
        "The time transformation's s(q, p) was not positive and finite (e.g. the default s at an "
        "equilibrium, where Hamilton's field vanishes); pass a TimeTransform(s=...) of your own."
    ),
}


def status_message(status):
    """The message of a status code (an int or a concrete array)."""
    return MESSAGES[Status(int(status))]


DENSE_LIMIT = 256  # unknowns per element up to which a dense Newton matrix is kept
SMALL = 32  # unknowns per element up to which a Newton update and refresh are cheap
THETA_FIXED_POINT = 0.5  # fixed-point rate above which a member switches to Newton
THETA_NEWTON = (0.03, 0.25)  # Newton rate above which a member refreshes (small, large systems)
PATIENCE = 8  # iterations in one element after which a Newton member refreshes anyway
PATIENCE_FIXED_POINT = (12, 24)  # ... and a fixed-point member switches to Newton (small, large)
NEWTON_STRETCH = 16  # elements a large system that switched to Newton stays with it
ALWAYS = 2**30  # elements of Newton: for good
FIXED_POINT_BLOCK = 2  # fixed-point updates per check (module docstring)
FIRST_BLOCK = 4  # ... in an element's first check, for a system of more than SMALL unknowns
STRAGGLERS = 8  # a batch gathers its last 1 / STRAGGLERS moving members (``_fixed_point``)
# GMRES for a Newton-Krylov direction: a relative residual of 1e-7 leaves 1e-7 of the error per
# update, so the updates reach the floor in 2 or 3; restarts of 20, at most 200 products
KRYLOV_TOLERANCE, KRYLOV_RESTART, KRYLOV_RESTARTS = 1e-7, 20, 10


@dataclasses.dataclass(frozen=True)
class Options:
    """The root finder's static options.

    Attributes:
        max_iterations: iterations per element after which a member fails.
        krylov: Newton by GMRES on Jacobian-vector products (``_Problem.newton_krylov``) for
            systems of more than ``DENSE_LIMIT`` unknowns, which otherwise have the fixed point
            only. Stiff large systems (h omega >~ 1) need it; it compiles about a second longer.
        fixed_point: the method has a fixed-point iteration; else every element is Newton's,
            by Newton-Krylov where no dense matrix is kept, whatever ``krylov`` says.
    """

    max_iterations: int
    krylov: bool = False
    fixed_point: bool = True


@pytree_dataclass
class Matrix:
    """The iteration matrix ``K`` of each member, kept across elements.

    Attributes:
        state: int32, shape ``(B, 2)`` (or ``(2,)`` for one run): ``newton`` and ``pending``
            in one array (one kernel and one copy per element, not two).
        inverse: ``(B, n, n)`` inverse Jacobians, or None when n > ``DENSE_LIMIT`` (then Newton
            is Newton-Krylov, with ``Options.krylov``, or there is none).

    ``newton``: the elements, this one included, that the member still solves by Newton; 0 for
    the fixed point (module docstring). ``pending``: ``inverse`` is yet to be computed.
    """

    state: jax.Array
    inverse: object

    @classmethod
    def of(cls, newton, pending, inverse):
        return cls(jnp.stack([jnp.asarray(newton, jnp.int32), jnp.asarray(pending, jnp.int32)], axis=-1), inverse)

    @property
    def newton(self):
        return self.state[..., 0]

    @property
    def pending(self):
        return self.state[..., 1] != 0


def initial_matrix(Z, fixed_point=True):
    """``Matrix`` for the first element of one run; ``fixed_point`` False: a method whose
    fixed-point iteration cannot contract solves every element by Newton."""
    n = Z.size
    dense = n <= DENSE_LIMIT
    newton = 1 if dense and n <= SMALL else 0
    return Matrix.of(newton if fixed_point else ALWAYS, True, jnp.zeros((n, n), Z.dtype) if dense else None)


def _matvec(K, r):
    """K @ r per member, ``(B, n, n) x (B, n)``, unrolled over the columns: one fused loop,
    where a batched dot or a broadcast-and-reduce of this size is several times slower."""
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
    max_iterations: int
    newton: bool  # a Newton phase is there to ask for
    unit: object = dataclasses.field(init=False)  # (B,): the scale of the ``sizes``, or None
    # the batched residual, jitted: its ~10 call sites (start, blocks, Newton matrix) reuse one trace
    _residual: object = dataclasses.field(init=False, repr=False)

    def __post_init__(self):
        # ``scale`` (1 where that is 0), computed once, outside the loops. None in float64:
        # scaled sizes cost 8 % of a Kepler step (measured), and a float64 square overflows
        # only past 1e154, where a kinetic energy |p|^2 / 2 in H does too.
        float64 = jnp.finfo(self.scale.dtype).bits == 64
        object.__setattr__(self, "unit", None if float64 else jnp.where(self.scale > 0, self.scale, 1.0))
        object.__setattr__(self, "_residual", jax.jit(jax.vmap(self.fn)))

    def residual(self, Z):
        return self._residual(Z, self.params)

    def newton_krylov(self, Z, r):
        """``dR/dZ(Z)^{-1} r`` per member, by restarted GMRES on Jacobian-vector products: the
        Newton direction of a system too large for a dense matrix, at the cost of a few
        residual linearisations per Krylov iteration (H's Hessian-vector products), however
        sparse H's Hessian. Each member solves alone (vmap), as it would in a run of its own."""

        tolerance = max(KRYLOV_TOLERANCE, 10 * float(jnp.finfo(r.dtype).eps))  # float32: 1.2e-6

        def direction(Z, r, params):
            _, jvp = jax.linearize(lambda Z: self.fn(Z, params), Z)
            return jax.scipy.sparse.linalg.gmres(jvp, r, tol=tolerance, restart=KRYLOV_RESTART,
                                                 maxiter=KRYLOV_RESTARTS)[0]

        return jax.vmap(direction)(Z, r, self.params)


# The scalars of each member travel as two stacked arrays for one run, the flags as 0/1 among
# the int32 counts: XLA then computes each group in one fused kernel, and copies it once per
# loop trip, not once per scalar (the loop's cost is mostly kernel launches; a third array of
# flags cost 3-10 % of a step, one float array for all 5-40 %, measured). A batch keeps them
# apart: a packed group is a concatenate, whose per-element indexing XLA does not vectorise.
_GROUPS = {"floats": ("damping", "step", "rate", "r_size"),
           "ints": ("newton", "fresh", "current", "asked", "active", "iterations", "status", "since")}
_FLAGS = ("newton", "fresh", "current", "asked", "active")


def _pack(c):
    if c["Z"].shape[0] > 1:
        return c
    packed = {k: v for k, v in c.items() if not any(k in names for names in _GROUPS.values())}
    return dict(packed, **{group: jnp.stack([c[k].astype(jnp.int32) if k in _FLAGS else c[k] for k in names])
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
            return value != 0 if name in _FLAGS else value
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
        r = _matvec(K, r) if r.shape[1] <= SMALL else jnp.einsum("bij,bj->bi", K, r)
    return damping[:, None] * r


def _block(problem, c, inverse, size):
    """``size`` updates of the moving members, checked once at the end: the one stopping
    rule (module docstring). ``inverse`` is the Newton phase's matrices, None in the
    fixed-point phase."""
    c = _unpack(c)
    n, dtype = c["Z"][0].size, c["Z"].dtype
    eps, tiny = jnp.finfo(dtype).eps, jnp.finfo(dtype).tiny
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
    bad = ~jnp.isfinite(step + r_size)
    rate = step / before  # NaN until a member has two updates with one K
    # the contraction rate: a block's last two updates' (an element's first ratio is its
    # largest and would hold it back a block), one update per check (Newton): the largest
    # of the element's ratios, as one ratio alone is noisy
    theta = rate if size > 1 else jnp.fmax(rate, c["rate"])
    floor = jnp.sqrt(eps) * (problem.scale + z_size + tiny)
    noisy = step <= 100.0 * eps * (problem.scale + z_size)  # updates this small are round-off, not a slow K
    # the error left after this update is below the round-off of the unknowns. (Allowing a
    # tenth of the state's instead, 9 % fewer iterations, left a bias of +0.008 eps |H| per
    # step in the discrete gradient's energy on Kepler: 2.4e-12 after 1e6 steps, not 6e-13.)
    iterations, large = c["iterations"] + size * moving, n > SMALL
    # a Newton member's patience counts from its matrix, a fixed-point member's from the start
    patience = jnp.where(newton, iterations - c["since"], iterations) >= jnp.where(newton, PATIENCE,
                                                                                 PATIENCE_FIXED_POINT[large])
    grown = (step >= before) | (step >= c["step"])  # within the block, or since the last one
    # round-off that still shrinks, by less than half an update, past the member's patience is
    # the floor too. (Accepted before the patience, it added a bias: the discrete gradient's
    # Kepler energy drifted twice as fast, 9e-14 after 4e6 steps, not 4e-14.)
    settled = noisy & ~grown & (theta > 0.5) & patience
    small = (step == 0) | settled | ((theta <= 0.5) & (step * theta <= (1.0 - theta) * eps * z_size))
    accept_here = small & ~bad & (r_size <= floor)
    # the updates stopped shrinking at the round-off floor (they grew, or shrink by less than
    # half: noise): keep the block's start, never the growing update. Below sqrt(eps) only with
    # a fresh Newton K (a stale K can stall far from the root; it is refreshed instead); at the
    # round-off of the state whatever the K.
    stale = ~(newton & fresh)  # a fixed-point K, or a Newton K from an earlier iterate
    stalled = ((~stale & (rate >= 1.0) & (step <= floor)) | (noisy & grown)) & (c["r_size"] <= floor)
    done = moving & (accept_here | stalled)
    going = moving & ~done
    # a Newton step that does not lower the residual is halved with a K taken at its start
    # (far from the root, e.g. at h omega ~ 1, Newton's full steps can wander; only there is
    # the Newton direction one in which the residual falls), else undone for such a K.
    # ``current`` implies a fresh Newton K (``_served`` sets all three), so not ``stale``.
    lowered = ~bad & (r_size < c["r_size"])
    backtrack = going & current & ~lowered & ~noisy & (damping > 1.0 / 64)
    rejected = going & ((stale & (bad | (rate > 1.0))) | (~stale & ~current & ~lowered & ~noisy))
    failed = going & current & bad & ~backtrack
    take = (done & accept_here) | (going & ~rejected & ~failed & ~backtrack)
    # computed once: without the barrier XLA repeats the decisions above in every fusion
    # that reads them (the selects below, the packed carries), which costs more than the rest
    take, going, failed, backtrack, rejected, accepted = jax.lax.optimization_barrier(
        (take, going, failed, backtrack, rejected, done & accept_here))
    slow = theta > jnp.where(newton, THETA_NEWTON[large], THETA_FIXED_POINT)
    unsure = small & ~bad & stale  # a small update but a large residual: K is off
    asks = rejected | ((slow | patience) & ~noisy) | unsure
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
        current=current if inverse is KRYLOV else current & ~take,  # a Krylov direction is always new
        damping=jnp.where(backtrack, 0.5 * damping, jnp.where(take, jnp.minimum(1.0, 2.0 * damping), damping)),
        step=jnp.where(moving, jnp.where(restart, jnp.nan, step), c["step"]),
        rate=jnp.where(moving, jnp.where(restart, jnp.nan, rate), c["rate"]),
        r_size=jnp.where(take, r_size, c["r_size"]), iterations=iterations,
        status=jnp.where(failed, Status.NONFINITE, c["status"]),
    ))


def _fixed_point(problem, c):
    """The fixed-point phase: members not in Newton mode iterate ``Z <- Z - R(Z)`` in blocks
    until they converge, fail or ask for a Newton matrix. Its loop carries no matrix.

    A batch of at least ``8 * STRAGGLERS`` runs as a whole while more than one member in
    ``STRAGGLERS`` moves, then gathers those left (the stragglers: a larger h, a harder
    stretch of orbit) and iterates them alone, so that the batch does not pay for its
    slowest members' last updates. (The Newton phase does not: measured, gathering the
    matrices of its few members cost more than it saved.)"""
    def moving(problem, c):
        return _live(problem, c) & ~_get(c, "asked") & ~_get(c, "newton")

    def blocks(problem, c, going):
        return jax.lax.while_loop(going, lambda c: _block(problem, c, None, FIXED_POINT_BLOCK), c)

    def loop(problem, c):
        return blocks(problem, c, lambda c: jnp.any(moving(problem, c)))

    B, n = c["Z"].shape[0], c["Z"][0].size
    if n > SMALL:
        c = _block(problem, c, None, FIRST_BLOCK)  # unconditional: a conditional costs more
    if B < 8 * STRAGGLERS:
        return loop(problem, c)
    capacity = B // STRAGGLERS
    c = blocks(problem, c, lambda c: jnp.sum(moving(problem, c)) > capacity)
    stragglers = lambda c: _gathered(problem, c, moving(problem, c), capacity, loop)
    return jax.lax.cond(jnp.any(moving(problem, c)), stragglers, lambda c: c, c)


def _members(problem, which, capacity):
    """The members ``which`` (at most ``capacity`` of them) as a batch of ``capacity``:
    ``(index, take, sub)``, ``take`` gathering a per-member array, ``sub`` their problem. The
    slots left over hold a copy of member B - 1 and index B, which ``.at[index]`` drops."""
    B = which.shape[0]
    index = jnp.nonzero(which, size=capacity, fill_value=B)[0]
    take = lambda x: x[jnp.minimum(index, B - 1)]
    return index, take, dataclasses.replace(problem, params=jax.tree.map(take, problem.params), scale=take(problem.scale))


def _gathered(problem, c, which, capacity, solve):
    """``solve(problem, c)`` for the members ``which`` alone, gathered (``_members``) and
    scattered back; the rest are unchanged, the slots left over inactive."""
    index, take, sub_problem = _members(problem, which, capacity)
    sub = jax.tree.map(lambda x: take(x) if jnp.ndim(x) else x, c)  # scalars are the batch's
    sub["active"] = sub["active"] & (index < which.shape[0])
    sub = solve(sub_problem, sub)
    return jax.tree.map(lambda x, y: x.at[index].set(y, mode="drop") if jnp.ndim(x) else y, c, sub)


def _served(c, served):
    """The members ``served`` a fresh Newton matrix: Newton mode, full steps, a new rate, the
    patience counted from here."""
    return dict(c, newton=c["newton"] | served, fresh=c["fresh"] | served, current=c["current"] | served,
                damping=jnp.where(served, 1.0, c["damping"]), asked=c["asked"] & ~served,
                step=jnp.where(served, jnp.nan, c["step"]), rate=jnp.where(served, jnp.nan, c["rate"]),
                since=jnp.where(served, c["iterations"], c["since"]))


def _refresh(problem, c, inverse):
    """A batch: fresh Newton matrices at the current iterates for the members that asked, at
    most ``capacity`` of them, gathered so that the work follows the askers, not the batch;
    those beyond it keep asking."""
    B = c["Z"].shape[0]
    capacity = min(B, max(8, B // 8))

    def refreshed(Z, inverse, asked):
        index, take, sub = _members(problem, asked, capacity)
        inverse = inverse.at[index].set(jnp.linalg.inv(block_jacobians(sub.residual, take(Z))), mode="drop")
        return inverse, jnp.zeros(B, bool).at[index].set(True, mode="drop")

    unchanged = lambda Z, inverse, asked: (inverse, jnp.zeros_like(asked))
    inverse, served = jax.lax.cond(jnp.any(c["asked"]), refreshed, unchanged, c["Z"], inverse, c["asked"])
    return _served(c, served), inverse


def _newton(problem, c, inverse):
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
            c, inverse = _refresh(problem, *state)
            return _block(problem, c, inverse, 1), inverse

        return jax.lax.while_loop(moving, step, (c, inverse))

    def round(state):
        c, inverse = state
        fresh = lambda c, _: (_pack(_served(_unpack(c), jnp.ones(1, bool))),
                              jnp.linalg.inv(block_jacobians(problem.residual, _unpack(c)["Z"])))
        c, inverse = jax.lax.cond(_get(c, "asked")[0], fresh, lambda *s: s, c, inverse)
        going = lambda c: jnp.any(_live(problem, c) & ~_get(c, "asked"))
        return jax.lax.while_loop(going, lambda c: _block(problem, c, inverse, 1), c), inverse

    return jax.lax.while_loop(moving, round, (c, inverse))


def _newton_krylov(problem, c):
    """The Newton phase of a system without a dense matrix: every update a fresh Newton
    direction, by GMRES (``_Problem.newton_krylov``). There is no matrix to wait for: every
    member that asks is served at once."""
    serve = lambda c: _pack(_served(_unpack(c), _get(c, "asked")))
    moving = lambda c: jnp.any(_live(problem, c) & (_get(c, "newton") | _get(c, "asked")))
    return jax.lax.while_loop(moving, lambda c: _block(problem, serve(c), KRYLOV, 1), serve(c))


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

    doubtful = ~(r_size < 0.1 * z_size) & ~skip
    Z, r, r_size = jax.lax.cond(jnp.any(doubtful), rival, lambda *a: a, Z_pred, r_pred, r_size)
    return Z, r, r_size, jnp.isfinite(r_size)


def _iterate(fn, options, params, Z_pred, Z_alt, matrix, scale, skip):
    """The iteration for a batch (every argument has a leading axis B); see the module docstring.

    Returns ``(Z, matrix, iterations, status, trips)``; ``trips`` counts the batch's updates.
    """
    B, n, dtype = Z_pred.shape[0], Z_pred[0].size, Z_pred.dtype
    krylov = matrix.inverse is None and (options.krylov or not options.fixed_point)
    problem = _Problem(fn, params, scale, options.max_iterations, matrix.inverse is not None or krylov)
    Z, r, r_size, ok = _start(problem, Z_pred, Z_alt, skip)
    nan, false = jnp.full(B, jnp.nan, dtype), jnp.zeros(B, bool)
    newton = matrix.newton > 0
    asked = newton & matrix.pending & ok & ~skip
    zero = jnp.zeros(B, jnp.int32)
    c = dict(Z=Z, r=r, newton=newton, fresh=newton if krylov else false, current=newton if krylov else false,
             asked=asked, damping=jnp.ones(B, dtype), step=nan, rate=nan, r_size=r_size, active=ok & ~skip,
             iterations=zero, since=zero,
             status=jnp.where(ok | skip, Status.SUCCESS, Status.NONFINITE).astype(jnp.int32))
    if B > 1:
        c["trips"] = jnp.int32(0)  # the batch's updates; a run alone's are its iterations
    c = _pack(c)
    if options.fixed_point:
        c = _fixed_point(problem, c)
    inverse = matrix.inverse
    if inverse is not None:
        c, inverse = _newton(problem, c, inverse)
    elif krylov:
        c = _newton_krylov(problem, c)
    c = _unpack(c)
    status = jnp.where(c["active"], Status.NEWTON_MAX_ITERATIONS, c["status"]).astype(jnp.int32)
    # a failed member's unknowns become its constant predictor: a finite point for the
    # linearisation, so no NaN reaches the others' gradients (its outputs are masked)
    Z = _select(status == Status.SUCCESS, c["Z"], Z_alt)
    # elements of Newton left: one fewer for a member in Newton mode, a stretch for one that switched
    switched = NEWTON_STRETCH if n > SMALL else ALWAYS
    left = jnp.where(newton, matrix.newton, jnp.where(c["newton"], switched, 0)) - c["newton"]
    matrix = Matrix.of(left, matrix.pending & ~c["fresh"], inverse)
    return Z, matrix, c["iterations"], status, jnp.broadcast_to(c.get("trips", c["iterations"]), (B,))


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


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def implicit(fn, params, Z, ok):
    """``Z``, a root of ``fn(., params)``, with the tangent of the implicit function theorem:
    ``dZ = -(dR/dZ)^{-1} dR/dparams dparams`` where ``ok``, zero elsewhere (a failed solve
    has no derivative; its states are NaN). The linear solve follows the forward solve's:
    dense up to ``DENSE_LIMIT`` unknowns, matrix-free GMRES above (``_tangent``)."""
    return Z


@implicit.defjvp
def _implicit_jvp(fn, primals, tangents):
    from . import _tangent

    params, Z, ok = primals
    Z = implicit(fn, params, Z, ok)  # Z moves with params where the rule is differentiated again
    return Z, _tangent.tangent(fn, params, Z, ok, tangents[0], dense_limit=DENSE_LIMIT)


def solve(fn, params, Z_pred, Z_alt, matrix, scale, skip, options):
    """The root of ``fn(Z, params) = 0`` for one run (vmappable: vmap axes join the batch).

    Args:
        fn: ``(Z, params) -> R``, same shape as Z; static.
        params: pytree of everything R depends on (method, state, h, args).
        Z_pred, Z_alt: the predictor and the constant-state fallback.
        matrix: the ``Matrix`` carried from the previous element.
        scale: size of the state the unknowns are increments of.
        skip: do not iterate (an earlier element failed).
        options: ``Options``; static.
    Returns:
        ``(Z, matrix, iterations, status, trips)``: ``trips`` counts the updates the batch
        ran (its slowest member's), ``iterations`` this member's.
    """
    iterate = _batched(fn, options)
    args = jax.lax.stop_gradient((params, Z_pred, Z_alt, matrix, scale, skip))
    expanded = jax.tree.map(lambda x: jnp.asarray(x)[None], args)
    Z, matrix, iterations, status, trips = jax.tree.map(lambda x: x[0], iterate(*expanded))
    Z = implicit(fn, params, Z, (status == Status.SUCCESS) & ~skip)  # skipped: no root, no derivative
    return Z, jax.lax.stop_gradient(matrix), iterations, status, trips
