"""Continuous and discontinuous Galerkin methods in time [GBS, Section 3].

Both act on ``z = (q, p)`` with ``z' = h J DH(z)``, ``J = [[0, I], [-I, 0]]``, so
``q' = h dH/dp`` and ``p' = -h dH/dq`` [GBS, eqs. (5), (9)]. The element unknowns are
Legendre (modal) coefficients of ``z - z_0`` or of ``z'``, and the test functions are
(2i + 1) P_i(2 alpha - 1). These span the paper's trial and test spaces, so the element
equations are those of eqs. (16) and (19) (Newton's method is invariant under the change
of basis), while every polynomial matrix is an exact integer matrix (see ``_basis``) and the
unknowns are increments, accurate relative to themselves.
"""

import jax
import jax.numpy as jnp
import numpy as np

from . import _basis
from ._defect import hamilton_field
from ._method import degree_and_rule
from ._pytree import pytree_dataclass


def _trial_basis(alpha, n, antiderivative):
    """z^h - z_0 at the points ``alpha`` per unknown: the Legendre antiderivatives (cG, whose
    unknowns are coefficients of z') or the Legendre polynomials (dG); shape ``(m, n)``."""
    return _basis.legendre_antiderivatives(alpha, n) if antiderivative else _basis.legendre_values(alpha, n)


def tested_field(H, quadrature, q0, p0, C, antiderivative, n_test, part=None):
    """(2i + 1) sum_l w_l P_i(alpha_l) J DH(z^h(alpha_l)), i < n_test: the DH integrals of eqs. (16), (19).

    ``z^h = (q0, p0) + basis(alpha) @ C`` with ``basis`` the Legendre antiderivatives (cG) or the
    Legendre polynomials themselves (dG); ``part`` "q" or "p": the q or p half alone
    (``hamilton_field``).
    """
    dtype, d = C.dtype, q0.shape[0]
    alpha = jnp.asarray(quadrature.points, dtype)
    w = jnp.asarray(quadrature.weights, dtype)
    basis = _trial_basis(alpha, len(C), antiderivative)
    # q and p at the points from C's column halves: where C is a concatenate of halves (the
    # sweep), XLA then reads them directly instead of copying them together and apart
    at_points = lambda x0, X: x0[None, :] + _basis.combine(basis, X)
    field = jax.vmap(hamilton_field(H, part))(at_points(q0, C[:, :d]), at_points(p0, C[:, d:]))
    scale = jnp.asarray(_basis.test_scale(n_test), dtype)
    return scale[:, None] * _basis.combine(_basis.legendre_values(alpha, n_test).T, w[:, None] * field)


def galerkin_jacobian(H, quadrature, q0, p0, Z, h, antiderivative, n_test, linear):
    """dR/dZ of R(Z) = ``linear`` Z - h ``tested_field(...)`` (eqs. (16), (19)), flat in Z's C
    order: ``linear`` (x) I - h sum_l G_il basis_lj (x) J_l, with G_il = (2i + 1) w_l P_i(alpha_l)
    and J_l the field's Jacobian d(J DH)/dz at z^h(alpha_l).

    The Jacobians at the m points take 2d tangents of the field at each; the Jacobian of R by its
    own tangents takes one per unknown, k times as many, each through all m points. Exact: the
    same matrix to round-off.
    """
    dtype, d, n = Z.dtype, q0.shape[0], len(Z)
    alpha = jnp.asarray(quadrature.points, dtype)
    w = jnp.asarray(quadrature.weights, dtype)
    basis = _trial_basis(alpha, n, antiderivative)
    points = jnp.concatenate([q0, p0])[None, :] + basis @ Z
    field = hamilton_field(H)
    J = jax.vmap(jax.jacfwd(lambda z: field(z[:d], z[d:])))(points)  # (m, 2d, 2d)
    G = jnp.asarray(_basis.test_scale(n_test), dtype)[:, None] * _basis.legendre_values(alpha, n_test).T * w[None, :]
    # [i, a, j, b], a sum over the points of broadcast products: one fused loop, where an einsum
    # is a dot and a transpose, kernels of their own
    total = jnp.asarray(linear, dtype)[:, None, :, None] * jnp.eye(2 * d, dtype=dtype)[None, :, None, :]
    for l in range(len(alpha)):
        total = total - h * (G[:, l, None] * basis[l, None, :])[:, None, :, None] * J[l][None, :, None, :]
    return total.reshape(n * 2 * d, n * 2 * d)


def _columns(Z, d, part):
    """The q (``part`` "q") or p ("p") columns of unknowns ``(m, 2d)``, or all (None)."""
    return {None: Z, "q": Z[:, :d], "p": Z[:, d:]}[part]


@pytree_dataclass
class CG(degree_and_rule("k", least=1)):
    """Continuous Galerkin cG(k) in time [GBS, eq. (16)].

    Trial functions are continuous, of degree k on each element (z_1 = z_0, eq. (13));
    test functions have degree k - 1. The rule is applied to the integrals that contain DH;
    all purely polynomial integrals are exact. With exact quadrature it conserves any
    autonomous H (Theorem 3.1); with k Gauss points it is k-stage Gauss collocation.

    Unknowns: ``C`` of shape ``(k, 2d)`` with ``(z^h)' = sum_j C_j P_j(2 alpha - 1)``, so
    ``z^h(alpha) = z_0 + sum_j C_j A_j(alpha)`` and ``z_1 = z_0 + C_0``.

    Args:
        k: the polynomial degree of the trial functions on each element, an integer >= 1;
            required. The order at the nodes is 2k with k Gauss points. Static: a new k means a
            new compilation.
        quadrature: the quadrature rule on [0, 1] for the integrals that contain DH, e.g.
            ``gauss_legendre(k)``; required. Its arrays may be traced, vmapped and
            differentiated.
    """

    fixed_point = True  # R = C - h (...): dR/dC = I at h = 0, so Z <- Z - R(Z) contracts for small h
    partition_axis = -1  # C's q | p columns; residual(..., part=): the sweep of ``_march.element_residual``

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        """Zero (the constant state), or the previous element's derivative continued (C is
        h z', so an element ``ratio`` times as long scales it by ``ratio``)."""
        if previous is None:
            return jnp.zeros((self.k, 2 * q0.shape[0]), q0.dtype)
        C = _basis.combine(_basis.continuation(self.k, ratio), previous[2])
        return C if ratio is None else ratio * C

    def residual(self, H, q0, p0, C, h, part=None):
        """R(C) = 0 is eq. (16) tested with (2i + 1) P_i, i < k: C_i - h (2i+1) Q[P_i J DH(z^h)];
        ``part`` "q" or "p": the equations of that half of the columns alone."""
        return _columns(C, q0.shape[0], part) - h * tested_field(H, self.quadrature, q0, p0, C, True, self.k, part)

    def jacobian(self, H, q0, p0, C, h):
        """dR/dC, flat (``galerkin_jacobian``): I - h sum_l G_l (x) J(z^h(alpha_l))."""
        return galerkin_jacobian(H, self.quadrature, q0, p0, C, h, True, self.k, np.eye(self.k))

    def increment(self, H, q0, p0, C, h):
        """z_1 - z_0 = z^h(1) - z_0 = C_0, split into (dq, dp)."""
        return tuple(jnp.split(C[0], 2))

    def polynomial(self, H, q0, p0, C, h):
        """Legendre coefficients of z^h - z_0, shape ``(k + 1, 2d)``."""
        return _basis.combine(_basis.antiderivative_matrix(self.k), C)


@pytree_dataclass
class DG(degree_and_rule("k", least=0)):
    """Discontinuous Galerkin dG(k) in time [GBS, eq. (19)].

    Trial and test functions have degree k; the jump term ``J dz_1 . (z^h(0) - z_0)`` imposes
    the initial value weakly (eq. (18)). With exact quadrature the energy of a quadratic H
    decays (Prop. 3.1); with k + 1 right Radau points it is Radau IIA.

    Unknowns: ``a`` of shape ``(k + 1, 2d)`` with ``z^h(alpha) = z_0 + sum_j a_j P_j(2 alpha - 1)``.

    Args:
        k: the polynomial degree of the trial and test functions on each element, an integer
            >= 0; required. Static: a new k means a new compilation.
        quadrature: the quadrature rule on [0, 1] for the integrals that contain DH, e.g.
            ``gauss_radau(k + 1)``; required. Its arrays may be traced, vmapped and
            differentiated.
    """

    partition_axis = -1  # a's q | p columns; residual(..., part=): the sweep of ``_march.element_residual``

    @property
    def fixed_point(self):
        """dG(0) only: for k >= 1, dR/da at h = 0 holds the derivative and jump terms, not I,
        and the fixed-point iteration Z <- Z - R(Z) cannot contract."""
        return self.k == 0

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        """Zero (the constant state), or the previous element's polynomial continued."""
        if previous is None:
            return jnp.zeros((self.k + 1, 2 * q0.shape[0]), q0.dtype)
        return _basis.combine(_basis.continuation(self.k + 1, ratio, subtract_end=True), previous[2])

    def residual(self, H, q0, p0, a, h, part=None):
        """R(a) = 0 is eq. (19) tested with (2i + 1) P_i, i <= k; ``part`` "q" or "p": the
        equations of that half of the columns alone."""
        n, dtype = self.k + 1, a.dtype
        columns = _columns(a, q0.shape[0], part)
        signs = jnp.asarray((-1.0) ** np.arange(n), dtype)  # P_j(-1)
        jump = signs @ columns  # z^h(0) - z_0
        derivative = _basis.combine(_basis.derivative_matrix(n), columns)
        tested_jump = jnp.asarray(_basis.test_scale(n), dtype) * signs
        field = tested_field(H, self.quadrature, q0, p0, a, False, n, part)
        return derivative + tested_jump[:, None] * jump[None, :] - h * field

    def jacobian(self, H, q0, p0, a, h):
        """dR/da, flat (``galerkin_jacobian``): the derivative and jump terms' constant matrix,
        less h sum_l G_l (x) J(z^h(alpha_l))."""
        n = self.k + 1
        signs = (-1.0) ** np.arange(n)
        linear = _basis.derivative_matrix(n) + np.outer(_basis.test_scale(n) * signs, signs)
        return galerkin_jacobian(H, self.quadrature, q0, p0, a, h, False, n, linear)

    def increment(self, H, q0, p0, a, h):
        """z_1 - z_0 = z^h(1) - z_0 = sum_j a_j, split into (dq, dp)."""
        return tuple(jnp.split(jnp.sum(a, axis=0), 2))

    def polynomial(self, H, q0, p0, a, h):
        """Legendre coefficients of z^h - z_0: the unknowns themselves, shape ``(k + 1, 2d)``."""
        return a
