"""jit / vmap / grad through step and integrate; gradients by the implicit function theorem."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, Q0, P0 = helpers.kepler(0.5)
N_STEPS = 20
RULES3 = [gj.gauss_legendre(3), gj.gauss_lobatto(3), gj.gauss_radau(3), gj.QuadratureRule([0.1, 0.5, 0.8], [0.3, 0.3, 0.4])]


def stack(trees):
    return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *trees)


def final_state(method, h=0.1, q0=Q0, p0=P0):
    sol = gj.integrate(H, q0, p0, method=method, h=h, n_steps=N_STEPS, save_every=N_STEPS)
    return jnp.concatenate([sol.q[-1], sol.p[-1]])


def test_vmap_over_step_sizes_equals_the_python_loop():
    method = gj.CG(2, gj.gauss_legendre(3))
    hs = jnp.array([0.02, 0.05, 0.1, 0.2])
    batched = jax.vmap(lambda h: final_state(method, h))(hs)
    looped = jnp.stack([final_state(method, float(h)) for h in hs])
    # same equations; batched Newton systems are solved by Gauss-Jordan instead of LAPACK
    np.testing.assert_allclose(batched, looped, rtol=0, atol=1e-13)


@pytest.mark.parametrize("family", [gj.CG, gj.DG])
def test_vmap_over_stacked_rules_equals_the_python_loop(family):
    methods = [family(2, rule) for rule in RULES3]
    batched = jax.vmap(final_state)(stack(methods))
    looped = jnp.stack([final_state(m) for m in methods])
    np.testing.assert_allclose(batched, looped, rtol=0, atol=1e-13)


def test_vmap_over_initial_states_and_args():
    H_args = lambda q, p, mu: 0.5 * (p @ p) - mu / jnp.sqrt(q @ q)
    method = gj.DG(1, gj.gauss_legendre(2))
    q0s = jnp.stack([Q0, 1.1 * Q0, 0.9 * Q0])
    mus = jnp.array([1.0, 1.2, 0.8])
    run = lambda q0, mu: gj.integrate(H_args, q0, P0, method=method, h=0.05, n_steps=10, args=mu).q[-1]
    batched = jax.vmap(run)(q0s, mus)
    looped = jnp.stack([run(q0, mu) for q0, mu in zip(q0s, mus)])
    np.testing.assert_allclose(batched, looped, rtol=0, atol=1e-13)


def loss(weights, points, h, q0):
    # normalised: central differences step off the sum-1 constraint, which QuadratureRule enforces
    method = gj.CG(2, gj.QuadratureRule(points, weights / jnp.sum(weights)))
    return jnp.sum(final_state(method, h, q0) ** 2)


# h a float64 array, not a weakly typed Python float: the differences' arguments then have
# the types of ARGS (no second compilation)
ARGS = (jnp.array([0.3, 0.4, 0.3]), jnp.array([0.15, 0.5, 0.85]), jnp.asarray(0.1, jnp.float64), Q0)


@functools.lru_cache(maxsize=None)
def value_and_gradient():
    """``loss`` and its gradient with respect to all four arguments: one compiled program for
    the four tests that read it, the values of their central differences included."""
    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3)))


@pytest.mark.parametrize("argnum, name", [(0, "weights"), (1, "points"), (2, "h"), (3, "q0")])
def test_gradient_equals_central_differences(argnum, name):
    value_and_grad = value_and_gradient()
    grad = np.atleast_1d(value_and_grad(*ARGS)[1][argnum])
    x = np.atleast_1d(np.asarray(ARGS[argnum], dtype=float))
    eps = 1e-6  # central differences: truncation ~ eps^2 ~ 1e-12, round-off ~ 1e-16 / eps ~ 1e-10
    for i in range(x.size):
        plus, minus = x.copy(), x.copy()
        plus[i] += eps
        minus[i] -= eps
        shape = np.shape(ARGS[argnum])
        args_p = list(ARGS); args_p[argnum] = jnp.asarray(plus.reshape(shape))
        args_m = list(ARGS); args_m[argnum] = jnp.asarray(minus.reshape(shape))
        fd = (value_and_grad(*args_p)[0] - value_and_grad(*args_m)[0]) / (2 * eps)
        assert grad[i] == pytest.approx(float(fd), rel=1e-6, abs=1e-8), name


def test_check_grads_forward_and_reverse():
    """The checks of ``jax.test_util.check_grads`` (order 1, forward and reverse mode) in one
    compiled program (``helpers.check_first_derivatives``)."""
    f = lambda w, h: loss(w, ARGS[1], h, Q0)
    # eps = 1e-6: the default 1e-4 leaves an O(eps^2) difference error of ~1e-5 here
    helpers.check_first_derivatives(f, (ARGS[0], 0.1), atol=1e-6, rtol=1e-6, eps=1e-6)


def test_derivatives_do_not_differentiate_the_newton_iterations():
    """The tangent map of one element is a linear solve: no while loop in its jaxpr."""
    method = gj.CG(2, gj.gauss_legendre(3))
    one_step = lambda q: gj.step(H, q, P0, method=method, h=0.1)[0]
    assert "while" in str(jax.make_jaxpr(one_step)(Q0))
    _, tangent = jax.linearize(one_step, Q0)
    assert "while" not in str(jax.make_jaxpr(tangent)(Q0))


def test_integrate_under_jit_equals_eager():
    method = gj.DG(2, gj.gauss_legendre(3))
    jitted = jax.jit(lambda q0: gj.integrate(H, q0, P0, method=method, h=0.1, n_steps=10).q)(Q0)
    eager = gj.integrate(H, Q0, P0, method=method, h=0.1, n_steps=10).q
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=1e-15)


def test_checkpointed_gradient_equals_the_plain_one_and_its_memory_grows_like_the_number_of_blocks():
    """The same gradient with and without checkpointing over 2000 elements; and compiled
    temporary memory: plain reverse mode stores every element (x4 for 4x the steps);
    checkpointed blocks of sqrt(N) elements store ~sqrt(N) states (x2)."""
    method = gj.CG(1, gj.gauss_legendre(2))

    def compiled(n_steps, block, checkpoint):
        loss = lambda q0: jnp.sum(gj.integrate(H, q0, P0, method=method, h=0.01, n_steps=n_steps, save_every=block,
                                               checkpoint=checkpoint).q[-1] ** 2)
        return jax.jit(jax.grad(loss)).lower(Q0).compile()

    programs = {key: compiled(*key) for key in ((2000, 2000, False), (8000, 8000, False), (2000, 40, True),
                                                 (8000, 80, True))}
    np.testing.assert_allclose(programs[2000, 40, True](Q0), programs[2000, 2000, False](Q0), rtol=1e-13)
    temp_bytes = {key: program.memory_analysis().temp_size_in_bytes for key, program in programs.items()}
    plain = temp_bytes[8000, 8000, False] / temp_bytes[2000, 2000, False]
    checkpointed = temp_bytes[8000, 80, True] / temp_bytes[2000, 40, True]
    assert plain > 3.5 and checkpointed < 2.5


def test_a_failed_member_of_a_vmapped_integrate_leaves_the_others_gradient_finite():
    """After a failure a run carries its finite initial state and is not solved again, so the
    masked-out member adds no 0 * NaN to the gradient of a shared parameter."""
    H_c = lambda q, p, c: p[0] * (c * q[0] ** 2 + 1.0)  # no element solution for h = 1

    def loss(c, steps):
        run = lambda h: gj.integrate(H_c, jnp.ones(1), jnp.ones(1), method=gj.CG(1, gj.midpoint()), h=h,
                                     n_steps=20, save_every=20, args=c)
        sol = jax.vmap(run)(jnp.asarray(steps))
        return jnp.sum(jnp.where((sol.status == 0)[:, None], sol.q[:, -1], 0.0))

    grad = jax.jit(jax.grad(loss), static_argnums=1)  # one compiled program per batch size
    with_failure, without = grad(1.0, (0.001, 0.002, 1.0)), grad(1.0, (0.001, 0.002))
    assert np.isfinite(float(with_failure))
    assert float(with_failure) == pytest.approx(float(without), rel=1e-12)
