"""The energy-momentum schemes: modified midpoint [GBS, eqs. (90)-(91)] and the discrete gradient."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, V, Q0, P0 = helpers.quartic()


def energy_and_momentum(method, H, q0, p0, h, n_steps):
    sol = gj.integrate(H, q0, p0, method=method, h=h, n_steps=n_steps)
    assert int(sol.status) == 0
    energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
    return sol, np.abs(energy / energy[0] - 1).max()


def test_modified_midpoint_conserves_energy_and_angular_momentum_over_1e4_steps():
    """Prop. 4.6 and Cor. 4.10 on the quartic scene (Figs. 4.6-4.7). Measured 6.6e-15 and 5.3e-15."""
    sol, energy_error = energy_and_momentum(gj.ModifiedMidpoint(), H, Q0, P0, 0.01, 10_000)
    L = np.asarray(jnp.cross(sol.q, sol.p))
    assert energy_error < 1e-13  # round-off: ~eps per step as a random walk over 10^4 steps
    assert np.abs(L - L[0]).max() / np.abs(L[0]).max() < 1e-13


@functools.cache
def discrete_gradient_run():
    """10^4 steps of the default discrete gradient on the quartic scene (h = 0.01), shared by two tests."""
    return energy_and_momentum(gj.DiscreteGradient(), H, Q0, P0, 0.01, 10_000)


def test_discrete_gradient_conserves_energy_over_1e4_steps():
    """Measured 5.8e-15 relative (1.2e-14 with the excess from H values; 3.9e-14 before the line
    rule's pairs were symmetric and the element took one more update): the solve iterates to
    its round-off floor, so each step adds only round-off, a random walk over 10^4 steps
    (6e-13 with the earlier stop at 10 eps); a plain midpoint rule is off by 5e-2."""
    _, energy_error = discrete_gradient_run()
    assert energy_error < 3e-13


def test_discrete_gradient_line_integral_and_h_values_give_one_scheme():
    """The excess from the line integral (default) and from H values (``line_points=0``) is the
    same number up to round-off, so both runs follow one trajectory (measured 1.1e-13 apart
    after 200 steps on the quartic scene; bound 9x); m = 1 has no check."""
    assert gj.DiscreteGradient().line_points == 6
    line_integral = np.asarray(discrete_gradient_run()[0].q[:201])  # its first 200 steps
    h_values = gj.integrate(H, Q0, P0, method=gj.DiscreteGradient(line_points=0), h=0.01, n_steps=200)
    assert np.abs(line_integral - np.asarray(h_values.q)).max() < 1e-12
    for bad in (1, -1, 2.0, True):
        with pytest.raises(ValueError, match="line_points"):
            gj.DiscreteGradient(line_points=bad)


def test_line_rules_are_symmetric_about_the_midpoint_to_the_last_bit():
    """The Gauss rules of the line integrals (``_excess``, ``_radial_slope``): points in pairs
    alpha, 1 - alpha that sum to 1 exactly, with equal weights, so that every odd moment about
    1/2 is zero, in float64 and in float32. Rounded one by one (before), two of the 6-point
    rule's pairs missed by 5.6e-17 and its first moment was 8.2e-18: an error of one sign in the
    discrete gradient's excess through every perihelion passage, which drifted Kepler's energy
    linearly (test_accuracy.py, test_discrete_gradient_energy_error_is_a_random_walk)."""
    from fractions import Fraction

    from galerkin_jax._midpoint import _off_midpoint_gauss

    def check(points, weights):
        x, w = [Fraction(float(a)) for a in points], [Fraction(float(b)) for b in weights]
        assert all(x[i] + x[-1 - i] == 1 and w[i] == w[-1 - i] for i in range(len(x)))
        for k in (1, 3, 5):
            assert sum(wi * (xi - Fraction(1, 2)) ** k for xi, wi in zip(x, w)) == 0

    for m in range(2, 11):
        check(*_off_midpoint_gauss(m))
    for m in range(2, 11):
        points, weights = _off_midpoint_gauss(m, np.float32)
        assert points.dtype == weights.dtype == np.float32
        check(points, weights)


@pytest.mark.parametrize("scene", ["non-separable", "pendulum"])
def test_discrete_gradient_conserves_energy_of_non_central_hamiltonians(scene):
    H_any, q0, p0 = {"non-separable": helpers.non_separable(), "pendulum": helpers.pendulum()}[scene]
    _, energy_error = energy_and_momentum(gj.DiscreteGradient(), H_any, q0, p0, 0.1, 2000)
    _, midpoint_error = energy_and_momentum(gj.CG(1, gj.midpoint()), H_any, q0, p0, 0.1, 2000)
    assert energy_error < 1e-13 < midpoint_error


def test_radial_slope_is_accurate_to_round_off_as_the_radii_meet():
    """(V2 - V1) / (r2^2 - r1^2) for Kepler's V = -1/r against its closed form
    1 / (r1 r2 (r1 + r2)), for relative changes of radius from 1e-14 to 1 of either sign.
    Measured at most 9 eps; the quotient of V values, used before where the radii differ by more
    than eps^(1/3), was off by up to 86 000 eps there (round-off ~eps |V| / |r2^2 - r1^2|):
    noise in the residual that the root finder cannot iterate below. Bound 16 eps."""
    from galerkin_jax._midpoint import _radial_slope

    potential = lambda q: -1.0 / jnp.sqrt(q @ q)
    q1, aside = jnp.array([1.3, 0.2]), jnp.array([0.0, 1e-3])
    x = np.concatenate([-np.logspace(-14, -0.3, 200), np.logspace(-14, 0, 200)])
    slope = jax.jit(jax.vmap(lambda x: _radial_slope(potential, q1, q1 * (1 + x) + aside * x)))(jnp.asarray(x))
    r1 = np.linalg.norm(q1)
    r2 = np.linalg.norm(np.asarray(q1)[None] * (1 + x[:, None]) + np.asarray(aside)[None] * x[:, None], axis=1)
    exact = 1.0 / (r1 * r2 * (r1 + r2))
    assert np.abs(np.asarray(slope) / exact - 1).max() < 16 * np.finfo(float).eps


def test_circular_orbit_takes_the_derivative_limit_smoothly():
    """r2 = r1 on a circular orbit: (V2 - V1) / (r2^2 - r1^2) is the mean of dV/d(r^2), whose
    limit is V'(r) / (2r)."""
    m, c, r = 2.0, 1000.0, 1.5
    speed = np.sqrt(2 * c * r * (r * r - 1) * r / m)  # m v^2 / r = V'(r)
    q0, p0 = jnp.array([r, 0.0, 0.0]), jnp.array([0.0, m * speed, 0.0])
    sol, energy_error = energy_and_momentum(gj.ModifiedMidpoint(), H, q0, p0, 0.001, 1000)
    radius = np.linalg.norm(np.asarray(sol.q), axis=1)
    assert energy_error < 1e-13 and np.ptp(radius) < 1e-12
    # the step stays differentiable through the switch
    grad = jax.grad(lambda q: gj.step(H, q, p0, method=gj.ModifiedMidpoint(), h=0.001)[0].sum())(q0)
    assert np.all(np.isfinite(np.asarray(grad)))


@pytest.mark.parametrize("method", [gj.ModifiedMidpoint(), gj.DiscreteGradient()], ids=["modified", "discrete-gradient"])
def test_equilibrium_gives_a_zero_increment_and_finite_gradients(method):
    """q1 == q0 exactly at rest on r = 1: the 0/0 branches must give 0, not NaN."""
    q0, p0 = jnp.array([1.0, 0.0, 0.0]), jnp.zeros(3)
    q1, p1 = gj.step(H, q0, p0, method=method, h=0.01)
    np.testing.assert_array_equal(np.concatenate([q1, p1]), np.concatenate([q0, p0]))
    grad = jax.grad(lambda q: gj.step(H, q, p0, method=method, h=0.01)[0].sum())(q0)
    assert np.all(np.isfinite(np.asarray(grad)))


@pytest.mark.parametrize("method", [gj.ModifiedMidpoint(), gj.DiscreteGradient()], ids=["modified", "discrete-gradient"])
def test_energy_momentum_schemes_are_second_order(method):
    H_kep, q0, p0 = helpers.kepler(0.5)
    T, ns = 2 * np.pi, [256, 512, 1024]
    sol = jax.vmap(lambda h: gj.integrate(H_kep, q0, p0, method=method, h=h, n_steps=max(ns)))(jnp.array([T / n for n in ns]))
    q_exact, p_exact = helpers.kepler_exact(T)
    errors = [max(np.abs(sol.q[j, n] - q_exact).max(), np.abs(sol.p[j, n] - p_exact).max()) for j, n in enumerate(ns)]
    assert helpers.fitted_order([T / n for n in ns], errors) == pytest.approx(2, abs=0.1)
