"""Structure read from H (gj.structure), explicit elements and compositions."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax._composition import SCHEMES
from galerkin_jax._explicit import explicit_form

import helpers

VERLET = gj.GalerkinVI(1, gj.trapezoid())
ITERATED = gj.SolverOptions(explicit=False)
KEPLER = helpers.kepler()  # one H for the module: its structure and compiled runs are cached per function


# --- structure ---------------------------------------------------------------------------


@jax.custom_jvp
def _sqrt_by_newton(x):
    """A while loop inside a custom derivative: the analysis follows it."""
    return jax.lax.while_loop(lambda c: jnp.abs(c * c - x) > 1e-12 * x, lambda c: 0.5 * (c + x / c), x)


_sqrt_by_newton.defjvp(lambda primals, tangents: (_sqrt_by_newton(primals[0]),
                                                  tangents[0] / (2 * _sqrt_by_newton(primals[0]))))

Q, P = jnp.array([1.0, 0.5]), jnp.array([0.2, -0.3])


@pytest.mark.parametrize("H", [
    lambda q, p: p @ p / 2 - 1 / jnp.sqrt(q @ q),
    lambda q, p: jnp.sum(jnp.cosh(p)) + jnp.linalg.norm(q) + jax.lax.cond(q[0] > 0, lambda: q[1] ** 2, lambda: q[0]),
    lambda q, p: p @ p / 2 + _sqrt_by_newton(q @ q + 1) + jax.lax.fori_loop(0, 3, lambda i, x: x * q[0], 1.0),
], ids=["kepler", "cosh-norm-cond", "custom-jvp-while-scan"])
def test_structure_reads_separable_programs_as_separable(H):
    s = gj.structure(H, Q, P)
    assert s.separable and not s.force_reads_p and not s.velocity_reads_q and s.reason == ""


@pytest.mark.parametrize("H, args", [
    (lambda q, p, eps: p @ p / 2 + q @ q / 2 + eps * (q @ p), 0.0),  # eps = 0 in args: zero by value only
    (lambda q, p: p @ p / 2 + q @ q / 2 + q @ p - p @ q, None),  # cancels numerically
    (lambda q, p: p @ p / 2 + q @ q / 2 + 0.0 * (q @ p), None),  # times 0.0
    (lambda q, p: p @ p / 2 + q @ q / 2 + (q[0] - 1.0) ** 2 * p[0], None),  # zero with its gradients at q0
    (lambda q, p: p @ p / 2 + _sqrt_by_newton(q @ q + p[0] ** 2 + 1), None),
    (lambda q, p: p @ p / 2 + jax.lax.while_loop(lambda c: c[1] < 3, lambda c: (c[0] * q[0], c[1] + 1), (1.0, 0))[0],
     None),  # no reverse mode through while_loop: undecidable, general
], ids=["eps-args", "qp-minus-pq", "times-zero", "zero-at-q0", "custom-jvp-p", "while-undecidable"])
def test_structure_is_general_where_separability_holds_only_by_value(H, args):
    """Never a wrong "separable": each H is non-separable as a program although each is
    separable at Q (or everywhere, by value)."""
    q0 = jnp.array([1.0, 0.5])
    assert not gj.structure(H, q0, P, args=args).separable


def test_structure_of_pytree_states_and_args():
    q = {"x": jnp.ones(3), "y": jnp.ones((2, 2))}
    p = jax.tree.map(jnp.zeros_like, q)
    kinetic = lambda p: sum(jnp.sum(x ** 2) for x in jax.tree.leaves(p)) / 2
    assert gj.structure(lambda q, p, a: kinetic(p) + a["k"] * jnp.sum(q["x"]) * jnp.sum(q["y"]), q, p,
                        args={"k": 2.0}).separable
    s = gj.structure(lambda q, p: kinetic(p) + jnp.sum(q["x"]) * jnp.sum(p["y"]), q, p)
    assert not s.separable and s.force_reads_p and s.velocity_reads_q


# --- explicit elements -------------------------------------------------------------------


@pytest.mark.parametrize("rule", [gj.trapezoid(), gj.gauss_lobatto(2)], ids=["trapezoid", "lobatto2"])
def test_explicit_verlet_equals_the_iterated_galerkin_vi_to_roundoff(rule):
    """Measured: 4e-16 (q), 9e-16 (p) after 1000 Kepler steps; 1e-13 leaves room for the
    round-off of other CPUs (it grows like sqrt(n))."""
    H, q0, p0 = KEPLER
    method = gj.GalerkinVI(1, rule)
    a = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=1000)
    b = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=1000, solver=ITERATED)
    assert int(a.stats["num_newton_iterations"]) == 0 and int(b.stats["num_newton_iterations"]) > 0
    assert int(a.status) == 0
    np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.p, b.p, rtol=0, atol=1e-13)
    np.testing.assert_allclose(gj.step(H, q0, p0, method=method, h=0.1),
                               gj.step(H, q0, p0, method=method, h=0.1, solver=ITERATED), rtol=0, atol=1e-15)


def test_explicit_verlet_is_stormer_verlet():
    """Kick-drift-kick written out [HLW, eq. (I.3.6)], for a non-quadratic T(p)."""
    T = lambda p: jnp.sum(jnp.cosh(p))
    V = lambda q: jnp.sum(q ** 4) / 4 + q[0] * q[1]
    H = lambda q, p: T(p) + V(q)
    q0, p0, h = jnp.array([0.3, -0.2]), jnp.array([0.1, 0.4]), 0.05
    half = p0 - h / 2 * jax.grad(V)(q0)
    q1 = q0 + h * jax.grad(T)(half)
    p1 = half - h / 2 * jax.grad(V)(q1)
    np.testing.assert_allclose(jnp.concatenate(gj.step(H, q0, p0, method=VERLET, h=h)), jnp.concatenate([q1, p1]),
                               rtol=0, atol=1e-15)


def test_general_h_keeps_the_iterated_element():
    H, q0, p0 = helpers.non_separable()
    sol = gj.integrate(H, q0, p0, method=VERLET, h=0.05, n_steps=20)
    assert int(sol.status) == 0 and int(sol.stats["num_newton_iterations"]) > 0


def test_explicit_verlet_has_order_2_and_is_symplectic():
    """Fitted slope over h = 2 pi / 200 ... / 1600: 2.00 (the Verlet error constant is smooth
    in h here); symplecticity defect of the AD Jacobian: round-off (measured 2e-16)."""
    H, q0, p0 = KEPLER
    T = 2 * np.pi
    qe, pe = helpers.kepler_exact(T)
    ns = (200, 400, 800, 1600)
    errs = []
    for n in ns:
        s = gj.integrate(H, q0, p0, method=VERLET, h=T / n, n_steps=n, error_estimate=False)
        errs.append(float(jnp.max(jnp.abs(jnp.concatenate([s.q[-1] - qe, s.p[-1] - pe])))))
    assert helpers.fitted_order([T / n for n in ns], errs) == pytest.approx(2.0, abs=0.1)
    A = gj.amplification_matrix(H, q0, p0, method=VERLET, h=0.1)
    assert helpers.symplecticity_defect(A) < 1e-14


def test_explicit_verlet_energy_stays_bounded():
    """Pendulum, h = 0.1, 20000 steps: the energy error oscillates at O(h^2) (measured max
    1.47e-3 in both halves of the run, equal to 1e-7) without drift; a drift of the first half's size would
    double it."""
    H, q0, p0 = helpers.pendulum()
    sol = gj.integrate(H, q0, p0, method=VERLET, h=0.1, n_steps=20000, save_every=10, error_estimate=False)
    e = np.abs(np.asarray(jax.vmap(H)(sol.q, sol.p)) - float(H(q0, p0)))
    first, second = e[: e.size // 2].max(), e[e.size // 2:].max()
    assert first < 5e-3 and second < 1.5 * first


def test_explicit_verlet_derivatives_vmap_and_save_at():
    H, q0, p0 = KEPLER
    run = lambda h: gj.integrate(H, q0, p0, method=VERLET, h=h, n_steps=100).q[-1, 0]
    eps = 1e-6
    fd = (run(0.01 + eps) - run(0.01 - eps)) / (2 * eps)
    # jitted gradients: one compiled program each (eagerly two, the forward pass's and the transpose's)
    assert float(jax.jit(jax.grad(run))(0.01)) == pytest.approx(float(fd), rel=1e-7)  # central FD: O(eps^2) + round-off
    gq = jax.jit(jax.grad(lambda q: gj.integrate(H, q, p0, method=VERLET, h=0.01, n_steps=50).p[-1, 1]))(q0)
    gq_iter = jax.jit(jax.grad(lambda q: gj.integrate(H, q, p0, method=VERLET, h=0.01, n_steps=50,
                                                      solver=ITERATED).p[-1, 1]))(q0)
    np.testing.assert_allclose(gq, gq_iter, rtol=1e-10)  # IFT through the iterations: the same derivative
    hs = jnp.array([0.01, 0.02])
    batch = jax.vmap(lambda h: gj.integrate(H, q0, p0, method=VERLET, h=h, n_steps=100).q[-1])(hs)
    np.testing.assert_allclose(batch[1], gj.integrate(H, q0, p0, method=VERLET, h=0.02, n_steps=100).q[-1],
                               rtol=0, atol=1e-14)
    ts = jnp.linspace(0.0, 1.0, 5)
    saved = gj.integrate(H, q0, p0, method=VERLET, h=0.01, t1=1.0, save_at=ts)
    nodes = gj.integrate(H, q0, p0, method=VERLET, h=0.01, n_steps=100)
    assert int(saved.status) == 0
    np.testing.assert_allclose(saved.q[-1], nodes.q[-1], rtol=0, atol=1e-12)


# --- compositions ------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SCHEMES))
def test_composition_coefficients_are_symmetric_and_consistent(name):
    """Sum 1, symmetric, and sum gamma^3 = 0 (order 4 for a symmetric order-2 base, HLW eq.
    (V.3.4)); order >= 6 also sum gamma^5 = 0. Measured: below 3e-16."""
    order, gamma = SCHEMES[name]
    g = np.asarray(gamma)
    assert abs(g.sum() - 1) < 1e-15 and np.array_equal(g, g[::-1])
    assert abs(np.sum(g ** 3)) < 1e-14
    if order >= 6:
        assert abs(np.sum(g ** 5)) < 1e-14


# measured slopes (Kepler, e = 0.5, one period): yoshida4 3.98, suzuki4 4.00, mclachlan4 4.00,
# yoshida6 6.00, kahan_li6 6.00, kahan_li8 8.1 (above 1e-11), kahan_li8_s17 8.0
@pytest.mark.parametrize("name, ns", [
    ("yoshida4", (100, 200, 400)), ("suzuki4", (100, 200, 400)), ("mclachlan4", (100, 200, 400)),
    ("yoshida6", (100, 200, 400)), ("kahan_li6", (100, 200, 400)), ("kahan_li8", (50, 100, 200)),
    ("kahan_li8_s17", (50, 100, 200)),
])
def test_composition_of_verlet_has_the_schemes_order(name, ns):
    H, q0, p0 = KEPLER
    T = 2 * np.pi
    qe, pe = helpers.kepler_exact(T)
    method = gj.Composition(VERLET, name)
    errs = []
    for n in ns:
        s = gj.integrate(H, q0, p0, method=method, h=T / n, n_steps=n, error_estimate=False)
        assert int(s.stats["num_newton_iterations"]) == 0  # explicit: no iteration
        errs.append(float(jnp.max(jnp.abs(jnp.concatenate([s.q[-1] - qe, s.p[-1] - pe])))))
    assert helpers.fitted_order([T / n for n in ns], errs, floor=1e-13) == pytest.approx(SCHEMES[method.scheme][0], abs=0.3)


def test_composition_of_midpoint_cg1_has_order_4():
    """cG(1) with the midpoint rule (implicit midpoint, symmetric, order 2) by the triple jump:
    measured slope 4.08 over these h."""
    H, q0, p0 = KEPLER
    T = 2 * np.pi
    qe, pe = helpers.kepler_exact(T)
    method = gj.Composition(gj.CG(1, gj.gauss_legendre(1)), "yoshida4")
    ns = (100, 200, 400)
    errs = []
    for n in ns:
        s = gj.integrate(H, q0, p0, method=method, h=T / n, n_steps=n, error_estimate=False)
        assert int(s.status) == 0
        errs.append(float(jnp.max(jnp.abs(jnp.concatenate([s.q[-1] - qe, s.p[-1] - pe])))))
    assert helpers.fitted_order([T / n for n in ns], errs) == pytest.approx(4.0, abs=0.2)


@pytest.mark.parametrize("method", [gj.Composition(gj.CG(1, gj.gauss_legendre(1)), "yoshida4"),
                                    gj.Composition(VERLET, "kahan_li6")], ids=["cg1-yoshida4", "verlet-kahan-li6"])
def test_composition_is_symplectic_and_symmetric(method):
    """Phi_{-h} o Phi_h = id, with Phi_{-h} for H that of -H for h: measured 2e-16; the
    symplecticity defect of the AD Jacobian: measured below 7e-16."""
    H, q0, p0 = KEPLER
    q1, p1 = gj.step(H, q0, p0, method=method, h=0.1)
    q2, p2 = gj.step(lambda q, p: -H(q, p), q1, p1, method=method, h=0.1)
    assert float(jnp.max(jnp.abs(jnp.concatenate([q2 - q0, p2 - p0])))) < 1e-14
    A = gj.amplification_matrix(H, q0, p0, method=method, h=0.1)
    assert helpers.symplecticity_defect(A) < 1e-13


def test_composition_save_at_and_refusals():
    H, q0, p0 = KEPLER
    method = gj.Composition(VERLET, "yoshida4")
    ts = jnp.linspace(0.0, 1.0, 5)
    saved = gj.integrate(H, q0, p0, method=method, h=0.01, t1=1.0, save_at=ts)
    nodes = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=100)
    assert int(saved.status) == 0
    np.testing.assert_allclose(saved.q[-1], nodes.q[-1], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="Composition with a PIDController"):
        gj.integrate(H, q0, p0, method=method, h=0.01, t1=1.0, controller=gj.PIDController(1e-6, 1e-6))
    with pytest.raises(ValueError, match="DG"):
        gj.Composition(gj.DG(1, gj.gauss_legendre(2)))
    with pytest.raises(ValueError, match="not symmetric"):
        gj.Composition(gj.CG(1, gj.gauss_radau(2)))
    with pytest.raises(ValueError, match="unknown scheme"):
        gj.Composition(VERLET, "yoshida5")
    with pytest.raises(ValueError, match="symmetric and sum to 1"):
        gj.Composition(VERLET, (0.5, 0.6))


# --- the closed form on every path -------------------------------------------------------


def _both(H, q0, p0, **kwargs):
    """The run with the closed form and the iterated one (``SolverOptions(explicit=False)``)."""
    return (gj.integrate(H, q0, p0, method=VERLET, **kwargs),
            gj.integrate(H, q0, p0, method=VERLET, solver=ITERATED, **kwargs))


def _gap(a, b):
    return float(jnp.max(jnp.abs(jnp.concatenate([jnp.ravel(a.q - b.q), jnp.ravel(a.p - b.p)]))))


@pytest.mark.parametrize("case", ["save_at", "events", "dense", "pid", "backwards", "save_at steps"])
def test_runs_whose_steps_a_loop_chooses_compute_the_closed_form(case):
    """save_at, events, dense output, a PIDController and a run backwards go through the loop of
    ``_adaptive``: each takes Verlet's closed form there (zero iterations) and equals the
    iterated solve to round-off (measured 7e-16, under PID 4e-15; the iterated run adds with
    compensation, the explicit one without), with the same error estimate (relative 1e-10)."""
    H, q0, p0 = KEPLER
    kwargs = {
        "save_at": dict(h=0.01, t1=3.0, save_at=jnp.linspace(0.0, 3.0, 7)),
        "events": dict(h=0.01, t1=3.0, events=gj.Event(lambda t, q, p: q[0], capacity=4)),
        "dense": dict(h=0.01, n_steps=300, dense=True),
        # GalerkinVI(1)'s momentum is constant on an element: its embedded estimate is O(h), and
        # the controller's steps shrink with the tolerance (593 steps to t = 0.5 at 1e-3)
        "pid": dict(h=0.01, t1=0.5, controller=gj.PIDController(1e-3, 1e-3)),
        "backwards": dict(h=0.01, t1=-3.0, save_at=jnp.linspace(0.0, -3.0, 4)),
        "save_at steps": dict(h=0.01, t1=1.0, save_at="steps"),
    }[case]
    a, b = _both(H, q0, p0, **kwargs)
    assert int(a.status) == int(b.status) == 0
    assert int(a.stats["num_newton_iterations"]) == 0 and int(b.stats["num_newton_iterations"]) > 0
    assert int(a.stats["num_accepted_steps"]) == int(b.stats["num_accepted_steps"])
    assert _gap(a, b) < 1e-13
    assert float(a.error_estimate) == pytest.approx(float(b.error_estimate), rel=1e-8)
    if case == "events":
        assert int(a.events.count) == int(b.events.count) >= 1
        np.testing.assert_allclose(a.events.t, b.events.t, rtol=0, atol=1e-13)
    if case == "dense":
        ts = jnp.linspace(0.0, 2.995, 41)
        np.testing.assert_allclose(jnp.concatenate(a.evaluate(ts), -1), jnp.concatenate(b.evaluate(ts), -1), rtol=0,
                                   atol=1e-13)


def test_a_time_transformed_run_iterates_its_non_separable_k():
    """A TimeTransform hands the method K = s(q, p) (H + p_t), which is not separable where H is:
    the run iterates (as the iterated one does) instead of using H's closed form."""
    H, q0, p0 = KEPLER
    a, b = _both(H, q0, p0, h=0.05, t1=3.0, controller=gj.TimeTransform())
    assert int(a.status) == 0 and int(a.stats["num_newton_iterations"]) > 0
    assert _gap(a, b) == 0.0


def test_sweeps_compute_the_closed_form():
    """A sweep's members (fixed steps, and a PIDController's) take the closed form: zero
    iterations, the iterated sweep's states to round-off (measured 2e-15; energy errors 4e-9
    relative)."""
    H, q0, p0 = KEPLER
    configs = gj.grid(method=VERLET, state=(q0, p0), h=[0.01, 0.02])
    for kwargs in (dict(n_steps=100), dict(t1=0.5, controller=gj.PIDController(1e-3, 1e-3))):
        a, b = gj.sweep(H, configs, **kwargs), gj.sweep(H, configs, solver=ITERATED, **kwargs)
        assert np.all(np.asarray(a.status) == 0) and np.all(np.asarray(a.num_newton_iterations) == 0)
        assert np.all(np.asarray(b.num_newton_iterations) > 0)
        np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-13)
        np.testing.assert_allclose(a.energy_error, b.energy_error, rtol=1e-6)


@functools.cache
def _jacobians(case):
    """d(q, p)(T) / d(q0, p0) of the closed form (autodiff of Verlet) and of the iterated solve
    (the implicit function theorem), each by forward and by reverse mode: one compiled program
    for all four, the products of one linearization and of its transpose (``helpers.jacobians``,
    as ``jax.jacfwd`` and ``jax.jacrev`` compute them), shared by the tests of the two modes."""
    H, q0, p0 = KEPLER
    kwargs = {"fixed": dict(h=0.01, n_steps=100), "save_at": dict(h=0.01, t1=1.0, save_at=jnp.linspace(0.0, 1.0, 3)),
              "pid": dict(h=0.01, t1=0.5, controller=gj.PIDController(1e-3, 1e-3))}[case]

    def final(z, solver):
        sol = gj.integrate(H, z[:2], z[2:], method=VERLET, solver=solver, **kwargs)
        return jnp.concatenate([sol.q[-1], sol.p[-1]])

    def modes(z, solver):
        _, forward, reverse = helpers.jacobians(lambda z: final(z, solver), z)
        return {"jacfwd": forward, "jacrev": reverse}

    return jax.jit(lambda z: (modes(z, None), modes(z, ITERATED)))(jnp.concatenate([q0, p0]))


@pytest.mark.parametrize("mode", ["jacfwd", "jacrev"])
@pytest.mark.parametrize("case", ["fixed", "save_at", "pid"])
def test_derivatives_of_the_closed_form_equal_the_iterated_ones(mode, case):
    """d(q, p)(T) / d(q0, p0) by forward and reverse mode through the closed form (autodiff of
    Verlet) and through the iterated solve (the implicit function theorem): the same Jacobian
    to round-off (measured at most 7e-15 on entries up to 8.3)."""
    closed_form, iterated = _jacobians(case)
    a, b = closed_form[mode], iterated[mode]
    assert bool(jnp.all(jnp.isfinite(a)))
    np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12)


def test_vmap_over_states_and_steps_of_the_closed_form():
    H, q0, p0 = KEPLER
    hs = jnp.array([0.01, 0.02, 0.005])
    run = lambda h, solver: gj.integrate(H, q0, p0, method=VERLET, h=h, t1=1.0, save_at=jnp.linspace(0.0, 1.0, 3),
                                         max_steps=256, solver=solver)
    a, b = jax.vmap(lambda h: run(h, None))(hs), jax.vmap(lambda h: run(h, ITERATED))(hs)
    assert np.all(np.asarray(a.stats["num_newton_iterations"]) == 0)
    np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-13)


def test_the_closed_form_compiles_no_solver():
    """A save_at run of the closed form compiles no root finder: its program is a fraction of
    the iterated run's (measured 750 and 2544 StableHLO operations with JAX 0.10.2)."""
    from test_program import operations

    H, q0, p0 = KEPLER
    run = lambda solver: lambda q, p: gj.integrate(H, q, p, method=VERLET, h=0.01, t1=1.0, solver=solver,
                                                   save_at=jnp.linspace(0.0, 1.0, 5)).q
    explicit, iterated = operations(run(None), q0, p0), operations(run(ITERATED), q0, p0)
    assert explicit < 0.4 * iterated, (explicit, iterated)


def test_a_non_finite_explicit_run_fails_as_the_iterated_one():
    """Verlet on a quartic potential far beyond its stability limit (h = 0.5): |q| grows like its
    cube each element and overflows in the eighth; status NONFINITE, NaN states from there,
    and the seven elements solved before it counted as the iterated run counts them."""
    H = lambda q, p: p @ p / 2 + jnp.sum(q ** 4)
    q0, p0 = jnp.array([1.7, 0.5]), jnp.array([0.3, 0.0])
    a, b = _both(H, q0, p0, h=0.5, n_steps=40)
    assert int(a.status) == int(b.status) == gj.Status.NONFINITE
    assert int(a.stats["num_accepted_steps"]) == int(b.stats["num_accepted_steps"]) == 7
    np.testing.assert_array_equal(np.isnan(a.q), np.isnan(b.q))
    assert bool(jnp.all(jnp.isnan(a.q[8:]))) and bool(jnp.all(jnp.isfinite(a.q[:8])))


def test_the_structure_is_read_once_per_function_and_shape(monkeypatch):
    """A loop of ``step`` calls traces grad H for ``gj.structure`` once (``_explicit.cached_structure``)."""
    from galerkin_jax import _explicit

    H = lambda q, p: p @ p / 2 + jnp.sum(q ** 4) / 4
    q, p = jnp.array([0.3, -0.1]), jnp.array([0.2, 0.0])
    q, p = gj.step(H, q, p, method=VERLET, h=0.1)
    calls = []
    monkeypatch.setattr(_explicit, "structure", lambda *a, **k: calls.append(a))
    for _ in range(5):
        q, p = gj.step(H, q, p, method=VERLET, h=0.1)
    assert calls == []


def test_integrate_refuses_zero_steps():
    H, q0, p0 = helpers.kepler()
    with pytest.raises(ValueError, match=r"n_steps must be an integer >= 1, got 0"):
        gj.integrate(H, q0, p0, method=gj.GalerkinVI(1, gj.trapezoid()), h=0.1, n_steps=0)


def test_kahan_li_schemes_are_named_by_their_stage_counts():
    """s15odr8 and s17odr8b are "kahan_li8_s15" and "kahan_li8_s17"; "kahan_li8", the old name
    of the 15-stage one, is the same scheme."""
    assert len(SCHEMES["kahan_li8_s15"][1]) == 15 and len(SCHEMES["kahan_li8_s17"][1]) == 17
    old, new = gj.Composition(VERLET, "kahan_li8"), gj.Composition(VERLET, "kahan_li8_s15")
    assert old.coefficients == new.coefficients and old == new


@pytest.mark.parametrize("inner, per_stage", [(gj.GalerkinVI(1, gj.trapezoid()), 1), (gj.Splitting("leapfrog"), 1),
                                              (gj.Splitting("blanes_moan_rkn4"), 6), (gj.Splitting("blanes_moan4"), 6)])
def test_forces_per_step_of_an_explicit_composition(inner, per_stage):
    """One element's program holds as many gradients of V (sin, from -cos) as a composition's
    ``forces_per_step`` says: stages times the inner method's count (its force first same as
    last, carried from stage to stage); None for a method that iterates."""
    H = lambda q, p: 0.5 * (p @ p) - jnp.sum(jnp.cos(q))
    q, p = jnp.array([0.3, 0.1]), jnp.array([0.0, 0.2])
    for scheme, stages in (("yoshida4", 3), ("kahan_li8_s15", 15)):
        method = gj.Composition(inner, scheme)
        explicit = explicit_form(method, H, q, p, None, gj.SolverOptions())
        g0 = explicit.explicit_start(H, q, p)
        jaxpr = jax.make_jaxpr(lambda q, p, g: explicit.explicit(H, q, p, 0.1, g))(q, p, g0)
        count = sum(eqn.primitive.name == "sin" for eqn in jaxpr.jaxpr.eqns)
        assert count == stages * per_stage == method.forces_per_step == explicit.forces_per_step
    assert gj.Composition(gj.CG(1, gj.gauss_legendre(1))).forces_per_step is None


def _morse_chain(n=8):
    """A chain of n atoms in 1-D, neighbours bound by Morse pairs V = (1 - exp(-(r - 1)))^2 at rest
    length 1, with small momenta; its fastest mode has omega ~ 2.8, so a step of 2 is unstable."""
    def H(q, p):
        r = jnp.abs(q[1:] - q[:-1])
        return 0.5 * (p @ p) + jnp.sum((1.0 - jnp.exp(-(r - 1.0))) ** 2)
    return H, jnp.arange(n, dtype=jnp.float64), 0.3 * jnp.sin(1.7 * jnp.arange(n))


@pytest.mark.parametrize("how", [dict(n_steps=50), dict(n_steps=200), dict(n_steps=50, error_estimate="full"),
                                 dict(n_steps=50, save_at="steps"), dict(n_steps=50, solver=ITERATED)])
def test_a_blown_up_explicit_run_is_inaccurate(how):
    """blanes_moan_rkn4 at h = 2 on a Morse chain: the chain flies apart (max |q| 1.1e3 after 50
    steps, 4.8e3 after 200) and the largest local error is 2.8e2 on an element whose state is of
    size 7 to 11, 25x or more the threshold 0.1 of it: status INACCURATE, with the states and the
    estimate kept, and throw=True raises. At h = 0.5 the estimate is 1e-4 of the state (1e-5 of it
    with the default): status 0."""
    H, q0, p0 = _morse_chain()
    method = gj.Splitting("blanes_moan_rkn4")
    n = how.pop("n_steps")
    save_at = how.pop("save_at", None)
    kw = dict(how, t1=2.0 * n, save_at=save_at) if save_at else dict(how, n_steps=n)
    sol = gj.integrate(H, q0, p0, method=method, h=2.0, **kw)
    assert int(sol.status) == gj.Status.INACCURATE
    assert float(sol.error_estimate) > 250 and bool(jnp.all(jnp.isfinite(sol.q[-1])))
    assert float(jnp.max(jnp.abs(sol.q[-1]))) > 1e3
    assert "accuracy" in gj.status_message(sol.status)
    with pytest.raises(gj.SolverError, match="INACCURATE"):
        gj.integrate(H, q0, p0, method=method, h=2.0, throw=True, **kw)
    good = gj.integrate(H, q0, p0, method=method, h=0.5, **dict(kw, t1=0.5 * n) if save_at else kw)
    assert int(good.status) == 0 and float(good.error_estimate) < 2e-4


def test_a_blown_up_sweep_member_is_inaccurate():
    """The sweep decides as integrate does: of h = 0.5 and 2, the second member is INACCURATE."""
    H, q0, p0 = _morse_chain()
    result = gj.sweep(H, gj.grid(method=[gj.Splitting("blanes_moan_rkn4")], h=[0.5, 2.0], state=[(q0, p0)]),
                      n_steps=50)
    assert [int(s) for s in result.status] == [0, gj.Status.INACCURATE]
    assert np.isfinite(np.asarray(result.energy_error)).all()


def test_the_success_message_fits_explicit_methods():
    message = gj.status_message(0)
    assert "explicit" in message and "error_estimate" in message


@pytest.mark.parametrize("h, n, iterate", [(0.08, 80, True), (0.05, 126, False)])
def test_the_default_estimate_of_a_composition_finds_its_largest_local_error(h, n, iterate):
    """kahan_li8_s15 of Verlet on Kepler (e = 0.5) from apocentre, one period: the default estimate
    (the full one on the four elements where the embedded one peaks) equals the full one on every
    element, by the explicit and the iterated path alike, and both are within 0.8-1.2 of the
    true largest local error (the element against 32 of h / 32 from its start: 0.92-0.93 measured).
    Before, the Hermite cubic's defect at alpha = 1 was zero, the ranking round-off:
    explicit 1.37e-11 against 1.96e-11 at h = 0.05; iterated 7.8e-10 against 1.40e-9 at h = 0.08."""
    H, _, _ = helpers.kepler()
    q0, p0 = (jnp.asarray(x) for x in helpers.kepler_exact(np.pi))
    method = gj.Composition(VERLET, "kahan_li8_s15")
    run = lambda **kw: gj.integrate(H, q0, p0, method=method, h=h, n_steps=n, **kw)
    sol, full = run(), run(error_estimate="full")
    explicit = explicit_form(method, H, q0, p0, None, gj.SolverOptions())

    def flow(z, k):
        def body(_, c):
            q, p, g = c
            _, (dq, dp), g = explicit.explicit(H, q, p, h / k, g)
            return q + dq, p + dp, g
        q, p = jnp.split(z, 2)
        return jnp.concatenate(jax.lax.fori_loop(0, k, body, (q, p, explicit.explicit_start(H, q, p)))[:2])

    starts = jnp.concatenate([sol.q, sol.p], axis=1)[:-1]
    true = float(jnp.max(jax.vmap(lambda z: jnp.max(jnp.abs(flow(z, 1) - flow(z, 32))))(starts)))
    for estimate in (sol.error_estimate, run(solver=ITERATED).error_estimate) if iterate else (sol.error_estimate,):
        np.testing.assert_allclose(float(estimate), float(full.error_estimate), rtol=1e-3)
    assert 0.8 < float(full.error_estimate) / true < 1.2, (float(full.error_estimate), true)


@pytest.mark.parametrize("method", [gj.Splitting("blanes_moan_rkn4"), gj.Composition(VERLET, "yoshida4")])
@pytest.mark.parametrize("error_estimate", [True, False])
def test_a_non_finite_explicit_run_never_has_status_0(method, error_estimate):
    """The quartic potential far beyond the stability limit (h = 1) overflows within five elements:
    NONFINITE, with or without an estimate (NaN never passes as status 0, nor as INACCURATE)."""
    H = lambda q, p: p @ p / 2 + jnp.sum(q ** 4)
    sol = gj.integrate(H, jnp.array([1.7, 0.5]), jnp.array([0.3, 0.0]), method=method, h=1.0, n_steps=40,
                       error_estimate=error_estimate)
    assert int(sol.status) == gj.Status.NONFINITE and bool(jnp.isnan(sol.q[-1]).all())


def test_an_inaccurate_run_keeps_its_derivatives():
    """INACCURATE keeps the states, and so their derivatives: d sum q(40) / d p0 of the blown-up
    Morse chain (h = 2) through the loop's adjoint (save_at) equals the fixed-step scan's (40.0 in
    every entry, measured to 1e-8)."""
    H, q0, p0 = _morse_chain()
    method = gj.Splitting("blanes_moan_rkn4")
    fixed = lambda p0: jnp.sum(gj.integrate(H, q0, p0, method=method, h=2.0, n_steps=20).q[-1])
    loop = lambda p0: jnp.sum(gj.integrate(H, q0, p0, method=method, h=2.0, t1=40.0, save_at=jnp.array([40.0])).q[-1])
    np.testing.assert_allclose(jax.grad(loop)(p0), jax.grad(fixed)(p0), rtol=1e-6)


@pytest.mark.parametrize("method", [gj.Composition(VERLET, "kahan_li8"), gj.Composition(gj.CG(2, gj.gauss_legendre(2))),
                                    gj.Splitting("blanes_moan_rkn6"), gj.Tao(), gj.Composition(gj.Tao(), "yoshida4")],
                         ids=["kahan_li8 of Verlet", "triple jump of cG(2)", "blanes_moan_rkn6", "Tao", "Tao, yoshida4"])
def test_an_elements_polynomial_and_estimate_from_its_increment_equal_the_methods_own(method):
    """A run hands ``polynomial_with`` and ``local_error_with`` the increment it has (and an
    explicit element the field at its ends), so a composition's stages are not computed again:
    the Hermite cubic and the local error equal ``polynomial`` and ``local_error`` computed
    from the unknowns alone, to round-off (measured: equal to 1e-16)."""
    H, q0, p0 = KEPLER
    h = 0.05
    form = explicit_form(method, H, q0, p0, None, gj.SolverOptions())
    if form is not None and callable(getattr(form, "explicit", None)):
        memo = form.explicit_start(H, q0, p0)
        Z, (dq, dp), memo1 = form.explicit(H, q0, p0, h, memo)
        fields = form.explicit_field(H, q0, p0, memo), form.explicit_field(H, q0 + dq, p0 + dp, memo1)
    else:  # the triple jump of cG(2) iterates: its element's root
        form = method
        Z = _root(method, H, q0, p0, h)
        dq, dp = method.increment(H, q0, p0, Z, h)
        fields = None
    dz = jnp.concatenate([dq, dp])
    own = form.polynomial(H, q0, p0, Z, h)
    for given in (None, fields):
        np.testing.assert_allclose(form.polynomial_with(H, q0, p0, Z, h, dz, given), own, rtol=0, atol=1e-15)
    np.testing.assert_allclose(form.local_error_with(H, q0, p0, Z, h, dz), form.local_error(H, q0, p0, Z, h),
                               rtol=1e-12)
    assert float(form.local_error(H, q0, p0, Z, h)) > 0


def _root(method, H, q0, p0, h):
    """The root of ``method``'s element equations from (q0, p0) (``_march.solve_element``)."""
    from galerkin_jax._march import solve_element, solver_options

    return solve_element(method, H, q0, p0, h, None, solver_options(method))[2]
