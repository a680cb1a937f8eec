"""The a posteriori error estimate, dense output, the choice of h, and round-off at Brouwer's limit."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

E = 0.6
H, Q0, P0 = helpers.kepler(E)
STARTS = np.linspace(0.0, 2 * np.pi, 7)[:-1]  # perihelion, aphelion and four points between
METHODS = {
    "cG(1) midpoint": gj.CG(1, gj.midpoint()),
    "cG(2) Gauss 2": gj.CG(2, gj.gauss_legendre(2)),
    "cG(2) Lobatto 3": gj.CG(2, gj.gauss_lobatto(3)),
    "dG(1) Gauss 3": gj.DG(1, gj.gauss_legendre(3)),
    "GalerkinVI(2) Gauss 3": gj.GalerkinVI(2, gj.gauss_legendre(3)),
    "DiscreteGradient": gj.DiscreteGradient(),
    "cG(1) one point at 0.3": gj.CG(1, gj.QuadratureRule([0.3], [1.0])),
}
# local orders (the exponent of h in the local error): 2k + 1 for cG(k) with exact enough
# quadrature, 2k + 2 for dG(k), 2s + 1 for GalerkinVI(s), 3 for the midpoint schemes, 2 for
# one non-symmetric point (order 1). cG(2) with Lobatto 3 has no order claimed here (measured
# slopes 4.4 to 4.7 on these h): its estimate ratio is what is checked.
ORDERS = {"cG(1) midpoint": 3, "cG(2) Gauss 2": 5, "cG(2) Lobatto 3": None, "dG(1) Gauss 3": 4,
          "GalerkinVI(2) Gauss 3": 5, "DiscreteGradient": 3, "cG(1) one point at 0.3": 2}
STEPS = [0.1, 0.05, 0.025]


def local_errors(method, h):
    """(true, estimated) local errors of one element from six exact states of the orbit."""
    starts = [helpers.kepler_exact(t, E) for t in STARTS]
    ends = np.array([np.concatenate(helpers.kepler_exact(t + h, E)) for t in STARTS])
    q0s, p0s = (jnp.asarray(np.array(x)) for x in zip(*starts))
    sol = jax.vmap(lambda q, p: gj.integrate(H, q, p, method=method, h=h, n_steps=1))(q0s, p0s)
    assert np.all(np.asarray(sol.status) == 0)
    true = np.abs(np.concatenate([sol.q[:, -1], sol.p[:, -1]], axis=1) - ends).max(axis=1)
    return true, np.asarray(sol.error_estimate)


@pytest.mark.parametrize("name", METHODS)
def test_the_estimate_tracks_the_true_local_error_at_the_methods_order(name):
    """The truncated Alekseev-Groebner formula gives the leading term of the local error, so
    estimate / true -> 1 (measured 0.983 to 1.024 over these points and h; 'never under by
    more than 2x' is the contract), and the estimate falls at the local order (measured 2.98,
    5.13, 3.85, 4.97, 2.93, 1.86)."""
    true, estimate = zip(*(local_errors(METHODS[name], h) for h in STEPS))
    ratios = np.array(estimate) / np.array(true)
    assert ratios.min() > 0.9 and ratios.max() < 1.1
    order = helpers.fitted_order(STEPS, [e.max() for e in estimate], floor=1e-13)
    if ORDERS[name] is not None:
        assert order == pytest.approx(ORDERS[name], abs=0.3)  # Kepler e = 0.6 is not yet asymptotic at h = 0.1


def test_the_estimate_is_large_for_a_step_that_means_nothing():
    """cG(1) + midpoint at h = 3 on Kepler (half the period): the solves converge (status 0)
    but the step is meaningless; the estimate says so (measured 4.8 for an O(1) state)."""
    sol = gj.integrate(H, Q0, P0, method=gj.CG(1, gj.midpoint()), h=3.0, n_steps=20)
    assert int(sol.status) == 0
    assert float(sol.error_estimate) > 1.0


def test_sweep_and_integrate_give_the_same_estimate_and_lagrangian_vi_gives_nan():
    method = gj.CG(2, gj.gauss_legendre(2))
    result = gj.sweep(H, gj.grid(method=method, h=[0.05, 0.1], state=(Q0, P0)), n_steps=40)
    for i, h in enumerate([0.05, 0.1]):
        sol = gj.integrate(H, Q0, P0, method=method, h=h, n_steps=40)
        assert float(result.error_estimate[i]) == pytest.approx(float(sol.error_estimate), rel=1e-12)
    skipped = gj.integrate(H, Q0, P0, method=method, h=0.1, n_steps=40, error_estimate=False)
    assert np.isnan(float(skipped.error_estimate))
    np.testing.assert_array_equal(skipped.q, sol.q)  # the estimate never feeds back into the run
    L = lambda q, v: 0.5 * (v @ v) + 1.0 / jnp.sqrt(q @ q)
    assert np.isnan(float(gj.integrate(L, Q0, P0, method=gj.LagrangianVI(1, gj.midpoint()), h=0.05, n_steps=4).error_estimate))


@pytest.mark.parametrize("k", [1, 2, 3])
def test_dense_output_between_the_nodes_has_the_nodes_local_order_and_the_states_at_nodes(k):
    """Within one element from an exact state, cG(k)'s dense output (the element polynomial
    refined, ``_output.refined``) is as far off the exact solution as the node z1 is: the same
    fitted order near 2k + 1 (measured 2.88, 4.87, 6.74, within 0.013 of z1's; the margin 0.1
    is far below the gap to the k + 1 an unrefined polynomial shows), and below 1.2 times z1's
    error (measured 0.80 to 0.95). At the nodes ``evaluate`` returns the saved states."""
    method = gj.CG(k, gj.gauss_legendre(k))
    alphas = np.linspace(0.0, 1.0, 9)[1:-1]
    inside, node = [], []
    for h in STEPS:
        q0, p0 = (jnp.asarray(x) for x in helpers.kepler_exact(0.7, E))
        sol = gj.integrate(H, q0, p0, method=method, h=h, n_steps=2, dense=True)
        q, p = sol.evaluate(alphas * h)
        exact = np.array([np.concatenate(helpers.kepler_exact(0.7 + a * h, E)) for a in alphas])
        inside.append(np.abs(np.concatenate([q, p], axis=1) - exact).max())
        z1 = np.concatenate(helpers.kepler_exact(0.7 + h, E))
        node.append(np.abs(np.concatenate([sol.q[1], sol.p[1]]) - z1).max())
        nodes = sol.evaluate(sol.t)
        np.testing.assert_array_equal(nodes[0], sol.q)
        np.testing.assert_array_equal(nodes[1], sol.p)
        assert sol.evaluate(0.5 * h)[0].shape == (2,)
    fitted = helpers.fitted_order(STEPS, inside, floor=1e-15)
    assert fitted == pytest.approx(helpers.fitted_order(STEPS, node, floor=1e-15), abs=0.1)
    assert fitted == pytest.approx(2 * k + 1, abs=0.4)
    assert np.all(np.array(inside) < 1.2 * np.array(node))


def test_evaluate_rejects_times_outside_the_run_and_runs_without_dense_output():
    # the runs (n_steps, dense) of the tests above: cG(1) with the midpoint rule is
    # cG(1, gauss_legendre(1)), so no program is compiled for this test
    sol = gj.integrate(H, Q0, P0, method=gj.CG(1, gj.midpoint()), h=0.1, n_steps=2, dense=True)
    with pytest.raises(ValueError, match="lie in"):
        sol.evaluate(0.5)
    with pytest.raises(ValueError, match="dense=True"):
        gj.integrate(H, Q0, P0, method=gj.CG(1, gj.midpoint()), h=0.1, n_steps=20).evaluate(0.1)


def test_suggested_step_meets_the_tolerance_over_the_orbit():
    """Pilot runs over the perihelion passage (t in [0, 1]); the chosen h keeps every
    element's estimate of one orbit below the tolerance (measured 1.6e-11 for 1e-10), and
    the step is not needlessly small (the estimate within 20x of the tolerance)."""
    method = gj.CG(3, gj.gauss_legendre(3))
    h, info = gj.suggest_step_size(H, Q0, P0, method=method, tolerance=1e-10, h=0.1, span=1.0)
    assert info["order"] == pytest.approx(7, abs=1)
    n = int(2 * np.pi / h)
    estimate = float(gj.integrate(H, Q0, P0, method=method, h=h, n_steps=n, save_every=n).error_estimate)
    assert 5e-12 < estimate <= 1e-10


@pytest.mark.parametrize("name, method, n, bound", [
    ("DiscreteGradient", gj.DiscreteGradient(), 200_000, 1e-14),
    ("ModifiedMidpoint", gj.ModifiedMidpoint(), 200_000, 2e-14),
    ("cG(3) Gauss 6", gj.CG(3, gj.gauss_legendre(6)), 100_000, 2e-14),
])
def test_energy_round_off_grows_no_faster_than_sqrt_n(name, method, n, bound):
    """Kepler e = 0.6, h = 0.01: the solves iterate to their round-off floor and polish the
    accepted iterate, the state sums its increments with compensation, and the discrete
    gradient and the modified midpoint rule take their differences of H and V from resolved line
    integrals, so round-off is a random walk (Brouwer's law: eps sqrt(n) = 1e-13 at n = 2e5).
    Measured max |dH/H| for h = 0.01, 0.00999, 0.01001: DiscreteGradient 5.6e-15, 6.2e-15,
    3.0e-15 after 2e5 steps (4.7e-15, 3.6e-15, 5.3e-15 before its line rule was made symmetric
    and it took one more update; without the polish 2.3e-14, 2.2e-14, 1.9e-14; with the excess
    from H values, before: 2.7e-13 at 1e5); ModifiedMidpoint 4.7e-15, 5.3e-15, 4.0e-15
    (5.8e-15, 4.9e-15, 1.8e-15 with the line rule's pairs rounded one by one; with the quotient
    of V values near the apsides, before: 5.7e-14 to 1.4e-13, 34 elements accepted stalled, up
    to 31 iterations, and one failed element under another code generation); cG(3) 6.2e-15,
    4.4e-15, 2.2e-15 after 1e5. Bounds ~1.6x, 3.8x and 3x above the largest. Every element
    converges in at most 10 (ModifiedMidpoint), 12 (DiscreteGradient) and 8 (cG(3))
    iterations, with at most one accepted stalled (DiscreteGradient): bounds of 16 and 4 leave
    a block's and a few elements' margin for other rounding."""
    sol = gj.integrate(H, Q0, P0, method=method, h=0.01, n_steps=n, save_every=n // 100)
    energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
    assert int(sol.status) == 0
    assert np.abs(energy / energy[0] - 1).max() < bound
    assert int(sol.stats["max_newton_iterations"]) <= 16 and int(sol.stats["num_accepted_stalled"]) <= 4


def test_discrete_gradient_energy_error_is_a_random_walk():
    """Brouwer's law for the discrete gradient on Kepler e = 0.6, four h from 0.0099 to 0.0101,
    10^6 steps each: the spread S(L) of the energy error's change over L steps (RMS over the
    runs and every start), L = 1e4 to 1e6, grows like L^gamma, gamma = 1/2 for round-off that
    is unbiased and up to 1 for a drift. Measured here 0.42 (the suite's compile flags); before
    the line rule's pairs were made symmetric and the element got one more fixed-point update
    (``DiscreteGradient.settle``) 0.75, a drift of -5e-5 eps a step (max |dH/H| 2.1e-14 after
    10^6 steps, 2.1e-13 after 10^7). Over 12 runs at h within 1 % of 0.01, every 4 of them:
    0.42 +- 0.09 (at most 0.56) now, 0.72 +- 0.03 (at least 0.63) before; the bound 0.6 lies
    2 sigma above the one and 4 below the other. gamma comes out under 1/2 where the error's
    bounded part (the rounding of the state) weighs on the short lags. About 11 s (21 s on a
    loaded machine)."""
    n, every = 1_000_000, 1000
    run = lambda h: gj.integrate(H, Q0, P0, method=gj.DiscreteGradient(), h=h, n_steps=n, save_every=every)
    sol = jax.vmap(run)(jnp.linspace(0.0099, 0.0101, 4))
    assert np.all(np.asarray(sol.status) == 0)
    q, p = (np.asarray(x).astype(np.longdouble) for x in (sol.q, sol.p))  # H to ~1e-19 where it is 80-bit
    energy = 0.5 * (p**2).sum(-1) - 1.0 / np.sqrt((q**2).sum(-1))
    error = (energy / energy[:, :1] - 1).astype(float)
    lags = np.array([10, 30, 100, 300, 1000])  # in saved states: L = 1e4 to 1e6 steps
    spread = [np.sqrt(np.mean((error[:, L:] - error[:, :-L]) ** 2)) for L in lags]
    gamma = np.polyfit(np.log10(lags), np.log10(spread), 1)[0]
    assert 0.1 < gamma < 0.6


def test_step_and_amplification_matrix_report_a_failed_solve_as_nan():
    """q' = q^2 + 1 from q0 = 1 with h = 1 has no element solution (test_integrate)."""
    blowup = lambda q, p: p[0] * (q[0] ** 2 + 1.0)
    q0, p0, method = jnp.array([1.0]), jnp.array([1.0]), gj.CG(1, gj.midpoint())
    assert np.isnan(np.asarray(gj.amplification_matrix(blowup, q0, p0, method=method, h=1.0))).all()
    assert np.isfinite(np.asarray(gj.amplification_matrix(blowup, q0, p0, method=method, h=0.01))).all()
    assert int(gj.integrate(blowup, q0, p0, method=method, h=1.0, n_steps=1).status) != 0
    assert "error_estimate" in gj.status_message(0)


def test_tangents_are_masked_by_status_not_by_value():
    """The implicit-function tangent of a converged solve passes a NaN on (an honest NaN
    gradient); a failed solve contributes zero whatever its Jacobian."""
    from galerkin_jax._solve import implicit

    fn = lambda Z, c: Z - c * jnp.sqrt(Z)  # at Z = 0, c = 0: dR/dZ = 1 - 0 / 0, a NaN Jacobian
    tangent = lambda ok: jax.jvp(lambda c: implicit(fn, 256, c, jnp.zeros(1), ok), (0.0,), (1.0,))[1]
    assert np.isnan(float(tangent(jnp.asarray(True))[0]))
    assert float(tangent(jnp.asarray(False))[0]) == 0.0
