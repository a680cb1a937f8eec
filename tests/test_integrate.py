"""Stepping, saving, status codes and input validation of step / integrate."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H_OSC, Q_OSC, P_OSC, OMEGA = helpers.oscillator()
H_KEP, Q_KEP, P_KEP = helpers.kepler(0.5)
CG2 = gj.CG(2, gj.gauss_legendre(3))


def blowup(q, p):
    """H = p (q^2 + 1): q' = q^2 + 1 (q = tan(t + c)), p' = -2 q p."""
    return p[0] * (q[0] ** 2 + 1.0)


def test_save_every_stores_every_nth_state_of_the_full_run():
    full = gj.integrate(H_KEP, Q_KEP, P_KEP, method=CG2, h=0.05, n_steps=40)
    thin = gj.integrate(H_KEP, Q_KEP, P_KEP, method=CG2, h=0.05, n_steps=40, save_every=8)
    assert thin.q.shape == (6, 2) and thin.t.shape == (6,)
    np.testing.assert_allclose(thin.t, full.t[::8], rtol=1e-15)
    # same elements, same predictors: equal to the last bits
    np.testing.assert_array_equal(thin.q, full.q[::8])
    np.testing.assert_array_equal(thin.p, full.p[::8])


def test_integrate_one_step_equals_step():
    sol = gj.integrate(H_KEP, Q_KEP, P_KEP, method=CG2, h=0.1, n_steps=1)
    q1, p1 = gj.step(H_KEP, Q_KEP, P_KEP, method=CG2, h=0.1)
    np.testing.assert_allclose(sol.q[1], q1, atol=1e-15)
    np.testing.assert_allclose(sol.p[1], p1, atol=1e-15)
    # Newton from the constant state: measured 4 iterations (the last confirms the floor)
    assert int(sol.status) == 0 and int(sol.stats["max_newton_iterations"]) <= 5


def test_args_reach_the_hamiltonian():
    # one H and one compiled run for both args (traced): H(., ., c) is H_OSC at c = OSC_C only
    H = lambda q, p, c: p @ p / (2 * helpers.OSC_M) - 0.5 * c * (q @ q)
    a = gj.integrate(H, Q_OSC, P_OSC, method=CG2, h=0.1, n_steps=5, args=-0.5)
    b = gj.integrate(H_OSC, Q_OSC, P_OSC, method=CG2, h=0.1, n_steps=5)
    # H_OSC = |p|^2/4 + |q|^2/8 has another stiffness: equal trajectories would mean args were ignored
    assert np.abs(a.q - b.q).max() > 1e-3
    c = gj.integrate(H, Q_OSC, P_OSC, method=CG2, h=0.1, n_steps=5, args=helpers.OSC_C)
    np.testing.assert_allclose(c.q, b.q, atol=1e-15)


def test_iterations_per_element_with_the_extrapolating_predictor():
    """The first element of a small system is solved by Newton from the constant state, the
    next ones by the fixed point from the extrapolating predictor, unless that takes more than
    12 iterations or contracts at a rate above 0.5. Linear scene (h omega = 0.35): the fixed
    point contracts at 0.18, the second element takes 14 iterations, and the run switches to
    Newton for good, which then takes 1 solve + 1 confirming iteration (measured mean 2.24,
    max 14). Kepler, h = 0.05: the fixed point, measured mean 6.05, max 12 (perihelion; 7.23
    and 16 with the linear extrapolation of the predictor's misses alone). The
    quartic scene of [GBS, Fig. 4.6] (h omega ~ 1 at h = 0.01, omega^2 = V''(2) / m = 11000,
    where no polynomial predictor is accurate) with dG(1), whose Jacobian at h = 0 is not I,
    so that the fixed point cannot contract: Newton, measured mean 5.8, max 8."""
    osc = gj.integrate(H_OSC, Q_OSC, P_OSC, method=gj.CG(1, gj.midpoint()), h=1.0, n_steps=50)
    assert int(osc.stats["max_newton_iterations"]) <= 16
    assert int(osc.stats["num_newton_iterations"]) / 50 <= 2.5
    kepler = gj.integrate(H_KEP, Q_KEP, P_KEP, method=CG2, h=0.05, n_steps=200)
    assert int(kepler.stats["max_newton_iterations"]) <= 16
    assert int(kepler.stats["num_newton_iterations"]) / 200 <= 7.5
    H_quartic, _, q0, p0 = helpers.quartic()
    quartic = gj.integrate(H_quartic, q0, p0, method=gj.DG(1, gj.gauss_legendre(2)), h=0.01, n_steps=200)
    assert int(quartic.status) == 0
    assert int(quartic.stats["max_newton_iterations"]) <= 10
    assert int(quartic.stats["num_newton_iterations"]) / 200 <= 6.5


def test_step_with_no_real_solution_reports_failure():
    """cG(1) + midpoint on q' = q^2 + 1 is q1 - q0 = h (m^2 + 1), m = (q0 + q1) / 2.

    With q1 = 2m - q0 this is h m^2 - 2 m + (2 q0 + h) = 0, whose discriminant
    4 - 4 h (2 q0 + h) is negative for q0 = 1, h = 1: no real m, so no real q1.
    """
    method = gj.CG(1, gj.midpoint())
    q0, p0, h = jnp.array([1.0]), jnp.array([1.0]), 1.0
    assert 4 - 4 * h * (2 * q0[0] + h) < 0
    sol = gj.integrate(blowup, q0, p0, method=method, h=h, n_steps=20)  # the next test's program
    assert int(sol.status) in (gj.Status.NEWTON_MAX_ITERATIONS, gj.Status.NONFINITE)
    assert np.all(np.isnan(sol.q[1:])) and np.all(np.isnan(sol.p[1:]))
    assert np.all(np.isnan(np.asarray(gj.step(blowup, q0, p0, method=method, h=h))))
    # the same problem with a small h has a solution: the failure is not an artefact
    ok = gj.integrate(blowup, q0, p0, method=method, h=0.01, n_steps=20)
    assert int(ok.status) == 0 and np.all(np.isfinite(ok.q))


def test_first_failure_is_kept_and_later_states_are_nan():
    # q = tan(t + pi/4) blows up at t = pi/4 ~ 0.785: the run must fail there and stay failed
    sol = gj.integrate(blowup, jnp.array([1.0]), jnp.array([1.0]), method=gj.CG(1, gj.midpoint()), h=0.1, n_steps=20)
    assert int(sol.status) != 0
    first_bad = int(np.argmax(np.isnan(np.asarray(sol.q[:, 0]))))
    assert 3 <= first_bad <= 12
    assert np.all(np.isnan(sol.q[first_bad:]))


def test_a_run_that_produces_nan_never_reports_success():
    H_nan = lambda q, p, a: p @ p / 2 + a * jnp.sqrt(q @ q - 0.5)  # NaN where |q|^2 < 0.5
    sol = gj.integrate(H_nan, Q_KEP, P_KEP, method=CG2, h=0.1, n_steps=5, args=1.0)
    assert int(sol.status) == gj.Status.NONFINITE
    sol = gj.integrate(H_nan, Q_KEP, P_KEP, method=CG2, h=0.1, n_steps=5, args=jnp.nan)
    assert int(sol.status) != 0
    assert gj.status_message(sol.status)


def test_traced_invalid_inputs_are_reported_through_status():
    run = jax.jit(lambda h, q0: gj.integrate(H_KEP, q0, P_KEP, method=CG2, h=h, n_steps=3).status)
    assert int(run(0.1, Q_KEP)) == 0
    assert int(run(-0.1, Q_KEP)) == gj.Status.INVALID_INPUT
    assert int(run(0.1, Q_KEP.at[0].set(jnp.inf))) == gj.Status.INVALID_INPUT


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(q0=jnp.zeros(3)), ValueError, "same shape"),
        (dict(q0=jnp.zeros((2, 1))), ValueError, r"same shape, got \(2, 1\) and \(2,\)"),
        (dict(q0=jnp.array([jnp.nan, 0.0])), ValueError, "finite"),
        (dict(h=0.0), ValueError, "h must be finite and > 0"),
        (dict(h=-1.0), ValueError, "h must be finite and > 0"),
        (dict(h=jnp.ones(2)), ValueError, "scalar"),
        (dict(n_steps=10, save_every=3), ValueError, "multiple"),
        (dict(n_steps=2.5), ValueError, "n_steps"),
        (dict(H=lambda q, p: q + p), ValueError, "scalar"),
        (dict(H="not a function"), TypeError, "callable"),
        (dict(method="cg"), TypeError, "method"),
        (dict(max_newton_iterations=0), ValueError, "max_newton_iterations"),
    ],
)
def test_bad_input_raises_before_compilation(kwargs, error, match):
    call = dict(H=H_KEP, q0=Q_KEP, p0=P_KEP, method=CG2, h=0.1, n_steps=4)
    call.update(kwargs)
    H = call.pop("H")
    with pytest.raises(error, match=match):
        gj.integrate(H, call.pop("q0"), call.pop("p0"), **call)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: gj.CG(0, gj.midpoint()), "k >= 1"),
        (lambda: gj.DG(-1, gj.midpoint()), "k >= 0"),
        (lambda: gj.CG(1.5, gj.midpoint()), "integer"),
        (lambda: gj.CG(1, [0.5]), "QuadratureRule"),
    ],
)
def test_bad_methods_raise(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_an_option_a_program_ignores_compiles_nothing_again():
    """``integrate`` hands one frozen ``Run`` to the compiled program, whose static parts key its
    cache: the options a program does not read are normalised before (``_dispatch``), so
    ``progress`` and ``save_every`` of a controlled run reuse the program compiled without them
    (they were part of the key after the Run's first version)."""
    from galerkin_jax import _integrate

    CG2 = gj.CG(2, gj.gauss_legendre(2))
    pid = lambda **kw: gj.integrate(H_KEP, Q_KEP, P_KEP, method=CG2, h=0.05, t1=1.0,
                                    controller=gj.PIDController(1e-6, 1e-6), **kw)
    for run, program, options in ((pid, _integrate._integrate_adaptive, dict(progress=True, save_every=2)),):
        first = run()
        compiled = program._cache_size()
        again = run(**options)
        assert program._cache_size() == compiled
        np.testing.assert_array_equal(again.q, first.q)
