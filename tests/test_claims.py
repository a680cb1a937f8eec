"""The claims of the README and of docs/methods.md, each in a fast form for the default tier.

Orders of convergence, Theorem 3.1's conservation and dG's dissipation, the equivalences with
classical Runge-Kutta schemes, symplecticity and the explicit paths, measured on small systems
with few step sizes. Each test compiles one program per method kind and degree: a ``vmap`` over step
sizes and over rules stacked by ``gj.stack_methods`` shares it. The thorough versions, on
Kepler and over long runs, are in test_convergence.py, test_conservation.py,
test_equivalences.py, test_variational.py, test_explicit.py, test_splitting.py and
test_midpoint.py (several in the slow tier). ``.ci/tiers.py`` keeps this file in the default
tier whatever its coverage (``CLAIMS``).

The scene: two uncoupled quartic oscillators, H = sum_i p_i^2 / (2 m_i) + q_i^4 / 4, whose
exact solution is q_i = A_i cn(w_i (t + t_i) | 1/2), w_i = A_i / sqrt(m_i) (Jacobi's elliptic
functions, SciPy). H is a polynomial of degree four, nonlinear, separable with a kinetic
energy quadratic in p (every method applies to it but the modified midpoint rule, for central
forces: Kepler below), with a Lagrangian L = sum_i m_i qdot_i^2 / 2 - q_i^4 / 4 of [Tang]'s
form (M = diag(m), not the identity).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import root
from scipy.special import ellipj

import galerkin_jax as gj
import helpers

AMPLITUDE, MASS, PHASE = np.array([1.0, 1.5]), np.array([1.0, 2.0]), np.array([0.3, 1.1])
OMEGA = AMPLITUDE / np.sqrt(MASS)
T = 4.0  # about half a period of each oscillator (4 K(1/2) / w_i = 7.4, 7.0)


def exact(t):
    """(q, p) at time t: q = A cn(w (t + t_i) | 1/2), p = m q'."""
    sn, cn, dn, _ = ellipj(OMEGA * (t + PHASE), 0.5)
    return AMPLITUDE * cn, -MASS * AMPLITUDE * OMEGA * sn * dn


def H(q, p):
    return 0.5 * p @ (p / MASS) + 0.25 * jnp.sum(q**4)


def L(q, v):
    return 0.5 * v @ (MASS * v) - 0.25 * jnp.sum(q**4)


def field(z):
    """Hamilton's field z' = (dH/dp, -dH/dq) in NumPy."""
    q, p = z[:2], z[2:]
    return np.concatenate([p / MASS, -(q**3)])


Q0, P0 = (jnp.asarray(x) for x in exact(0.0))
Z0 = np.concatenate([Q0, P0])


def runs(methods, ns, f=H):
    """Every method at every h = T / n, n in ns, in one compiled program (a ``vmap`` over the
    stacked methods and the step sizes), each for max(ns) elements with every state saved:
    ``(solution, errors)``, errors[i][j] the max error of (q, p) at t = T of methods[i] with
    h = T / ns[j], against ``exact``."""
    hs = jnp.asarray([T / n for _ in methods for n in ns])
    run = lambda m, h: gj.integrate(f, Q0, P0, method=m, h=h, n_steps=max(ns), error_estimate=False)
    if len(methods) == 1:  # a concrete method: an explicit one is read as such (not from traced rules)
        sol = jax.vmap(lambda h: run(methods[0], h))(hs)
    else:
        sol = jax.vmap(run)(gj.stack_methods([m for m in methods for _ in ns]), hs)
    assert np.all(np.asarray(sol.status) == 0)
    q, p = np.asarray(sol.q), np.asarray(sol.p)
    qe, pe = exact(T)
    errors = [[max(np.abs(q[i * len(ns) + j, n] - qe).max(), np.abs(p[i * len(ns) + j, n] - pe).max())
               for j, n in enumerate(ns)] for i in range(len(methods))]
    return sol, errors


def order(ns, errors):
    return helpers.fitted_order([T / n for n in ns], errors, floor=1e-13)


def energy_drift(sol):
    """max_n |H_n / H_0 - 1| of each member of a batched run."""
    energy = np.asarray(jax.vmap(jax.vmap(H))(sol.q, sol.p))
    return np.abs(energy / energy[:, :1] - 1).max(axis=1)


def collocation(nodes, h, n_steps):
    """The collocation Runge-Kutta method on ``nodes`` (Gauss points: Gauss; right Radau points:
    Radau IIA) in NumPy, its stage equations solved by SciPy: the states of n_steps steps."""
    a, b = helpers.collocation_tableau(np.asarray(nodes))
    s, z, states = len(nodes), Z0.copy(), [Z0]
    for _ in range(n_steps):
        stages = lambda K: (K.reshape(s, -1) - np.stack([field(z + h * a[i] @ K.reshape(s, -1))
                                                         for i in range(s)])).ravel()
        K = root(stages, np.tile(field(z), s), method="hybr", options={"xtol": 1e-15}).x.reshape(s, -1)
        z = z + h * b @ K
        states.append(z)
    return np.stack(states)


def nodal_states(sol, member, n_steps):
    """(q, p) of one member of a batched run at its first n_steps + 1 nodes, as rows."""
    return np.concatenate([np.asarray(sol.q[member, : n_steps + 1]), np.asarray(sol.p[member, : n_steps + 1])], axis=1)


# step counts per degree: every error in the asymptotic range and above 1e-13 (largest error
# 1.5e-3 .. 4e-8, smallest 1.3e-4 .. 1.6e-12)
NS = {0: (256, 512, 1024), 1: (32, 64, 128), 2: (16, 32, 64), 3: (16, 32, 64)}


@pytest.mark.parametrize("k", [1, 2, 3])
def test_cg_has_order_2k_conserves_energy_with_2k_gauss_points_and_is_gauss_collocation_with_k(k):
    """cG(k) [GBS, eq. (16)], one program for the rules of 2k and of k Gauss points.

    Order 2k at the nodes with both: measured 1.997, 3.987, 5.987 (2k points) and 1.997, 3.989,
    5.984 (k points); the margin 0.1 separates 2k from 2k +- 1. Theorem 3.1: with 2k points
    every integral of the DH terms is exact (the test function, of degree k - 1, times DH(w),
    cubic in w of degree k, is of degree 4k - 1, which 2k Gauss points integrate), so H is kept
    to round-off at every step size: measured at most 1.0e-15 over 128 steps; bound 1e-14,
    where a drift of one eps per step would reach 1.4e-14 after 64 steps. With k points it is
    not kept (a rule exact to degree 2k - 1; for k = 1 the midpoint rule on a quartic V, Table
    5.1's C* box, which only the modified midpoint rule conserves): measured 9.3e-5 .. 1.6e-11
    at the smallest h; bound 1e-12, a thousand times round-off. With k points cG(k) is k-stage
    Gauss collocation (the classical equivalence; cG(k): [GBS, Section 3.1]): its first 8 steps
    equal those of the collocation method written out in NumPy (measured 4.4e-16; bound 1e-12,
    SciPy solving each stage system to 1e-15)."""
    ns = NS[k]
    sol, errors = runs([gj.CG(k, gj.gauss_legendre(2 * k)), gj.CG(k, gj.gauss_legendre(k))], ns)
    for e in errors:
        assert order(ns, e) == pytest.approx(2 * k, abs=0.1)
    exact_rule, gauss_points = energy_drift(sol).reshape(2, len(ns))
    assert exact_rule.max() < 1e-14
    assert gauss_points.min() > 1e-12
    gauss = collocation(np.asarray(gj.gauss_legendre(k).points), T / ns[0], 8)
    np.testing.assert_allclose(nodal_states(sol, len(ns), 8), gauss, rtol=0, atol=1e-12)


def H_or_hooke(q, p, hooke):
    """H (hooke = 0) or, with U = |q|^2 / 2 for sum_i q_i^4 / 4, a quadratic H (hooke = 1): one
    program for both."""
    return 0.5 * p @ (p / MASS) + (1 - hooke) * 0.25 * jnp.sum(q**4) + hooke * 0.5 * (q @ q)


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_dg_has_order_2k_plus_1_dissipates_and_with_k_plus_1_radau_points_is_radau_iia(k):
    """dG(k) [GBS, eq. (19)], one program for two rules, three step sizes and two Hamiltonians.

    Order 2k + 1 at the nodes on H with k + 2 Gauss points and with k + 1 right Radau points
    (measured 0.986, 2.996, 4.984, 6.986 and 0.986, 2.995, 4.982, 6.984; margin 0.1). With the
    Radau points it is the (k + 1)-stage Radau IIA method (Lesaint-Raviart; k = 0: implicit
    Euler): its first 8 steps equal those of the collocation method on the Radau points in
    NumPy (measured 4.4e-16 .. 1.5e-14; bound 1e-12, SciPy solving each stage system to 1e-15).
    Both rules are exact for a quadratic H, whose energy then decreases at every step (Prop. 3.1
    (ii), Prop. 4.3): at the largest h, by at least 1.3e-4, 3.0e-6, 2.4e-8, 6.5e-12 of H a step
    for k = 0..3, each far above round-off (~1e-16); dG(0) decreases the convex, non-quadratic
    H too (Prop. 3.1 (i); at least 4.0e-5). The thorough versions, 50 steps of h omega = 0.35:
    test_conservation.py."""
    ns = NS[k]
    methods = [gj.DG(k, gj.gauss_legendre(k + 2)), gj.DG(k, gj.gauss_radau(k + 1))]
    rows = [(m, n, hooke) for m in methods for hooke in (0.0, 1.0) for n in ns]
    sol = jax.vmap(lambda m, h, hooke: gj.integrate(H_or_hooke, Q0, P0, method=m, h=h, n_steps=max(ns), args=hooke,
                                                    error_estimate=False))(
        gj.stack_methods([r[0] for r in rows]), jnp.asarray([T / r[1] for r in rows]), jnp.asarray([r[2] for r in rows]))
    assert np.all(np.asarray(sol.status) == 0)
    q, p = np.asarray(sol.q), np.asarray(sol.p)
    hooke = np.asarray([r[2] for r in rows]) == 1.0
    qe, pe = exact(T)
    for i in (0, 2 * len(ns)):  # the rows of H, each rule's
        errors = [max(np.abs(q[i + j, n] - qe).max(), np.abs(p[i + j, n] - pe).max()) for j, n in enumerate(ns)]
        assert order(ns, errors) == pytest.approx(2 * k + 1, abs=0.1)
    energy = np.asarray(jax.vmap(jax.vmap(H_or_hooke, in_axes=(0, 0, None)))(sol.q, sol.p, jnp.asarray(hooke, float)))
    largest = np.asarray([r[1] for r in rows]) == ns[0]  # at smaller h, dG(3)'s decrement nears round-off
    decrement = -np.diff(energy[largest], axis=1) / energy[largest, :1]
    assert decrement[hooke[largest]].min() > 0
    if k == 0:
        assert decrement[~hooke[largest]].min() > 0
    radau = collocation(np.asarray(gj.gauss_radau(k + 1).points), T / ns[0], 8)
    np.testing.assert_allclose(nodal_states(sol, 2 * len(ns), 8), radau, rtol=0, atol=1e-12)


def test_galerkin_vi_has_order_2s_and_lagrangian_vi_equals_it():
    """GalerkinVI(s) [Tang, eqs. (2.21), (2.34)-(2.35)], s = 3: order 2s (Corollary 2.1) with
    s + 1 Gauss and s + 1 Lobatto points (measured 5.990 and 6.044; margin 0.1). LagrangianVI(3)
    [Tang, eqs. (2.16)-(2.17)] on L = qdot^T M qdot / 2 - U(q) is the same scheme [Tang, Section
    3]: every state of its runs equals GalerkinVI's (measured 1.1e-15; bound 1e-13). s = 1, 2
    (orders 2, 4 on Kepler) and LagrangianVI(2) = GalerkinVI(2) on another L run in the default
    tier too: test_reproduce.py (``tang_order``, ``tang_equivalence``)."""
    s, ns = 3, NS[3]
    rule = gj.gauss_legendre(s + 1)
    sol, errors = runs([gj.GalerkinVI(s, rule), gj.GalerkinVI(s, gj.gauss_lobatto(s + 1))], ns)
    for e in errors:
        assert order(ns, e) == pytest.approx(2 * s, abs=0.1)
    lagrangian, _ = runs([gj.LagrangianVI(s, rule)], ns, f=L)
    np.testing.assert_allclose(lagrangian.q, sol.q[: len(ns)], rtol=0, atol=1e-13)
    np.testing.assert_allclose(lagrangian.p, sol.p[: len(ns)], rtol=0, atol=1e-13)


def test_galerkin_vi_is_symmetric():
    """Phi_{-h}(Phi_h(z)) = z [Tang, Corollary 2.1] for GalerkinVI(2) with 3 Gauss and 3 Lobatto
    points, Phi_{-h} being the step of -H with h (one program, H's sign its argument): measured
    1.1e-16 after a step that moves the state by at least 0.048; bound 1e-14, where an order-4
    method that is not symmetric is off by O(h^5) ~ 1e-4."""
    signed = lambda q, p, sign: sign * H(q, p)
    methods = gj.stack_methods([gj.GalerkinVI(2, gj.gauss_legendre(3)), gj.GalerkinVI(2, gj.gauss_lobatto(3))])
    step = jax.jit(jax.vmap(lambda m, q, p, sign: gj.step(signed, q, p, method=m, h=0.2, args=sign),
                            in_axes=(0, 0, 0, None)))
    q1, p1 = step(methods, jnp.stack([Q0, Q0]), jnp.stack([P0, P0]), 1.0)
    q2, p2 = step(methods, q1, p1, -1.0)
    z0 = np.concatenate([Q0, P0])[None]
    back = np.abs(np.concatenate([q2, p2], axis=1) - z0)
    assert np.abs(np.concatenate([q1, p1], axis=1) - z0).min() > 0.04  # a step that moves (measured 0.048)
    assert back.max() < 1e-14, back


VERLET = gj.GalerkinVI(1, gj.trapezoid())


def test_symplecticity():
    """max |A^T J A - J| of the step's Jacobian A (jacfwd through the solve) at h = 0.3: round-off
    for Gauss collocation (cG(2) with 2 Gauss points), for LagrangianVI(2) (the map of a discrete
    Lagrangian, [Tang, Section 2.1.1, eq. (2.5)]), for Stormer-Verlet, a splitting and a composition (measured at most 4.4e-16; bound 1e-13);
    not for cG(2) with 4 Gauss points, which conserves H instead (Theorem 3.1; measured 3.5e-5,
    bound 1e-6). GalerkinVI's and dG(1)'s: test_reproduce.py (``tang_symplecticity``)."""
    defect = lambda method, f=H: helpers.symplecticity_defect(gj.amplification_matrix(f, Q0, P0, method=method, h=0.3))
    cg = jax.vmap(lambda m: gj.amplification_matrix(H, Q0, P0, method=m, h=0.3))(
        gj.stack_methods([gj.CG(2, gj.gauss_legendre(2)), gj.CG(2, gj.gauss_legendre(4))]))
    symplectic = {"cG(2) Gauss 2": helpers.symplecticity_defect(cg[0]),
                  "LagrangianVI(2) Gauss 3": defect(gj.LagrangianVI(2, gj.gauss_legendre(3)), L),
                  "Verlet": defect(VERLET), "blanes_moan6": defect(gj.Splitting("blanes_moan6")),
                  "kahan_li8": defect(gj.Composition(VERLET, "kahan_li8"))}
    assert max(symplectic.values()) < 1e-13, symplectic
    assert helpers.symplecticity_defect(cg[1]) > 1e-6


# (method, order, step counts, margin). Measured: 2.002; 4.005, 6.063, 4.005, 5.937; 3.978, 5.974,
# 8.231. kahan_li8's slope falls to 8 from above as h falls (8.7 from T / 8 to T / 16, 8.4 from
# T / 12 to T / 24, 8.1 from T / 24 to T / 48) and meets round-off first: its margin 0.35 still
# tells 8 from 7 and 9.
EXPLICIT = {
    "Verlet": (VERLET, 2, (32, 64, 128), 0.15),
    "blanes_moan4": (gj.Splitting("blanes_moan4"), 4, (16, 32, 64), 0.15),
    "blanes_moan6": (gj.Splitting("blanes_moan6"), 6, (8, 16, 32), 0.15),
    "blanes_moan_rkn4": (gj.Splitting("blanes_moan_rkn4"), 4, (16, 32, 64), 0.15),
    "blanes_moan_rkn6": (gj.Splitting("blanes_moan_rkn6"), 6, (8, 16, 32), 0.15),
    "yoshida4": (gj.Composition(VERLET, "yoshida4"), 4, (16, 32, 64), 0.15),
    "kahan_li6": (gj.Composition(VERLET, "kahan_li6"), 6, (8, 16, 32), 0.15),
    "kahan_li8": (gj.Composition(VERLET, "kahan_li8"), 8, (12, 24, 48), 0.35),
}


@pytest.mark.parametrize("name", EXPLICIT)
def test_explicit_paths_have_their_orders(name):
    """Stormer-Verlet as GalerkinVI(1, trapezoid()) [Tang, eq. (2.21) with the trapezoidal
    rule], Blanes and Moan's splittings and compositions of Verlet: no Newton iteration (H is
    separable), and the scheme's order at the nodes."""
    method, expected, ns, margin = EXPLICIT[name]
    sol, (errors,) = runs([method], ns)
    assert np.all(np.asarray(sol.stats["num_newton_iterations"]) == 0)
    assert order(ns, errors) == pytest.approx(expected, abs=margin)


@pytest.mark.parametrize("method", [gj.ModifiedMidpoint(), gj.DiscreteGradient()], ids=["modified", "discrete-gradient"])
def test_energy_momentum_schemes_conserve_energy_and_have_order_2(method):
    """Kepler (e = 0.5), a central force, one program over h = 2 pi / 64, / 128, / 256: the
    modified midpoint rule [GBS, eqs. (90)-(91)] keeps H and the angular momentum to round-off
    (Prop. 4.6, Cor. 4.10; measured 1.8e-15 and 3.3e-16), the discrete gradient H (4.0e-15;
    its angular momentum drifts, 8e-3); bound 1e-13, a random walk of eps per step over 256
    steps being ~4e-15. Both have order 2 against the exact orbit (measured 2.008, 2.009;
    margin 0.1)."""
    Hk, q0, p0 = helpers.kepler(0.5)
    period, ns = 2 * np.pi, (64, 128, 256)
    sol = jax.vmap(lambda h: gj.integrate(Hk, q0, p0, method=method, h=h, n_steps=max(ns), error_estimate=False))(
        jnp.asarray([period / n for n in ns]))
    assert np.all(np.asarray(sol.status) == 0)
    energy = np.asarray(jax.vmap(jax.vmap(Hk))(sol.q, sol.p))
    q, p = np.asarray(sol.q), np.asarray(sol.p)
    momentum = q[..., 0] * p[..., 1] - q[..., 1] * p[..., 0]
    qe, pe = helpers.kepler_exact(period)
    errors = [max(np.abs(sol.q[j, n] - qe).max(), np.abs(sol.p[j, n] - pe).max()) for j, n in enumerate(ns)]
    assert helpers.fitted_order([period / n for n in ns], errors) == pytest.approx(2, abs=0.1)
    assert np.abs(energy / energy[:, :1] - 1).max() < 1e-13
    if isinstance(method, gj.ModifiedMidpoint):
        assert np.abs(momentum - momentum[:, :1]).max() < 1e-13
