"""Equivalences between the Galerkin methods and classical Runge-Kutta schemes, each measured
against an independent NumPy/SciPy implementation, and the structure each method preserves."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import root

import galerkin_jax as gj
import helpers

H, Q0, P0 = helpers.kepler(0.5)
N_STEPS, STEP = 40, 0.1


def field(z):
    """Kepler in NumPy: z' = (p, -q / |q|^3)."""
    q, p = z[:2], z[2:]
    return np.concatenate([p, -q / np.linalg.norm(q) ** 3])


def runge_kutta(nodes, z0, h, n_steps):
    """Implicit RK with the collocation tableau on ``nodes``; stage equations by SciPy's root."""
    a, b = helpers.collocation_tableau(np.asarray(nodes))
    s, z = len(nodes), np.asarray(z0, dtype=float)
    for _ in range(n_steps):
        stages = lambda K: (K.reshape(s, -1) - np.stack([field(z + h * a[i] @ K.reshape(s, -1)) for i in range(s)])).ravel()
        K = root(stages, np.tile(field(z), s), method="hybr", options={"xtol": 1e-15}).x.reshape(s, -1)
        z = z + h * b @ K
    return z


def final(method, h=STEP):
    sol = gj.integrate(H, Q0, P0, method=method, h=h, n_steps=N_STEPS)
    assert int(sol.status) == 0
    return np.concatenate([sol.q[-1], sol.p[-1]])


Z0 = np.concatenate([Q0, P0])
# SciPy's hybr solves each stage system to ~1e-15 relative; 40 steps of Kepler amplify that to <1e-12
TOLERANCE = 1e-11


def test_cg1_midpoint_equals_dg1_midpoint_equals_the_implicit_midpoint_rule():
    """Prop. 3.2: one point at 1/2 makes dG(1) continuous and equal to cG(1): the implicit midpoint rule."""
    midpoint_rule = runge_kutta([0.5], Z0, STEP, N_STEPS)
    cg, dg = final(gj.CG(1, gj.midpoint())), final(gj.DG(1, gj.midpoint()))
    np.testing.assert_allclose(cg, midpoint_rule, atol=TOLERANCE)
    np.testing.assert_allclose(dg, cg, atol=1e-14)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_cg_with_k_gauss_points_is_gauss_collocation(k):
    gauss = runge_kutta(np.asarray(gj.gauss_legendre(k).points), Z0, STEP, N_STEPS)
    np.testing.assert_allclose(final(gj.CG(k, gj.gauss_legendre(k))), gauss, atol=TOLERANCE)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_dg_with_k_plus_1_right_radau_points_is_radau_iia(k):
    """dG(k) with the (k + 1)-point right Radau rule equals the (k + 1)-stage Radau IIA method
    (Lesaint-Raviart); k = 0 is the implicit Euler method. h = 0.05: with h = 0.1 implicit
    Euler's dissipation drives Kepler into the singularity within 40 steps."""
    radau = runge_kutta(np.asarray(gj.gauss_radau(k + 1).points), Z0, STEP / 2, N_STEPS)
    np.testing.assert_allclose(final(gj.DG(k, gj.gauss_radau(k + 1)), STEP / 2), radau, atol=TOLERANCE)


def test_galerkin_vi_with_s_gauss_points_is_gauss_collocation_too():
    gauss = runge_kutta(np.asarray(gj.gauss_legendre(2).points), Z0, STEP, N_STEPS)
    np.testing.assert_allclose(final(gj.GalerkinVI(2, gj.gauss_legendre(2))), gauss, atol=TOLERANCE)


STRUCTURE = {
    # name: (method, symplectic?, energy conserved for every H?)
    "cG(1) midpoint": (gj.CG(1, gj.midpoint()), True, False),
    "cG(2) Gauss 2": (gj.CG(2, gj.gauss_legendre(2)), True, False),
    # one point more than k: not Gauss collocation, not symplectic (docs/adaptive.md)
    "cG(2) Gauss 3": (gj.CG(2, gj.gauss_legendre(3)), False, False),
    # Theorem 3.1 for any H, up to the quadrature error: here (degree 9, h = 0.05) below round-off
    "cG(2) Gauss 5 (~exact)": (gj.CG(2, gj.gauss_legendre(5)), False, True),
    "dG(1) Gauss 2": (gj.DG(1, gj.gauss_legendre(2)), False, False),
    "GalerkinVI(2) Gauss 3": (gj.GalerkinVI(2, gj.gauss_legendre(3)), True, False),
    "GalerkinVI(2) Lobatto 3": (gj.GalerkinVI(2, gj.gauss_lobatto(3)), True, False),
    "ModifiedMidpoint": (gj.ModifiedMidpoint(), False, True),
    "DiscreteGradient": (gj.DiscreteGradient(), False, True),
}


@pytest.mark.parametrize("name", STRUCTURE)
def test_which_methods_are_symplectic(name):
    """max |A^T J A - J| of the exact step Jacobian on Kepler at h = 0.3 (README table)."""
    method, symplectic, _ = STRUCTURE[name]
    defect = helpers.symplecticity_defect(gj.amplification_matrix(H, Q0, P0, method=method, h=0.3))
    assert (defect < 1e-13) == symplectic, defect


@pytest.mark.parametrize("name", STRUCTURE)
def test_which_methods_conserve_a_non_polynomial_energy(name):
    """Kepler is not polynomial: the energy-momentum schemes keep H exactly, cG(k) with a rule of
    high degree keeps it to its quadrature error (Theorem 3.1), the others do not."""
    method, _, conserving = STRUCTURE[name]
    sol = gj.integrate(H, Q0, P0, method=method, h=0.05, n_steps=400)
    error = np.abs(np.asarray(jax.vmap(H)(sol.q, sol.p)) / float(H(Q0, P0)) - 1).max()
    assert (error < 1e-13) == conserving, error


@pytest.mark.parametrize("k, points", [(1, 1), (1, 2), (2, 2), (2, 3)])
def test_the_energy_error_of_a_step_has_the_order_of_its_quadrature(k, points):
    """cG(k) conserves H exactly with exact quadrature (Theorem 3.1): the energy balance of a
    step is ``H(z1) - H(z0) = int DH(w) . w' - Q[DH(w) . w']``, the error of an N_q-point Gauss
    rule, O(h^(2 N_q + 1)). With N_q = k that is the step's own local order; one point more
    makes it O(h^(2k + 3)) at the cost of one gradient per iteration, which keeps the phase of
    an orbit (docs/adaptive.md, "Which quadrature under a PIDController"). Measured on Kepler
    e = 0.3 at t = 0.3, from h = 0.1 to 0.05: 3.03, 4.98, 5.19, 7.00; margin 0.3 (from h = 0.2
    to 0.1 the slopes were within 0.1 of these; the errors, 5e-5 to 5e-12, are far above
    round-off)."""
    He = helpers.kepler(0.3)[0]
    q0, p0 = (jnp.asarray(x) for x in helpers.kepler_exact(0.3, 0.3))  # not at perihelion, a symmetry point
    method = gj.CG(k, gj.gauss_legendre(points))
    errors = []
    for h in (0.1, 0.05):
        sol = gj.integrate(He, q0, p0, method=method, h=h, n_steps=1, error_estimate=False)
        errors.append(abs(float(He(sol.q[-1], sol.p[-1]) - He(q0, p0))))
    assert abs(np.log2(errors[0] / errors[1]) - (2 * points + 1)) < 0.3, errors
