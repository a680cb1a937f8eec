"""The time transformation's default step density where Hamilton's field vanishes
(docs/adaptive.md, "Where Hamilton's field vanishes"): the pendulum at rest, at its
saddle and near its separatrix, Henon-Heiles near its equilibrium, Kepler from apocentre as
before and from pericentre at the cap's price, the cap itself, and K's closed-form gradient
against autodiff of the same density. Figures: the one-off ``density_bound`` study of notes/README.md
(cG(4) + Gauss 4, h = 0.2 in tau unless said)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import galerkin_jax as gj
from galerkin_jax._controllers import S_MAX, default_step_density, field_scale, poincare

CG4 = gj.CG(4, gj.gauss_legendre(4))
UNBOUNDED = gj.TimeTransform(s_max=float("inf"))


def pendulum(q, p):
    return 0.5 * (p @ p) - jnp.cos(q[0])


def kepler(q, p):
    return 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)


def run(H, q0, p0, t1, controller=gj.TimeTransform(), h=0.2, **kw):
    return gj.integrate(H, jnp.asarray(q0, float), jnp.asarray(p0, float), method=CG4, h=h, t1=t1,
                        controller=controller, dense=True, error_estimate=False, **kw)


def steps(sol):
    return int(sol.stats["num_accepted_steps"])


def largest_error(sol, field, z0, t1, n=401):
    """The largest max-norm distance of the run from SciPy's DOP853 (rtol = 1e-13) at n times."""
    times = np.linspace(0.0, t1, n)
    ref = solve_ivp(field, (0.0, t1), z0, method="DOP853", rtol=1e-13, atol=1e-16, t_eval=times).y.T
    q, p = sol.evaluate(jnp.asarray(times))
    return float(np.max(np.abs(np.c_[q, p] - ref)))


def pendulum_field(t, z):
    return [z[1], -np.sin(z[0])]


def test_a_pendulum_at_rest_stays_there_with_steps_h():
    """F(z0) = 0: the unbounded density was 0 / 0 (status TIME_TRANSFORM before the first step);
    now s = 1 (``field_scale`` is 0), the run takes 200 steps of h = 0.2 to t = 40 and the
    state stays exactly at rest (F = 0 makes the element's solution the constant state)."""
    for controller in (gj.TimeTransform(), UNBOUNDED):
        sol = run(pendulum, [0.0], [0.0], 40.0, controller)
        assert int(sol.status) == 0 and steps(sol) == 200
        assert float(sol.q[-1, 0]) == 0.0 and float(sol.p[-1, 0]) == 0.0


def test_a_pendulum_at_its_saddle_leaves_it_as_its_round_off_grows():
    """q0 = pi (the float: sin(q0) = 1.2e-16) is an equilibrium to round-off: |F(z0)| is below
    16 eps |D^2H(z0) z0|, so s = 1, as at rest. The unbounded density's steps in t shrank like
    |F|^(-3/4) as the state left the saddle: 20000 steps ended at max_steps (NaN state). Now
    200 steps to t = 40; q - pi follows the linearised flow x0 cosh t from the float's offset
    x0 = -1.22e-16 (measured 0.68 x0 cosh t at t = 10 and 20: the round-off of the first
    elements adds to x0; the bounds 0.3..3 say the departure is round-off's, not the method's),
    and |H - 1| stays below 1.1e-11 over the whole run (bound 1e-10: the excursion after t = 36
    is an O(1) homoclinic loop)."""
    sol = run(pendulum, [np.pi], [0.0], 40.0)
    assert int(sol.status) == 0 and steps(sol) == 200
    ts = np.asarray([10.0, 20.0])
    q, _ = sol.evaluate(jnp.asarray(ts))
    x0 = -np.sin(np.pi)  # the float pi minus pi
    ratio = (np.asarray(q[:, 0]) - np.pi) / (x0 * np.cosh(ts))
    assert np.all((0.3 < ratio) & (ratio < 3)), ratio
    n = steps(sol)
    energy = jax.vmap(pendulum)(*sol.dense.view(sol.dense.z[: n + 1]))
    assert float(jnp.max(jnp.abs(energy - 1.0))) < 1e-10
    assert np.isfinite(np.asarray(sol.q[-1])).all()


def test_near_the_separatrix_the_capped_density_is_accurate():
    """p0 = 1.99999 (0.99998 of the separatrix energy), t = 40: the unbounded density's s rose
    to about 75 at the turning points near the saddle, steps 5.4 long in t, and the run ended
    0.63 rad off with status 0 (now, with other rounding, its solve fails after 11 steps:
    status 1). Capped at s_max = 3: 95 steps, largest error over the run 6.9e-7 against DOP853,
    where fixed steps of the same number err by 9.3e-4 (s = 1 at h = 0.2, 200 steps: 2.7e-7 at
    the end). Bounds: 3e-6 (4x the measured error: the phase error near a separatrix moves with
    the rounding of the period), fixed steps at least 100x worse (measured 1350x)."""
    z0 = [0.0, 1.99999]
    sol = run(pendulum, z0[:1], z0[1:], 40.0)
    assert int(sol.status) == 0 and steps(sol) == 95
    n = steps(sol)
    assert float(np.max(np.diff(np.asarray(sol.dense.t[: n + 1])))) <= 3 * 0.2 * (1 + 1e-9)  # h s_max
    error = largest_error(sol, pendulum_field, z0, 40.0)
    assert error < 3e-6
    fixed = gj.integrate(pendulum, jnp.asarray([0.0]), jnp.asarray([1.99999]), method=CG4, h=40.0 / n, t1=40.0,
                         dense=True, error_estimate=False)
    assert largest_error(fixed, pendulum_field, z0, 40.0) > 100 * error
    unbounded = run(pendulum, z0[:1], z0[1:], 40.0, UNBOUNDED)
    assert int(unbounded.status) != 0 or largest_error(unbounded, pendulum_field, z0, 40.0) > 0.1


def test_henon_heiles_near_its_equilibrium():
    """Energy 1e-4 (|z| ~ 0.014), t = 100: |F| ~ sqrt(2 H) changes by 1.7 % along the orbit, s
    stays in [0.98, 1], the cap never acts: 500 steps, the largest error 3.8e-11 against DOP853
    (3.9e-11 unbounded; bound 1e-10), the energy error below 1e-18 (bound 1e-16: round-off of
    an energy of 1e-4)."""
    hh = lambda q, p: 0.5 * (p @ p + q @ q) + q[0] ** 2 * q[1] - q[1] ** 3 / 3

    def field(t, z):
        x, y, px, py = z
        return [px, py, -x - 2 * x * y, -y - x * x + y * y]

    z0 = [0.0, 0.0, np.sqrt(2e-4), 0.0]
    sol = run(hh, z0[:2], z0[2:], 100.0)
    assert int(sol.status) == 0 and steps(sol) == 500
    assert largest_error(sol, field, z0, 100.0, n=201) < 1e-10
    n = steps(sol)
    energy = jax.vmap(hh)(*sol.dense.view(sol.dense.z[: n + 1]))
    assert float(jnp.max(jnp.abs(energy - 1e-4))) < 1e-16


def kepler_at(e, where):
    sign = 1 if where == "apocentre" else -1
    return jnp.asarray([1 + sign * e, 0.0]), jnp.asarray([0.0, np.sqrt((1 - sign * e) / (1 + sign * e))])


def max_energy_error(sol, H, q0, p0):
    n = steps(sol)
    return float(jnp.max(jnp.abs(jax.vmap(H)(*sol.dense.view(sol.dense.z[: n + 1])) - H(q0, p0))))


def test_kepler_from_apocentre_keeps_its_steps_and_energy_error():
    """Kepler e = 0.9 from apocentre over 5 orbits, h = 0.8: s <= 1 along the orbit, so the cap
    only scales s by at most (1 + k^2)^(3/8) = 1.021 near pericentre: 127 steps against 129
    unbounded, largest energy error 4.00e-7 against 4.05e-7. Bounds: steps within 3 %, the
    energy error within 1.5x of the unbounded run's (over 100 orbits in
    the ``density_bound`` study, part c: 1.7-1.9 % fewer steps, energy errors 0.74-1.37x, where
    changing s_max from 10 to inf, s by 1e-4, moves them by up to 6x at e = 0.99)."""
    q0, p0 = kepler_at(0.9, "apocentre")
    T5 = 5 * 2 * np.pi
    capped, unbounded = (run(kepler, q0, p0, T5, c, h=0.8) for c in (gj.TimeTransform(), UNBOUNDED))
    assert int(capped.status) == 0 and int(unbounded.status) == 0
    assert steps(unbounded) == 129 and abs(steps(capped) - steps(unbounded)) <= 0.03 * steps(unbounded)
    ours, before = max_energy_error(capped, kepler, q0, p0), max_energy_error(unbounded, kepler, q0, p0)
    assert before < 1e-6 and ours < 1.5 * before


def test_kepler_from_pericentre_pays_the_cap_in_steps():
    """The price of a cap relative to the first step: Kepler e = 0.9 from pericentre over 2
    orbits, h = 0.8 (0.360 / 100.1)^(3/4) = 0.0117 (the unbounded density then takes the
    apocentre run's steps): the unbounded density's s reaches 68 at apocentre, the cap holds
    it at 3: 7.1x the steps (measured 367 against 52) for a 100x smaller energy error (6.1e-9
    against 6.3e-7). Bounds: 5x..9x the steps, a smaller energy error. ``TimeTransform(s_max=inf)`` restores the
    unbounded density; Kepler's own s = r^(3/2) is better still (docs/adaptive.md)."""
    q0, p0 = kepler_at(0.9, "pericentre")
    qa, pa = kepler_at(0.9, "apocentre")
    from galerkin_jax._controllers import field_norm

    h = 0.8 * float((field_norm(kepler, qa, pa) / field_norm(kepler, q0, p0)) ** 0.75)
    capped, unbounded = (run(kepler, q0, p0, 2 * 2 * np.pi, c, h=h) for c in (gj.TimeTransform(), UNBOUNDED))
    assert int(capped.status) == 0 and int(unbounded.status) == 0
    assert 5 * steps(unbounded) < steps(capped) < 9 * steps(unbounded)
    assert max_energy_error(capped, kepler, q0, p0) < max_energy_error(unbounded, kepler, q0, p0)


def test_the_cap_and_its_checks():
    """s(z0) = 1, s = s_max exactly where F vanishes, s <= s_max everywhere; s_max = inf is
    (|F(z0)| / |F|)^(3/4); ``field_scale`` is 0 at rest and at the float's saddle."""
    q0, p0 = jnp.asarray([0.0]), jnp.asarray([1.99999])
    u = field_scale(pendulum, q0, p0)
    assert float(u) == pytest.approx(1 / 1.99999 ** 2, rel=1e-15)
    for s_max in (2.0, S_MAX, 8.0):
        s = default_step_density(pendulum, u, s_max)
        assert float(s(q0, p0)) == pytest.approx(1.0, rel=1e-15)
        assert float(s(jnp.asarray([np.pi]), jnp.asarray([0.0]))) == pytest.approx(s_max, rel=1e-12)
        values = jax.vmap(s)(jnp.linspace(-4, 4, 101)[:, None], jnp.linspace(-3, 3, 101)[:, None])
        assert float(jnp.max(values)) <= s_max * (1 + 1e-12)
    q, p = jnp.asarray([2.0]), jnp.asarray([0.3])
    F = np.hypot(np.sin(2.0), 0.3)
    assert float(default_step_density(pendulum, u, float("inf"))(q, p)) == pytest.approx((1.99999 / F) ** 0.75,
                                                                                           rel=1e-14)
    assert float(field_scale(pendulum, jnp.asarray([0.0]), jnp.asarray([0.0]))) == 0.0
    assert float(field_scale(pendulum, jnp.asarray([np.pi]), jnp.asarray([0.0]))) == 0.0
    assert float(field_scale(pendulum, jnp.asarray([np.pi]), jnp.asarray([1e-12]))) == pytest.approx(1e24, rel=1e-3)
    for bad in (1.0, 0.5, -3.0, float("nan")):
        with pytest.raises(ValueError, match="s_max must be > 1"):
            gj.TimeTransform(s_max=bad)
    with pytest.raises(ValueError, match="s_max must be a number"):
        gj.TimeTransform(s_max="3")
    with pytest.raises(ValueError, match="s_max bounds the default density"):
        gj.TimeTransform(s=lambda q, p: 1.0 + 0 * q[0], s_max=3.0)


@pytest.mark.parametrize("scene", ["bound active", "bound inactive", "equilibrium start"])
def test_the_closed_form_gradient_is_autodiffs(scene):
    """``_default_transformed`` (K's gradient by hand, s a function of |DH|^2) against
    ``jax.grad`` and ``jax.hessian`` of K written plainly with ``default_step_density``: the
    value, the gradient and the Hessian on the extended state (q, t | p, p_t), with
    H + p_t != 0 so that Ds counts, where the cap acts (the pendulum near its saddle: u |F|^2 =
    4.6e-4, k^2 = 0.057), where it does not (Kepler near pericentre, started at apocentre:
    u |F|^2 = 1e5) and at an equilibrium start (u = 0, s = 1). Measured agreement: at most
    1.1e-15 of the largest entry (bound 1e-12)."""
    H, q0, p0, q, p = {
        "bound active": (pendulum, [0.0], [1.99999], [3.1], [0.01]),
        "bound inactive": (kepler, [1.9, 0.0], [0.0, 0.2294157338705618], [-0.08, 0.05], [-0.3, 2.5]),
        "equilibrium start": (pendulum, [0.0], [0.0], [0.4], [-0.2]),
    }[scene]
    q0, p0, q, p = (jnp.asarray(x, float) for x in (q0, p0, q, p))
    d = q0.shape[0]
    K, _, _, a, _ = poincare(H, gj.TimeTransform(), q0, p0, 0.0, None)
    u = a[1]
    plain = lambda qt, pt, a: default_step_density(H, a[1])(qt[:d], pt[:d]) * (H(qt[:d], pt[:d]) + pt[d])
    x = jnp.concatenate([q, jnp.asarray([1.3]), p, jnp.asarray([-H(q, p) + 0.37])])
    split = lambda f: (lambda x: f(x[: d + 1], x[d + 1 :], a))
    if scene == "bound active":
        assert float(u * jnp.sum(jnp.asarray(jax.grad(H, argnums=(0, 1))(q, p)) ** 2)) < 1e-3
    if scene == "equilibrium start":
        assert float(u) == 0.0
    for derivative in (lambda f: f, jax.grad, jax.hessian):
        ours, reference = derivative(split(K))(x), derivative(split(plain))(x)
        scale = float(jnp.max(jnp.abs(reference)))
        assert float(jnp.max(jnp.abs(ours - reference))) <= 1e-12 * max(scale, 1e-300), (derivative, ours, reference)
