"""Inputs as users write them: closures, ``jax.jit`` with Python times, pytrees with static
leaves (an equinox module), a density of one's own, H's program read anew, and the edges of a
time span (``galerkin_jax._inputs``, ``_span``, ``_explicit.cached_structure``).

Derivatives are compared with the same run's ``args`` derivative (the contract: a closed-over
array differentiates exactly as if passed in ``args``, so to round-off) and with central
differences (step 1e-5 on O(1) functions: truncation ~1e-10, round-off ~1e-11; margin 1e-7).
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj

CG3 = gj.CG(3, gj.gauss_legendre(3))
Q0, P0 = jnp.array([1.0]), jnp.array([0.0])


def oscillator(q, p, k):
    return 0.5 * p @ p + 0.5 * k * q @ q + 0.1 * (q @ q) ** 2


def central(f, x, eps=1e-5):
    return (f(x + eps) - f(x - eps)) / (2 * eps)


def test_jit_of_a_fixed_step_run_to_a_python_t1_equals_the_run_outside_it():
    H = lambda q, p: -q @ p  # q' = -q: q(1) = exp(-1)
    run = lambda q0: gj.integrate(H, q0, jnp.array([1.0]), method=CG3, h=0.1, t1=1.0).q[-1, 0]
    eager, jitted = run(jnp.array([1.0])), jax.jit(run)(jnp.array([1.0]))
    assert float(jitted) == float(eager)
    assert abs(float(eager) - np.exp(-1.0)) < 1e-9  # cG(3): order 6, h = 0.1
    only_args = lambda k: gj.integrate(oscillator, Q0, P0, method=CG3, h=0.1, t1=1.0, args=k).q[-1, 0]
    assert float(jax.jit(only_args)(2.0)) == float(only_args(2.0))


@pytest.mark.parametrize("controller", [None, gj.PIDController(rtol=1e-8, atol=1e-8)], ids=["fixed", "pid"])
def test_a_closure_in_H_differentiates_as_args_in_both_modes_under_jit_and_vmap(controller):
    span = dict(t1=1.0) if controller is not None else dict(n_steps=10)

    def closed(k):
        return gj.integrate(lambda q, p: oscillator(q, p, k), Q0, P0, method=CG3, h=0.1, controller=controller,
                            **span).q[-1, 0]

    def passed(k):
        return gj.integrate(oscillator, Q0, P0, method=CG3, h=0.1, controller=controller, args=k, **span).q[-1, 0]

    k = 2.0
    reference = jax.grad(passed)(k)
    assert float(jax.grad(closed)(k)) == pytest.approx(float(reference), rel=1e-12, abs=1e-14)
    assert float(jax.jvp(closed, (k,), (1.0,))[1]) == pytest.approx(float(reference), rel=1e-12, abs=1e-14)
    assert abs(float(reference) - float(central(passed, k))) < 1e-7
    ks = jnp.array([1.5, 2.0])
    np.testing.assert_allclose(jax.vmap(closed)(ks), jax.vmap(passed)(ks), rtol=1e-14)
    if controller is None:  # a controller's run under jit and vmap: the harness (test_combinations)
        assert float(jax.jit(jax.grad(closed))(k)) == pytest.approx(float(reference), rel=1e-12, abs=1e-14)
        np.testing.assert_allclose(jax.vmap(jax.grad(closed))(ks), jax.vmap(jax.grad(passed))(ks), rtol=1e-12)


def test_a_closure_in_a_step_density_differentiates_as_args():
    H = lambda q, p: oscillator(q, p, 1.0)
    density = lambda q, p, c: 1.0 / (1.0 + c * q @ q)

    def closed(c):
        return gj.integrate(H, Q0, P0, method=CG3, h=0.25, t1=3.0,
                            controller=gj.TimeTransform(lambda q, p: density(q, p, c))).q[-1, 0]

    H_args = lambda q, p, c: H(q, p)  # s(q, p, args) reads args; H takes args too, unread

    def passed(c):  # one H and one s for every call: one program
        return gj.integrate(H_args, Q0, P0, method=CG3, h=0.25, t1=3.0, args=c,
                            controller=gj.TimeTransform(density)).q[-1, 0]

    c = 0.5
    assert float(closed(c)) == pytest.approx(float(passed(c)), rel=1e-14)
    reference = jax.grad(passed)(c)
    assert float(jax.grad(closed)(c)) == pytest.approx(float(reference), rel=1e-10, abs=1e-16)
    # the final state reads s only through the discretisation error: a small derivative, still that of
    # central differences (h = 0.25, a visible error)
    assert abs(float(reference) - float(central(passed, c, 1e-4))) < 1e-8


def test_an_equinox_mlp_trains_through_integrate_without_partition():
    mlp = eqx.nn.MLP(2, 1, 8, 2, activation=jnp.tanh, key=jax.random.PRNGKey(0))
    mlp = jax.tree.map(lambda x: x.astype(jnp.float64) if eqx.is_array(x) else x, mlp)
    H = lambda q, p, net: 0.5 * p @ p + 0.5 * q @ q + 0.1 * net(jnp.concatenate([q, p]))[0] ** 2

    def loss(net):
        return gj.integrate(H, Q0, jnp.array([0.3]), method=CG3, h=0.1, n_steps=10, args=net).q[-1, 0]

    params, static = eqx.partition(mlp, eqx.is_array)
    direction = jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(1), x.shape), params)
    along = lambda e: loss(eqx.combine(jax.tree.map(lambda a, b: a + e * b, params, direction), static))
    grads = eqx.filter_grad(loss)(mlp)
    reverse = sum(jnp.sum(g * d) for g, d in zip(jax.tree.leaves(eqx.filter(grads, eqx.is_array)),
                                                  jax.tree.leaves(direction)))
    forward = jax.jvp(along, (0.0,), (1.0,))[1]
    assert float(forward) == pytest.approx(float(reverse), rel=1e-10)
    assert abs(float(reverse) - float(central(along, 0.0))) < 1e-7
    assert float(eqx.filter_jit(loss)(mlp)) == pytest.approx(float(loss(mlp)), rel=1e-14)


def test_static_leaves_of_args_are_read_as_python_values():
    def H(q, p, args):  # an int that sizes a loop, a function, a string: static
        assert args["name"] == "poly"
        V = sum(args["coeffs"][i] * (q @ q) ** (i + 1) for i in range(args["terms"]))
        return args["kinetic"](p) + V

    args = dict(terms=2, coeffs=jnp.array([0.5, 0.1]), kinetic=lambda p: 0.5 * p @ p, name="poly")
    sol = gj.integrate(H, Q0, jnp.array([0.3]), method=CG3, h=0.1, n_steps=10, args=args)
    same = gj.integrate(lambda q, p: 0.5 * p @ p + 0.5 * q @ q + 0.1 * (q @ q) ** 2, Q0, jnp.array([0.3]),
                        method=CG3, h=0.1, n_steps=10)
    np.testing.assert_allclose(sol.q, same.q, rtol=1e-14)
    g = jax.grad(lambda c: gj.integrate(H, Q0, jnp.array([0.3]), method=CG3, h=0.1, n_steps=10,
                                        args=dict(args, coeffs=c)).q[-1, 0])(args["coeffs"])
    assert g.shape == (2,) and np.all(np.isfinite(g)) and abs(float(g[0])) > 1e-3


def test_a_density_of_ones_own_under_jit_of_grad_in_t1():
    H = lambda q, p: 0.5 * p @ p + 0.5 * q @ q  # q(t) = cos t: dq(t1)/dt1 = -sin t1
    run = lambda t1: gj.integrate(H, Q0 * 0 + 1.0, P0, method=gj.CG(2, gj.gauss_legendre(2)), h=0.1, t1=t1,
                                  controller=gj.TimeTransform(lambda q, p: 1.0 / (1.0 + q @ q))).q[-1, 0]
    eager, jitted = jax.grad(run)(1.0), jax.jit(jax.grad(run))(1.0)
    assert float(jitted) == pytest.approx(float(eager), rel=1e-12)
    assert abs(float(eager) + np.sin(1.0)) < 1e-6  # cG(2), h = 0.1 in tau: the states' error ~1e-7


def test_the_separability_verdict_follows_the_program_that_runs():
    flag = dict(coupled=False)

    def H(q, p):
        energy = 0.5 * p @ p + 0.5 * q @ q + 0.1 * (q @ q) ** 2
        return energy + 0.01 * (q @ p) ** 2 if flag["coupled"] else energy

    verlet, p0 = gj.GalerkinVI(1, gj.trapezoid()), jnp.array([0.3])
    run = lambda **kw: gj.integrate(H, Q0, p0, method=verlet, h=0.1, n_steps=20, **kw)
    separable = run()
    assert int(separable.stats["num_newton_iterations"]) == 0
    flag["coupled"] = True
    coupled, iterated = run(), run(solver=gj.SolverOptions(explicit=False))
    assert int(coupled.stats["num_newton_iterations"]) > 20  # solved, not the stale closed form
    np.testing.assert_allclose(coupled.q, iterated.q, rtol=1e-12)
    # the coupling moves the state by ~1e-2 at t = 2: the stale verdict would be off by that much
    assert abs(float(coupled.q[-1, 0] - separable.q[-1, 0])) > 1e-3


def test_an_undecidable_structure_warns_where_a_method_could_run_without_iteration():
    def V(q):
        jax.debug.callback(lambda x: None, q)
        return 0.5 * q @ q

    H = lambda q, p: 0.5 * p @ p + V(q)
    with pytest.warns(gj.UndecidedStructureWarning, match="debug_callback"):
        sol = gj.integrate(H, Q0, jnp.array([0.3]), method=gj.GalerkinVI(1, gj.trapezoid()), h=0.1, n_steps=3)
    assert int(sol.status) == 0 and int(sol.stats["num_newton_iterations"]) > 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a method with no explicit form: no warning
        gj.integrate(H, Q0, jnp.array([0.3]), method=CG3, h=0.1, n_steps=3)
    with pytest.raises(ValueError, match="separable"):
        gj.integrate(H, Q0, jnp.array([0.3]), method=gj.Splitting("leapfrog"), h=0.1, n_steps=3)


RUNS = dict(fixed={}, pid=dict(controller=gj.PIDController(rtol=1e-6, atol=1e-6)),
            transform=dict(controller=gj.TimeTransform()), save_at=dict(save_at=jnp.array([1.0])),
            events=dict(events=gj.Event(lambda t, q, p: q[0])), dense=dict(dense=True))


@pytest.mark.parametrize("kind", RUNS)
def test_a_span_of_no_length_returns_the_initial_state(kind):
    q0, p0 = jnp.array([1.0]), jnp.array([0.5])
    sol = gj.integrate(lambda q, p: 0.5 * p @ p + 0.5 * q @ q, q0, p0, method=gj.CG(2, gj.gauss_legendre(2)),
                       h=0.1, t0=1.0, t1=1.0, **RUNS[kind])
    assert int(sol.status) == 0
    np.testing.assert_array_equal(sol.t, 1.0)
    np.testing.assert_array_equal(sol.q, np.broadcast_to(q0, sol.q.shape))
    np.testing.assert_array_equal(sol.p, np.broadcast_to(p0, sol.p.shape))


def test_a_derivative_in_t1_of_fixed_steps_needs_no_max_steps_outside_jit():
    H = lambda q, p: 0.5 * p @ p + 0.5 * q @ q
    run = lambda t1: gj.integrate(H, Q0, jnp.array([0.5]), method=CG3, h=0.1, t1=t1).q[-1, 0]
    # q(t) = cos t + 0.5 sin t
    assert abs(float(jax.grad(run)(1.0)) - (-np.sin(1.0) + 0.5 * np.cos(1.0))) < 1e-9


def test_inputs_that_cannot_mean_anything_raise_naming_what_to_do():
    H = lambda q, p: 0.5 * p @ p + 0.5 * q @ q
    with pytest.raises(TypeError, match="returns a boolean.*q\\[0\\] - 1.0"):
        gj.integrate(H, Q0, P0 + 1, method=CG3, h=0.1, t1=3.0, events=gj.Event(lambda t, q, p: q[0] < 0))
    with pytest.raises(ValueError, match="runs until a terminal event"):
        gj.integrate(H, Q0, P0, method=CG3, h=0.1, t1=jnp.inf, events=gj.Event(lambda t, q, p: q[0]))
    with pytest.raises(ValueError, match="need max_steps"):
        gj.integrate(H, Q0, P0, method=CG3, h=0.1, t1=jnp.inf, events=gj.Event(lambda t, q, p: q[0], terminal=True))
    with pytest.raises(ValueError) as error:
        gj.integrate(H, jnp.full(1000, jnp.nan), jnp.zeros(1000), method=CG3, h=0.1, n_steps=3)
    assert "1000 of 1000 entries not finite" in str(error.value) and len(str(error.value)) < 120


@pytest.mark.parametrize("kind", ["fixed", "pid", "backwards"])
def test_a_closure_in_an_event_differentiates_in_both_modes_under_jit_and_vmap(kind):
    """The first time q = cos t falls to thr: arccos(thr), d/dthr = -1 / sqrt(1 - thr^2) (backwards:
    its negative)."""
    H = lambda q, p: 0.5 * p @ p + 0.5 * q @ q
    options = dict(fixed=dict(t1=3.0), pid=dict(t1=3.0, controller=gj.PIDController(rtol=1e-9, atol=1e-9)),
                   backwards=dict(t1=-3.0))[kind]
    sign = -1.0 if kind == "backwards" else 1.0

    def event_time(thr):
        return gj.integrate(H, Q0, P0, method=CG3, h=0.1, events=gj.Event(lambda t, q, p: q[0] - thr),
                            **options).events.t[0]

    thr = 0.5
    assert abs(float(event_time(thr)) - sign * np.arccos(thr)) < 1e-9  # the root to the run's accuracy
    exact = -sign / np.sqrt(1 - thr ** 2)
    reverse = jax.grad(event_time)(thr)
    assert abs(float(reverse) - exact) < 1e-8
    assert float(jax.jit(jax.grad(event_time))(thr)) == pytest.approx(float(reverse), rel=1e-12)
    assert float(jax.jvp(event_time, (thr,), (1.0,))[1]) == pytest.approx(float(reverse), rel=1e-12)
    thresholds = jnp.array([0.3, 0.5])
    np.testing.assert_allclose(jax.vmap(jax.grad(event_time))(thresholds), -sign / np.sqrt(1 - thresholds ** 2),
                               atol=1e-8)


@pytest.mark.parametrize("kind", ["fixed", "pid", "transform", "backwards"])
def test_an_infinite_t1_runs_until_the_terminal_event(kind):
    """q = cos t first falls to 1/2 at t = pi / 3 (backwards: -pi / 3)."""
    options = dict(fixed=dict(max_steps=100), pid=dict(controller=gj.PIDController(rtol=1e-9, atol=1e-9)),
                   transform=dict(controller=gj.TimeTransform()),
                   backwards=dict(controller=gj.PIDController(rtol=1e-9, atol=1e-9)))[kind]
    sign = -1.0 if kind == "backwards" else 1.0
    sol = gj.integrate(lambda q, p: 0.5 * p @ p + 0.5 * q @ q, Q0, P0, method=CG3, h=0.1, t1=sign * jnp.inf,
                       events=gj.Event(lambda t, q, p: q[0] - 0.5, terminal=True), **options)
    assert int(sol.status) == 0 and bool(sol.events.ended)
    assert abs(float(sol.t[-1]) - sign * np.pi / 3) < 1e-9  # h = 0.1 (in tau), cG(3): the root to ~1e-11
    assert abs(float(sol.q[-1, 0]) - 0.5) < 1e-9
