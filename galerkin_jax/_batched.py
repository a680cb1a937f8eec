"""Batch-aware Newton for sweeps: one loop for the whole batch, Jacobians kept across elements.

Under ``vmap`` a ``lax.cond`` becomes a ``select`` that runs both branches, so a vmapped
per-member Newton loop pays for a Jacobian and a linear factorisation in every iteration.
Here the batch axis is explicit. Each member keeps the inverse of a Newton matrix from an
earlier element and iterates with it (the simplified Newton method, as in Hairer and
Wanner's Radau5); it asks for a fresh Jacobian, at its current iterate, only when its
iteration contracts too slowly or an update goes astray (``simplified_newton``). The batch
computes Jacobians only in the iterations where some member asks, and only the members that
asked adopt them, so no other member's value enters a member's arithmetic: a sweep gives the
numbers of the configuration run by itself, up to how XLA compiles another batch size.
Derivatives come from ``jax.lax.custom_root``, as in ``_newton``.
"""

import jax
import jax.numpy as jnp

from ._integrate import advance, bind_args, chain, input_status, select, start_carry
from ._newton import Status, solvable

THETA = 0.25  # contraction rate above which a member refreshes its Jacobian
PATIENCE = 8  # iterations in one element after which a member refreshes it anyway


def batched_residual(method, H, args, q0, p0, h):
    """Z -> R(Z) for every member at once; leaves of every argument have a leading batch axis."""

    def one(m, a, q, p, Z, step):
        return m.residual(bind_args(H, a), q, p, Z, step)

    return lambda Z: jax.vmap(one)(method, args, q0, p0, Z, h)


def block_jacobians(residual, Z):
    """dR_b / dZ_b for every member b, shape ``(B, n, n)``: the residual is block diagonal, so
    n JVPs with the same unit direction in every member give every block's columns."""
    B, n = Z.shape[0], Z[0].size
    _, jvp = jax.linearize(residual, Z)
    units = jnp.eye(n, dtype=Z.dtype).reshape((n,) + Z.shape[1:])
    columns = jax.vmap(lambda e: jvp(jnp.broadcast_to(e, Z.shape)))(units)
    return jnp.moveaxis(columns.reshape(n, B, n), 0, -1)


def _per_member(fn, x):
    return fn(x.reshape(x.shape[0], -1), axis=1)


def simplified_newton(residual, Z0, r0, inverse, scale, max_iterations, skip):
    """Simplified Newton for all members; returns ``(Z, iterations, status, inverse)``.

    The iteration ``Z <- Z - K R(Z)``, ``K`` an inverse Newton matrix from an earlier iterate,
    contracts linearly at a rate ``theta``, estimated as the larger of the last two update
    ratios (they scatter). A member stops at the round-off floor ``tol = 10 eps (scale + max|Z|)``:
    when its update is below ``tol`` and ``K`` is known to contract (fresh, or theta <= 1/2);
    when the error left after the update, ``~ |dZ| theta / (1 - theta)``, is below ``tol / 10``
    (measured on Kepler with h <= 0.1: a bound of tol left up to 1e-14 in an element's end
    state, tol / 10 leaves 7e-16); or, with a Jacobian from this element, when the updates have
    stopped shrinking (ratio 1/2 to 2) below ``sqrt(eps) (scale + max|Z|)``.

    A member asks for a fresh ``K`` at its current iterate when theta exceeds ``THETA``, after
    ``PATIENCE`` iterations in one element (theta just below ``THETA`` would need ~25), or
    when an update with a stale ``K`` diverges (ratio > 1) or leads to a non-finite residual;
    such an update is rejected. A non-finite residual after an update with a fresh ``K`` is
    a failure. Members in ``skip`` (already failed) and members with a non-finite ``Z0`` or
    ``r0`` do not iterate.
    """
    B, dtype = Z0.shape[0], Z0.dtype
    eps, tiny = jnp.finfo(dtype).eps, jnp.finfo(dtype).tiny

    def refreshed(Z, inverse, asked):
        new = jnp.linalg.inv(block_jacobians(residual, Z))
        return select(asked, new, inverse)

    def cond(carry):
        it, *_, active, _, _ = carry
        return (it < max_iterations) & jnp.any(active)

    def body(carry):
        it, Z, r, inverse, fresh, previous_step, previous_rate, active, iterations, status = carry
        dz = jnp.einsum("bij,bj->bi", inverse, r.reshape(B, -1))
        Z_new = Z - dz.reshape(Z.shape)
        step = jnp.max(jnp.abs(dz), axis=1)  # max propagates NaN
        size = scale + _per_member(jnp.max, jnp.abs(Z_new)) + tiny
        tol = 10.0 * eps * size
        rate = step / previous_step  # NaN until a member has two updates with one K
        theta = jnp.fmax(rate, previous_rate)
        contracting = fresh | (theta <= 0.5)
        converged = (step <= tol) & contracting
        converged |= (theta <= 0.5) & (step * theta / (1.0 - theta) <= 0.1 * tol)
        converged |= fresh & (step <= jnp.sqrt(eps) * size) & (rate >= 0.5) & (rate <= 2.0)
        done = active & converged & jnp.isfinite(step)
        going = active & ~done
        # the residual at the new iterate: the next update's, and the test of this one
        r_new = jax.lax.cond(jnp.any(going), residual, lambda _: r, Z_new)
        bad = ~jnp.isfinite(step) | ~_per_member(jnp.all, jnp.isfinite(r_new))
        rejected = going & ~fresh & (bad | (rate > 1.0))
        failed = going & fresh & bad
        accept = done | (going & ~rejected & ~failed)
        Z, r = select(accept, Z_new, Z), select(accept, r_new, r)
        iterations = iterations + active
        status = jnp.where(failed, Status.NONFINITE, status)
        active = going & ~failed
        asked = active & (rejected | (theta > THETA) | (iterations >= PATIENCE))
        inverse = jax.lax.cond(jnp.any(asked), refreshed, lambda Z, inverse, _: inverse, Z, inverse, asked)
        fresh = fresh | asked
        previous_step = jnp.where(asked, jnp.nan, jnp.where(active, step, previous_step))
        previous_rate = jnp.where(asked, jnp.nan, jnp.where(active, rate, previous_rate))
        return it + 1, Z, r, inverse, fresh, previous_step, previous_rate, active, iterations, status

    ok = _per_member(jnp.all, jnp.isfinite(Z0)) & _per_member(jnp.all, jnp.isfinite(r0))
    nan = jnp.full(B, jnp.nan, dtype)
    init = (
        jnp.int32(0), Z0, r0, inverse, jnp.zeros(B, bool), nan, nan, ok & ~skip, jnp.zeros(B, jnp.int32),
        jnp.where(ok | skip, Status.SUCCESS, Status.NONFINITE).astype(jnp.int32),
    )
    _, Z, _, inverse, _, _, _, active, iterations, status = jax.lax.while_loop(cond, body, init)
    status = jnp.where(active, Status.NEWTON_MAX_ITERATIONS, status).astype(jnp.int32)
    # a failed member's unknowns become the constant state: custom_root linearises there, and
    # a finite point keeps 0 * NaN out of the others' gradients (its outputs are masked)
    Z = select(status == Status.SUCCESS, Z, jnp.zeros_like(Z))
    return Z, iterations, status, inverse


def solve_batched(residual, Z0, r0, inverse, scale, max_iterations, skip):
    """Roots of the block-diagonal ``residual`` near ``Z0``; derivatives by the implicit function theorem.

    ``r0`` must be ``residual(Z0)`` (custom_root calls ``solve`` with ``Z0`` only).

    Returns:
        ``(Z, iterations, status, inverse)``, the counts int32 and per member.
    """
    B = Z0.shape[0]

    def solve(f, Z):
        Z, iterations, status, new_inverse = simplified_newton(f, Z, r0, inverse, scale, max_iterations, skip)
        # aux travels as float: integer aux breaks custom_root's JVP (jax-ml/jax#24295)
        return Z, (iterations.astype(Z.dtype), status.astype(Z.dtype), new_inverse)

    def tangent_solve(g, y):
        J, usable = solvable(block_jacobians(g, y))
        x = jnp.linalg.solve(J, y.reshape(B, -1, 1)).reshape(y.shape)
        return select(usable, x, jnp.zeros_like(x))

    Z, aux = jax.lax.custom_root(residual, Z0, solve, tangent_solve, has_aux=True)
    iterations, status, inverse = jax.lax.stop_gradient(aux)
    return Z, iterations.astype(jnp.int32), status.astype(jnp.int32), inverse


def solve_elements(method, H, args, q0, p0, h, previous, correction, inverse, max_iterations, skip):
    """One element for every member: ``(q1, p1, Z, iterations, status, inverse, miss)``.

    The predictor is, per member, the previous element's polynomial continued plus
    ``correction`` (an extrapolation of earlier ``miss``es, the continuation's errors
    ``Z - continued``) or, where that one's residual is not small against its size,
    whichever of it, the plain continuation and the constant state has the smallest
    residual. Members in ``skip`` are not solved (their ``Z`` is the predictor).
    """
    residual = batched_residual(method, H, args, q0, p0, h)
    guess = jax.vmap(lambda m, q, p, prev: m.initial_guess(q, p, prev))
    continued, constant = guess(method, q0, p0, previous), guess(method, q0, p0, None)
    Z_continued = continued + correction
    r_continued = residual(Z_continued)
    size = lambda x: _per_member(jnp.max, jnp.abs(x))
    # a continued polynomial whose residual is small against its own size needs no rival;
    # the constant state's residual is computed only when some member's is not
    doubtful = ~(size(r_continued) < 0.1 * size(Z_continued))

    def rival(Z, r):
        for Z_other in (continued, constant):
            r_other = residual(Z_other)
            use = ~doubtful | (size(r) < size(r_other))  # NaN residuals lose every comparison
            Z, r = select(use, Z, Z_other), select(use, r, r_other)
        return Z, r

    Z0, r0 = jax.lax.cond(jnp.any(doubtful), rival, lambda Z, r: (Z, r), Z_continued, r_continued)
    Z0 = select(skip, constant, Z0)  # finite, and not iterated
    scale = jax.lax.stop_gradient(jnp.maximum(jnp.max(jnp.abs(q0), axis=1), jnp.max(jnp.abs(p0), axis=1)))
    Z, iterations, status, inverse = solve_batched(residual, Z0, r0, inverse, scale, max_iterations, skip)
    q1, p1 = jax.vmap(lambda m, a, q, p, Z, step: m.end_state(bind_args(H, a), q, p, Z, step))(method, args, q0, p0, Z, h)
    finite = _per_member(jnp.all, jnp.isfinite(q1)) & _per_member(jnp.all, jnp.isfinite(p1))
    status = jnp.where((status == Status.SUCCESS) & ~finite, Status.NONFINITE, status).astype(jnp.int32)
    return q1, p1, Z, iterations, status, inverse, Z - continued


def march_batched(method, H, args, q0, p0, h, *, n_blocks, block_size, max_iterations, observe, acc0,
                  checkpoint=False):
    """``_integrate.march`` for a batch: ``n_blocks * block_size`` elements of every member.

    ``acc = observe(acc, q1, p1)`` (batched: leading axis B) folds each new state into the
    carry (a failed member's stand-in state once it has failed, see ``_integrate.advance``).

    Returns:
        ``(final, (qs, ps))``: ``final`` holds ``q, p, status, total, most, acc`` (leading axis B)
        and ``batch``, the iterations the batch ran (per element the largest member count);
        ``qs, ps`` have shape ``(B, n_blocks, d)``, the state at the end of each block.
    """
    guess = jax.vmap(lambda m, q, p: m.initial_guess(q, p))(method, q0, p0)
    inverse0 = jax.lax.stop_gradient(jnp.linalg.inv(block_jacobians(batched_residual(method, H, args, q0, p0, h), guess)))
    carry, start = start_carry(q0, p0, guess, jax.vmap(input_status)(q0, p0, h))
    misses = (jnp.zeros_like(guess), jnp.zeros_like(guess))
    carry.update(misses=misses, count=jnp.int32(0), inverse=inverse0, batch=jnp.int32(0), acc=acc0)

    def element(c):
        # The continuation's miss varies smoothly from element to element; its linear
        # extrapolation from the last two leaves O(h^2) of it (iterations 3.9 -> 3.2 per
        # element in benchmarks/bench_sweep.py). ``count`` elements are done (capped at 3);
        # the first one has no continuation, hence no miss.
        weights = jnp.asarray([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [2.0, -1.0]], q0.dtype)[c["count"]]
        correction = weights[0] * c["misses"][0] + weights[1] * c["misses"][1]
        q1, p1, Z, iterations, status, inverse, miss = solve_elements(
            method, H, args, c["q"], c["p"], h, c["previous"], correction, c["inverse"], max_iterations,
            c["status"] != Status.SUCCESS)
        misses = tuple(jnp.where(c["count"] >= 1, new, old) for new, old in zip((miss, c["misses"][0]), c["misses"]))
        c = advance(c, start, q1, p1, Z, iterations, status)
        return dict(c, misses=misses, count=jnp.minimum(c["count"] + 1, 3), inverse=inverse,
                    batch=c["batch"] + jnp.max(iterations), acc=observe(c["acc"], c["q"], c["p"]))

    final, (qs, ps) = chain(element, carry, n_blocks=n_blocks, block_size=block_size, checkpoint=checkpoint)
    return final, (jnp.moveaxis(qs, 0, 1), jnp.moveaxis(ps, 0, 1))
