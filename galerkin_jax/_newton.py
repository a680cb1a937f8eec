"""Newton's method for the element equations, differentiated by the implicit function theorem."""

import enum

import jax
import jax.numpy as jnp


class Status(enum.IntEnum):
    """Codes of ``Solution.status``; the first failure of a run is kept."""

    SUCCESS = 0
    NEWTON_MAX_ITERATIONS = 1
    NONFINITE = 2
    INVALID_INPUT = 3


MESSAGES = {
    Status.SUCCESS: "Every implicit solve converged.",
    Status.NEWTON_MAX_ITERATIONS: (
        "Newton did not converge within max_newton_iterations; reduce h or raise the cap. "
        "The element equations may have no real solution for this h."
    ),
    Status.NONFINITE: "NaN or inf in the element unknowns; check H, args and the initial state.",
    Status.INVALID_INPUT: "Invalid traced input: h <= 0 or a non-finite initial state.",
}


def status_message(status):
    """The message of a status code (an int or a concrete array)."""
    return MESSAGES[Status(int(status))]


SMALL_SYSTEM = 16


@jax.custom_batching.custom_vmap
def linear_solve(A, b):
    """A^{-1} b for the Newton update (never differentiated: the solve sits inside custom_root)."""
    return jnp.linalg.solve(A, b)


@linear_solve.def_vmap
def _linear_solve_batched(axis_size, in_batched, A, b):
    # Under vmap (sweeps) small systems go through an unrolled Gauss-Jordan elimination:
    # vector operations over the batch instead of one LAPACK call per member.
    A, b = (x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, batched in zip((A, b), in_batched))
    solve = _gauss_jordan if A.shape[-1] <= SMALL_SYSTEM else jnp.linalg.solve
    return jax.vmap(solve)(A, b), True


def _gauss_jordan(A, b):
    """Gauss-Jordan elimination with partial pivoting, unrolled over the columns."""
    n = A.shape[0]
    M = jnp.concatenate([A, b[:, None]], axis=1)
    rows = jnp.arange(n)
    for k in range(n):
        pivot = k + jnp.argmax(jnp.abs(M[k:, k]))
        M = M[jnp.where(rows == k, pivot, jnp.where(rows == pivot, k, rows))]
        pivot_row = M[k] / M[k, k]
        M = M - jnp.where(rows == k, 0.0, M[:, k])[:, None] * pivot_row[None, :]
        M = M.at[k].set(pivot_row)
    return M[:, n]


def newton(residual, Z0, max_iterations, scale=0.0, skip=False):
    """Newton on ``residual(Z) = 0`` in a ``lax.while_loop``; never raises.

    It stops at the round-off floor ``tol = 10 eps (scale + max|Z|)``, where ``scale`` is
    the size of the state the unknowns are added to (the unknowns are increments): when
    the update is below ``tol``; when convergence is quadratic (rate ``r = |dZ_k| / |dZ_{k-1}| <= 0.1``)
    and the error left, ``~ |dZ_k| r^2``, is below ``tol``; or when the updates have
    stopped shrinking while below ``sqrt(eps) (scale + max|Z|)`` (ill-conditioned systems,
    e.g. huge h omega, cannot reach ``tol``).

    With ``skip`` (an earlier element failed) nothing is iterated. A failed solve returns the
    constant state ``Z = 0``, a finite point for the linearisation (see ``solve_implicit``).

    Returns:
        ``(Z, iterations, status)`` with ``status`` a ``Status`` code (int32).
    """
    shape, dtype = Z0.shape, Z0.dtype
    eps = jnp.finfo(dtype).eps

    def r_flat(z):
        return residual(z.reshape(shape)).reshape(-1)

    def cond(carry):
        it, _, _, done, _ = carry
        return (it < max_iterations) & ~done

    def body(carry):
        it, z, dz_prev, _, _ = carry
        r, jvp = jax.linearize(r_flat, z)
        jac = jax.vmap(jvp, out_axes=1)(jnp.eye(z.size, dtype=dtype))
        dz = linear_solve(jac, r)
        z = z - dz
        size = scale + jnp.max(jnp.abs(z)) + jnp.finfo(dtype).tiny
        step = jnp.max(jnp.abs(dz))
        finite = jnp.all(jnp.isfinite(z))
        tol = 10.0 * eps * size
        rate = step / dz_prev  # a contraction rate only from the second update on
        converged = (step <= tol) | (
            (it > 0)
            & (
                # quadratic phase: the error left after this update is ~ step * rate^2
                ((rate <= 0.1) & (step * rate**2 <= tol))
                # round-off floor of an ill-conditioned system: updates stopped shrinking
                | ((step <= jnp.sqrt(eps) * size) & (rate >= 0.5))
            )
        )
        status = jnp.where(finite, Status.SUCCESS, Status.NONFINITE).astype(jnp.int32)
        return it + 1, z, step, converged | ~finite, status

    z0 = Z0.reshape(-1)
    finite0 = jnp.all(jnp.isfinite(z0))
    init = (
        jnp.int32(0),
        z0,
        jnp.asarray(jnp.inf, dtype),
        ~finite0 | skip,
        jnp.where(finite0 | skip, Status.SUCCESS, Status.NONFINITE).astype(jnp.int32),
    )
    it, z, _, done, status = jax.lax.while_loop(cond, body, init)
    status = jnp.where(done, status, Status.NEWTON_MAX_ITERATIONS).astype(jnp.int32)
    z = jnp.where(status == Status.SUCCESS, z, jnp.zeros_like(z))
    return z.reshape(shape), it, status


def solvable(J):
    """J with non-invertible blocks (NaN, or singular: a failed solve) replaced by the identity,
    and the mask of the blocks kept; shape ``(..., n, n)``. A failed member's outputs are
    masked, so its tangent right-hand side is zero and its solution must be zero too: a NaN
    there would reach shared parameters as 0 * NaN."""
    probe = jnp.linalg.solve(J, jnp.ones(J.shape[:-1] + (1,), J.dtype))
    usable = jnp.all(jnp.isfinite(probe), axis=(-2, -1))
    identity = jnp.broadcast_to(jnp.eye(J.shape[-1], dtype=J.dtype), J.shape)
    return jnp.where(usable[..., None, None], J, identity), usable


def solve_implicit(residual, Z0, max_iterations, scale=0.0, skip=False):
    """Root of ``residual`` near ``Z0``; derivatives by the implicit function theorem.

    ``jax.lax.custom_root`` differentiates the converged root through
    ``dZ = -(dR/dZ)^{-1} dR/dtheta`` for every value closed over by ``residual``
    (q0, p0, h, quadrature, args), never through the Newton iterations.

    Args:
        scale: size of the state the unknowns are increments of (sets the round-off floor).
    Returns:
        ``(Z, iterations, status)``, both counts int32.
    """

    def solve(f, z0):
        Z, it, status = newton(f, z0, max_iterations, scale, skip)
        # aux travels as float: integer aux breaks custom_root's JVP (jax-ml/jax#24295)
        return Z, (it.astype(Z.dtype), status.astype(Z.dtype))

    def tangent_solve(g, y):
        J, usable = solvable(jax.jacfwd(g)(y).reshape(y.size, y.size))
        return jnp.where(usable, jnp.linalg.solve(J, y.reshape(-1)), 0.0).reshape(y.shape)

    Z, (it, status) = jax.lax.custom_root(residual, Z0, solve, tangent_solve, has_aux=True)
    it, status = jax.lax.stop_gradient((it, status))
    return Z, it.astype(jnp.int32), status.astype(jnp.int32)
