"""Galerkin and Lagrangian variational integrators [Tang]: symplectic, symmetric, order 2s, equivalent."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import galerkin_jax as gj
import helpers
from galerkin_jax import _basis
from galerkin_jax._march import solve_element, solver_options

KEPLER = helpers.kepler(0.5)
SCENES = {"kepler": KEPLER, "pendulum": helpers.pendulum(), "non-separable": helpers.non_separable()}


# every s on the non-separable H (the general case); the separable scenes at s = 2
@pytest.mark.parametrize("scene, s", [("non-separable", 1), ("non-separable", 2), ("non-separable", 3),
                                      ("kepler", 2), ("pendulum", 2)])
def test_galerkin_vi_is_symplectic(scene, s):
    """A^T J A = J for the exact step Jacobian (Corollary 2.1), with Gauss and Lobatto rules."""
    H, q0, p0 = SCENES[scene]
    for rule in (gj.gauss_legendre(s + 1), gj.gauss_lobatto(s + 1)):
        A = gj.amplification_matrix(H, q0, p0, method=gj.GalerkinVI(s, rule), h=0.3)
        # 1e-13: the Newton solve and jacfwd are exact to ~10 eps times the entries of A
        assert helpers.symplecticity_defect(A) < 1e-13


def test_lagrangian_vi_is_symplectic():
    L = lambda q, v: 0.5 * v @ v * (1 + 0.1 * q @ q) - 0.5 * q @ q - 0.25 * q[0] ** 4
    for s in (1, 2, 3):
        A = gj.amplification_matrix(L, jnp.array([0.8, -0.3]), jnp.array([0.2, 0.4]),
                                    method=gj.LagrangianVI(s, gj.gauss_legendre(s + 2)), h=0.2)
        assert helpers.symplecticity_defect(A) < 1e-13


@pytest.mark.parametrize("scene", SCENES)
def test_galerkin_vi_is_symmetric(scene):
    """Phi_{-h}(Phi_h(z)) = z for non-reversible H too (the element equations with -h)."""
    H, q0, p0 = SCENES[scene]
    method = gj.GalerkinVI(2, gj.gauss_legendre(3))
    element = jax.jit(lambda q, p, h: solve_element(method, H, q, p, h, None, solver_options(method, 32, False)))
    q1, p1, *_ = element(q0, p0, 0.2)
    q2, p2, _, _, status = element(q1, p1, -0.2)
    assert int(status) == 0
    np.testing.assert_allclose(jnp.concatenate([q2, p2]), jnp.concatenate([q0, p0]), atol=1e-14)


def test_a_non_symmetric_rule_breaks_symmetry_but_not_symplecticity():
    H, q0, p0 = KEPLER
    method = gj.GalerkinVI(1, gj.QuadratureRule([0.3], [1.0]))
    element = jax.jit(lambda q, p, h: solve_element(method, H, q, p, h, None, solver_options(method, 32, False)))
    q1, p1, *_ = element(q0, p0, 0.2)
    q2, p2, *_ = element(q1, p1, -0.2)
    assert np.abs(np.concatenate([q2 - q0, p2 - p0])).max() > 1e-4
    assert helpers.symplecticity_defect(gj.amplification_matrix(H, q0, p0, method=method, h=0.2)) < 1e-13


@pytest.mark.parametrize("s, ns", [(1, [128, 256, 512]), (2, [64, 128, 256]), (3, [64, 96, 128]), (4, [32, 48, 64])])
def test_galerkin_vi_has_nodal_order_2s(s, ns):
    """Kepler e = 0.5 at t = 2 pi against the exact orbit; s + 2 Gauss points."""
    H, q0, p0 = KEPLER
    T = 2 * np.pi
    method = gj.GalerkinVI(s, gj.gauss_legendre(s + 2))
    sol = jax.vmap(lambda h: gj.integrate(H, q0, p0, method=method, h=h, n_steps=max(ns)))(jnp.array([T / n for n in ns]))
    q_exact, p_exact = helpers.kepler_exact(T)
    errors = [max(np.abs(sol.q[j, n] - q_exact).max(), np.abs(sol.p[j, n] - p_exact).max()) for j, n in enumerate(ns)]
    # measured 2.00, 4.00, 6.00, 7.96: the Newton floor lets order 8 show above 1e-12
    assert helpers.fitted_order([T / n for n in ns], errors, floor=1e-12) == pytest.approx(2 * s, abs=0.1)


# jitted: one compiled program per shape instead of one per operation of an eager call
antiderivatives = jax.jit(_basis.legendre_antiderivatives, static_argnums=1)
values = jax.jit(_basis.legendre_values, static_argnums=1)


def kernel_A(tau, sigma, s):
    """A_{tau,sigma} = sum_i int_0^tau l_i(x) dx l_i(sigma) (eq. (2.35), index corrected)."""
    scale = _basis.test_scale(s)
    A = np.asarray(antiderivatives(jnp.asarray(tau), s))
    P = np.asarray(values(jnp.asarray(sigma), s))
    return (A * scale) @ P.T


def kernel_A_hat(tau, sigma, s):
    """Ahat_{tau,sigma} = 1 - sum_i int_0^sigma l_i(x) dx l_i(tau) (eq. (2.35))."""
    return 1.0 - kernel_A(sigma, tau, s).T


def test_element_satisfies_the_weak_form_and_the_cspkr_kernels():
    """The converged element satisfies (2.21a)-(2.21b) for every test function, and its stages
    are reproduced by the continuous-stage PRK (2.34) with the corrected kernel of (2.35)."""
    H, q0, p0 = SCENES["non-separable"]
    s, h = 3, 0.25
    rule = gj.gauss_legendre(5)
    method = gj.GalerkinVI(s, rule)
    q1, p1, Z, _, _ = jax.jit(lambda q, p: solve_element(method, H, q, p, h, None, solver_options(method, 32, False)))(q0, p0)
    c, mu = np.split(np.asarray(Z), 2)
    alpha, w = np.asarray(rule.points), np.asarray(rule.weights)
    Q = lambda t: np.asarray(q0) + np.asarray(antiderivatives(jnp.asarray(t), s)) @ c
    P = lambda t: np.asarray(p0) + np.asarray(values(jnp.asarray(t), s)) @ mu
    dHdq, dHdp = (np.asarray(x) for x in jax.jit(jax.vmap(jax.grad(H, argnums=(0, 1))))(jnp.asarray(Q(alpha)), jnp.asarray(P(alpha))))
    f, g = dHdp, -dHdq
    x, wx = np.polynomial.legendre.leggauss(12)  # exact for the polynomial terms
    x, wx = (x + 1) / 2, wx / 2
    for j in range(s):  # (2.21a) with phi = P_j, after integration by parts (2.23)
        phi = lambda t: np.polynomial.legendre.legval(2 * t - 1, np.eye(s)[j])
        dQ = (Q(x + 1e-7) - Q(x - 1e-7)) / 2e-7  # Q is a polynomial: this is exact to ~1e-9
        lhs = (wx * phi(x)) @ dQ
        np.testing.assert_allclose(lhs, h * (w * phi(alpha)) @ f, atol=1e-8)
    for j in range(s + 1):  # (2.21b) with varphi = P_j (degree <= s)
        phi = lambda t: np.polynomial.legendre.legval(2 * t - 1, np.eye(s + 1)[j])
        dphi = lambda t: 2 * np.polynomial.legendre.legval(2 * t - 1, np.polynomial.legendre.legder(np.eye(s + 1)[j]))
        lhs = (wx * dphi(x)) @ P(x) + h * (w * phi(alpha)) @ g
        np.testing.assert_allclose(lhs, np.asarray(p1) * phi(1.0) - np.asarray(p0) * phi(0.0), atol=1e-13)
    tau = np.array([0.0, 0.3, 0.77, 1.0])
    np.testing.assert_allclose(Q(tau), np.asarray(q0) + h * kernel_A(tau, alpha, s) @ (w[:, None] * f), atol=1e-14)
    np.testing.assert_allclose(P(tau), np.asarray(p0) + h * kernel_A_hat(tau, alpha, s) @ (w[:, None] * g), atol=1e-14)
    # Theorem 2.2's symplecticity condition B Ahat(t, s) + Bhat A(s, t) = B Bhat, pointwise
    np.testing.assert_allclose(kernel_A_hat(tau, tau, s) + kernel_A(tau, tau, s).T, 1.0, atol=1e-14)


M_MATRIX = jnp.array([[2.0, 0.5], [0.5, 1.0]])
U = lambda q: 0.5 * q @ q + 0.25 * q[0] ** 4 + 0.1 * q[0] * q[1] ** 2
L_QUADRATIC = lambda q, v: 0.5 * v @ M_MATRIX @ v - U(q)
H_QUADRATIC = lambda q, p: 0.5 * p @ jnp.linalg.solve(M_MATRIX, p) + U(q)
Q0, P0 = jnp.array([1.0, 0.2]), jnp.array([0.1, 0.8])


@pytest.mark.parametrize("s", [1, 3])
def test_lagrangian_vi_equals_galerkin_vi_for_quadratic_kinetic_energy(s):
    """[Tang, Section 3]: identical (q_n, p_n) for L = qdot^T M qdot / 2 - U(q), M SPD non-diagonal.
    s = 2 on this L, M, U and initial state: ``reproduce.tang_equivalence`` (test_reproduce.py)."""
    rule = gj.gauss_legendre(s + 1)
    a = gj.integrate(H_QUADRATIC, Q0, P0, method=gj.GalerkinVI(s, rule), h=0.05, n_steps=200)
    b = gj.integrate(L_QUADRATIC, Q0, P0, method=gj.LagrangianVI(s, rule), h=0.05, n_steps=200)
    assert int(a.status) == int(b.status) == 0
    # measured <= 2e-15 over 200 steps: the two are the same scheme up to round-off
    np.testing.assert_allclose(b.q, a.q, atol=1e-13)
    np.testing.assert_allclose(b.p, a.p, atol=1e-13)


def chain_potential(q):
    stretch = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
    return 0.5 * stretch @ stretch + 0.25 * jnp.sum(stretch**4)


def test_lagrangian_vi_with_non_unit_mass_above_the_dense_limit_equals_galerkin_vi():
    """M = 3 I on a chain of 130 masses, s = 2: 260 unknowns per element, above the dense
    limit of 256, where the fixed point Z <- Z - R(Z) would diverge (dR/dv = M at h = 0, so
    its rate is |1 - 3| = 2) and no dense Newton matrix is kept. LagrangianVI has no fixed
    point: Newton-Krylov solves every element. It equals GalerkinVI on H = p^T M^-1 p / 2 + U
    [Tang, Section 3]."""
    d, s, mass = 130, 2, 3.0
    L = lambda q, v: 0.5 * mass * v @ v - chain_potential(q)
    H = lambda q, p: 0.5 * p @ p / mass + chain_potential(q)
    q0, p0 = jnp.asarray(0.3 * np.sin(np.linspace(0.0, 3.0, d))), jnp.asarray(0.2 * np.cos(np.arange(d)))
    rule = gj.gauss_legendre(s + 1)
    run = lambda f, method: gj.integrate(f, q0, p0, method=method, h=0.05, n_steps=100, save_every=10)
    a, b = run(H, gj.GalerkinVI(s, rule)), run(L, gj.LagrangianVI(s, rule))
    assert int(a.status) == int(b.status) == 0
    # measured 1.1e-13 (states of size 0.42), nearly all GalerkinVI's: against a chain of
    # elements each solved by 6 dense Newton steps, GalerkinVI's fixed point (520 unknowns)
    # is 1.1e-13 off, LagrangianVI 8e-16; 1e-12 leaves a factor 9 for the fixed point's floor
    np.testing.assert_allclose(b.q, a.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.p, a.p, rtol=0, atol=1e-12)


L_REL = lambda q, v: -jnp.sqrt(1 - v @ v) - 0.5 * q @ q
H_REL = lambda q, p: jnp.sqrt(1 + p @ p) + 0.5 * q @ q


def one_step_difference(s, hs):
    """max |GalerkinVI step - LagrangianVI step| from (Q0, P0), vmapped over h."""
    rule = gj.gauss_legendre(s + 2)
    run = lambda H, method: jax.vmap(lambda h: jnp.concatenate(gj.step(H, Q0, P0, method=method, h=h)))(jnp.asarray(hs))
    a = run(H_REL, gj.GalerkinVI(s, rule))
    b = run(L_REL, gj.LagrangianVI(s, rule))
    return np.abs(np.asarray(a - b)).max(axis=1)


def test_relativistic_lagrangian_where_p_is_not_a_polynomial():
    """Remark 2.1: for s = 1 P is constant on the element and the methods coincide; for s = 2
    P(tau) = qdot / sqrt(1 - |qdot|^2) is not a polynomial and one step differs by O(h^5)
    (measured slope 5.0; over t = 2 the difference is O(h^4): 8.3e-8, 5.2e-9, 3.2e-10 at
    h = 0.1, 0.05, 0.025), i.e. two different schemes of the same order 4."""
    hs = np.array([0.2, 0.1, 0.05, 0.025])
    assert one_step_difference(1, hs).max() < 1e-15
    differences = one_step_difference(2, hs)
    assert differences[-1] > 1e-12
    assert helpers.fitted_order(hs, differences, floor=1e-14) == pytest.approx(5, abs=0.2)


def test_lagrangian_vi_converges_at_order_2s_on_the_relativistic_problem():
    reference = solve_ivp(
        lambda t, z: np.concatenate([z[2:] / np.sqrt(1 + z[2:] @ z[2:]), -z[:2]]),
        (0, 2.0), np.concatenate([Q0, P0]), method="DOP853", rtol=1e-13, atol=1e-13,
    ).y[:, -1]
    hs, ns = [0.2, 0.1, 0.05], [10, 20, 40]
    # one compiled run vmapped over h, each read at its step n (t = 2)
    method = gj.LagrangianVI(2, gj.gauss_legendre(4))
    sol = jax.vmap(lambda h: gj.integrate(L_REL, Q0, P0, method=method, h=h, n_steps=max(ns)))(jnp.asarray(hs))
    assert np.all(np.asarray(sol.status) == 0)
    errors = [np.abs(np.concatenate([sol.q[j, n], sol.p[j, n]]) - reference).max() for j, n in enumerate(ns)]
    assert helpers.fitted_order(hs, errors) == pytest.approx(4, abs=0.2)


def test_galerkin_vi_energy_error_is_bounded_over_long_runs():
    """No secular drift over 2 10^4 steps (64 periods) of Kepler e = 0.6: the energy error of
    the second half is no larger than that of the first (a drift would double it)."""
    H, q0, p0 = helpers.kepler(0.6)
    sol = gj.integrate(H, q0, p0, method=gj.GalerkinVI(2, gj.gauss_legendre(3)), h=0.02, n_steps=20_000, save_every=10)
    assert int(sol.status) == 0
    error = np.abs(np.asarray(jax.vmap(H)(sol.q, sol.p)) - float(H(q0, p0)))
    half = len(error) // 2
    assert error[half:].max() < 1.5 * error[:half].max()
    assert error.max() < 1e-5


@pytest.mark.parametrize("k", [1, 2])
def test_cg_energy_stays_at_round_off_for_a_polynomial_hamiltonian(k):
    """Quartic scene: DH is cubic in z, so 2k Gauss points make every DH integral exact
    (degree (k - 1) + 3k = 4k - 1) and Theorem 3.1 holds to round-off over 10^4 steps."""
    H, _, q0, p0 = helpers.quartic()
    sol = gj.integrate(H, q0, p0, method=gj.CG(k, gj.gauss_legendre(2 * k)), h=0.01, n_steps=10_000, save_every=10)
    energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
    # ~ eps per step as a random walk over 10^4 steps, times the Newton condition number (~10^2)
    assert np.abs(energy / energy[0] - 1).max() < 1e-12
