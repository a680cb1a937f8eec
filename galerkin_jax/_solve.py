"""The one root finder for the element equations ``R(Z) = 0``, and its status codes.

Every path (``step``, ``integrate``, ``jax.vmap(integrate)``, ``sweep``,
``amplification_matrix``) solves its elements here. The iteration is written over an
explicit batch axis B: a ``custom_vmap`` rule folds any ``vmap`` axes into it, so a vmapped
run pays for a Jacobian only in the iterations where some member asks for one (under a
plain ``vmap`` a ``lax.cond`` becomes a ``select`` that runs both branches every time).

Iteration (per member): ``Z <- Z - K R(Z)`` with ``K`` either the identity (the fixed-point
iteration of ``Z = h Phi(Z)``: every method's residual has Jacobian I at h = 0) or the
inverse of a Jacobian ``dR/dZ`` taken at an earlier iterate and kept across elements (the
simplified Newton method, as in Hairer and Wanner's Radau5). A member leaves the fixed-point
iteration, for good, when it contracts too slowly; it refreshes its Newton matrix when that
contracts too slowly or an update with it goes astray (the update is rejected), and halves a
full Newton step that does not lower the residual. Small systems start with Newton.

Stopping rule: a member stops when the error left after its update, ``|dZ| theta / (1 - theta)``
(theta the contraction rate), is below the round-off ``eps |Z|`` of the unknowns, or when its
updates stop shrinking: at the round-off of the state whatever K, below ``sqrt(eps)`` of the
state only with a fresh Newton matrix (the floor of an ill-conditioned system). A growing
update is never applied, and the residual at the accepted iterate must be below ``sqrt(eps)``
of the state. An accepted iterate gets one more update from its residual, which is already
known (a product, no residual). Iterating to the floor, not to a tolerance, and that last
update leave no systematic iteration error in the states, so round-off grows like sqrt(n)
(Brouwer's law), not like n.

Derivatives come from the implicit function theorem (``implicit``), never from the iterations.
"""

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


MESSAGES = {
    Status.SUCCESS: (
        "Every implicit solve converged to round-off. This says nothing about accuracy: "
        "see error_estimate for the local error of the steps."
    ),
    Status.NEWTON_MAX_ITERATIONS: (
        "An implicit solve did not converge within max_newton_iterations; reduce h or raise the "
        "cap. The element equations may have no real solution for this h."
    ),
    Status.NONFINITE: "NaN or inf in the element unknowns; check H, args and the initial state.",
    Status.INVALID_INPUT: "Invalid traced input: h <= 0 or a non-finite initial state.",
}


def status_message(status):
    """The message of a status code (an int or a concrete array)."""
    return MESSAGES[Status(int(status))]


DENSE_LIMIT = 256  # unknowns per element up to which a dense Newton matrix is kept
NEWTON_FIRST = 32  # unknowns per element up to which a run starts with Newton, not fixed point
THETA_NEWTON = 0.03  # Newton contraction rate above which a small system refreshes its matrix
THETA_NEWTON_LARGE = 0.25  # ... and a large one (n > NEWTON_FIRST), whose refresh costs n^3
THETA_FIXED_POINT = 0.5  # fixed-point rate above which a member switches to Newton
PATIENCE = 8  # iterations in one element after which a Newton member refreshes anyway
PATIENCE_FIXED_POINT = 24  # ... and a fixed-point member switches to Newton


@pytree_dataclass
class Matrix:
    """The iteration matrix ``K`` of each member, kept across elements.

    Attributes:
        newton: bool, shape ``(B,)`` (or ``()`` for one run): K is a Newton matrix, not I.
        pending: bool, like ``newton``: K is to be computed before its first use.
        inverse: ``(B, n, n)`` inverse Jacobians, or None when n > ``DENSE_LIMIT`` (then the
            iteration is the fixed-point one only).
    """

    newton: jax.Array
    pending: jax.Array
    inverse: object


def _matvec(K, r):
    """K @ r per member, ``(B, n, n) x (B, n)``, unrolled over the columns: one fused loop,
    where a batched dot or a broadcast-and-reduce of this size is several times slower."""
    total = K[:, :, 0] * r[:, :1]
    for j in range(1, r.shape[1]):
        total = total + K[:, :, j] * r[:, j : j + 1]
    return total


def _size(x):
    return jnp.max(jnp.abs(x.reshape(x.shape[0], -1)), axis=1)


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


def initial_matrix(Z):
    """``Matrix`` for the first element of one run: Newton (a Jacobian at the first iterate)
    for small systems, the fixed-point iteration otherwise."""
    n = Z.size
    newton = jnp.asarray(n <= NEWTON_FIRST)
    return Matrix(newton=newton, pending=newton, inverse=None if n > DENSE_LIMIT else jnp.zeros((n, n), Z.dtype))


def _iterate(fn, max_iterations, params, Z_pred, Z_alt, matrix, scale, skip):
    """The iteration for a batch (every argument has a leading axis B); see the module docstring.

    ``Z_alt`` is a second predictor (the constant state), tried only where ``Z_pred``'s residual
    is not small against ``Z_pred`` (a continued polynomial can overshoot at large h omega).
    Returns ``(Z, matrix, iterations, status, trips)``; ``trips`` is the loop count of the batch.
    """
    B, n, dtype = Z_pred.shape[0], Z_pred[0].size, Z_pred.dtype
    eps, tiny = jnp.finfo(dtype).eps, jnp.finfo(dtype).tiny
    dense = matrix.inverse is not None
    residual = lambda Z: jax.vmap(fn)(Z, params)

    def rival(Z, r):
        r_alt = residual(Z_alt)
        better = (_size(r_alt) < _size(r)) | ~jnp.isfinite(_size(r))
        return _select(better, Z_alt, Z), _select(better, r_alt, r)

    r_pred = residual(Z_pred)
    doubtful = ~(_size(r_pred) < 0.1 * _size(Z_pred)) & ~skip
    Z0, r0 = jax.lax.cond(jnp.any(doubtful), rival, lambda Z, r: (Z, r), Z_pred, r_pred)

    capacity = B if B <= 8 else max(8, B // 8)  # members whose Jacobians one refresh computes

    def refreshed(Z, inverse, asked):
        """Inverse Jacobians for up to ``capacity`` of the members that asked, gathered so
        that the work follows the askers, not the batch; returns ``(inverse, served)``."""
        if capacity == B:
            return _select(asked, jnp.linalg.inv(block_jacobians(residual, Z)), inverse), asked
        index = jnp.nonzero(asked, size=capacity, fill_value=B)[0]
        take = lambda x: x[jnp.minimum(index, B - 1)]
        sub = jax.tree.map(take, params)
        J = block_jacobians(lambda Z: jax.vmap(fn)(Z, sub), take(Z))
        inverse = inverse.at[index].set(jnp.linalg.inv(J), mode="drop")
        return inverse, jnp.zeros(B, bool).at[index].set(True, mode="drop")

    def refresh(c):
        """Fresh matrices for the members that asked (those beyond ``capacity`` keep asking)."""
        asked, inverse = c["asked"], c["inverse"]
        if not dense:
            return c
        inverse, served = jax.lax.cond(jnp.any(asked), refreshed, lambda Z, inverse, asked: (inverse, jnp.zeros_like(asked)),
                                       c["Z"], inverse, asked)
        return dict(c, inverse=inverse, newton=c["newton"] | served, fresh=c["fresh"] | served,
                    damping=jnp.where(served, 1.0, c["damping"]), asked=asked & ~served)

    # one run: the scalars packed (fewer kernel launches); a batch: apart (a packed group is a
    # concatenate, whose per-element indexing XLA does not vectorise)
    pack, unpack = (_pack, _unpack) if B == 1 else (lambda c: c, lambda c: c)
    flag = lambda c, name: c["flags"][_GROUPS["flags"].index(name)] if B == 1 else c[name]

    def rounds(c):
        return (c["trips"] < max_iterations) & jnp.any(flag(c, "active"))

    def iterating(c):
        return (c["trips"] < max_iterations) & jnp.any(flag(c, "active") & ~flag(c, "asked"))

    def one_round(c):
        """One run (B = 1): refresh once per round, then iterate until the member converges,
        fails or asks again; a conditional costs as much as an iteration of a small system."""
        return jax.lax.while_loop(iterating, body, pack(refresh(unpack(c))))

    def batch_iteration(c):
        """A batch: the askers are served at once, every iteration (the conditional is cheap
        against the batch's work, and nobody waits for a round to end)."""
        return body(pack(refresh(unpack(c))))

    def update(r, newton, inverse, damping):
        """``damping K r`` per member, flat: K the Newton inverse where ``newton``, else I."""
        r_flat = r.reshape(B, -1)
        dz = r_flat
        if dense and n <= NEWTON_FIRST:  # fused, no conditional: cheaper than skipping it
            dz = _select(newton, _matvec(inverse, r_flat), r_flat)
        elif dense:  # only in iterations where some member uses Newton
            dz = jax.lax.cond(jnp.any(newton), lambda: _select(newton, jnp.einsum("bij,bj->bi", inverse, r_flat), r_flat),
                              lambda: r_flat)
        return damping[:, None] * dz

    def body(c):
        c = unpack(c)
        Z, r, newton, fresh, inverse, damping = c["Z"], c["r"], c["newton"], c["fresh"], c["inverse"], c["damping"]
        moving = c["active"] & ~c["asked"]  # members that asked wait for their matrix
        dz = update(r, newton, inverse, damping)
        Z_new = Z - dz.reshape(Z.shape)
        r_new = residual(Z_new)
        # max propagates NaN, so a non-finite update or residual shows in ``step`` or
        # ``r_size``; one run takes the three sizes in one reduction (one launch)
        if B == 1:
            step, z_size, r_size = jnp.max(jnp.abs(jnp.stack([dz, Z_new.reshape(B, -1), r_new.reshape(B, -1)])), axis=-1)
        else:
            step, z_size, r_size = _size(dz), _size(Z_new), _size(r_new)
        bad = ~jnp.isfinite(step + r_size)
        rate = step / c["step"]  # NaN until a member has two updates with one K
        theta = jnp.fmax(rate, c["rate"])
        floor = jnp.sqrt(eps) * (scale + z_size + tiny)
        noisy = step <= 100.0 * eps * (scale + z_size)  # updates this small are round-off, not a slow K
        # the error left after this update is below the round-off of the unknowns. (Allowing a
        # tenth of the state's instead, 9 % fewer iterations, left a bias of +0.008 eps |H| per
        # step in the discrete gradient's energy on Kepler: 2.4e-12 after 1e6 steps, not 6e-13.)
        small = (step == 0) | ((theta <= 0.5) & (step * theta <= (1.0 - theta) * eps * z_size))
        accept_here = small & ~bad & (r_size <= floor)
        # the updates stopped shrinking at the round-off floor: keep Z, never the growing update.
        # Below sqrt(eps) only with a fresh Newton K (a stale K can stall far from the root; it
        # is refreshed instead); at the round-off of the state whatever the K.
        stale = ~(newton & fresh)  # a fixed-point K, or a Newton K from an earlier iterate
        stalled = ((~stale & (rate >= 1.0) & (step <= floor)) | (noisy & (step >= c["last"]))) & (c["r_size"] <= floor)
        done = moving & (accept_here | stalled)
        going = moving & ~done
        rejected = going & stale & (bad | (rate > 1.0))
        # a Newton step with a fresh K that does not lower the residual is halved (far from the
        # root, e.g. at h omega ~ 1, Newton's full steps can wander)
        backtrack = going & ~stale & (bad | (r_size >= c["r_size"])) & ~noisy & (damping > 1.0 / 64)
        failed = going & ~stale & bad & ~backtrack
        take = (done & accept_here) | (going & ~rejected & ~failed & ~backtrack)
        # computed once: without the barrier XLA repeats the decisions above in every fusion
        # that reads them (the selects below, the packed carries), which costs more than the rest
        take, going, failed, backtrack, rejected = jax.lax.optimization_barrier((take, going, failed, backtrack, rejected))
        Z, r = _select(take, Z_new, Z), _select(take, r_new, r)
        iterations = c["iterations"] + moving
        status = jnp.where(failed, Status.NONFINITE, c["status"])
        active = (c["active"] & ~moving) | (going & ~failed)
        slow = theta > jnp.where(newton, THETA_NEWTON if n <= NEWTON_FIRST else THETA_NEWTON_LARGE, THETA_FIXED_POINT)
        patience = iterations >= jnp.where(newton, PATIENCE, PATIENCE_FIXED_POINT)
        unsure = small & ~bad & stale  # a small update but a large residual: K is off
        asked = c["asked"] | (going & ~failed & ~backtrack & (rejected | ((slow | patience) & ~noisy) | unsure) & dense)
        damping = jnp.where(backtrack, 0.5 * damping, jnp.where(take, jnp.minimum(1.0, 2.0 * damping), damping))
        restart = asked | backtrack
        return pack(dict(
            trips=c["trips"] + 1, Z=Z, r=r, newton=newton, fresh=fresh, inverse=inverse, asked=asked,
            damping=damping, step=jnp.where(restart, jnp.nan, step), rate=jnp.where(restart, jnp.nan, rate),
            last=jnp.where(take, step, c["last"]), r_size=jnp.where(take, r_size, c["r_size"]), active=active,
            iterations=iterations, status=status, accepted=c["accepted"] | (done & accept_here),
        ))

    r0_size = _size(r0)
    ok = jnp.isfinite(_size(Z0) + r0_size)
    nan = jnp.full(B, jnp.nan, dtype)
    init = dict(
        trips=jnp.int32(0), Z=Z0, r=r0, newton=matrix.newton, fresh=jnp.zeros(B, bool), inverse=matrix.inverse,
        asked=matrix.pending & ok & ~skip,
        damping=jnp.ones(B, dtype), step=nan, rate=nan, last=nan, r_size=r0_size, active=ok & ~skip, iterations=jnp.zeros(B, jnp.int32),
        status=jnp.where(ok | skip, Status.SUCCESS, Status.NONFINITE).astype(jnp.int32), accepted=jnp.zeros(B, bool),
    )
    c = unpack(jax.lax.while_loop(rounds, one_round if B == 1 else batch_iteration, pack(init)))
    # The accepted iterate's residual is already known: one more update with it costs a
    # product, no residual, and leaves theta times less of the iteration error, which is
    # systematic (it follows the predictor's smooth miss) and would add up over the elements.
    polish = update(c["r"], c["newton"], c["inverse"], c["damping"]).reshape(c["Z"].shape)
    c["Z"] = _select(c["accepted"], c["Z"] - polish, c["Z"])
    status = jnp.where(c["active"], Status.NEWTON_MAX_ITERATIONS, c["status"]).astype(jnp.int32)
    # a failed member's unknowns become its constant predictor: a finite point for the
    # linearisation, so no NaN reaches the others' gradients (its outputs are masked)
    Z = _select(status == Status.SUCCESS, c["Z"], Z_alt)
    matrix = Matrix(newton=c["newton"], pending=matrix.pending & ~(ok & ~skip), inverse=c["inverse"])
    return Z, matrix, c["iterations"], status, jnp.broadcast_to(c["trips"], (B,))


# For one run the per-member scalars of the loop travel as three stacked arrays: XLA then
# computes each group in one fused kernel, not one kernel per scalar (the loop's cost is
# mostly launches).
_GROUPS = {"floats": ("damping", "step", "rate", "last", "r_size"), "flags": ("newton", "fresh", "asked", "active", "accepted"),
           "counts": ("iterations", "status")}


def _pack(c):
    packed = {k: v for k, v in c.items() if not any(k in names for names in _GROUPS.values())}
    return dict(packed, **{group: jnp.stack([c[k] for k in names]) for group, names in _GROUPS.items()})


def _unpack(c):
    values = {k: v for k, v in c.items() if k not in _GROUPS}
    return dict(values, **{k: c[group][i] for group, names in _GROUPS.items() for i, k in enumerate(names)})


def _fold(x, batched, axis_size):
    """Leading vmap axis of size ``axis_size`` folded into the batch axis B."""
    if not batched:
        x = jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
    return x.reshape((-1,) + x.shape[2:])


def _batched(fn, max_iterations):
    @jax.custom_batching.custom_vmap
    def iterate(*args):
        return _iterate(fn, max_iterations, *args)

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
    has no derivative; its states are NaN)."""
    return Z


@implicit.defjvp
def _implicit_jvp(fn, primals, tangents):
    params, Z, ok = primals
    _, dR = jax.jvp(lambda p: fn(Z, p), (params,), (tangents[0],))
    J = jax.jacfwd(lambda z: fn(z.reshape(Z.shape), params).reshape(-1))(Z.reshape(-1))
    J = jnp.where(ok, J, jnp.eye(J.shape[0], dtype=J.dtype))
    dZ = -jnp.linalg.solve(J, dR.reshape(-1))
    return Z, jnp.where(ok, dZ, 0.0).reshape(Z.shape)


def solve(fn, params, Z_pred, Z_alt, matrix, scale, skip, max_iterations):
    """The root of ``fn(Z, params) = 0`` for one run (vmappable: vmap axes join the batch).

    Args:
        fn: ``(Z, params) -> R``, same shape as Z; static.
        params: pytree of everything R depends on (method, state, h, args).
        Z_pred, Z_alt: the predictor and the constant-state fallback.
        matrix: the ``Matrix`` carried from the previous element.
        scale: size of the state the unknowns are increments of.
        skip: do not iterate (an earlier element failed).
        max_iterations: cap on iterations; static.
    Returns:
        ``(Z, matrix, iterations, status, trips)``: ``trips`` counts the iterations the batch
        ran (its slowest member's), ``iterations`` this member's.
    """
    iterate = _batched(fn, max_iterations)
    args = jax.lax.stop_gradient((params, Z_pred, Z_alt, matrix, scale, skip))
    expanded = jax.tree.map(lambda x: jnp.asarray(x)[None], args)
    Z, matrix, iterations, status, trips = jax.tree.map(lambda x: x[0], iterate(*expanded))
    Z = implicit(fn, params, Z, (status == Status.SUCCESS) & ~skip)  # skipped: no root, no derivative
    return Z, jax.lax.stop_gradient(matrix), iterations, status, trips
