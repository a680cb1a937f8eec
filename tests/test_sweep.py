"""Batched sweeps: equal to one-by-one runs, padding-invariant, failure-isolated, shardable."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, Q0, P0 = helpers.kepler(0.5)
ANGULAR = {"L": lambda q, p: q[0] * p[1] - q[1] * p[0]}
RULES = [gj.gauss_legendre(2), gj.gauss_lobatto(3), gj.midpoint(), gj.QuadratureRule([0.3, 0.8], [0.5, 0.5])]
STEPS = [0.01, 0.02, 0.05, 0.1]
STATES = [(Q0, P0), (0.9 * Q0, P0), (Q0, 1.05 * P0), (1.1 * Q0, 0.95 * P0)]
N_STEPS = 100


def relative_change(values):
    values = np.asarray(values)
    return np.abs(values - values[0]).max() / np.abs(values[0])


def test_sweep_of_64_configurations_equals_one_by_one_runs():
    methods = [gj.CG(2, rule) for rule in RULES]
    result = gj.sweep(H, gj.grid(method=methods, h=STEPS, state=STATES), n_steps=N_STEPS, invariants=ANGULAR)
    assert result.energy_error.shape == (64,) and np.all(np.asarray(result.status) == 0)
    # the batch runs, per element, as many iterations as its slowest member
    assert int(result.batch_newton_iterations[0]) >= int(result.num_newton_iterations.max())
    rows = [(m, h, s) for m in methods for h in STEPS for s in STATES]
    along = jax.jit(lambda q, p: (jax.vmap(H)(q, p), jax.vmap(ANGULAR["L"])(q, p)))
    for i, (method, h, (q0, p0)) in enumerate(rows):
        sol = gj.integrate(H, q0, p0, method=method, h=h, n_steps=N_STEPS)  # the unpadded rule
        energy, L = along(sol.q, sol.p)
        # one solver: a member of the batch runs the iteration of the run alone, with its own
        # matrices and stops, also where it is one of the stragglers the batch (64 = 8 x
        # STRAGGLERS members) gathers apart; measured bitwise equal, a few ulps allowed for how
        # XLA compiles another batch size. (Fails if the stragglers' updates are not scattered
        # back.)
        np.testing.assert_allclose(result.q[i], sol.q[-1], rtol=0, atol=1e-15)
        np.testing.assert_allclose(result.p[i], sol.p[-1], rtol=0, atol=1e-15)
        # the diagnostics evaluate H and L in the loop, the test afterwards: XLA compiles the
        # two evaluations apart, so they may round differently, by a few ulps of |T| + |V| ~ 2
        # relative to |H| = 0.5 (measured up to 1.2e-15)
        assert float(result.energy_error[i]) == pytest.approx(relative_change(energy), rel=1e-12, abs=4e-15)
        assert float(result.invariant_errors["L"][i]) == pytest.approx(relative_change(L), rel=1e-12, abs=4e-15)


@pytest.mark.parametrize("method", [gj.CG(2, gj.gauss_legendre(2)), gj.DG(1, gj.gauss_radau(2)), gj.GalerkinVI(2, gj.gauss_lobatto(3))])
def test_a_zero_weight_padded_rule_gives_the_same_step(method):
    padded = jax.tree.map(lambda r: gj.pad_rule(r, 5) if isinstance(r, gj.QuadratureRule) else r, method,
                          is_leaf=lambda x: isinstance(x, gj.QuadratureRule))
    assert padded.quadrature.num_points == 5
    a = gj.step(H, Q0, P0, method=method, h=0.1)
    b = gj.step(H, Q0, P0, method=padded, h=0.1)
    np.testing.assert_allclose(jnp.concatenate(b), jnp.concatenate(a), rtol=0, atol=1e-15)


def blowup(q, p):
    return p[0] * (q[0] ** 2 + 1.0)  # q = tan(t + c): no element solution for large h


def test_a_failed_configuration_does_not_poison_the_others():
    state = [(jnp.array([1.0]), jnp.array([1.0]))]
    configs = gj.grid(method=[gj.CG(1, gj.midpoint())], h=[0.001, 1.0, 0.002, 0.5], state=state)
    result = gj.sweep(H=blowup, configs=configs, n_steps=50, reference=(jnp.zeros((4, 1)), jnp.zeros((4, 1))))
    status = np.asarray(result.status)
    assert status[0] == status[2] == 0 and status[1] != 0 and status[3] != 0
    assert np.isnan(result.energy_error[1]) and np.isnan(result.q[1]).all()
    for i, h in ((0, 0.001), (2, 0.002)):
        solo = gj.sweep(blowup, gj.grid(method=[gj.CG(1, gj.midpoint())], h=[h], state=state), n_steps=50)
        np.testing.assert_array_equal(result.q[i], solo.q[0])
        assert int(solo.batch_newton_iterations[0]) == int(solo.num_newton_iterations[0])
        assert float(result.energy_error[i]) == float(solo.energy_error[0])


def test_save_every_returns_batched_trajectories():
    configs = gj.grid(method=[gj.DG(1, gj.gauss_legendre(2))], h=[0.05, 0.1], state=STATES[:2])
    result = gj.sweep(H, configs, n_steps=20, save_every=5)
    assert result.solution.q.shape == (4, 5, 2)
    sol = gj.integrate(H, *STATES[1], method=gj.DG(1, gj.gauss_legendre(2)), h=0.05, n_steps=20, save_every=5)
    np.testing.assert_allclose(result.solution.q[1], sol.q, atol=1e-15)


def test_gradient_of_a_sweep_diagnostic_equals_central_differences():
    """The diagnostics themselves, energy_error and invariant_errors["L"] of four members (cG(1)
    on the asymmetric rule (0.3, 0.8), h 0.02 and 0.05, two states, 40 steps: errors 0.011 to
    0.14, maxima over the nodes at isolated nodes), differentiated in reverse mode with respect
    to the rule's weights, against central differences of step 1e-6 from the same compiled
    program. Measured: entries -0.58 to 0.48, the largest disagreement 2.6e-9 relative (the
    run's round-off, ~1e-15, over the step 1e-6); bound 5e-8 relative, 19x that. The loss this
    test took before, the final q, left the diagnostics' derivative untested."""

    def diagnostics(weights):
        method = gj.CG(1, gj.QuadratureRule(jnp.array([0.3, 0.8]), weights / jnp.sum(weights)))
        configs = gj.grid(method=[method], h=[0.02, 0.05], state=STATES[:2])
        result = gj.sweep(H, configs, n_steps=40, invariants=ANGULAR)
        return jnp.concatenate([result.energy_error, result.invariant_errors["L"]])

    w = jnp.array([0.45, 0.55])
    # one compiled program for the values and the Jacobian
    values_and_jacobian = jax.jit(lambda w: (diagnostics(w), jax.jacrev(diagnostics)(w)))
    values, jacobian = values_and_jacobian(w)
    assert float(jnp.min(values)) > 0.005 and float(jnp.min(jnp.abs(jacobian))) > 0.01  # far from round-off
    for i in range(2):
        e = jnp.zeros(2).at[i].set(1e-6)
        fd = (values_and_jacobian(w + e)[0] - values_and_jacobian(w - e)[0]) / 2e-6
        np.testing.assert_allclose(jacobian[:, i], fd, rtol=5e-8, atol=0, err_msg=f"weight {i}")


def test_a_sweep_in_chunks_equals_the_sweep_at_once_and_so_does_its_gradient():
    """``batch_size`` runs the members in chunks, one chunk after another: a controller's members
    (15 to 305 steps) take the same steps and reach the same states, and the gradient through
    them, from each member's own adjoint sweep, is the batched one; fixed steps likewise.
    Measured: the same states and gradients to the last bit (the unbatched and batched root
    finders take the same updates here); asserted to round-off, 1e-13 in the states and 1e-12
    relative in the gradient, since they may stop an update apart. Each member's gradient
    costing its own steps is measured in ``bench_gradients.py --only members``."""
    B = 5
    method = gj.stack_methods([gj.CG(4, gj.gauss_legendre(4))] * B)
    tols = jnp.array([1e-5, 1e-6, 1e-8, 1e-10, 1e-12])
    q0s = jnp.stack([Q0 * (1 + 0.01 * i) for i in range(B)])

    def run(q0s, batch_size):
        configs = gj.Configs(method=method, h=jnp.full(B, 0.05), q0=q0s, p0=jnp.stack([P0] * B))
        return gj.sweep(H, configs, t1=3.0, controller=gj.PIDController(tols, tols), batch_size=batch_size,
                        invariants=ANGULAR)

    # a jitted gradient is one compiled program (eagerly: the forward pass's and the transpose's)
    grad_of_loss = jax.jit(jax.grad(lambda q0s, batch_size: jnp.sum(run(q0s, batch_size).q ** 2)), static_argnums=1)
    at_once, at_once_grad = run(q0s, None), grad_of_loss(q0s, None)
    assert np.asarray(at_once.num_accepted_steps).tolist() == [15, 22, 51, 123, 305]
    for batch_size in (1, 2):
        chunks = run(q0s, batch_size)
        np.testing.assert_array_equal(chunks.num_accepted_steps, at_once.num_accepted_steps)
        np.testing.assert_allclose(chunks.q, at_once.q, rtol=0, atol=1e-13)
        np.testing.assert_allclose(chunks.invariant_errors["L"], at_once.invariant_errors["L"], rtol=1e-12)
    grad = grad_of_loss(q0s, 1)  # chunks of 2 (and a remainder of 1) differ in the forward run alone
    assert float(jnp.max(jnp.abs(grad - at_once_grad)) / jnp.max(jnp.abs(at_once_grad))) < 1e-12
    configs = gj.grid(method=[gj.CG(2, RULES[0])], h=[0.02, 0.05], state=STATES[:2])
    fixed, fixed_chunks = (gj.sweep(H, configs, n_steps=40, batch_size=b, save_every=10) for b in (None, 3))
    np.testing.assert_allclose(fixed_chunks.q, fixed.q, rtol=0, atol=1e-14)
    np.testing.assert_allclose(fixed_chunks.solution.q, fixed.solution.q, rtol=0, atol=1e-14)


@pytest.mark.parametrize("kwargs, match", [
    (dict(batch_size=0), "positive integer"),
    (dict(batch_size=1.5), "positive integer"),
    (dict(batch_size=True), "positive integer"),
    (dict(batch_size=2, devices=jax.devices()), "devices"),
    (dict(batch_size=2, progress=True), "progress"),
])
def test_sweep_rejects_a_bad_batch_size(kwargs, match):
    configs = gj.grid(method=[gj.CG(1, gj.midpoint())], h=[0.1], state=STATES[:2])
    with pytest.raises(ValueError, match=match):
        gj.sweep(H, configs, n_steps=10, **kwargs)


def test_sweep_rejects_bad_input():
    configs = gj.grid(method=[gj.CG(1, gj.midpoint())], h=[0.1], state=STATES[:1])
    with pytest.raises(TypeError, match="Configs"):
        gj.sweep(H, {"h": 1}, n_steps=10)
    with pytest.raises(ValueError, match="h must be finite"):
        gj.sweep(H, gj.grid(method=[gj.CG(1, gj.midpoint())], h=[-0.1], state=STATES[:1]), n_steps=10)
    with pytest.raises(ValueError, match="save_every"):
        gj.sweep(H, configs, n_steps=10, save_every=0)
    with pytest.raises(ValueError, match="reference"):
        gj.sweep(H, configs, n_steps=10, reference=(Q0, P0))
    with pytest.raises(ValueError, match="one kind"):
        gj.stack_methods([gj.CG(1, gj.midpoint()), gj.CG(2, gj.midpoint())])


SHARDED = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import galerkin_jax as gj
    assert len(jax.devices()) == 4, jax.devices()
    H = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
    q0, p0 = jnp.array([0.5, 0.0]), jnp.array([0.0, 3.0 ** 0.5])
    configs = gj.grid(method=[gj.CG(2, gj.gauss_legendre(2)), gj.CG(2, gj.gauss_lobatto(3))],
                      h=[0.01, 0.02, 0.05], state=[(q0, p0), (0.9 * q0, p0), (q0, 1.1 * p0)])  # B = 18
    plain = gj.sweep(H, configs, n_steps=50)
    sharded = gj.sweep(H, configs, n_steps=50, devices=jax.devices())
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(sharded)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    print("sharded equals unsharded on", len(jax.devices()), "devices")
    """
)


def test_sharded_sweep_on_4_host_devices_equals_the_unsharded_run():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, "-c", SHARDED], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "sharded equals unsharded on 4 devices" in done.stdout


def test_sweep_gradients_pass_the_checks_of_check_grads_in_forward_and_reverse_mode():
    """Final states and the energy and L diagnostics, with respect to points, weights, h, q0, p0
    and args, through the batched simplified Newton (custom_root). The rule is not symmetric,
    so the diagnostics are O(1e-4), far above round-off, and their maxima are isolated."""
    H_mu = lambda q, p, mu: 0.5 * (p @ p) - mu / jnp.sqrt(q @ q)

    def loss(points, weights, h, q0, p0, mu):
        method = gj.stack_methods([gj.CG(2, gj.QuadratureRule(points, weights / jnp.sum(weights)))] * 2)
        configs = gj.Configs(method=method, q0=jnp.stack([q0, 0.9 * q0]), p0=jnp.stack([p0, p0]),
                             h=jnp.stack([h, 2 * h]), args=jnp.stack([mu, 1.1 * mu]))
        result = gj.sweep(H_mu, configs, n_steps=30, invariants=ANGULAR)
        diagnostics = jnp.sum(result.energy_error) + jnp.sum(result.invariant_errors["L"])
        return jnp.sum(result.q ** 2) + jnp.sum(result.p[:, 0]) + 100 * diagnostics

    args = (jnp.array([0.2, 0.5, 0.9]), jnp.array([0.3, 0.4, 0.3]), jnp.asarray(0.02), Q0, P0, jnp.asarray(1.0))
    # eps = 1e-6: second-order differences leave ~1e-12 truncation, ~1e-10 round-off
    helpers.check_first_derivatives(loss, args, atol=1e-6, rtol=1e-6, eps=1e-6)


def test_sweep_converges_at_huge_h_omega_and_keeps_theorem_3_1():
    """h omega from 0.1 to 1000 in one batch: stale Jacobians are refreshed where they stop
    contracting, every member converges, and cG(1) with exact quadrature keeps the quadratic
    energy to round-off (Theorem 3.1) at every h."""
    H_osc, q0, p0, omega = helpers.oscillator()
    h = [float(x) / omega for x in (0.1, 1.0, 10.0, 100.0, 1000.0)]
    result = gj.sweep(H_osc, gj.grid(method=[gj.CG(1, gj.gauss_legendre(2))], h=h, state=[(q0, p0)]), n_steps=200)
    assert np.all(np.asarray(result.status) == 0)
    # ~eps per step as a random walk over 200 steps, times cond(Newton matrix) <= 1 + (h omega)^2 / 4
    # relative to |z|: the energy itself is exactly conserved by the scheme
    assert np.all(np.asarray(result.energy_error) < 1e-13)
    for i, step in enumerate(h):
        sol = gj.integrate(H_osc, q0, p0, method=gj.CG(1, gj.gauss_legendre(2)), h=step, n_steps=200, save_every=200)
        np.testing.assert_allclose(result.q[i], sol.q[-1], rtol=0, atol=1e-12)


def test_checkpointed_sweep_gradient_is_equal_and_stores_about_sqrt_n_carries():
    """Blocks of ~sqrt(N) elements rematerialised in reverse mode: the same gradient, and
    compiled temporary memory that grows like sqrt(N) (x2 for 4x the steps) instead of N (x4)."""
    method = gj.CG(1, gj.gauss_legendre(2))

    def loss(q0, n_steps, checkpoint):
        configs = gj.Configs(method=gj.stack_methods([method] * 2), q0=jnp.stack([q0, 0.9 * q0]),
                             p0=jnp.stack([P0, P0]), h=jnp.array([0.01, 0.02]))
        result = gj.sweep(H, configs, n_steps=n_steps, invariants=ANGULAR, checkpoint=checkpoint)
        return jnp.sum(result.q ** 2) + jnp.sum(result.energy_error)

    compiled = {(n, checkpoint): jax.jit(jax.grad(loss), static_argnums=(1, 2)).lower(Q0, n, checkpoint).compile()
                for n in (2000, 8000) for checkpoint in (False, True)}
    np.testing.assert_allclose(compiled[2000, True](Q0), compiled[2000, False](Q0), rtol=1e-12)
    temp_bytes = {key: program.memory_analysis().temp_size_in_bytes for key, program in compiled.items()}
    assert temp_bytes[8000, False] / temp_bytes[2000, False] > 3.5
    assert temp_bytes[8000, True] / temp_bytes[2000, True] < 2.5


def test_an_update_that_overshoots_with_a_stale_jacobian_is_rejected():
    """H = p^2/2 - 2 sqrt(q) + q/2 is undefined for q < 0. dG(1) with h up to 0.8 from q0 = 0.05:
    an update with an old Jacobian can land at q < 0 or diverge; it must be rejected and
    retried with a fresh Jacobian from the last good iterate, as integrate's Newton succeeds."""
    H_sqrt = lambda q, p: 0.5 * (p @ p) - 2.0 * jnp.sqrt(q[0]) + 0.5 * q[0]
    q0, p0, method = jnp.array([0.05]), jnp.array([0.0]), gj.DG(1, gj.gauss_radau(2))
    steps = [0.05, 0.1, 0.2, 0.4, 0.8]
    result = gj.sweep(H_sqrt, gj.grid(method=[method], h=steps, state=[(q0, p0)]), n_steps=200)
    assert np.all(np.asarray(result.status) == 0)
    for i, h in enumerate(steps):
        sol = gj.integrate(H_sqrt, q0, p0, method=method, h=h, n_steps=200, save_every=200)
        # |q| reaches ~12: measured agreement <= 4e-13, round-off amplified over 200 steps
        np.testing.assert_allclose(result.q[i], sol.q[-1], rtol=0, atol=2e-12)
        np.testing.assert_allclose(result.p[i], sol.p[-1], rtol=0, atol=2e-12)


def test_a_failed_member_costs_no_more_iterations_and_no_nan_gradients():
    """After its failure a member is no longer solved: the batch runs the healthy member's
    iterations, and the gradient of a loss over the healthy members with respect to a shared
    parameter is the one without the failed member (0 * NaN would otherwise reach it)."""
    H_c = lambda q, p, c: p[0] * (c * q[0] ** 2 + 1.0)  # no element solution for h = 1

    def run(c, steps):
        B = len(steps)
        configs = gj.Configs(method=gj.stack_methods([gj.CG(1, gj.midpoint())] * B), q0=jnp.ones((B, 1)),
                             p0=jnp.ones((B, 1)), h=jnp.asarray(steps), args=jnp.full(B, c))
        return gj.sweep(H_c, configs, n_steps=50)

    def loss(c, steps):
        result = run(c, steps)
        return jnp.sum(jnp.where((result.status == 0)[:, None], result.q, 0.0)), result

    # one compiled program per batch: the runs come with the gradients
    grad = jax.jit(jax.grad(loss, has_aux=True), static_argnums=1)
    with_failure, mixed = grad(1.0, (0.001, 1.0))
    without, alone = grad(1.0, (0.001,))
    assert int(mixed.status[0]) == 0 and int(mixed.status[1]) != 0
    # the batch waits for the failing member only in the elements up to its failure: at most
    # its own iterations more than the healthy member alone (50 elements would cost >= 100)
    failed_cost = int(mixed.num_newton_iterations[1])
    assert int(alone.batch_newton_iterations[0]) <= int(mixed.batch_newton_iterations[0])
    assert int(mixed.batch_newton_iterations[0]) <= int(alone.batch_newton_iterations[0]) + failed_cost
    assert failed_cost < int(mixed.num_newton_iterations[0]) / 2
    assert np.isfinite(float(with_failure))
    assert float(with_failure) == pytest.approx(float(without), rel=1e-12)


def test_updates_at_the_round_off_floor_that_shrink_slowly_end_the_iteration():
    """A chain of 10 masses with stiff springs and a quartic term, cG(2) + Gauss 2 (40
    unknowns), h omega = 0.3 .. 1.6: near the root the updates are round-off that still shrinks
    by 0.8 .. 0.99 an update. Such noise counts as the floor, not as a slow iteration to wait
    for, so every member converges within 32 iterations (measured at most 30; counting only
    growing noise as the floor, one member ran into the cap of 32)."""
    rng = np.random.default_rng(0)

    def H(q, p):
        strain = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return 0.5 * (p @ p) + 15.0 * (strain @ strain) + 0.25 * jnp.sum(strain**4)

    q0, p0 = jnp.asarray(rng.normal(size=10)) * 0.5, jnp.asarray(rng.normal(size=10))
    configs = gj.grid(method=gj.CG(2, gj.gauss_legendre(2)), h=list(np.linspace(0.03, 0.15, 13)),
                      state=[(q0, p0), (0.7 * q0, 1.2 * p0)])
    result = gj.sweep(H, configs, n_steps=100, max_newton_iterations=32)
    assert np.all(np.asarray(result.status) == 0)


def test_a_member_keeps_its_predictor_where_another_member_of_the_batch_is_doubtful():
    """The constant state is tried only where the continued predictor's residual is not small
    against it (``_solve._start``), member by member, so a batch in which another member is
    doubtful starts a member where its run alone starts (the linear equations 10 Z = b)."""
    from galerkin_jax import _solve

    fn = lambda Z, params: params[0] * Z - params[1]
    b = jnp.array([[1.0, 2.0]])
    Z_pred, Z_alt = b / 10 + 1e-4 * b, b / 10 * (1 + 1e-12)  # not doubtful; Z_alt has the smaller residual
    A, zero = jnp.full((1, 2), 10.0), jnp.zeros_like(b)  # the other member: Z_pred = 0 and b = 0 is doubtful

    def start(params, Z_pred, Z_alt):
        B = Z_pred.shape[0]
        problem = _solve._Problem(fn, params, jnp.ones(B), jnp.zeros(B), gj.SolverOptions(max_iterations=32), True,
                                  False)
        return _solve._start(problem, Z_pred, Z_alt, jnp.zeros(B, bool))[0]

    alone = start((A[None], b[None]), Z_pred[None], Z_alt[None])
    batch = start((jnp.stack([A, A]), jnp.stack([zero, b])), jnp.stack([zero, Z_pred]), jnp.stack([zero, Z_alt]))
    np.testing.assert_array_equal(batch[1], alone[0])
    np.testing.assert_array_equal(alone[0], Z_pred)
