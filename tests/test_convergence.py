"""Nodal convergence orders on Kepler (e = 0.5) against the exact orbit from Kepler's equation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, Q0, P0 = helpers.kepler(0.5)
T = 2 * np.pi


def nodal_errors(method, ns):
    """Max error of (q, p) at t = T for h = T / n, n in ns.

    One compiled, vmapped run over h: each configuration runs max(ns) elements and its
    state after n elements (t = T) is compared with the exact orbit.
    """
    hs = jnp.array([T / n for n in ns])
    sol = jax.vmap(lambda h: gj.integrate(H, Q0, P0, method=method, h=h, n_steps=max(ns)))(hs)
    assert np.all(np.asarray(sol.status) == 0)
    q_exact, p_exact = helpers.kepler_exact(T)
    return [max(np.abs(sol.q[j, n] - q_exact).max(), np.abs(sol.p[j, n] - p_exact).max()) for j, n in enumerate(ns)]


# Quadrature with k + 2 Gauss points (exact to degree 2k + 3) so that quadrature error does not
# limit the order. The step counts put all errors in the asymptotic range and above 1e-12.
CASES = [
    ("cG", 1, [128, 256, 512], 2),
    ("cG", 2, [64, 128, 256], 4),
    ("cG", 3, [64, 96, 128], 6),
    ("dG", 1, [128, 256, 512], 3),
    ("dG", 2, [64, 128, 256], 5),
    ("dG", 3, [48, 64, 96], 7),
]


@pytest.mark.parametrize("family, k, ns, order", CASES, ids=[f"{c[0]}({c[1]})" for c in CASES])
def test_nodal_order_is_2k_for_cg_and_2k_plus_1_for_dg(family, k, ns, order):
    method = (gj.CG if family == "cG" else gj.DG)(k, gj.gauss_legendre(k + 2))
    errors = nodal_errors(method, ns)
    # measured slopes lie within 0.03 of the theory here; 0.1 is loose but separates 2k from 2k+1
    assert helpers.fitted_order([T / n for n in ns], errors, floor=1e-12) == pytest.approx(order, abs=0.1)


def test_cg_with_k_gauss_points_keeps_order_2k():
    """cG(k) with k Gauss points is Gauss collocation, of order 2k."""
    ns = [64, 96, 128]
    errors = nodal_errors(gj.CG(2, gj.gauss_legendre(2)), ns)
    assert helpers.fitted_order([T / n for n in ns], errors, floor=1e-12) == pytest.approx(4, abs=0.1)
