"""Energy laws of cG(k) and dG(k) on the isotropic oscillator [GBS, Sections 3-4].

Theorem 3.1 (cG(k) conserves a quadratic H to round-off), Props. 3.1 and 4.3 (dG(k)
dissipates), and the sign convention of J.
"""

import jax
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, Q0, P0, OMEGA = helpers.oscillator()
M, C = helpers.OSC_M, helpers.OSC_C


@pytest.mark.parametrize("k", [1, 2, 3])
def test_cg_conserves_a_quadratic_hamiltonian_to_round_off(k):
    """Theorem 3.1: k + 1 Gauss points integrate test (deg k-1) x field (deg k) exactly, and so do
    k points (degree 2k - 1 = enough). Both rules in one vmapped program (``stack_methods`` pads
    the k-point rule with a point of weight zero, which adds an exact zero)."""
    methods = gj.stack_methods([gj.CG(k, gj.gauss_legendre(k + 1)), gj.CG(k, gj.gauss_legendre(k))])
    sol = jax.vmap(lambda m: gj.integrate(H, Q0, P0, method=m, h=1.0, n_steps=1000))(methods)
    energy = np.asarray(jax.vmap(jax.vmap(H))(sol.q, sol.p))
    assert energy.shape == (2, 1001) and np.all(np.asarray(sol.status) == 0)
    # exact integer matrices leave only round-off, a random walk of ~eps per step:
    # ~ eps sqrt(1000) ~ 1e-14; a drift of 1 eps per step would reach 2e-13
    assert np.abs(energy / energy[:, :1] - 1).max() < 2e-14


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_dg_energy_of_a_quadratic_hamiltonian_strictly_decays(k):
    """Prop. 3.1 (ii) and Prop. 4.3 with exact quadrature."""
    sol = gj.integrate(H, Q0, P0, method=gj.DG(k, gj.gauss_legendre(k + 2)), h=1.0, n_steps=50)
    energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
    assert np.all(np.diff(energy) < 0)


def test_dg0_energy_decays_for_a_convex_non_quadratic_hamiltonian():
    """Prop. 3.1 (i): k = 0 and an arbitrary convex H."""
    H_convex = lambda q, p: p @ p / 2 + (q @ q) ** 2 / 4 + q @ q / 2
    sol = gj.integrate(H_convex, Q0, P0 * 3, method=gj.DG(0, gj.gauss_legendre(1)), h=0.3, n_steps=50)
    energy = np.asarray(jax.vmap(H_convex)(sol.q, sol.p))
    assert int(sol.status) == 0 and np.all(np.diff(energy) < 0)


def test_sign_convention_q_dot_is_dH_dp_and_p_dot_is_minus_dH_dq():
    h = 1e-6
    q1, p1 = gj.step(H, Q0, P0, method=gj.CG(1, gj.midpoint()), h=h)
    # difference quotients are O(h) = 1e-6 away from the derivatives
    np.testing.assert_allclose((q1 - Q0) / h, P0 / M, atol=1e-6)
    np.testing.assert_allclose((p1 - P0) / h, C * Q0, atol=1e-6)


def test_energy_and_angular_momentum_stay_at_round_off_over_many_steps():
    """cG(1) + midpoint, h omega = 0.35, 10^5 elements with 101 states stored: Theorem 3.1 and
    Cor. 4.7 hold to round-off, a random walk of ~eps per step: eps sqrt(10^5) ~ 7e-14
    (measured 7e-15 and 9e-15). A drift of one eps per step would reach 2.2e-11; the bound, 2e-12,
    lies a factor of ten from either."""
    sol = gj.integrate(H, Q0, P0, method=gj.CG(1, gj.midpoint()), h=1.0, n_steps=100_000, save_every=1_000)
    assert int(sol.status) == 0 and sol.q.shape == (101, 3)
    energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
    L = np.cross(np.asarray(sol.q), np.asarray(sol.p))
    assert np.abs(energy / energy[0] - 1).max() < 2e-12
    assert np.abs(L - L[0]).max() / np.abs(L[0]).max() < 2e-12
