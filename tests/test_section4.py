"""Amplification matrices, spectral radii and the rho^2 laws of [GBS, Section 4.2].

The reference formulas are written here in NumPy from the paper's equations, independently
of the library; the library's matrices come from ``jax.jacfwd`` through the Newton solve.

Misprint: eq. (57) prints the diagonal of the cG(1) amplification matrix as
``(1 + beta1 beta2 Omega^2)``. With B = h J H, B^2 = -Omega^2 I, the scheme
(I - beta2 B) z2 = (I + beta1 B) z1 gives A = (I + beta2 B)(I + beta1 B) / (1 + beta2^2 Omega^2)
= ((1 - beta1 beta2 Omega^2) I + (beta1 + beta2) B) / (1 + beta2^2 Omega^2): the sign is
minus. Only the corrected form reduces to eq. (51) for beta1 = beta2 = 1/2 and has
det = eq. (59); eqs. (51), (52), (59), (63)-(69) are correct as printed.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, Q0, P0, OMEGA = helpers.oscillator()
M, C = helpers.OSC_M, helpers.OSC_C
SAMPLING = np.logspace(-1, 2, 7)  # Omega = h omega from 0.1 to 100
I3 = np.eye(3)

RULES = {
    "midpoint": gj.midpoint(),
    "trapezoid": gj.trapezoid(),
    "gauss2": gj.gauss_legendre(2),
    "gauss3": gj.gauss_legendre(3),
    "lobatto3": gj.gauss_lobatto(3),
    "lobatto4": gj.gauss_lobatto(4),
    "one point at 0.3": gj.QuadratureRule([0.3], [1.0]),
    "non-symmetric two point": gj.QuadratureRule([0.2, 0.7], [0.6, 0.4]),
}


def betas(rule):
    """beta_i [GBS, eq. (58)] and beta_ij [eq. (68)] for M_1 = 1 - alpha, M_2 = alpha."""
    points, weights = np.asarray(rule.points), np.asarray(rule.weights)
    shape = np.stack([1.0 - points, points], axis=1)
    return shape.T @ weights, (shape * weights[:, None]).T @ shape


def blocks(a, b, c_, d):
    """The 6 x 6 matrix [[a I, b I], [c I, d I]] in the ordering z = (q, p)."""
    return np.block([[a * I3, b * I3], [c_ * I3, d * I3]])


def cg1_matrix_eq51(h):
    Om2 = (h * OMEGA) ** 2
    return blocks(1 - Om2 / 4, h / M, h * C, 1 - Om2 / 4) / (1 + Om2 / 4)


def cg1_matrix_eq57_corrected(h, rule):
    """[GBS, eq. (57)] with the diagonal sign corrected to 1 - beta1 beta2 Omega^2."""
    (b1, b2), _ = betas(rule)
    Om2 = (h * OMEGA) ** 2
    diagonal = 1 - b1 * b2 * Om2
    return blocks(diagonal, h / M * (b1 + b2), h * C * (b1 + b2), diagonal) / (1 + b2**2 * Om2)


def dg1_matrix_eq63(h):
    Om2 = (h * OMEGA) ** 2
    return -2 * blocks(7 * Om2 - 18, h / M * (Om2 - 18), h * C * (Om2 - 18), 7 * Om2 - 18) / (Om2**2 + 4 * Om2 + 36)


def dg1_matrix_eqs66_67(h, rule):
    """Eliminate z1 from [GBS, eqs. (66)-(67)] by a NumPy linear solve."""
    _, B = betas(rule)
    hJH = h * np.block([[0 * I3, I3 / M], [C * I3, 0 * I3]])
    E = np.eye(6)
    system = np.block([[0.5 * E - B[0, 0] * hJH, 0.5 * E - B[0, 1] * hJH], [-(0.5 * E + B[0, 1] * hJH), 0.5 * E - B[1, 1] * hJH]])
    return np.linalg.solve(system, np.vstack([E, 0 * E]))[6:]


def rho2_cg1_eq59(Om, rule):
    (b1, b2), _ = betas(rule)
    return (1 + b1**2 * Om**2) / (1 + b2**2 * Om**2)


def rho2_dg1_eq69(Om, rule):
    _, B = betas(rule)
    b11, b12, b22 = B[0, 0], B[0, 1], B[1, 1]
    top = 1 + 4 * b12**2 * Om**2
    return top / (top + (b22 - b11) ** 2 * Om**2 + 4 * (b12**2 - b11 * b22) ** 2 * Om**4)


def amplification(method, h):
    return np.asarray(gj.amplification_matrix(H, Q0, P0, method=method, h=h))


def spectral_radius_squared(A):
    return np.max(np.abs(np.linalg.eigvals(A))) ** 2


@pytest.mark.parametrize("Om", SAMPLING)
def test_cg1_exact_quadrature_has_amplification_matrix_eq_51(Om):
    A = amplification(gj.CG(1, gj.gauss_legendre(2)), Om / OMEGA)
    # 1e-14: a 6 x 6 solve of entries <= 1 in float64
    np.testing.assert_allclose(A, cg1_matrix_eq51(Om / OMEGA), atol=1e-14)


@pytest.mark.parametrize("name", RULES)
def test_cg1_with_quadrature_has_the_corrected_eq_57(name):
    for Om in SAMPLING:
        A = amplification(gj.CG(1, RULES[name]), Om / OMEGA)
        np.testing.assert_allclose(A, cg1_matrix_eq57_corrected(Om / OMEGA, RULES[name]), atol=1e-13)


def test_the_printed_eq_57_is_wrong_for_a_non_symmetric_rule():
    rule, h = RULES["one point at 0.3"], 2.0 / OMEGA
    (b1, b2), _ = betas(rule)
    printed_diagonal = (1 + b1 * b2 * 4.0) / (1 + b2**2 * 4.0)
    assert abs(amplification(gj.CG(1, rule), h)[0, 0] - printed_diagonal) > 0.5


@pytest.mark.parametrize("Om", SAMPLING)
def test_dg1_exact_quadrature_has_amplification_matrix_eq_63(Om):
    A = amplification(gj.DG(1, gj.gauss_legendre(2)), Om / OMEGA)
    np.testing.assert_allclose(A, dg1_matrix_eq63(Om / OMEGA), atol=1e-13)


@pytest.mark.parametrize("name", RULES)
def test_dg1_with_quadrature_is_the_scheme_eqs_66_67(name):
    for Om in SAMPLING:
        A = amplification(gj.DG(1, RULES[name]), Om / OMEGA)
        np.testing.assert_allclose(A, dg1_matrix_eqs66_67(Om / OMEGA, RULES[name]), atol=1e-12)


@pytest.mark.parametrize("name", RULES)
def test_squared_spectral_radius_is_eq_59_for_cg1_and_eq_69_for_dg1(name):
    rule = RULES[name]
    for Om in SAMPLING:
        cg = spectral_radius_squared(amplification(gj.CG(1, rule), Om / OMEGA))
        dg = spectral_radius_squared(amplification(gj.DG(1, rule), Om / OMEGA))
        # relative 1e-12: eigenvalues of a well-separated 2 x 2 block structure
        assert cg == pytest.approx(rho2_cg1_eq59(Om, rule), rel=1e-12)
        assert dg == pytest.approx(rho2_dg1_eq69(Om, rule), rel=1e-11)
    if name in ("midpoint",):
        assert dg == pytest.approx(1.0, rel=1e-13)  # Lemma 4.8: only symmetric one-point keeps rho = 1


def test_dg1_exact_quadrature_spectral_radius_is_eq_65():
    for Om in SAMPLING:
        rho2 = spectral_radius_squared(amplification(gj.DG(1, gj.gauss_legendre(3)), Om / OMEGA))
        assert rho2 == pytest.approx((4 * Om**2 + 36) / (Om**4 + 4 * Om**2 + 36), rel=1e-12)


@pytest.mark.parametrize("family", ["cG", "dG"])
@pytest.mark.parametrize("name", ["gauss2", "trapezoid", "lobatto3", "one point at 0.3", "non-symmetric two point"])
def test_energy_and_angular_momentum_scale_by_rho2_each_step(family, name):
    """H_{n+1} = rho^2 H_n (Lemmas 4.3, 4.7) and L_{n+1} = rho^2 L_n (Prop. 4.5), h = 1."""
    rule, h = RULES[name], 1.0
    method = gj.CG(1, rule) if family == "cG" else gj.DG(1, rule)
    rho2 = (rho2_cg1_eq59 if family == "cG" else rho2_dg1_eq69)(h * OMEGA, rule)
    sol = gj.integrate(H, Q0, P0, method=method, h=h, n_steps=20)
    energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
    L = np.asarray(jnp.cross(sol.q, sol.p))
    np.testing.assert_allclose(energy[1:] / energy[:-1], rho2, rtol=1e-12)
    np.testing.assert_allclose(L[1:], rho2 * L[:-1], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_cg_conserves_a_quadratic_hamiltonian_to_round_off(k):
    """Theorem 3.1: k + 1 Gauss points integrate test (deg k-1) x field (deg k) exactly."""
    for rule in (gj.gauss_legendre(k + 1), gj.gauss_legendre(k)):  # k points: degree 2k - 1 = enough
        sol = gj.integrate(H, Q0, P0, method=gj.CG(k, rule), h=1.0, n_steps=1000)
        energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
        # exact integer matrices leave only round-off, a random walk of ~eps per step:
        # ~ eps sqrt(1000) ~ 1e-14; a drift of 1 eps per step would reach 2e-13
        assert np.abs(energy / energy[0] - 1).max() < 2e-14


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
