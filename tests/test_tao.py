"""Tao's extended phase space map for any H (gj.Tao): order, symmetry, energy, the binding omega,
and every path of a run computing the same map."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import galerkin_jax as gj
from galerkin_jax._tao import extended_map


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


def test_every_path_computes_the_same_map():
    """Fixed steps, step, save_at, vmap and a sweep: the same nodes (the iterated paths solve
    R(Z) = Z - Phi_h(z0) + z0 in one update; measured differences below 1e-15, asserted to
    1e-13)."""
    method, h = gj.Tao(omega=0.5), 0.02
    H, q0, p0 = double_pendulum, DP_Q0, DP_P0
    Z = jnp.arange(4.0)
    assert method.initial_guess(q0, p0, (q0, p0, Z)) is Z and not jnp.any(method.initial_guess(q0, p0))
    nodes = gj.integrate(H, q0, p0, method=method, h=h, n_steps=50, error_estimate=False)
    q, p = q0, p0
    for _ in range(3):
        q, p = gj.step(H, q, p, method=method, h=h)
    three = gj.integrate(H, q0, p0, method=method, h=h, n_steps=3, error_estimate=False)
    np.testing.assert_allclose(q, three.q[-1], rtol=0, atol=1e-14)
    saved = gj.integrate(H, q0, p0, method=method, h=h, t1=1.0, save_at=jnp.linspace(0.0, 1.0, 5))
    assert int(saved.status) == 0 and int(saved.stats["num_accepted_steps"]) == 50
    np.testing.assert_allclose(saved.q[-1], nodes.q[-1], rtol=0, atol=1e-13)
    result = gj.sweep(H, gj.grid(method=[method], h=[h, 2 * h], state=(q0, p0)), n_steps=50)
    assert np.all(np.asarray(result.status) == 0)
    np.testing.assert_allclose(np.asarray(result.q)[0], nodes.q[-1], rtol=0, atol=1e-13)
    batch = jax.vmap(lambda q: gj.integrate(H, q, p0, method=method, h=h, n_steps=50,
                                            error_estimate=False).q[-1])(jnp.stack([q0, q0]))
    np.testing.assert_allclose(batch[0], nodes.q[-1], rtol=0, atol=1e-14)


def test_dense_output_and_events():
    """Dense output: the nodes, and between them the refined element polynomial, at t = 0.625
    measured 6.4e-7 from an order-4 run, as far as the nodes of a run of 62 steps to t = 0.625
    (6.5e-7): asserted within 1.2 times that. An event (the upper rod through the vertical):
    located where the dense output's q[0] is 0 (measured 2e-7, the polynomials' difference)."""
    method, h = gj.Tao(omega=0.5), 0.01
    H, q0, p0 = double_pendulum, DP_Q0, DP_P0
    dense = gj.integrate(H, q0, p0, method=method, h=h, n_steps=300, dense=True)
    np.testing.assert_allclose(dense.evaluate(1.0)[0], dense.q[100], rtol=0, atol=1e-13)
    fine = gj.integrate(H, q0, p0, method=gj.Composition(gj.Tao(), "yoshida4"), h=0.625 / 500, n_steps=500)
    nodal = gj.integrate(H, q0, p0, method=method, h=0.625 / 62, n_steps=62)
    node_error = float(jnp.max(jnp.abs(nodal.q[-1] - fine.q[-1])))
    assert float(jnp.max(jnp.abs(dense.evaluate(0.625)[0] - fine.q[-1]))) < 1.2 * node_error
    crossing = gj.integrate(H, q0, p0, method=method, h=h, t1=3.0, events=gj.Event(lambda t, q, p: q[0]))
    t_event = crossing.events.t[0]
    print(float(t_event), float(dense.evaluate(t_event)[0][0]), float(crossing.events.q[0, 0]))
    assert abs(float(crossing.events.q[0, 0])) < 1e-12
    assert abs(float(dense.evaluate(t_event)[0][0])) < 1e-6


def test_gradient_reverse_and_forward_agree():
    """d p(T) / d (q0, args) through 20 fixed steps: reverse and forward mode agree to round-off
    (measured 1e-15; asserted 1e-12), and with central differences (measured 3e-10)."""
    H = lambda q, p, k: tao_h(q, p) + 0.5 * k * q[0] ** 4
    run = lambda q0, k: gj.integrate(H, q0, P0, args=k, method=gj.Tao(), h=0.05, n_steps=20,
                                     error_estimate=False).p[-1, 0]
    reverse = jax.jit(jax.grad(run, argnums=(0, 1)))(Q0, 0.1)
    forward = jax.jit(jax.jacfwd(run, argnums=(0, 1)))(Q0, 0.1)
    np.testing.assert_allclose(reverse[0], forward[0], rtol=1e-12)
    np.testing.assert_allclose(reverse[1], forward[1], rtol=1e-12)
    eps = 1e-6
    fd = (run(Q0, 0.1 + eps) - run(Q0, 0.1 - eps)) / (2 * eps)
    assert float(reverse[1]) == pytest.approx(float(fd), rel=1e-7)


def test_derivatives_forward_reverse_and_differences_agree():
    """d q(T) / d (q0, p0, args, h): reverse mode (fixed steps and the save_at path), forward
    mode and central differences agree (measured: modes to 1e-15, differences to 4e-10 relative)."""
    H = lambda q, p, k: double_pendulum(q, p) + 0.5 * k * q[1] ** 2

    def run(q0, p0, k, h, save_at=None):
        fixed = save_at is None
        sol = gj.integrate(H, q0, p0, args=k, method=gj.Tao(0.5), h=h, n_steps=50 if fixed else None,
                           t1=None if fixed else 1.0, save_at=save_at, error_estimate=False)
        return sol.q[-1, 0]

    theta = (DP_Q0, DP_P0, 0.3, 0.02)
    reverse = jax.jit(jax.grad(run, argnums=(0, 1, 2, 3)))(*theta)
    through_save = jax.grad(lambda *a: run(*a, save_at=jnp.array([0.0, 1.0])), argnums=(0, 1, 2))(*theta)
    forward = jax.jacfwd(run, argnums=(0, 1, 2, 3))(*theta)
    for r, f in zip(reverse, forward):
        np.testing.assert_allclose(r, f, rtol=1e-12, atol=1e-13)
    for r, s in zip(reverse, through_save):
        np.testing.assert_allclose(s, r, rtol=1e-10, atol=1e-12)
    eps = 1e-6
    fd_k = (run(DP_Q0, DP_P0, 0.3 + eps, 0.02) - run(DP_Q0, DP_P0, 0.3 - eps, 0.02)) / (2 * eps)
    fd_h = (run(DP_Q0, DP_P0, 0.3, 0.02 + eps) - run(DP_Q0, DP_P0, 0.3, 0.02 - eps)) / (2 * eps)
    assert float(reverse[2]) == pytest.approx(float(fd_k), abs=1e-8)
    assert float(reverse[3]) == pytest.approx(float(fd_h), rel=1e-8)


def _carried(omega, h, n):
    """The copies carried from step to step by Tao's extended map (his scheme, which gj.Tao does
    not run): the largest |q - x|, |p - y| over n steps on Tao's H."""
    def body(state, _):
        state = extended_map(tao_h, state, h, omega)
        return state, jnp.max(jnp.abs(jnp.concatenate([state[0] - state[2], state[1] - state[3]])))
    return float(jax.lax.scan(body, (Q0, P0, Q0, P0), None, length=n)[1].max())


def test_what_omega_does():
    """Carried from step to step (Tao's scheme), unbound copies part: over 2 * 10^4 steps of
    h = 0.05 on Tao's H their distance reaches 6.0 at omega = 0 (the size of the orbit) and
    stays 0.040 at omega = 10 (2 h omega = 1; measured). gj.Tao lifts them anew each element,
    so there omega only adds error: the triple jump's error at T = 2, h = 2 / 400 grows from
    5.0e-9 (omega = 0) to 1.0e-7 (omega = 1) and 5.1e-7 (omega = 5): margin 20 %. The copies'
    distance at an element's end is in the run's error estimate: 1.42 (half the distance) for
    steps of 0.5, too long for this orbit, against 1.2e-3 for steps of 0.05 (the defect
    estimate's; the copies' 3.2e-4)."""
    assert _carried(0.0, 0.05, 20000) == pytest.approx(6.0, rel=0.05)
    assert _carried(10.0, 0.05, 20000) == pytest.approx(0.040, rel=0.1)
    ref = _reference(tao_h, Q0, P0, 2.0)
    errs = [_errors(gj.Composition(gj.Tao(w), "yoshida4"), 2.0, (400,), ref)[1][0] for w in (0.0, 1.0, 5.0)]
    np.testing.assert_allclose(errs, [5.0e-9, 1.0e-7, 5.1e-7], rtol=0.2)
    estimate = lambda h: float(gj.integrate(tao_h, Q0, P0, method=gj.Tao(), h=h, n_steps=4,
                                            error_estimate="full").error_estimate)
    assert estimate(0.5) == pytest.approx(1.42, rel=0.01)
    assert estimate(0.05) == pytest.approx(1.2e-3, rel=0.05)


def test_refusals():
    with pytest.raises(ValueError, match="Tao.omega must be finite and >= 0"):
        gj.Tao(-1.0)
    with pytest.raises(ValueError, match="Tao.omega must be finite and >= 0"):
        gj.Tao(float("nan"))
    with pytest.raises(TypeError, match="Tao.omega must be a real number"):
        gj.Tao(jnp.ones(2))
    with pytest.raises(TypeError, match="Tao.stages must be a tuple"):
        gj.Tao(stages=[1.0])
    with pytest.raises(ValueError, match="Tao.stages must be symmetric and sum to 1"):
        gj.Tao(stages=(0.5, 0.4))
    with pytest.raises(ValueError, match="symmetric to high order only"):
        gj.integrate(tao_h, Q0, P0, method=gj.Composition(gj.Tao()), h=0.1, n_steps=10, checkpoint="reversible")


def test_controllers():
    """A TimeTransform runs (its K is not H: the iterated path, about 2 fixed-point updates an
    element; measured error 8.1e-4 at T = 2 in 150 steps); a PIDController is refused (its
    estimate measures the cubic: it took 5 steps and missed by 370)."""
    sol = gj.integrate(tao_h, Q0, P0, method=gj.Tao(), h=0.02, t1=2.0, controller=gj.TimeTransform(),
                       error_estimate=False)
    error = np.abs(np.concatenate([sol.q[-1], sol.p[-1]]) - _reference(tao_h, Q0, P0, 2.0)).max()
    assert int(sol.status) == 0 and error == pytest.approx(8.1e-4, rel=0.1)
    for method in (gj.Tao(), gj.Composition(gj.Tao())):
        with pytest.raises(ValueError, match="with a PIDController"):
            gj.integrate(tao_h, Q0, P0, method=method, h=0.02, t1=2.0, controller=gj.PIDController(1e-6, 1e-6))


def test_weak_instability_on_the_harmonic_oscillator():
    """Not symplectic, not exactly symmetric: on H = (q^2 + p^2) / 2 the one-step matrix has
    det A = 1 + h^6 / 64 and spectral radius 1 + h^6 / 128 (measured 1.2206e-4 at h = 0.5, to
    1e-3 relative); the triple jump's radius less 1 falls as h^10 (measured 9.2e-7 and 7.4e-10
    at h = 0.5 and 0.25: ratio 2^10.3; margin 0.5 in the exponent). A binding only raises it
    (omega = 1 / h: 9.1e-4 at h = 0.5)."""
    H = lambda q, p: 0.5 * (p @ p + q @ q)

    def radius(method, h):
        A = np.asarray(gj.amplification_matrix(H, jnp.zeros(1), jnp.zeros(1), method=method, h=h))
        return np.abs(np.linalg.eigvals(A)).max() - 1, np.linalg.det(A) - 1

    r, det = radius(gj.Tao(), 0.5)
    assert det == pytest.approx(0.5**6 / 64, rel=1e-9)
    assert r == pytest.approx(0.5**6 / 128, rel=1e-3)
    assert radius(gj.Tao(omega=1 / 0.5), 0.5)[0] > 5 * r
    jump = gj.Composition(gj.Tao(), "yoshida4")
    ratio = radius(jump, 0.5)[0] / radius(jump, 0.25)[0]
    assert np.log2(ratio) == pytest.approx(10.3, abs=0.5)


def test_a_composition_is_one_map_on_the_extended_space():
    """Composition(Tao) hands its element to Tao with the scheme's stages (``lifted``), nested
    compositions multiply them, and with ``SolverOptions(explicit=False)`` the iterated
    residual (through Composition's members) finds the same nodes (measured 0 and 1e-16
    apart; asserted 1e-13)."""
    jump = gj.Composition(gj.Tao(), "yoshida4")
    gamma = jump.coefficients
    assert jump.lifted == gj.Tao(0.0, gamma)
    nested = gj.Composition(jump, "yoshida4")
    assert nested.lifted.stages == tuple(g * s for g in gamma for s in gamma)
    assert gj.Composition(gj.Composition(gj.GalerkinVI(1, gj.trapezoid())), "yoshida4").lifted is None
    H, q0, p0 = double_pendulum, DP_Q0, DP_P0
    closed = gj.integrate(H, q0, p0, method=jump, h=0.05, n_steps=20, error_estimate=False)
    iterated = gj.integrate(H, q0, p0, method=jump, h=0.05, n_steps=20, error_estimate="full",
                            solver=gj.SolverOptions(explicit=False))
    assert int(iterated.status) == 0
    np.testing.assert_allclose(iterated.q[-1], closed.q[-1], rtol=0, atol=1e-13)
    assert float(iterated.error_estimate) > 0


def test_the_command_line_names_it():
    """``galerkin-jax run -m tao`` and ``-m yoshida4@tao``: the spec builds the method."""
    from galerkin_jax import _cli_specs as specs

    assert specs.build(specs.complete(specs.parse_spec("tao"))) == gj.Tao()
    assert specs.build(specs.complete(specs.parse_spec("yoshida4@tao"))) == gj.Composition(gj.Tao(), "yoshida4")
