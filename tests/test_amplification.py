"""Amplification matrices and energy laws of cG(1)/dG(1) on the isotropic oscillator [GBS, Sections 3-4].

The library's one-step matrices come from ``gj.amplification_matrix`` (``jax.jacfwd`` through
the Newton solve); the reference formulas below are written in NumPy from the paper, with
beta_i [GBS, eq. (58)] and beta_ij [eq. (68)] computed from the rule's points and weights.

Derivation (z = (q, p), H = diag(-c I, I/m), J = [[0, I], [-I, 0]], B := h J H). Then
B = h [[0, I/m], [c I, 0]] and B^2 = h^2 (c/m) I = -Omega^2 I, so every one-step matrix is a
rational function r(B) = a I + b B with eigenvalues r(+-i Omega), rho^2 = a^2 + b^2 Omega^2.

- cG(1), eq. (38): (I - beta2 B) z2 = (I + beta1 B) z1, z1 = z0, and
  (I - beta2 B)^-1 = (I + beta2 B) / (1 + beta2^2 Omega^2), hence
  A = ((1 - beta1 beta2 Omega^2) I + (beta1 + beta2) B) / (1 + beta2^2 Omega^2).
  MISPRINT: eq. (57) prints the diagonal as (1 + beta1 beta2 Omega^2). With beta1 = beta2 = 1/2
  (exact quadrature) the printed form has diagonal 1, not eq. (51)'s (1 - Omega^2/4)/(1 + Omega^2/4);
  only the minus sign gives |lambda|^2 = (1 + beta1^2 Omega^2)(1 + beta2^2 Omega^2) /
  (1 + beta2^2 Omega^2)^2, i.e. eq. (59), which is correct as printed.
- dG(1), eqs. (66)-(67) (correct as printed, they follow from eqs. (30)-(31)): with b = B,
  z1 = (1/2 + beta12 b)^-1 (1/2 - beta22 b) z2, so
  r(b) = (1 + 2 beta12 b) / (1 - s b + 2 D b^2), s = beta11 + beta22, D = beta11 beta22 - beta12^2.
  |r(i Omega)|^2 = (1 + 4 beta12^2 Omega^2) / ((1 - 2 D Omega^2)^2 + s^2 Omega^2), and
  s^2 - 4 D = (beta22 - beta11)^2 + 4 beta12^2: this is eq. (69) as printed. Exact quadrature
  (1/3, 1/6, 1/3) gives r(b) = 2 (3 + b) / (b^2 - 4 b + 6): eqs. (63), (64), (65) as printed.
  The paper omits the general dG(1) matrix; it is ``dg1_matrix_closed_form`` below.
Eqs. (51), (52), (54), (56), (59), (63)-(69) check out; only eq. (57) has a sign misprint.
(Minor: in eqs. (62), (72) the sums over pairs run to int(N_q / 2) and so count one pair, or
the middle point, twice; harmless, since every term vanishes for symmetric rules.)
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, Q0, P0, OMEGA = helpers.oscillator()  # m = 2, c = -0.25, omega = sqrt(-c / m)
M, C = helpers.OSC_M, helpers.OSC_C
EPS = np.finfo(np.float64).eps
SAMPLING = np.logspace(-1, 2, 13)  # Omega = h omega from 0.1 to 100
I3 = np.eye(3)

RULES = {
    "midpoint": gj.midpoint(),
    "trapezoid": gj.trapezoid(),
    "gauss2": gj.gauss_legendre(2),
    "gauss3": gj.gauss_legendre(3),
    "lobatto3": gj.gauss_lobatto(3),
    "lobatto4": gj.gauss_lobatto(4),
    "radau2 (non-symmetric)": gj.gauss_radau(2),
    "one point at 0.3 (non-symmetric)": gj.QuadratureRule([0.3], [1.0]),
    "two points (non-symmetric)": gj.QuadratureRule([0.2, 0.7], [0.6, 0.4]),
    "three points (non-symmetric)": gj.QuadratureRule([0.1, 0.45, 0.95], [0.3, 0.3, 0.4]),
}
SYMMETRIC = ("midpoint", "trapezoid", "gauss2", "gauss3", "lobatto3", "lobatto4")


# ---------------------------------------------------------------- paper formulas (NumPy)


def betas(rule):
    """(beta1, beta2) [GBS, eq. (58)] and (beta11, beta12, beta22) [eq. (68)], M_1 = 1 - alpha, M_2 = alpha."""
    alpha, w = np.asarray(rule.points, float), np.asarray(rule.weights, float)
    shape = np.stack([1.0 - alpha, alpha])
    b = shape @ w
    bb = (shape * w) @ shape.T
    return b, (bb[0, 0], bb[0, 1], bb[1, 1])


def blocks(a, b, c_, d):
    """[[a I, b I], [c I, d I]] in the ordering z = (q, p)."""
    return np.block([[a * I3, b * I3], [c_ * I3, d * I3]])


def hJH(Om):
    """B = h J H for H = diag(-c I, I / m) [GBS, eq. (45)], h = Omega / omega."""
    h = Om / OMEGA
    return blocks(0.0, h / M, h * C, 0.0)


def cg1_matrix_eq51(Om):
    h, x = Om / OMEGA, Om**2 / 4
    return blocks(1 - x, h / M, h * C, 1 - x) / (1 + x)


def cg1_eigenvalue_eq52(Om):
    return (4 - Om**2 + 4j * Om) / (4 + Om**2)


def cg1_matrix_eq57_printed(Om, rule):
    """[GBS, eq. (57)] exactly as printed (diagonal 1 + beta1 beta2 Omega^2): wrong."""
    (b1, b2), _ = betas(rule)
    h, diag = Om / OMEGA, 1 + b1 * b2 * Om**2
    return blocks(diag, h / M * (b1 + b2), h * C * (b1 + b2), diag) / (1 + b2**2 * Om**2)


def cg1_matrix_eq57_corrected(Om, rule):
    """[GBS, eq. (57)] corrected: diagonal (1 - beta1 beta2 Omega^2), from (I - b2 B)^-1 (I + b1 B)."""
    (b1, b2), _ = betas(rule)
    h, diag = Om / OMEGA, 1 - b1 * b2 * Om**2
    return blocks(diag, h / M * (b1 + b2), h * C * (b1 + b2), diag) / (1 + b2**2 * Om**2)


def rho2_cg1_eq59(Om, rule):
    (b1, b2), _ = betas(rule)
    return (1 + b1**2 * Om**2) / (1 + b2**2 * Om**2)


def dg1_matrix_eq63(Om):
    h, x = Om / OMEGA, Om**2
    return -2 * blocks(7 * x - 18, h / M * (x - 18), h * C * (x - 18), 7 * x - 18) / (x**2 + 4 * x + 36)


def dg1_eigenvalue_eq64(Om):
    return -2 * (7 * Om**2 - 18 + 1j * Om * (Om**2 - 18)) / (Om**4 + 4 * Om**2 + 36)


def rho2_dg1_eq65(Om):
    return (4 * Om**2 + 36) / (Om**4 + 4 * Om**2 + 36)


def dg1_matrix_eqs66_67(Om, rule):
    """z2 from [GBS, eqs. (66)-(67)] for z0 = the unit vectors: a 12 x 12 NumPy solve."""
    _, (b11, b12, b22) = betas(rule)
    B, E = hJH(Om), np.eye(6)
    system = np.block([[0.5 * E - b12 * B, 0.5 * E - b11 * B], [0.5 * E - b22 * B, -(0.5 * E + b12 * B)]])
    return np.linalg.solve(system, np.vstack([E, 0 * E]))[:6]  # unknowns ordered (z2, z1)


def dg1_matrix_closed_form(Om, rule):
    """General dG(1) matrix (omitted in [GBS] after eq. (68)): r(B), r(b) = (1 + 2 b12 b) / (1 - s b + 2 D b^2)."""
    _, (b11, b12, b22) = betas(rule)
    s, D = b11 + b22, b11 * b22 - b12**2
    real = 1 - 2 * D * Om**2  # 1 - s B + 2 D B^2 = real I - s B, inverted with B^2 = -Omega^2 I
    den = real**2 + s**2 * Om**2
    return ((real - 2 * b12 * s * Om**2) * np.eye(6) + (s + 2 * b12 * real) * hJH(Om)) / den


def rho2_dg1_eq69(Om, rule):
    _, (b11, b12, b22) = betas(rule)
    top = 1 + 4 * b12**2 * Om**2
    return top / (top + (b22 - b11) ** 2 * Om**2 + 4 * (b12**2 - b11 * b22) ** 2 * Om**4)


def constituent_matrices_eq54():
    """A_{1,1}, A_{1,2} [GBS, eq. (54)]: the spectral projectors of B for +-i Omega."""
    imw = 1j * OMEGA * M
    return 0.5 * blocks(1, 1 / imw, imw, 1), 0.5 * blocks(1, -1 / imw, -imw, 1)


# ---------------------------------------------------------------- library side


@jax.jit
def _amplification(method, h):
    return gj.amplification_matrix(H, Q0, P0, method=method, h=h)


def amplification(family, rule, Om):
    """One compilation per family and point count; Omega only changes a traced h."""
    return np.asarray(_amplification(family(1, rule), Om / OMEGA))


def lambda1(A):
    """lambda_1 of [GBS, eqs. (49), (52), (64)]: the eigenvalue on the range of A_{1,1} (eq. (54)).

    Asserts that it is a numerical eigenvalue of A and that A = lambda1 A_11 + conj(lambda1) A_12.
    """
    A11, A12 = constituent_matrices_eq54()
    lam = np.trace(A @ A11) / 3  # A_11 is a projector of rank 3
    assert np.abs(np.linalg.eigvals(A) - lam).min() < 1e-12 * max(1.0, abs(lam))
    np.testing.assert_allclose(A, (lam * A11 + np.conj(lam) * A12).real, atol=1e-13 * np.abs(A).max())
    return lam


def rho2(A):
    return np.max(np.abs(np.linalg.eigvals(A))) ** 2


def energies(sol):
    return np.asarray(jax.vmap(H)(sol.q, sol.p))


def assert_matrix_close(A, ref, what):
    # the library computes z1 = z0 + (increment), so its round-off is relative to
    # max(|z0|, |z1|), i.e. to max(1, max|A|) for unit z0; measured <= 28 eps over all rules
    # and Omega <= 100 (eqs. (66)-(67) by NumPy: <= 9 eps). 64 eps leaves room, while the
    # misprint of eq. (57) moves entries by O(1).
    err = np.abs(A - ref).max() / max(1.0, np.abs(ref).max())
    assert err < 64 * EPS, f"{what}: max deviation {err / EPS:.1f} eps"


# ---------------------------------------------------------------- amplification matrices


def test_cg1_exact_quadrature_has_amplification_matrix_eq51_and_eigenvalues_eq52():
    for Om in SAMPLING:
        A = amplification(gj.CG, gj.gauss_legendre(2), Om)  # exact: integrand has degree 1
        assert_matrix_close(A, cg1_matrix_eq51(Om), f"eq. (51), Omega={Om}")
        # eigenvalues of a semisimple triple pair: error ~ eps cond(eigenvectors) ~ 1e-15
        assert abs(lambda1(A) - cg1_eigenvalue_eq52(Om)) < 1e-13


def test_dg1_exact_quadrature_has_amplification_matrix_eq63_and_eigenvalues_eq64():
    for Om in SAMPLING:
        A = amplification(gj.DG, gj.gauss_legendre(2), Om)  # exact: integrand has degree 2
        assert_matrix_close(A, dg1_matrix_eq63(Om), f"eq. (63), Omega={Om}")
        assert abs(lambda1(A) - dg1_eigenvalue_eq64(Om)) < 1e-13


@pytest.mark.parametrize("name", RULES)
def test_cg1_with_quadrature_has_the_sign_corrected_eq57(name):
    rule = RULES[name]
    for Om in SAMPLING:
        assert_matrix_close(amplification(gj.CG, rule, Om), cg1_matrix_eq57_corrected(Om, rule), f"Omega={Om}")


def test_printed_eq57_contradicts_eq51_and_the_library():
    """The printed diagonal (1 + beta1 beta2 Omega^2) is wrong, even for exact quadrature."""
    for Om in (0.5, 2.0):
        for rule in (gj.gauss_legendre(2), RULES["one point at 0.3 (non-symmetric)"]):
            (b1, b2), _ = betas(rule)
            A = amplification(gj.CG, rule, Om)
            gap = 2 * b1 * b2 * Om**2 / (1 + b2**2 * Om**2)  # printed minus corrected diagonal
            assert np.abs(A - cg1_matrix_eq57_printed(Om, rule)).max() == pytest.approx(gap, rel=1e-12)
            assert gap > 0.1
        assert np.abs(cg1_matrix_eq57_printed(Om, gj.gauss_legendre(2)) - cg1_matrix_eq51(Om)).max() > 0.1


@pytest.mark.parametrize("name", RULES)
def test_dg1_with_quadrature_is_the_scheme_eqs66_67_with_closed_form_matrix(name):
    rule = RULES[name]
    for Om in SAMPLING:
        A = amplification(gj.DG, rule, Om)
        assert_matrix_close(A, dg1_matrix_eqs66_67(Om, rule), f"eqs. (66)-(67), Omega={Om}")
        assert_matrix_close(A, dg1_matrix_closed_form(Om, rule), f"closed form, Omega={Om}")


# ---------------------------------------------------------------- spectral radii


@pytest.mark.parametrize("name", RULES)
def test_squared_spectral_radius_is_eq59_for_cg1_and_eq69_for_dg1(name):
    rule = RULES[name]
    for Om in SAMPLING:
        cg, dg = rho2(amplification(gj.CG, rule, Om)), rho2(amplification(gj.DG, rule, Om))
        # numerical eigenvalues of a semisimple 6 x 6 matrix: relative error a few eps times
        # the eigenvector condition (<= ~1e3 at Omega = 100); measured <= 1e-13
        assert cg == pytest.approx(rho2_cg1_eq59(Om, rule), rel=1e-12)
        assert dg == pytest.approx(rho2_dg1_eq69(Om, rule), rel=1e-12)
        assert dg <= 1 + 1e-13  # eq. (69): the denominator exceeds the numerator for any rule
        if name in SYMMETRIC:  # Lemma 4.4
            assert cg == pytest.approx(1.0, rel=1e-13)
        if name in SYMMETRIC and name != "midpoint":  # Lemma 4.8: rho^2 < 1 unless one point at 1/2
            assert dg < 1 - 1e-8
    if name == "midpoint":  # Corollary 4.2
        assert dg == pytest.approx(1.0, rel=1e-13)


def test_dg1_exact_quadrature_has_squared_spectral_radius_eq65_below_one():
    for Om in SAMPLING:
        r2 = rho2(amplification(gj.DG, gj.gauss_legendre(3), Om))
        assert r2 == pytest.approx(rho2_dg1_eq65(Om), rel=1e-12)
        assert r2 < 1  # Lemma 4.6


@pytest.mark.parametrize("family", [gj.CG, gj.DG], ids=["cG1", "dG1"])
def test_constituent_matrices_are_eq54_and_satisfy_eq56_for_every_rule(family):
    """Lemmas 4.1, 4.3, 4.5, 4.7: A = lambda1 A_11 + lambda2 A_12, A_1i of eq. (54) for any rule."""
    A11, A12 = constituent_matrices_eq54()
    Hm = blocks(-C, 0.0, 0.0, 1 / M)  # [GBS, eq. (45)]
    # eq. (56): A_11^T H A_12 + A_12^T H A_11 = H, A_1i^T H A_1i = 0
    np.testing.assert_allclose(A11.T @ Hm @ A12 + A12.T @ Hm @ A11, Hm, atol=1e-15)
    np.testing.assert_allclose(A11.T @ Hm @ A11, 0, atol=1e-15)
    np.testing.assert_allclose(A12.T @ Hm @ A12, 0, atol=1e-15)
    for name in RULES:
        for Om in SAMPLING[::3]:
            lambda1(amplification(family, RULES[name], Om))  # asserts eqs. (49), (54)


# ---------------------------------------------------------------- energy and momentum laws


@pytest.mark.parametrize("family", [gj.CG, gj.DG], ids=["cG1", "dG1"])
@pytest.mark.parametrize("name", ["gauss2", "trapezoid", "lobatto3", "one point at 0.3 (non-symmetric)",
                                  "two points (non-symmetric)"])
def test_energy_and_angular_momentum_scale_by_rho2_each_step(family, name):
    """H_{n+1} = rho^2 H_n (Lemmas 4.3, 4.7) and L_{n+1} = rho^2 L_n (Prop. 4.5), h = 1."""
    rule, h = RULES[name], 1.0
    rho2 = (rho2_cg1_eq59 if family is gj.CG else rho2_dg1_eq69)(h * OMEGA, rule)
    sol = gj.integrate(H, Q0, P0, method=family(1, rule), h=h, n_steps=20)
    L = np.asarray(jnp.cross(sol.q, sol.p))
    # 20 steps of a linear map with entries ~1: relative round-off ~20 eps per ratio
    np.testing.assert_allclose(energies(sol)[1:] / energies(sol)[:-1], rho2, rtol=1e-12)
    np.testing.assert_allclose(L[1:], rho2 * L[:-1], rtol=1e-12, atol=1e-15)
