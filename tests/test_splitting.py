"""Splitting methods for separable H (gj.Splitting): Blanes and Moan's schemes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax._splitting import SCHEMES

import helpers

VERLET = gj.GalerkinVI(1, gj.trapezoid())


def henon_heiles(q, p):
    return 0.5 * (p @ p) + 0.5 * (q @ q) + q[0] ** 2 * q[1] - q[1] ** 3 / 3


HH_Q0, HH_P0 = jnp.array([0.1, -0.2]), jnp.array([0.3, 0.25])


def relativistic(q, p):
    """T(p) not quadratic: an RKN scheme's extra conditions do not hold."""
    return jnp.sum(jnp.sqrt(1 + p * p)) + 0.5 * (q @ q) + 0.1 * q[0] ** 4


def _errors(H, q0, p0, method, T, ns):
    """Max-norm errors at T against Kahan and Li's order-8 composition of Verlet at h = T / 2000
    (another method: the reference's error is below 1e-15 here)."""
    ref = gj.integrate(H, q0, p0, method=gj.Composition(VERLET, "kahan_li8"), h=T / 2000, n_steps=2000,
                       error_estimate=False)
    ze = jnp.concatenate([ref.q[-1], ref.p[-1]])
    errs = []
    for n in ns:
        s = gj.integrate(H, q0, p0, method=method, h=T / n, n_steps=n, error_estimate=False)
        assert int(s.status) == 0 and int(s.stats["num_newton_iterations"]) == 0  # explicit
        errs.append(float(jnp.max(jnp.abs(jnp.concatenate([s.q[-1], s.p[-1]]) - ze))))
    return [T / n for n in ns], errs


def _numpy_splitting(grad_V, grad_T, kicks, drifts, q, p, h, n):
    """The splitting written out in NumPy: kick, drift, ..., kick, every force computed afresh."""
    q, p = np.array(q, float), np.array(p, float)
    for _ in range(n):
        for i, b in enumerate(kicks):
            p = p - b * h * grad_V(q)
            if i < len(drifts):
                q = q + drifts[i] * h * grad_T(p)
    return q, p


@pytest.mark.parametrize("name", list(SCHEMES))
def test_coefficients_are_palindromes_summing_to_one(name):
    _, b, a, _ = SCHEMES[name]
    assert len(b) == len(a) + 1
    assert abs(sum(b) - 1) < 1e-15 and abs(sum(a) - 1) < 1e-15
    assert b == b[::-1] and a == a[::-1]


# measured slopes on Henon-Heiles over T = 4: leapfrog 2.00, blanes_moan4 4.00, blanes_moan6 6.00,
# blanes_moan_rkn4 4.00, blanes_moan_rkn6 5.99 (errors 1e-3 .. 1e-13)
@pytest.mark.parametrize("name, ns", [
    ("leapfrog", (20, 40, 80, 160)), ("blanes_moan4", (20, 40, 80, 160)), ("blanes_moan6", (20, 40, 80)),
    ("blanes_moan_rkn4", (20, 40, 80, 160)), ("blanes_moan_rkn6", (10, 20, 40)),
])
def test_measured_order(name, ns):
    hs, errs = _errors(henon_heiles, HH_Q0, HH_P0, gj.Splitting(name), 4.0, ns)
    assert helpers.fitted_order(hs, errs, floor=1e-13) == pytest.approx(SCHEMES[name][0], abs=0.15)


@pytest.mark.parametrize("name, order", [("blanes_moan4", 4), ("blanes_moan6", 6)])
def test_order_on_a_kinetic_energy_not_quadratic(name, order):
    """The PRK schemes keep their order on any separable H (T = sum sqrt(1 + p^2): measured 4.0
    and 6.0); the RKN schemes need T quadratic (below)."""
    hs, errs = _errors(relativistic, jnp.array([1.0, -0.5]), jnp.array([0.4, 1.2]), gj.Splitting(name), 4.0,
                       (20, 40, 80))
    assert helpers.fitted_order(hs, errs, floor=1e-13) == pytest.approx(order, abs=0.15)


M = jnp.array([[2.0, 0.5], [0.5, 1.0]])
V4 = lambda q: jnp.sum(q ** 4)


@pytest.mark.parametrize("T, quadratic", [
    (lambda p: 0.5 * p @ p, True), (lambda p: 0.5 * jnp.sum(p ** 2), True), (lambda p: 0.5 * p @ M @ p, True),
    (lambda p: jnp.sum(jnp.square(p) / jnp.array([2.0, 6.0])), True), (lambda p: 0.5 * p @ p + p[0], True),
    (lambda p: jnp.sum(jnp.sqrt(1 + p * p)), False), (lambda p: jnp.sum(p ** 4), False),
    (lambda p: 0.5 * p @ p + 0.0 * p[0] ** 3, False)])  # a cubic term that vanishes only by value
def test_structure_reads_whether_t_is_quadratic(T, quadratic):
    """``Structure.kinetic_quadratic``: d^2H/dp^2's program reads neither q nor p. Never a wrong
    True (a term that vanishes by value reads as not quadratic); False for a non-separable H."""
    found = gj.structure(lambda q, p: T(p) + V4(q), HH_Q0, HH_P0)
    assert found.separable and found.kinetic_quadratic == quadratic
    assert not gj.structure(lambda q, p: T(p) * (1 + q @ q), HH_Q0, HH_P0).kinetic_quadratic


@pytest.mark.parametrize("name", ["blanes_moan_rkn4", "blanes_moan_rkn6"])
def test_an_rkn_scheme_needs_a_quadratic_kinetic_energy(name):
    """On T = sum sqrt(1 + p^2) SRKN_11^b's order falls from 6 to 4 (measured 4.01 before the
    refusal), so an RKN scheme refuses a T that ``gj.structure`` does not read as quadratic, and
    runs on one that it does: M constant and N-body masses in args."""
    with pytest.raises(ValueError, match="Runge-Kutta-Nystrom scheme"):
        gj.integrate(relativistic, HH_Q0, HH_P0, method=gj.Splitting(name), h=0.1, n_steps=10)
    H = lambda q, p, m: 0.5 * jnp.sum(p ** 2 / m) + V4(q)
    sol = gj.integrate(H, HH_Q0, HH_P0, method=gj.Splitting(name), h=0.1, n_steps=10, args=jnp.array([1.0, 3.0]))
    assert int(sol.status) == 0


@pytest.mark.parametrize("name", list(SCHEMES))
def test_equals_a_numpy_splitting_to_roundoff(name):
    """Kepler, 200 steps of h = 0.03: measured differences up to 3.3e-14 (the run's compensated
    sum against plain addition, the force handed on against computed afresh; the state is O(1))."""
    H, q0, p0 = helpers.kepler()
    _, b, a, _ = SCHEMES[name]
    grad_V = lambda q: q / np.linalg.norm(q) ** 3
    grad_T = lambda p: p
    qn, pn = _numpy_splitting(grad_V, grad_T, b, a, q0, p0, 0.03, 200)
    s = gj.integrate(H, q0, p0, method=gj.Splitting(name), h=0.03, n_steps=200, error_estimate=False)
    np.testing.assert_allclose(np.concatenate([s.q[-1], s.p[-1]]), np.concatenate([qn, pn]), rtol=0, atol=1e-13)


@pytest.mark.parametrize("name", list(SCHEMES))
def test_symplectic_and_symmetric(name):
    """AD Jacobian: A^T J A = J (measured defect at most 4.4e-16); Phi_{-h} o Phi_h = id,
    Phi_{-h} being the step of -H (measured at most 6e-17)."""
    H, q0, p0 = helpers.kepler()
    method = gj.Splitting(name)
    A = gj.amplification_matrix(H, q0, p0, method=method, h=0.1)
    assert helpers.symplecticity_defect(A) < 1e-13
    q1, p1 = gj.step(H, q0, p0, method=method, h=0.1)
    q2, p2 = gj.step(lambda q, p: -H(q, p), q1, p1, method=method, h=0.1)
    assert float(jnp.max(jnp.abs(jnp.concatenate([q2 - q0, p2 - p0])))) < 1e-14


def test_energy_stays_bounded():
    """Pendulum, h = 0.25, 40000 steps of blanes_moan4: the energy error oscillates without drift
    (measured max 1.77e-7 in both halves, equal to 1e-11)."""
    H, q0, p0 = helpers.pendulum()
    sol = gj.integrate(H, q0, p0, method=gj.Splitting("blanes_moan4"), h=0.25, n_steps=40000, save_every=10,
                       error_estimate=False)
    e = np.abs(np.asarray(jax.vmap(H)(sol.q, sol.p)) - float(H(q0, p0)))
    first, second = e[: e.size // 2].max(), e[e.size // 2:].max()
    assert first < 1e-6 and second < 1.5 * first


def test_forces_per_step_first_same_as_last():
    """One element's program holds as many gradients of V (here: sin, from -cos) as
    ``forces_per_step`` says: the last kick's force is handed to the next element."""
    H = lambda q, p: 0.5 * (p @ p) - jnp.sum(jnp.cos(q))
    q, p = jnp.array([0.3, 0.1]), jnp.array([0.0, 0.2])
    for name, forces in [("leapfrog", 1), ("blanes_moan4", 6), ("blanes_moan6", 10), ("blanes_moan_rkn4", 6),
                         ("blanes_moan_rkn6", 11)]:
        method = gj.Splitting(name)
        g0 = method.explicit_start(H, q, p)
        jaxpr = jax.make_jaxpr(lambda q, p, g: method.explicit(H, q, p, 0.1, g))(q, p, g0)
        assert sum(eqn.primitive.name == "sin" for eqn in jaxpr.jaxpr.eqns) == forces == method.forces_per_step


def test_composition_of_leapfrog_is_the_composition_of_verlet():
    """Yoshida's triple jump of the leapfrog splitting and of explicit GalerkinVI(1, trapezoid):
    the same map, its arithmetic in another order (measured difference 6e-14 after 100 steps, a
    Kepler orbit amplifying round-off)."""
    H, q0, p0 = helpers.kepler()
    a = gj.integrate(H, q0, p0, method=gj.Composition(gj.Splitting("leapfrog"), "yoshida4"), h=0.05, n_steps=100)
    b = gj.integrate(H, q0, p0, method=gj.Composition(VERLET, "yoshida4"), h=0.05, n_steps=100)
    np.testing.assert_allclose(np.concatenate([a.q[-1], a.p[-1]]), np.concatenate([b.q[-1], b.p[-1]]),
                               rtol=0, atol=3e-13)


def test_save_at_events_gradients_vmap_and_sweep():
    H, q0, p0 = helpers.kepler()
    method = gj.Splitting("blanes_moan4")
    nodes = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=100)
    # save_at and events run the iterated loop: the residual's root is the explicit element's
    ts = jnp.linspace(0.0, 1.0, 5)
    saved = gj.integrate(H, q0, p0, method=method, h=0.01, t1=1.0, save_at=ts)
    assert int(saved.status) == 0
    np.testing.assert_allclose(saved.q[-1], nodes.q[-1], rtol=0, atol=1e-13)
    crossing = gj.integrate(H, q0, p0, method=method, h=0.01, t1=4.0, events=gj.Event(lambda t, q, p: q[1]))
    t_event = float(crossing.events.t[0])
    # q[1] = 0 first at the apocentre of Kepler's orbit of e = 0.5 started at the pericentre: t = pi
    # (located on the refined element polynomial of this order-4 run: measured error 5e-10)
    assert t_event == pytest.approx(np.pi, abs=1e-8)
    # a gradient through the explicit scan, against central differences
    run = lambda h: gj.integrate(H, q0, p0, method=method, h=h, n_steps=100).q[-1, 0]
    eps = 1e-6
    fd = (run(0.01 + eps) - run(0.01 - eps)) / (2 * eps)
    assert float(jax.jit(jax.grad(run))(0.01)) == pytest.approx(float(fd), rel=1e-7)  # one program (eagerly two)
    hs = jnp.array([0.01, 0.02])
    batch = jax.vmap(lambda h: gj.integrate(H, q0, p0, method=method, h=h, n_steps=100).q[-1])(hs)
    np.testing.assert_allclose(batch[0], nodes.q[-1], rtol=0, atol=1e-14)
    result = gj.sweep(H, gj.grid(method=[method], h=[0.01, 0.02], state=(q0, p0)), n_steps=100)
    assert np.all(np.asarray(result.status) == 0)
    np.testing.assert_allclose(np.asarray(result.q)[0], nodes.q[-1], rtol=0, atol=1e-13)


def test_reversible_gradient_rebuilds_the_states():
    """checkpoint="reversible" rebuilds each state by the step of -H (the scheme is symmetric):
    the gradient equals the stored one (measured difference 1.6e-14 of 8.8)."""
    H, q0, p0 = helpers.kepler()
    method = gj.Splitting("blanes_moan4")
    run = lambda q, checkpoint: gj.integrate(H, q, p0, method=method, h=0.01, n_steps=200,
                                             checkpoint=checkpoint).p[-1, 1]
    # jitted gradients: one compiled program each (eagerly two, the forward pass's and the transpose's)
    stored = jax.jit(jax.grad(lambda q: run(q, False)))(q0)
    rebuilt = jax.jit(jax.grad(lambda q: run(q, "reversible")))(q0)
    np.testing.assert_allclose(rebuilt, stored, rtol=0, atol=1e-12)


def test_refusals():
    H, q0, p0 = helpers.kepler()
    method = gj.Splitting("blanes_moan4")
    general, g_q0, g_p0 = helpers.non_separable()
    with pytest.raises(ValueError, match=r"Splitting\('blanes_moan4'\) needs a separable H"):
        gj.integrate(general, g_q0, g_p0, method=method, h=0.01, n_steps=10)
    with pytest.raises(ValueError, match=r"Splitting\('leapfrog'\) needs a separable H"):
        gj.step(general, g_q0, g_p0, method=gj.Composition(gj.Splitting("leapfrog")), h=0.01)
    with pytest.raises(ValueError, match="Splitting with a PIDController"):
        gj.integrate(H, q0, p0, method=method, h=0.01, t1=1.0, controller=gj.PIDController(1e-6, 1e-6))
    with pytest.raises(ValueError, match="Splitting with a TimeTransform"):
        gj.integrate(H, q0, p0, method=gj.Composition(gj.Splitting("leapfrog")), h=0.01, t1=1.0,
                     controller=gj.TimeTransform())
    with pytest.raises(ValueError, match="unknown scheme"):
        gj.Splitting("blanes_moan8")


# --- McLachlan's optimised compositions (gj.Composition) -----------------------------------


@pytest.mark.parametrize("name, ns, order", [("mclachlan6", (100, 200, 400), 6), ("mclachlan8", (50, 100, 200), 8)])
def test_mclachlan_compositions_of_verlet_have_their_order(name, ns, order):
    """Kepler (e = 0.5), one period: measured slopes 6.00 and 8.09, the errors below Kahan and
    Li's of as many stages (s9odr6a, s17odr8b: 8.8e-6 and 5.9e-7 at the largest h here)."""
    H, q0, p0 = helpers.kepler()
    T = 2 * np.pi
    qe, pe = helpers.kepler_exact(T)
    errs = []
    for n in ns:
        s = gj.integrate(H, q0, p0, method=gj.Composition(VERLET, name), h=T / n, n_steps=n, error_estimate=False)
        errs.append(float(jnp.max(jnp.abs(jnp.concatenate([s.q[-1] - qe, s.p[-1] - pe])))))
    assert helpers.fitted_order([T / n for n in ns], errs, floor=1e-13) == pytest.approx(order, abs=0.15)
    assert errs[0] < {"mclachlan6": 6e-6, "mclachlan8": 5.9e-7}[name]  # measured 4.6e-6, 5.4e-7


@pytest.mark.parametrize("name", ["leapfrog", "blanes_moan4", "blanes_moan_rkn6"])
def test_the_field_at_an_elements_end_and_the_default_error_estimate(name):
    """``explicit_field`` is Hamilton's field at the element's end, from the carried force where
    the element ends with a kick (leapfrog, the RKN schemes) and from a fresh one where it ends
    with a drift (the PRK schemes, whose last kick is zero): equal to autodiff's to round-off
    (measured <= 1.1e-16). The default estimate, the full one on the four elements where the
    embedded one (the Hermite cubic's defect at alpha = 1/4, ``embedded_alpha``) peaks, runs and
    lies at or below "full"'s exact maximum: measured 1.0 (leapfrog), 0.39 (blanes_moan4, whose
    local error varies 2.4x over the run and peaks where the cubic's defect does not) and 0.99
    (blanes_moan_rkn6) of it on Henon-Heiles."""
    method = gj.Splitting(name)
    H = henon_heiles
    g0 = method.explicit_start(H, HH_Q0, HH_P0)
    _, (dq, dp), memo = method.explicit(H, HH_Q0, HH_P0, 0.1, g0)
    q1, p1 = HH_Q0 + dq, HH_P0 + dp
    exact = jnp.concatenate([jax.grad(H, 1)(q1, p1), -jax.grad(H, 0)(q1, p1)])
    assert float(jnp.max(jnp.abs(method.explicit_field(H, q1, p1, memo) - exact))) < 1e-15
    runs = {est: gj.integrate(H, HH_Q0, HH_P0, method=method, h=0.1, n_steps=200, error_estimate=est)
            for est in (True, "full")}
    assert all(int(sol.status) == 0 for sol in runs.values())
    ratio = float(runs[True].error_estimate) / float(runs["full"].error_estimate)
    assert 0.35 < ratio <= 1.0 + 1e-12
