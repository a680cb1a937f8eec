"""The tangent of an element's root by the implicit function theorem.

At a root ``R(Z, params) = 0`` the root moves with the parameters as

    dZ = -(dR/dZ)^{-1} (dR/dparams) dparams.

Forward mode (``jvp``) evaluates this; reverse mode (``grad``) transposes it, so that a
cotangent meets ``(dR/dZ)^{-T}``. The linear solve follows the forward solve of ``_solve``:

* up to ``dense_limit`` unknowns (where the forward solve keeps a dense Newton matrix too),
  ``dR/dZ`` by ``jacfwd`` and an LU solve: exact to round-off, and cheap at that size;
* above it, matrix-free on Jacobian-vector products of R (``jax.linearize``), whose transpose
  is the same on vector-Jacobian products: Richardson's iteration x <- x + (b - dR/dZ x),
  which contracts wherever the forward solve's fixed point does (dR/dZ is I less the fixed
  point's Jacobian; a few products to the tolerance), and restarted GMRES from where it
  stopped where it does not (``_iterated``). Reverse mode then stores O(n) numbers per element,
  never an n x n matrix, and a product costs about one linearised residual evaluation, where
  the matrix costs n of them and its LU n^3 / 3 multiplications.

Both stop at a relative residual ``|dR/dZ dZ - b| <= TOLERANCE eps |b|`` (Richardson's, like
the forward solve, where the residual its last update leaves, estimated from its contraction
rate, is below it): there are no later updates to refine the tangent (unlike a Newton
direction), and the error of every element's tangent is carried into the gradient of the
whole run. GMRES's result is accepted when
its residual, recomputed, is below ``sqrt(eps) |b|`` (the forward solve's bound on an
accepted residual): that admits the floor ``~eps cond(dR/dZ) |b|`` of an ill-conditioned
matrix, where GMRES runs out of restarts without reaching its tolerance. A solve left above
it did not converge, and gives NaN, not a finite wrong tangent.
"""

import jax
import jax.numpy as jnp

from ._contraction import error_left_below

# GMRES stops at a relative residual of TOLERANCE * eps (float64: 1.4e-14, float32: 7.6e-6);
# a tighter one sits below the round-off of a product with an O(1)-conditioned matrix
TOLERANCE = 64
# Krylov spaces of RESTART vectors (each member keeps RESTART + 1 of n numbers), at most
# RESTARTS of them: at most 400 products. The element Jacobian of a method with a fixed point
# is I + O(h omega), and GMRES reaches its tolerance in a few tens of products at h omega <~ 1;
# a stiff element (h omega ~ 10) can use them all and stop above it, still far below the
# acceptance bound.
RESTART, RESTARTS = 40, 10


def tangent(fn, params, Z, ok, dparams, *, dense_limit):
    """``dZ = -(dR/dZ)^{-1} (dR/dparams) dparams`` at the root ``Z`` of ``fn(., params)``,
    zero where ``ok`` is False (a failed solve has no derivative).

    Args:
        fn: ``(Z, params) -> R``, same shape as Z.
        params: pytree; ``dparams`` its tangent.
        Z: the root, any shape; ``ok``: bool scalar.
        dense_limit: the most unknowns solved densely; above, matrix-free GMRES.
    Returns:
        dZ, shape of Z; NaN where GMRES did not converge.
    """
    _, dR = jax.jvp(lambda p: fn(Z, p), (params,), (dparams,))
    if Z.size <= dense_limit:
        dZ = _dense(fn, params, Z, ok, dR)
    else:
        _, jvp = jax.linearize(lambda z: fn(z, params), Z)
        # a failed member's matrix is I: a finite solve, whose result is masked below
        matvec = lambda v: jnp.where(ok, jvp(v), v)
        dZ = -jax.lax.custom_linear_solve(matvec, dR, solve=_iterated, transpose_solve=_iterated)
    return jnp.where(ok, dZ, 0.0)


def structured_jacobian(fn, params, Z):
    """dR/dZ at Z, flat ``(n, n)``, from the element's structure where ``fn`` carries one
    (``fn.jacobian``: ``_march.element_residual``, a Galerkin method's field Jacobians at its
    quadrature points), else None."""
    jacobian = getattr(fn, "jacobian", None)
    return None if jacobian is None else jacobian(Z, params)


def _dense(fn, params, Z, ok, dR):
    J = structured_jacobian(fn, params, Z)
    if J is None:
        J = jax.jacfwd(lambda z: fn(z.reshape(Z.shape), params).reshape(-1))(Z.reshape(-1))
    J = jnp.where(ok, J, jnp.eye(J.shape[0], dtype=J.dtype))
    return -jnp.linalg.solve(J, dR.reshape(-1)).reshape(Z.shape)


# Richardson iterations before GMRES takes over: the fixed point's contraction, where it
# converges, reaches the tolerance in a few tens
RICHARDSON = 48


def _iterated(matvec, b):
    """``x`` with ``matvec(x) = b`` by Richardson's iteration x <- x + (b - matvec(x)), which
    contracts where the forward solve's fixed point does (the element Jacobian is I minus its
    iteration's), at the cost of one product per iteration and nothing else; GMRES (``_gmres``)
    from where it stopped, where it did not reach the tolerance (a stiff element).

    The residual r = b - matvec(x) is the next update, and the residuals contract at the rate
    theta of the last two: the stopping rule is the forward solve's (``_contraction``), what the
    updates after this one add up to, ``|r| theta / (1 - theta)``, below the tolerance (or |r|
    itself), and the converged x gets the update r, whose product is never taken. At the fixed
    point's fast contraction this saves the product that would only confirm it."""
    b_size = jnp.sqrt(jnp.sum(b * b))
    limit = TOLERANCE * jnp.finfo(b.dtype).eps * b_size

    def converged(k, r_size, theta):  # theta is measured from the first product on
        return (r_size <= limit) | ((k > 0) & error_left_below(r_size, theta, limit))

    def going(s):
        k, _, _, r_size, theta = s
        return (k < RICHARDSON) & ~converged(k, r_size, theta) & (theta < 1.0)

    def step(s):  # x and its residual r = b - matvec(x)
        k, x, r, r_size, _ = s
        x = x + r
        r_new = b - matvec(x)
        r_size_new = jnp.sqrt(jnp.sum(r_new * r_new))
        return k + 1, x, r_new, r_size_new, r_size_new / r_size

    s = (0, jnp.zeros_like(b), b, b_size, jnp.zeros((), b.dtype))
    k, x, r, r_size, theta = jax.lax.while_loop(going, step, s)
    return jax.lax.cond(converged(k, r_size, theta), lambda x, r: x + r, lambda x, r: _gmres(matvec, b, x), x, r)


def _gmres(matvec, b, x0):
    """``x`` with ``matvec(x) = b`` by restarted GMRES from ``x0`` (``jax.scipy.sparse.linalg.gmres``,
    Givens-rotation variant: it stops inside a restart once converged), NaN unless the
    recomputed residual is below ``sqrt(eps) |b|``. Called by ``custom_linear_solve`` with the
    product and, in reverse mode, with its transpose: each solve checks its own residual."""
    eps = jnp.finfo(b.dtype).eps
    x, _ = jax.scipy.sparse.linalg.gmres(matvec, b, x0, tol=TOLERANCE * eps, restart=RESTART, maxiter=RESTARTS,
                                         solve_method="incremental")
    residual, size = jnp.sqrt(jnp.sum((matvec(x) - b) ** 2)), jnp.sqrt(jnp.sum(b * b))
    return jnp.where(residual <= jnp.sqrt(eps) * size, x, jnp.nan)
