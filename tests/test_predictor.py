"""The predictor's extrapolation of the continuation's misses (``_march.miss_correction``) and
the Newton steps it starts (``_solve``: halving only with a matrix taken at the step's start)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers
from galerkin_jax import _march, scenes


@pytest.mark.parametrize("m", [2, 6])
def test_extrapolation_is_exact_for_polynomials_of_degree_below_its_order(m):
    """Newton's backward formula of order m: exact (to round-off) on a polynomial sequence of
    degree m - 1, off on one of degree m by m! h^m times the leading coefficient (h = 1)."""
    n = np.arange(m + 1, dtype=float)[::-1]  # the next term's index m first, the history after
    exact = n ** (m - 1) - 2.0 * n + 0.5
    misses = jnp.asarray(exact[1:])
    assert abs(float(_march._extrapolated(misses, m)) - exact[0]) < 1e-12 * math.factorial(m)
    beyond = n**m
    assert float(_march._extrapolated(jnp.asarray(beyond[1:]), m)) == pytest.approx(beyond[0] - math.factorial(m))


def test_the_correction_takes_the_order_that_came_closer():
    """A history of a degree-5 polynomial: order 6 predicted the latest term exactly, so the next
    correction is order 6's (exact again); a history whose latest term breaks the pattern,
    which the linear extrapolation came closer to, gets the linear one."""
    t = np.arange(8, dtype=float)[::-1]
    smooth = 1e-3 * (t**5 - 3 * t**2 + t)
    history, latest = jnp.asarray(smooth[2:]), jnp.asarray(smooth[1])
    _, correction = _march.miss_correction(history, latest, 10)
    assert float(correction) == pytest.approx(smooth[0], rel=1e-12)
    jump = 2 * smooth[2] - smooth[3]  # exactly the linear extrapolation's guess
    _, correction = _march.miss_correction(history, jnp.asarray(jump), 10)
    assert float(correction) == pytest.approx(2 * jump - smooth[2], rel=1e-12)


def test_an_order_competes_only_once_its_backtest_is_made_of_real_misses():
    """The history starts at zeros and element 0's miss is not real (nothing was continued).
    Misses s_n = c (n + 1)(n + 2)...(n + 5) continue the zeros as a polynomial of degree 5, so
    order 6 wins every backtest against them; yet element 0 gets no correction, element 1 its
    miss, elements 2 to 6 the linear extrapolation (off by O(c n^3)), and only from element 7,
    whose order-6 backtest is made of real misses, the exact order-6 one."""
    s = lambda n: 1e-3 * math.prod(n + i for i in range(1, 6))
    history = jnp.zeros(max(gj.SolverOptions().miss_orders))
    for n in range(10):
        history, correction = _march.miss_correction(history, jnp.asarray(s(n)), n)
        expected = 0.0 if n == 0 else s(1) if n == 1 else 2 * s(n) - s(n - 1) if n <= 6 else s(n + 1)
        assert float(correction) == pytest.approx(expected, rel=1e-12, abs=1e-18), n
        if 2 <= n <= 6:
            assert abs(expected - s(n + 1)) > 0.1  # the gate decided: order 6 would have been exact


def iterations(scene, method, h, n_steps, orders):
    """Iterations per element and the solution with the predictor's orders
    (``SolverOptions.miss_orders``) set to ``orders``."""
    solver = gj.SolverOptions(miss_orders=orders)
    sol = gj.integrate(scene.H, scene.q0, scene.p0, method=method, h=h, n_steps=n_steps, save_every=n_steps,
                       solver=solver)
    assert int(sol.status) == 0
    return float(sol.stats["num_newton_iterations"]) / n_steps, sol


def test_order_six_saves_fixed_point_blocks_where_the_misses_are_smooth():
    """Kepler e = 0.6, cG(3) + Gauss 3, h = 0.01: the choice of orders (2, 6) takes a block of
    two updates fewer in most elements than the linear extrapolation alone (the figures are
    the one-off ``solver`` study); asserted with room: at least one update fewer per element. The
    two runs agree to round-off (the same roots)."""
    scene = scenes.kepler(0.6)
    method = gj.CG(3, gj.gauss_legendre(3))
    linear, a = iterations(scene, method, 0.01, 2000, (2,))
    chosen, b = iterations(scene, method, 0.01, 2000, gj.SolverOptions().miss_orders)
    assert chosen <= linear - 1.0
    assert float(jnp.max(jnp.abs(a.q - b.q))) < 1e-12


def test_discrete_gradient_on_the_quartic_force_stays_far_from_the_cap():
    """The quartic force of [GBS, Fig. 4.6] at h = 0.01 (h omega up to ~1) with the discrete
    gradient, 10^4 steps: some elements start far from their root and need damped Newton.
    Halving steps with a matrix from an earlier iterate took one element to 48 iterations (the
    cap); with a matrix refreshed where the full step failed, measured max 20, mean 8.5 (17
    elements accepted at the stall floor, ``num_accepted_stalled``)."""
    H, _, q0, p0 = helpers.quartic()
    sol = gj.integrate(H, q0, p0, method=gj.DiscreteGradient(), h=0.01, n_steps=10_000, save_every=10_000)
    assert int(sol.status) == 0
    assert int(sol.stats["max_newton_iterations"]) <= 32
    assert float(sol.stats["num_newton_iterations"]) / 10_000 <= 9.5


@pytest.mark.parametrize("subtract_end", [False, True])
def test_the_continuation_over_a_longer_or_shorter_element_is_exact_for_polynomials(subtract_end):
    """``_basis.continuation(n, r)``: a Legendre series of degree n - 1 on [0, 1] continued over
    [1, 1 + r] and re-expanded on [0, 1], less its value at 1 with ``subtract_end``; at r = 1 the
    exact static ``shift_matrix``. Checked against the series evaluated directly."""
    from numpy.polynomial import legendre as npleg

    from galerkin_jax import _basis

    n = 5
    c = np.random.default_rng(0).normal(size=n)
    a = np.linspace(0.0, 1.0, 7)
    for r in (0.3, 1.0, 2.5):
        T = np.asarray(_basis.continuation(n, jnp.asarray(r), subtract_end))
        expected = npleg.legval(1.0 + 2.0 * r * a, c) - (npleg.legval(1.0, c) if subtract_end else 0.0)
        assert np.max(np.abs(npleg.legval(2.0 * a - 1.0, T @ c) - expected)) < 1e-13 * (1 + r) ** n
    assert np.max(np.abs(np.asarray(_basis.continuation(n, jnp.asarray(1.0), subtract_end))
                         - _basis.shift_matrix(n, subtract_end))) < 1e-13


@pytest.mark.parametrize("method", [gj.CG(3, gj.gauss_legendre(3)), gj.DG(2, gj.gauss_legendre(3)),
                                    gj.GalerkinVI(2, gj.gauss_legendre(3))], ids=["cG(3)", "dG(2)", "GalerkinVI(2)"])
def test_adaptive_steps_continue_the_last_element_over_the_next_ones_length(method):
    """Under a constant force (H = p^2 / 2 + q) the solution is a quadratic in t, which each of
    these elements reproduces exactly; the continued polynomial is then the next element's
    root whatever its length, if the continuation reaches over that length. The controller
    grows h by ``factormax`` every step (the estimate is round-off), so a continuation over
    the previous element's own length would miss by O(h^2). Each element after the first then
    takes the two updates of one check (measured: 24 updates for 10 elements, the first 4-6
    from the constant guess; continued over the previous length: 38-44)."""
    H = lambda q, p: 0.5 * jnp.sum(p**2) + jnp.sum(q)
    q0, p0 = jnp.asarray([0.0]), jnp.asarray([1.0])
    sol = gj.integrate(H, q0, p0, method=method, h=1e-3, t1=10.0,
                       controller=gj.PIDController(1e-8, 1e-8, factormax=3.0))
    steps = int(sol.stats["num_accepted_steps"]) + int(sol.stats["num_rejected_steps"])
    assert int(sol.status) == 0 and steps >= 6
    assert int(sol.stats["num_newton_iterations"]) <= 2 * steps + 4
    np.testing.assert_allclose(sol.q[-1], q0 + 10.0 * p0 - 50.0, rtol=1e-12)
