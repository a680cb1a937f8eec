"""``integrate(..., checkpoint="reversible")``: a fixed-step run's gradient whose backward pass
rebuilds each state by an element of step -h (``_reversible``), memory O(1) in the steps."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _reversible
from galerkin_jax._march import solver_options

MIDPOINT = gj.CG(1, gj.gauss_legendre(1))
Q0, P0 = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.2])  # Kepler, e = 0.44


def kepler(q, p, args=1.0):
    return 0.5 * jnp.sum(p**2) - args / jnp.linalg.norm(q)


def _kepler_grads(n, checkpoint, h=0.01, save_every=None):
    def loss(q0, p0):
        s = gj.integrate(kepler, q0, p0, method=MIDPOINT, h=h, n_steps=n, save_every=save_every or n,
                         checkpoint=checkpoint)
        return jnp.sum(s.q[-1] ** 2) + jnp.sum(s.p[-1])

    return np.concatenate([np.asarray(g) for g in jax.jit(jax.grad(loss, argnums=(0, 1)))(Q0, P0)])


def test_reversible_gradient_equals_stored_over_1e5_steps():
    """Over 10^5 midpoint steps of Kepler (h = 0.01, ~120 orbits) the gradient that rebuilds
    the states backwards equals the stored one to 2.9e-11 of its largest entry (3.6e3) as
    measured; 3e-10 leaves 10x for other CPUs' rounding. The difference is the rebuild's
    round-off (2.5e-11 on z_0 here, ``test_rebuild_roundoff_...``) carried through the
    linearised flow, whose shear makes the gradient grow like n."""
    stored, reversible = _kepler_grads(10**5, False), _kepler_grads(10**5, "reversible")
    assert np.max(np.abs(reversible - stored)) / np.max(np.abs(stored)) < 3e-10


def test_rebuild_roundoff_grows_like_n_to_three_halves_on_kepler():
    """z_0 rebuilt from z_n by n elements of step -h (the backward pass's reconstruction) lies,
    as measured, 1.9e-14, 7.5e-13, 2.5e-11 from the true z_0 after 10^3, 10^4, 10^5 steps: slope
    1.56 in log-log, n^(3/2) eps. Each element's round-off (a random walk, sqrt(n)) is sheared by
    Kepler's flow, whose linearisation grows linearly in time (the period depends on the
    energy): sqrt(sum_k k^2) ~ n^(3/2). On the harmonic oscillator (no shear) the growth is
    slower (benchmarks/results/reversible_gradient.json); on a chaotic orbit it would be
    exponential. Asserted: each distance within 10x of its measured value, slope in [1.2, 1.9]."""
    measured = {10**3: 1.9e-14, 10**4: 7.5e-13, 10**5: 2.5e-11}
    errors = []
    for n, value in measured.items():
        s = gj.integrate(kepler, Q0, P0, method=MIDPOINT, h=0.01, n_steps=n, save_every=n)
        z_end = jnp.concatenate([s.q[-1], s.p[-1]])
        z0, status = jax.jit(lambda z, n=n: _reversible.rebuild(MIDPOINT, kepler, z, jnp.asarray(0.01), None,
                                                                  solver_options(MIDPOINT), n))(z_end)
        assert int(status) == 0
        errors.append(float(jnp.max(jnp.abs(z0 - jnp.concatenate([Q0, P0])))))
        assert errors[-1] < 10 * value
    slope = np.polyfit(np.log10(list(measured)), np.log10(errors), 1)[0]
    assert 1.2 < slope < 1.9


@pytest.mark.parametrize("method, save_every", [(gj.GalerkinVI(2, gj.gauss_lobatto(3)), 8)],
                         ids=["VI2-lobatto3-every8"])  # cG(1), GalerkinVI(1), compositions: below
def test_reversible_gradient_equals_stored_for_every_input(method, save_every):
    """d/d(q0, p0, args, h, the rule's weights) of a loss on every saved state, 40 elements of a
    pendulum-like H with args: equal to the stored gradient to 1e-12 relative (measured ~1e-14;
    a rebuild over at most 40 elements adds ~40 eps)."""
    def H(q, p, args):
        return 0.5 * jnp.sum(p**2) / args[0] - args[1] * jnp.sum(jnp.cos(q))

    def loss(q0, p0, args, h, weights, checkpoint):
        m = dataclass_with_weights(method, weights)
        s = gj.integrate(H, q0, p0, method=m, h=h, n_steps=40, args=args, save_every=save_every,
                         checkpoint=checkpoint)
        return jnp.sum(s.q[-1] ** 2) + jnp.sum(jnp.sin(s.p) * jnp.arange(s.p.shape[0])[:, None])

    inputs = (jnp.array([0.8, -0.3]), jnp.array([0.1, 0.4]), jnp.array([1.3, 0.9]), 0.05,
              method.quadrature.weights)
    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3, 4)), static_argnums=5)
    stored, reversible = grad(*inputs, False), grad(*inputs, "reversible")
    for a, b in zip(stored, reversible):
        assert np.max(np.abs(np.asarray(a) - np.asarray(b))) <= 1e-12 * max(1.0, np.max(np.abs(np.asarray(a))))


def dataclass_with_weights(method, weights):
    return dataclasses.replace(method, quadrature=gj.QuadratureRule(method.quadrature.points, weights))


@pytest.mark.parametrize("t1", [-1.03], ids=["backwards"])  # a shortened last element, of -H
def test_reversible_gradient_to_a_concrete_t1(t1):
    """Fixed steps to t1 (the last element shortened, h_last) and backwards (t1 < t0, the run
    of -H): d/d(q0, p0) equal to the stored one to 1e-12 (measured ~1e-15)."""
    def loss(q0, p0, h, t1, checkpoint):
        s = gj.integrate(kepler, q0, p0, method=MIDPOINT, h=h, t1=t1, checkpoint=checkpoint)
        return jnp.sum(s.q[-1] ** 3) + jnp.sum(s.p[-1])

    grad = jax.grad(loss, argnums=(0, 1))
    stored, reversible = (grad(Q0, P0, 0.1, t1, c) for c in (False, "reversible"))
    for a, b in zip(stored, reversible):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)


def test_reversible_gradient_memory_does_not_grow_with_the_steps():
    """XLA's temporary buffers of the reversible gradient are the same for 200 and 2000 steps
    (measured 6280 bytes for Kepler, save_every = n), where the stored gradient's grow about
    10x (measured 2.2e5 -> 2.2e6 bytes at 10^3 -> 10^4 steps)."""
    def temp(n, checkpoint):
        def loss(q0, p0):
            s = gj.integrate(kepler, q0, p0, method=MIDPOINT, h=0.01, n_steps=n, save_every=n, checkpoint=checkpoint)
            return jnp.sum(s.q[-1] ** 2)
        return jax.jit(jax.grad(loss)).lower(Q0, P0).compile().memory_analysis().temp_size_in_bytes

    small, large = temp(200, "reversible"), temp(2000, "reversible")
    assert large == small < 2e4
    assert temp(2000, False) > 5 * large


@pytest.mark.parametrize("kwargs, match", [
    (dict(method=gj.DG(1, gj.gauss_legendre(2))), "DG"),
    (dict(method=gj.CG(2, gj.QuadratureRule(jnp.array([0.2, 0.9]), jnp.array([0.5, 0.5])))), "not symmetric"),
    (dict(controller=gj.PIDController(1e-6, 1e-6), t1=1.0), "controller"),
    (dict(save_at=jnp.array([0.5]), t1=1.0), "save_at"),
    (dict(dense=True), "dense"),
    (dict(events=gj.Event(lambda t, q, p: q[0])), "events"),
    (dict(max_steps=20), "reserve"),
    (dict(max_steps=20, t1=0.105), "reserve"),
])
def test_reversible_refuses_what_it_cannot_rebuild(kwargs, match):
    """A method that is not symmetric, or a run whose elements are not fixed in advance: a
    ValueError naming the combination, before anything runs."""
    options = dict(method=MIDPOINT, h=0.01, n_steps=10, checkpoint="reversible")
    options.update(kwargs)
    if "t1" in options:
        del options["n_steps"]
    with pytest.raises(ValueError, match=match):
        gj.integrate(kepler, Q0, P0, **options)


def test_checkpoint_takes_only_its_documented_values():
    with pytest.raises(ValueError, match="checkpoint must be"):
        gj.integrate(kepler, Q0, P0, method=MIDPOINT, h=0.01, n_steps=10, checkpoint="yes")


@pytest.mark.parametrize("method", [gj.GalerkinVI(1, gj.trapezoid()), gj.ModifiedMidpoint(),
                                    gj.Composition(MIDPOINT, "yoshida4")],
                         ids=["explicit-verlet", "modified-midpoint", "yoshida4"])
def test_reversible_gradient_of_other_symmetric_methods(method):
    """Stormer-Verlet (explicit: its closed form run with -H), the energy-momentum midpoint
    and a composition are symmetric too: d/d(q0, p0, h) over 60 Kepler steps in blocks of 6
    equal to the stored gradient to 1e-13 relative (measured at most 2.2e-15)."""
    def loss(q0, p0, h, checkpoint):
        s = gj.integrate(kepler, q0, p0, method=method, h=h, n_steps=60, save_every=6, checkpoint=checkpoint)
        return jnp.sum(s.q[-1] ** 2) + jnp.sum(s.p**2)

    stored, reversible = (np.concatenate([np.ravel(g) for g in jax.grad(loss, argnums=(0, 1, 2))(Q0, P0, 0.02, c)])
                          for c in (False, "reversible"))
    assert np.max(np.abs(reversible - stored)) < 1e-13 * np.max(np.abs(stored))


def test_reversible_gradient_under_vmap_equals_each_members():
    """A vmapped gradient (two initial momenta) equals each member's own, to 1e-13 (measured
    ~1e-15): the custom_vjp's backward pass batches like the forward run."""
    def loss(p0):
        s = gj.integrate(kepler, Q0, p0, method=MIDPOINT, h=0.02, n_steps=50, save_every=10, checkpoint="reversible")
        return jnp.sum(s.q[-1] ** 2)

    grad = jax.jit(jax.grad(loss))
    p0s = jnp.stack([P0, P0 * 0.9])
    batched = jax.jit(jax.vmap(jax.grad(loss)))(p0s)
    for i in range(2):
        np.testing.assert_allclose(batched[i], grad(p0s[i]), rtol=1e-13, atol=1e-13)


def test_a_failed_run_has_a_nan_reversible_gradient():
    """A run whose solve fails (status nonzero: one Newton iteration allowed) has NaN states
    and a NaN gradient, never a plausible number."""
    def loss(q0):
        s = gj.integrate(kepler, q0, P0, method=gj.CG(3, gj.gauss_legendre(3)), h=0.5, n_steps=10,
                         max_newton_iterations=1, checkpoint="reversible")
        return jnp.sum(s.q[-1] ** 2), s.status

    g, status = jax.grad(loss, has_aux=True)(Q0)
    assert int(status) != 0 and np.all(np.isnan(np.asarray(g)))


@pytest.mark.parametrize("mode", ["jvp", "jacfwd under jit"])
def test_forward_mode_of_a_reversible_run_says_what_to_use_instead(mode):
    """The reversible gradient is a ``jax.custom_vjp``, which has no forward mode: ``jax.jvp`` and
    ``jax.jacfwd`` raise a TypeError that names checkpoint=False (found by the combination
    harness, where JAX's own message named no cause); reverse mode equals checkpoint=False's."""
    H = lambda q, p: 0.5 * (p @ p + q @ q)
    run = lambda checkpoint: lambda s: gj.integrate(H, jnp.array([1.0]) * s, jnp.array([0.0]),
                                                    method=gj.CG(2, gj.gauss_legendre(2)), t1=2.5, h=0.1,
                                                    checkpoint=checkpoint).q[-1, 0]
    forward = {"jvp": lambda f: jax.jvp(f, (1.0,), (1.0,))[1], "jacfwd under jit": lambda f: jax.jit(jax.jacfwd(f))(1.0)}
    with pytest.raises(TypeError, match="checkpoint=False"):
        forward[mode](run("reversible"))
    np.testing.assert_allclose(jax.grad(run("reversible"))(1.0), forward[mode](run(False)), rtol=1e-10)
