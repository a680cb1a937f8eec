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
    ``bench_solver.py``'s); asserted with room: at least one update fewer per element. The
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
