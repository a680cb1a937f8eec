"""Continuous and discontinuous Galerkin methods in time [GBS, Section 3].

Both act on ``z = (q, p)`` with ``z' = h J DH(z)``, ``J = [[0, I], [-I, 0]]``, so
``q' = h dH/dp`` and ``p' = -h dH/dq`` [GBS, eqs. (5), (9)]. Trial functions use the
Lagrange basis on Gauss-Lobatto nodes (0 and 1 among them); test functions are
Legendre polynomials. Any basis of the test space gives the same element equations,
and Newton's method is invariant under that choice.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import _basis
from ._quadrature import QuadratureRule


def symplectic_field(H):
    """z -> J DH(z) for z = (q, p) stacked, with DH from ``jax.grad`` [GBS, eq. (6)]."""
    dH = jax.grad(H, argnums=(0, 1))

    def field(z):
        q, p = jnp.split(z, 2)
        dHdq, dHdp = dH(q, p)
        return jnp.concatenate([dHdp, -dHdq])

    return field


def _check_degree(cls, k, least):
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < least:
        raise ValueError(f"{cls} needs an integer degree k >= {least}, got {k!r}.")


def _check_rule(cls, quadrature):
    if not isinstance(quadrature, QuadratureRule):
        raise TypeError(f"{cls} needs a QuadratureRule, got {type(quadrature).__name__}.")


def _weighted_field(H, quadrature, Z_nodes, k, n_test, dtype):
    """sum_l w_l psi_I(alpha_l) J DH(z^h(alpha_l)): the quadrature of eqs. (16) and (19)."""
    alpha = jnp.asarray(quadrature.points, dtype)
    w = jnp.asarray(quadrature.weights, dtype)
    z_at_points = _basis.lagrange_values(alpha, k) @ Z_nodes
    field = jax.vmap(symplectic_field(H))(z_at_points)
    return _basis.legendre_values(alpha, n_test).T @ (w[:, None] * field)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CG:
    """Continuous Galerkin cG(k) in time [GBS, eq. (16)].

    Trial functions are continuous, of degree k on each element (z_1 = z_0, eq. (13));
    test functions have degree k - 1. The rule is applied to the integrals that
    contain DH; all purely polynomial integrals are exact. With exact quadrature it
    conserves any autonomous H (Theorem 3.1); with k Gauss points it is k-stage
    Gauss-Legendre collocation.

    Args:
        k: degree, k >= 1. Static: a new k means a new compilation.
        quadrature: rule on [0, 1]; its arrays may be traced, vmapped and differentiated.
    """

    k: int = dataclasses.field(metadata=dict(static=True))
    quadrature: QuadratureRule

    def __post_init__(self):
        _check_degree("CG", self.k, 1)
        _check_rule("CG", self.quadrature)

    def initial_guess(self, q0, p0, previous=None):
        """Z0, shape ``(k, 2d)``: constant, or the previous element's polynomial extrapolated.

        Args:
            previous: ``(q, p, Z)`` of the previous element, or None.
        """
        z0 = jnp.concatenate([q0, p0])
        if previous is None:
            return jnp.tile(z0, (self.k, 1))
        q, p, Z = previous
        nodes = jnp.concatenate([jnp.concatenate([q, p])[None], Z])
        return jnp.asarray(_basis.extrapolation(self.k)[1:], Z.dtype) @ nodes

    def residual(self, H, q0, p0, Z, h):
        """R(Z) = 0 is eq. (16) for the nodal values z_2 ... z_{k+1}; shape ``(k, 2d)``."""
        nodes = jnp.concatenate([jnp.concatenate([q0, p0])[None], Z])
        K = jnp.asarray(_basis.stiffness(self.k, self.k), Z.dtype)
        return K @ nodes - h * _weighted_field(H, self.quadrature, nodes, self.k, self.k, Z.dtype)

    def end_state(self, H, q0, p0, Z, h):
        """(q1, p1) = z_{k+1}, the value at alpha = 1."""
        return tuple(jnp.split(Z[-1], 2))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DG:
    """Discontinuous Galerkin dG(k) in time [GBS, eq. (19)].

    Trial and test functions have degree k; the jump term ``J dz_1 . (z_1 - z_0)``
    imposes the initial value weakly (eq. (18)). With exact quadrature the energy of a
    quadratic H decays (Prop. 3.1); with k + 1 right Radau points it is Radau IIA.

    Args:
        k: degree, k >= 0. Static.
        quadrature: rule on [0, 1]; its arrays may be traced, vmapped and differentiated.
    """

    k: int = dataclasses.field(metadata=dict(static=True))
    quadrature: QuadratureRule

    def __post_init__(self):
        _check_degree("DG", self.k, 0)
        _check_rule("DG", self.quadrature)

    def initial_guess(self, q0, p0, previous=None):
        """Z0, shape ``(k + 1, 2d)``: constant, or the previous element extrapolated."""
        if previous is None:
            return jnp.tile(jnp.concatenate([q0, p0]), (self.k + 1, 1))
        Z = previous[2]
        return jnp.asarray(_basis.extrapolation(self.k), Z.dtype) @ Z

    def residual(self, H, q0, p0, Z, h):
        """R(Z) = 0 is eq. (19) for the nodal values z_1 ... z_{k+1}; shape ``(k + 1, 2d)``."""
        k, dtype = self.k, Z.dtype
        K = jnp.asarray(_basis.stiffness(k + 1, k), dtype)
        at_zero = jnp.asarray(_basis.lagrange_values_np([0.0], k)[0], dtype)
        test_at_zero = jnp.asarray((-1.0) ** np.arange(k + 1), dtype)  # P_I(-1)
        jump = at_zero @ Z - jnp.concatenate([q0, p0])
        weighted = _weighted_field(H, self.quadrature, Z, k, k + 1, dtype)
        return K @ Z - h * weighted + test_at_zero[:, None] * jump[None, :]

    def end_state(self, H, q0, p0, Z, h):
        """(q1, p1) = z^h(1)."""
        at_one = jnp.asarray(_basis.lagrange_values_np([1.0], self.k)[0], Z.dtype)
        return tuple(jnp.split(at_one @ Z, 2))
