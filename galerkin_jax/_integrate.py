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


def select(mask, x, y):
    """``x`` where ``mask``, else ``y``, per run: ``mask`` has shape () (one run) or ``(B,)``
    (a batch; x and y have a leading axis B)."""
    return jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - mask.ndim)), x, y)


def nan_if_failed(x, status):
    """``x`` where ``status`` is SUCCESS, NaN elsewhere (per run, as in ``select``)."""
    return select(status != Status.SUCCESS, jnp.full_like(x, jnp.nan), x)


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
    return nan_if_failed(q1, status), nan_if_failed(p1, status)


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


def start_carry(q0, p0, guess, status):
    """The scan carry before the first element, and ``start``, the stand-in after a failure."""
    zero = jnp.zeros(status.shape, jnp.int32)
    start = (q0, p0, (q0, p0, guess))
    return dict(q=q0, p=p0, previous=start[2], status=status, total=zero, most=zero), start


def advance(carry, start, q1, p1, Z, iterations, status):
    """The carry after one element. The first failure's status is kept; from then on the run
    carries its finite ``start`` as a stand-in and is not solved again, so no NaN enters the
    linearisation and, under vmap, the reverse-mode gradients of the other runs stay finite
    (0 * NaN would not). Reported states are NaN (``nan_if_failed``)."""
    status = jnp.where(carry["status"] == Status.SUCCESS, status, carry["status"])
    now = (q1, p1, (carry["q"], carry["p"], Z))
    q1, p1, previous = jax.tree.map(lambda a, b: select(status != Status.SUCCESS, a, b), start, now)
    return dict(carry, q=q1, p=p1, previous=previous, status=status, total=carry["total"] + iterations,
                most=jnp.maximum(carry["most"], iterations))


def chain(element, carry, *, n_blocks, block_size, checkpoint):
    """``carry -> element(carry)`` over ``n_blocks * block_size`` elements by a nested ``lax.scan``.

    ``checkpoint=True`` rematerialises each block in reverse mode, so a gradient stores one
    carry per block instead of the residuals of every element.

    Returns:
        ``(final, (qs, ps))``: the last carry with its ``q, p`` NaN where failed, and the states
        at the end of each block (block axis first), NaN where failed.
    """

    def reported(carry):
        return nan_if_failed(carry["q"], carry["status"]), nan_if_failed(carry["p"], carry["status"])

    def block(carry, _):
        carry, _ = jax.lax.scan(lambda c, _: (element(c), None), carry, None, length=block_size)
        return carry, reported(carry)

    if checkpoint:
        block = jax.checkpoint(block)
    carry, saved = jax.lax.scan(block, carry, None, length=n_blocks)
    q, p = reported(carry)
    return dict(carry, q=q, p=p), saved


def march(method, fn, q0, p0, h, *, n_blocks, block_size, max_iterations, checkpoint=False):
    """Chain ``n_blocks * block_size`` elements of one run (see ``chain``).

    Returns:
        ``(final, (qs, ps))``: ``final`` holds ``q, p, status, total, most``; ``qs, ps``
        have shape ``(n_blocks, d)``, the state at the end of each block.
    """
    carry, start = start_carry(q0, p0, method.initial_guess(q0, p0), input_status(q0, p0, h))

    def element(c):
        solved = solve_element(method, fn, c["q"], c["p"], h, c["previous"], max_iterations,
                               c["status"] != Status.SUCCESS)
        return advance(c, start, *solved)

    return chain(element, carry, n_blocks=n_blocks, block_size=block_size, checkpoint=checkpoint)


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
