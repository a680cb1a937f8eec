"""One time element (``step``) and many (``integrate``): Newton per element, ``lax.scan`` over elements."""

import functools

import jax
import jax.numpy as jnp

from . import _checks
from ._newton import Status, solve_implicit
from ._pytree import pytree_dataclass

DEFAULT_MAX_NEWTON_ITERATIONS = 32


@pytree_dataclass
class Solution:
    """Saved states of ``integrate``.

    Attributes:
        t: shape ``(m,)``, ``m = n_steps // save_every + 1``, starting at 0.
        q, p: shape ``(m, d)``, the initial state first.
        status: int32 ``Status`` code, 0 when every implicit solve converged. After the
            first failure the remaining states are NaN.
        stats: ``num_newton_iterations`` (total) and ``max_newton_iterations`` (largest
            count in one element).
    """

    t: jax.Array
    q: jax.Array
    p: jax.Array
    status: jax.Array
    stats: dict


def bind_args(H, args):
    return H if args is None else (lambda q, p: H(q, p, args))


def input_status(q0, p0, h):
    ok = jnp.isfinite(h) & (h > 0) & jnp.all(jnp.isfinite(q0)) & jnp.all(jnp.isfinite(p0))
    return jnp.where(ok, Status.SUCCESS, Status.INVALID_INPUT).astype(jnp.int32)


def nan_if_failed(x, status):
    """``x`` where ``status`` is SUCCESS, NaN elsewhere; ``status`` broadcasts over x's trailing axes."""
    failed = (status != Status.SUCCESS).reshape(status.shape + (1,) * (x.ndim - status.ndim))
    return jnp.where(failed, jnp.nan, x)


def solve_element(method, H, q0, p0, h, previous, max_iterations, skip=False):
    """Solve one element; returns ``(q1, p1, Z, iterations, status)``.

    The predictor is the previous element's polynomial extrapolated, or the constant
    state when that has the larger residual (it can overshoot at large h omega). With
    ``skip`` (an earlier element failed) nothing is solved.
    """
    residual = lambda Z: method.residual(H, q0, p0, Z, h)
    Z0 = method.initial_guess(q0, p0)
    if previous is not None:
        Z_extrapolated = method.initial_guess(q0, p0, previous)
        r0, r1 = (jnp.max(jnp.abs(residual(Z))) for Z in (Z0, Z_extrapolated))
        Z0 = jnp.where(r1 < r0, Z_extrapolated, Z0)
    scale = jax.lax.stop_gradient(jnp.maximum(jnp.max(jnp.abs(q0)), jnp.max(jnp.abs(p0))))
    Z, iterations, status = solve_implicit(residual, Z0, max_iterations, scale, skip)
    q1, p1 = method.end_state(H, q0, p0, Z, h)
    finite = jnp.all(jnp.isfinite(q1)) & jnp.all(jnp.isfinite(p1))
    status = jnp.where((status == 0) & ~finite, Status.NONFINITE, status).astype(jnp.int32)
    return q1, p1, Z, iterations, status


def prepare(H, q0, p0, method, h, args):
    _checks.check_function(H)
    _checks.check_method(method)
    q0, p0 = _checks.check_state(q0, p0)
    _checks.check_step_size(h)
    fn = bind_args(H, args)
    _checks.check_scalar_output(fn, q0, p0)
    return q0, p0, jnp.asarray(h, q0.dtype)


def step(H, q, p, *, method, h, args=None, max_newton_iterations=DEFAULT_MAX_NEWTON_ITERATIONS):
    """One time element: ``(q, p) -> (q1, p1)``.

    A failed solve returns NaN, never a plausible state; ``integrate`` reports why.

    Args:
        H: ``H(q, p)`` or ``H(q, p, args)`` returning a scalar (``L(q, qdot)`` for LagrangianVI).
        q, p: shape ``(d,)``.
        method: e.g. ``CG(k, rule)``, ``DG(k, rule)``.
        h: step size, scalar > 0.
    Returns:
        ``(q1, p1)``, each shape ``(d,)``.
    """
    q, p, h = prepare(H, q, p, method, h, args)
    _checks.check_iterations(max_newton_iterations)
    return _step(H, q, p, method, h, args, max_newton_iterations)


@functools.partial(jax.jit, static_argnums=(0, 6))
def _step(H, q, p, method, h, args, max_iterations):
    q1, p1, _, _, status = solve_element(method, bind_args(H, args), q, p, h, None, max_iterations)
    status = jnp.maximum(status, input_status(q, p, h))
    bad = status != Status.SUCCESS
    return jnp.where(bad, jnp.nan, q1), jnp.where(bad, jnp.nan, p1)


def integrate(
    H,
    q0,
    p0,
    *,
    method,
    h,
    n_steps,
    args=None,
    save_every=1,
    max_newton_iterations=DEFAULT_MAX_NEWTON_ITERATIONS,
    checkpoint=False,
):
    """Integrate Hamilton's equations over ``n_steps`` elements of size ``h``.

    The elements are chained by a nested ``lax.scan`` (outer over saves, inner over
    ``save_every`` elements), so memory is O(n_steps / save_every).

    Args:
        H: ``H(q, p)`` or ``H(q, p, args)`` (``L(q, qdot)`` for LagrangianVI).
        q0, p0: shape ``(d,)`` (p0 is the initial momentum for LagrangianVI too).
        method: a method object (CG, DG, GalerkinVI, ...).
        h: step size > 0; may be traced (vmap over step sizes).
        n_steps: number of elements, a multiple of ``save_every``. Static.
        args: pytree passed to ``H`` as third argument; may be traced.
        save_every: store every ``save_every``-th state. Static.
        max_newton_iterations: iteration cap per element. Static.
        checkpoint: rematerialise each saved block in reverse mode: a gradient then stores
            one state per save instead of every element's residuals. Static.
    Returns:
        ``Solution`` with ``m = n_steps // save_every + 1`` saved states.
    """
    q0, p0, h = prepare(H, q0, p0, method, h, args)
    _checks.check_counts(n_steps, save_every)
    _checks.check_iterations(max_newton_iterations)
    return _integrate(H, q0, p0, method, h, args, n_steps, save_every, max_newton_iterations, checkpoint)


def march(method, fn, q0, p0, h, *, n_blocks, block_size, max_iterations, checkpoint=False):
    """Chain ``n_blocks * block_size`` elements by a nested ``lax.scan``.

    ``checkpoint=True`` rematerialises each block in reverse mode, so a gradient stores
    one carry per block instead of the residuals of every element.

    Returns:
        ``(final, (qs, ps))``: ``final`` holds ``q, p, status, total, most``; ``qs, ps``
        have shape ``(n_blocks, d)``, the state at the end of each block.
    """
    status0 = input_status(q0, p0, h)
    zero = jnp.int32(0)
    start = (q0, p0, method.initial_guess(q0, p0))

    def element(carry, _):
        q, p, previous, status, total, most = carry
        q1, p1, Z, iterations, s = solve_element(method, fn, q, p, h, previous, max_iterations,
                                                 status != Status.SUCCESS)
        status = jnp.where(status == Status.SUCCESS, s, status)
        # after a failure the run carries its finite initial state as a stand-in, not solved
        # again; no NaN enters the linearisation, so under vmap the reverse-mode gradients of
        # the other members stay finite (0 * NaN would not). Reported states are NaN.
        failed = status != Status.SUCCESS
        q1, p1 = jnp.where(failed, q0, q1), jnp.where(failed, p0, p1)
        previous = jax.tree.map(lambda a, b: jnp.where(failed, a, b), start, (q, p, Z))
        return (q1, p1, previous, status, total + iterations, jnp.maximum(most, iterations)), None

    def block(carry, _):
        carry, _ = jax.lax.scan(element, carry, None, length=block_size)
        return carry, (nan_if_failed(carry[0], carry[3]), nan_if_failed(carry[1], carry[3]))

    if checkpoint:
        block = jax.checkpoint(block)
    carry = (q0, p0, start, status0, zero, zero)
    carry, saved = jax.lax.scan(block, carry, None, length=n_blocks)
    q, p, _, status, total, most = carry
    final = {"q": nan_if_failed(q, status), "p": nan_if_failed(p, status), "status": status, "total": total,
             "most": most}
    return final, saved


@functools.partial(jax.jit, static_argnums=(0, 6, 7, 8, 9))
def _integrate(H, q0, p0, method, h, args, n_steps, save_every, max_iterations, checkpoint):
    n_saves = n_steps // save_every
    final, (qs, ps) = march(
        method, bind_args(H, args), q0, p0, h, n_blocks=n_saves, block_size=save_every,
        max_iterations=max_iterations, checkpoint=checkpoint,
    )
    return Solution(
        t=jnp.arange(n_saves + 1, dtype=q0.dtype) * (save_every * h),
        q=jnp.concatenate([q0[None], qs]),
        p=jnp.concatenate([p0[None], ps]),
        status=final["status"],
        stats={"num_newton_iterations": final["total"], "max_newton_iterations": final["most"]},
    )


def amplification_matrix(H, q, p, *, method, h, args=None):
    """A = d z_1 / d z_0 of one element, by ``jax.jacfwd`` through the implicit solve [GBS, eq. (48)].

    For a quadratic H this is the amplification matrix of the two-level scheme
    ``z_{k+1} = A z_0``; in general it is the Jacobian of the one-step map.

    Returns:
        shape ``(2d, 2d)`` in the ordering ``z = (q, p)``.
    """
    q, p, h = prepare(H, q, p, method, h, args)
    d = q.shape[0]

    def one_step(z):
        return jnp.concatenate(_step(H, z[:d], z[d:], method, h, args, DEFAULT_MAX_NEWTON_ITERATIONS))

    return jax.jacfwd(one_step)(jnp.concatenate([q, p]))
