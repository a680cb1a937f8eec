"""Galerkin and Lagrangian variational integrators [Tang, Section 2].

Both use the Legendre polynomials P_i(2 tau - 1) (Tang's l_i = sqrt(2i + 1) P_i, eq. (2.1))
and their antiderivatives A_i(tau) = int_0^tau P_i; purely polynomial integrals are exact,
the given rule evaluates the integrals of f = dH/dp, g = -dH/dq (or of dL/dq, dL/dqdot).

Misprint: eq. (2.35) prints A_{tau,sigma} = sum_i int_0^tau l_i(x) dx l_j(sigma), with a
free index j. Inserting (2.26) into the integral of (2.25) gives l_i(sigma):
A_{tau,sigma} = sum_i int_0^tau l_i(x) dx l_i(sigma) (as in (2.27) and (3.3)).
"""

import jax
import jax.numpy as jnp
import numpy as np

from . import _basis, _explicit
from ._method import degree_and_rule
from ._pytree import pytree_dataclass


def _rule_arrays(rule, dtype):
    return jnp.asarray(rule.points, dtype), jnp.asarray(rule.weights, dtype)


def _continued(C, s, ratio=None):
    """Legendre coefficients of a degree s - 1 series continued over the next element, ``ratio``
    times as long (``_basis.continuation``)."""
    return _basis.combine(_basis.continuation(s, ratio), C)


@pytree_dataclass
class GalerkinVI(degree_and_rule("s", least=1)):
    """Galerkin variational integrator [Tang, eqs. (2.21)-(2.22)], as the continuous-stage
    partitioned Runge-Kutta method (2.34) with kernels

        A_{tau,sigma} = sum_i (2i+1) A_i(tau) P_i(sigma),
        Ahat_{tau,sigma} = 1 - sum_i (2i+1) A_i(sigma) P_i(tau),   B = Bhat = 1   (i < s).

    Q in P^s is continuous (numerical flux Qhat_n = Q(t_n^+)); P in P^{s-1} jumps at both
    ends, with fluxes Phat_n = p_n and Phat_{n+1} = p_n + h int g. Symplectic and symmetric
    for any rule, of order 2s with exact enough quadrature (Corollary 2.1).

    Unknowns, shape ``(2s, d)``: ``c`` with Q' = sum_i c_i P_i (eq. (2.25)), and ``mu`` with
    P = p_n + sum_i mu_i P_i (eq. (2.31), lambda_i shifted by the flux).

    Args:
        s: the polynomial degree of the position Q on each element, an integer >= 1;
            required. Static: a new s means a new compilation.
        quadrature: the quadrature rule on [0, 1] for the element's integrals, e.g.
            ``gauss_legendre(s)``; required. Its arrays may be traced, vmapped and
            differentiated.
    """

    fixed_point = True  # dR/dZ = I at h = 0
    partition_axis = 0  # Z's c (q) | mu (p) rows; residual(..., part=): the sweep of ``_march.element_residual``

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        if previous is None:
            return jnp.zeros((2 * self.s, q0.shape[0]), q0.dtype)
        _, p_prev, Z = previous
        c, mu = jnp.split(Z, 2)
        mu = _continued(mu, self.s, ratio).at[0].add(p_prev - p0)  # P_prev(1 + ratio tau) - p_n
        c = _continued(c, self.s, ratio)  # c is h Q'
        return jnp.concatenate([c if ratio is None else ratio * c, mu])

    def _stages(self, H, q0, p0, Z):
        s, dtype = self.s, Z.dtype
        alpha, w = _rule_arrays(self.quadrature, dtype)
        c, mu = jnp.split(Z, 2)
        P_at = _basis.legendre_values(alpha, s)
        A_at = _basis.legendre_antiderivatives(alpha, s)
        Q, P = q0[None, :] + _basis.combine(A_at, c), p0[None, :] + _basis.combine(P_at, mu)
        dHdq, dHdp = jax.vmap(jax.grad(H, argnums=(0, 1)))(Q, P)
        return w, P_at, A_at, dHdp, -dHdq

    def residual(self, H, q0, p0, Z, h, part=None):
        """c_i = (2i+1) h Q[f P_i] (2.26); mu_i = (2i+1) h Q[g (delta_i0 - A_i)] (2.32);
        ``part`` "q" or "p": the c or mu equations alone (XLA drops the other half's work)."""
        w, P_at, A_at, f, g = self._stages(H, q0, p0, Z)
        scale = jnp.asarray(_basis.test_scale(self.s), Z.dtype)[:, None]
        first = jnp.asarray(np.eye(self.s)[0], Z.dtype)
        c, mu = jnp.split(Z, 2)
        r_c = c - h * scale * _basis.combine(P_at.T, w[:, None] * f)
        r_mu = mu - h * scale * _basis.combine((first[None, :] - A_at).T, w[:, None] * g)
        return {None: jnp.concatenate([r_c, r_mu]), "q": r_c, "p": r_mu}[part]

    def increment(self, H, q0, p0, Z, h):
        """Qhat_{n+1} - q_n = c_0 (2.29), Phat_{n+1} - p_n = h int g (2.32)."""
        w, _, _, _, g = self._stages(H, q0, p0, Z)
        return Z[0], h * _basis.combine(w, g)

    def polynomial(self, H, q0, p0, Z, h):
        """Legendre coefficients of (Q - q_n, P - p_n), shape ``(s + 1, 2d)`` (P has degree s - 1)."""
        c, mu = jnp.split(Z, 2)
        Q = _basis.combine(_basis.antiderivative_matrix(self.s), c)
        return jnp.concatenate([Q, jnp.concatenate([mu, jnp.zeros_like(mu[:1])])], axis=1)

    @property
    def forces_per_step(self):
        """Gradients of V per element of its closed form on a separable H (``explicit_form``): 1
        (the force at q1; the one at q0 is the previous element's); None where it has none (s > 1,
        a point inside (0, 1) or traced points: the element iterates)."""
        return 1 if self.s == 1 and _explicit.endpoint_indices(self.quadrature) is not None else None

    def explicit_form(self, structure):
        """For s = 1, a concrete rule with points at alpha = 0 and 1 only and a separable H: the
        element in closed form (``_explicit.ExplicitVI``; the trapezoid: Stormer-Verlet); else None."""
        indices = _explicit.endpoint_indices(self.quadrature) if self.s == 1 else None
        if indices is None or not structure.separable:
            return None
        return _explicit.ExplicitVI(self, *indices)


@pytree_dataclass
class LagrangianVI(degree_and_rule("s", least=1)):
    """Lagrangian variational integrator from the discrete Hamilton principle [Tang, eqs. (2.16)-(2.17)].

    The function given to ``integrate`` is the Lagrangian ``L(q, qdot)``; p0 is the initial
    momentum and ``Solution.p`` the discrete momenta p_n = -dL_h/dx (eq. (2.5)). Qdot is a
    polynomial of degree s - 1, Qdot = sum_j v_j P_j (eq. (2.7)), Q = q_n + h sum_j v_j A_j
    (eq. (2.9)); P = dL/dqdot(Q, Qdot) need not be a polynomial (Remark 2.1), so every
    integral uses the rule. For L = qdot^T M qdot / 2 - U(q) it equals ``GalerkinVI``
    (Section 3).

    Unknowns, shape ``(s, d)``: the coefficients ``v``.

    Args:
        s: the polynomial degree of the position Q on each element, an integer >= 1;
            required. Static: a new s means a new compilation.
        quadrature: the quadrature rule on [0, 1] for the element's integrals, e.g.
            ``gauss_legendre(s)``; required. Its arrays may be traced, vmapped and
            differentiated.
    """

    # dR/dv at h = 0 is the mass matrix d^2 L / dqdot^2 along the element, not I: Z <- Z - R(Z)
    # contracts only where its eigenvalues lie in (0, 2), and a preconditioner taken at one
    # state is off wherever the mass matrix depends on q or qdot. Newton (Newton-Krylov above
    # the dense limit) needs neither.
    hamiltonian = False  # given L: its polynomial is read as it is between the nodes
    fixed_point = False

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        if previous is None:
            return jnp.zeros((self.s, q0.shape[0]), q0.dtype)
        return _continued(previous[2], self.s, ratio)  # v is Q' in t, not scaled by h

    def _stages(self, L, q0, v, h):
        alpha, w = _rule_arrays(self.quadrature, v.dtype)
        P_at = _basis.legendre_values(alpha, self.s)
        A_at = _basis.legendre_antiderivatives(alpha, self.s)
        Q, Qdot = q0[None, :] + h * _basis.combine(A_at, v), _basis.combine(P_at, v)
        Pdot, P = jax.vmap(jax.grad(L, argnums=(0, 1)))(Q, Qdot)  # eq. (2.12)
        return w, P_at, A_at, P, Pdot

    def residual(self, L, q0, p0, v, h):
        """(2i+1) [Q[P P_i] - p_n delta_i0 - h Q[(delta_i0 - A_i) Pdot]] = 0, eq. (2.16a)."""
        w, P_at, A_at, P, Pdot = self._stages(L, q0, v, h)
        scale = jnp.asarray(_basis.test_scale(self.s), v.dtype)[:, None]
        first = jnp.asarray(np.eye(self.s)[0], v.dtype)
        momentum = _basis.combine(P_at.T, w[:, None] * P) - first[:, None] * p0[None, :]
        impulse = _basis.combine((first[None, :] - A_at).T, w[:, None] * Pdot)
        return scale * (momentum - h * impulse)

    def increment(self, L, q0, p0, v, h):
        """q_{n+1} - q_n = h int Qdot, p_{n+1} - p_n = h int Pdot, eq. (2.16b)."""
        w, _, _, _, Pdot = self._stages(L, q0, v, h)
        return h * v[0], h * _basis.combine(w, Pdot)

    def polynomial(self, L, q0, p0, v, h):
        """Legendre coefficients of (Q - q_n, P - p_n), shape ``(s + 1, 2d)``: Q exactly, and the
        momentum P = dL/dqdot(Q, Qdot) (not a polynomial, Remark 2.1) projected onto P^s by
        Gauss quadrature with s + 1 points."""
        T = jnp.asarray(_basis.antiderivative_matrix(self.s), v.dtype)
        x, w = np.polynomial.legendre.leggauss(self.s + 1)
        alpha, w = jnp.asarray((x + 1) / 2, v.dtype), jnp.asarray(w / 2, v.dtype)
        Q = q0[None, :] + h * (_basis.legendre_antiderivatives(alpha, self.s) @ v)
        P = jax.vmap(jax.grad(L, argnums=1))(Q, _basis.legendre_values(alpha, self.s) @ v)
        projection = jnp.asarray(_basis.test_scale(self.s + 1), v.dtype)[:, None] * (
            _basis.legendre_values(alpha, self.s + 1).T @ (w[:, None] * (P - p0[None, :])))
        return jnp.concatenate([h * (T @ v), projection], axis=1)

    def local_error(self, L, q0, p0, v, h):
        """NaN: the estimate needs Hamilton's field, and the method is given a Lagrangian."""
        return jnp.asarray(jnp.nan, v.dtype)
