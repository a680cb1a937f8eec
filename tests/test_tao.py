"""Tao's extended phase space map for any H (gj.Tao): order, symmetry, energy, the binding omega,
and every path of a run computing the same map."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import galerkin_jax as gj
from galerkin_jax._tao import extended_map

import helpers


def tao_h(q, p):
    """H = (q^2 + 1)(p^2 + 1) / 2, Tao's first example: non-separable [Tao 2016, Sec. 5.1]."""
    return 0.5 * jnp.sum((q**2 + 1) * (p**2 + 1))


Q0, P0 = jnp.array([-3.0]), jnp.array([0.0])


def double_pendulum(q, p):
    """Two unit masses on unit rods, g = 1: a kinetic energy that reads q (non-separable)."""
    c, s = jnp.cos(q[0] - q[1]), jnp.sin(q[0] - q[1])
    return (p[0] ** 2 + 2 * p[1] ** 2 - 2 * p[0] * p[1] * c) / (2 * (1 + s**2)) - 2 * jnp.cos(q[0]) - jnp.cos(q[1])


DP_Q0, DP_P0 = jnp.array([1.0, 0.5]), jnp.array([0.0, 0.3])


def _reference(H, q0, p0, T):
    """DOP853 at rtol = atol = 1e-13 (its error here below 1e-11, far below the errors fitted)."""
    d = q0.shape[0]
    field = jax.jit(lambda z: jnp.concatenate([jax.grad(H, 1)(z[:d], z[d:]), -jax.grad(H, 0)(z[:d], z[d:])]))
    sol = solve_ivp(lambda t, z: np.asarray(field(z)), (0.0, T), np.concatenate([q0, p0]), method="DOP853",
                    rtol=1e-13, atol=1e-13)
    return sol.y[:, -1]


def _slope(hs, errs):
    return float(np.polyfit(np.log(hs), np.log(errs), 1)[0])


def _errors(method, T, ns, ref):
    errs = []
    for n in ns:
        s = gj.integrate(tao_h, Q0, P0, method=method, h=T / n, n_steps=n, error_estimate=False)
        assert int(s.status) == 0 and int(s.stats["num_newton_iterations"]) == 0  # explicit
        errs.append(float(np.max(np.abs(np.concatenate([s.q[-1], s.p[-1]]) - ref))))
    return [T / n for n in ns], errs


def test_order_two_and_four_on_a_non_separable_h():
    """Fitted orders against DOP853 at T = 2: measured 2.00 (Tao) and 4.02 (its triple jump on
    the extended space); margin 0.1 for the fit over three step sizes."""
    T = 2.0
    ref = _reference(tao_h, Q0, P0, T)
    hs, errs = _errors(gj.Tao(), T, (100, 200, 400), ref)
    print("order 2", errs, _slope(hs, errs))
    assert _slope(hs, errs) == pytest.approx(2.0, abs=0.1)
    hs, errs = _errors(gj.Composition(gj.Tao(), "yoshida4"), T, (100, 200, 400), ref)
    print("order 4", errs, _slope(hs, errs))
    assert _slope(hs, errs) == pytest.approx(4.0, abs=0.1)


def test_orders_six_and_eight_by_composition():
    """Yoshida's order-6 and Kahan and Li's order-8 schemes composed on the extended space:
    measured fitted orders 5.99 and 8.00 at T = 2 (errors 1.9e-5 to 4.6e-9 and 1.8e-6 to
    3.8e-11, above the reference's); margin 0.25 for the fit over three step sizes."""
    T = 2.0
    ref = _reference(tao_h, Q0, P0, T)
    for scheme, order, ns in (("yoshida6", 6, (25, 50, 100)), ("kahan_li8", 8, (13, 25, 50))):
        hs, errs = _errors(gj.Composition(gj.Tao(), scheme), T, ns, ref)
        print(scheme, errs, _slope(hs, errs))
        assert _slope(hs, errs) == pytest.approx(order, abs=0.25)


def _symmetry_defect(method, h):
    """max |Phi_{-h}(Phi_h(z0)) - z0| on the double pendulum (the element's closed form)."""
    memo = method.explicit_start(double_pendulum, DP_Q0, DP_P0)
    _, (dq, dp), _ = method.explicit(double_pendulum, DP_Q0, DP_P0, h, memo)
    _, (dq2, dp2), _ = method.explicit(double_pendulum, DP_Q0 + dq, DP_P0 + dp, -h, memo)
    return float(jnp.max(jnp.abs(jnp.concatenate([dq + dq2, dp + dp2]))))


def test_symmetric_to_high_order():
    """Phi_{-h} o Phi_h = id + O(h^6) for Tao's map, + O(h^10) for its triple jump (the copies
    part by O(h^{p+1}) and their mean cancels the next terms). Measured on the double pendulum:
    Tao's 3.9e-8, 5.4e-10, 8.4e-12 at h = 0.1, 0.05, 0.025 (fitted slope 6.1; margin 0.3),
    the triple jump's 1.3e-5, 6.0e-9, 1.2e-11 at h = 0.4, 0.2, 0.1 (fitted 10.0; margin 1, its
    local slopes 11.0 and 9.0)."""
    tao = [_symmetry_defect(gj.Tao(), h) for h in (0.1, 0.05, 0.025)]
    assert _slope((0.1, 0.05, 0.025), tao) == pytest.approx(6.1, abs=0.3)
    assert tao[-1] < 2e-11
    hs = (0.4, 0.2, 0.1)
    jump = [_symmetry_defect(gj.Composition(gj.Tao(), "yoshida4"), h) for h in hs]
    assert _slope(hs, jump) == pytest.approx(10.0, abs=1.0)


def _energy_errors(method, h, n, H=tao_h, q0=Q0, p0=P0):
    """|H - H(z0)| / |H(z0)| at every node of a fixed-step run."""
    s = gj.integrate(H, q0, p0, method=method, h=h, n_steps=n, error_estimate=False)
    E = jax.vmap(H)(s.q, s.p)
    return np.abs(np.asarray(E - E[0]) / float(E[0]))


def _first_and_last_tenth(e):
    return e[: e.size // 10].max(), e[-(e.size // 10):].max()


def test_energy_error_stays_small_short():
    """10^4 steps of h = 0.05 (T = 500) on Tao's H: the triple jump's largest energy error in the
    last tenth of the run is that of the first (measured 2.23e-5 and 2.23e-5: margin 10 %)."""
    first, last = _first_and_last_tenth(_energy_errors(gj.Composition(gj.Tao(), "yoshida4"), 0.05, 10000))
    assert first == pytest.approx(2.23e-5, rel=0.05)
    assert last < 1.1 * first


def test_energy_error_over_1e5_steps():
    """10^5 steps of h = 0.05 (T = 5000). Tao's H: the triple jump's energy error stays at its
    first tenth's size (measured 2.23e-5 and 2.34e-5: margin 15 %); Tao's map of order 2, not
    symplectic and symmetric to O(h^6), drifts (measured 2.86e-3 to 1.60e-2), and at h = 0.02
    drifts little (2.40e-4 to 2.92e-4: margin 30 %). The double pendulum (chaotic here: the
    trajectory, not the bound, depends on round-off): the triple jump's error stays below
    2e-5 (measured 1.03e-5 and 0.99e-5)."""
    jump = gj.Composition(gj.Tao(), "yoshida4")
    first, last = _first_and_last_tenth(_energy_errors(jump, 0.05, 100000))
    assert first == pytest.approx(2.23e-5, rel=0.05) and last < 1.15 * first
    first, last = _first_and_last_tenth(_energy_errors(gj.Tao(), 0.05, 100000))
    assert first == pytest.approx(2.86e-3, rel=0.05) and 3 < last / first < 8
    first, last = _first_and_last_tenth(_energy_errors(gj.Tao(), 0.02, 100000))
    assert first == pytest.approx(2.40e-4, rel=0.05) and last < 1.3 * first
    e = _energy_errors(jump, 0.05, 100000, double_pendulum, DP_Q0, DP_P0)
    assert e.max() < 2e-5
