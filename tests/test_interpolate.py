"""States between two nodes (``_interpolate.refine``, ``interpolate``): the element polynomial
refined by Picard sweeps has the nodes' local order. Each element starts on the exact orbit,
so the error inside it is the local error of the interpolant against the exact flow, and the
node's is the local error of z1; measured over three h (docs/accuracy.md, "States between
the nodes")."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers
from galerkin_jax import _adaptive, _interpolate, _output
from galerkin_jax._march import bind_args

ALPHA = np.linspace(0.1, 0.9, 9)


@functools.partial(jax.jit, static_argnums=(0, 1))
def elements(H, k, z0, h):
    """For each (z0, h): z1, the element polynomial at ``ALPHA`` and ``interpolate`` there with
    order 2k + 1, and ``refine``'s polynomial at 0 and 1."""

    def one(z0, h):
        z1, W = helpers.cg_element(k, H, z0, h)
        refined = _interpolate.refine(H, z0, z1, W, h, order=2 * k + 1)
        return (z1, _output.on_polynomial(z0, W, jnp.asarray(ALPHA)),
                _interpolate.interpolate(H, z0, z1, W, h, jnp.asarray(ALPHA), order=2 * k + 1),
                _output.on_polynomial(z0, refined, jnp.asarray([0.0, 1.0])))

    return jax.vmap(one)(z0, h)


def kepler_states(t, e):
    return np.concatenate(helpers.kepler_exact(np.asarray(t, float), e)).T


def assert_order_of_the_node(hs, error, node, order):
    """The error inside has z1's fitted order (within 0.3; measured within 0.03 in every case
    here), within -0.6 / +0.8 of ``order`` (pre-asymptotic slopes: measured -0.29 to +0.67),
    and it is below 1.5 times z1's at every h (measured 0.82 to 1.00: both have the same
    leading term, so the ratio moves little with h). With one sweep fewer (order 2k) each
    order test here fails: fitted orders 0.5 to 1.35 below z1's."""
    fitted = helpers.fitted_order(hs, error, floor=1e-15)
    assert abs(fitted - helpers.fitted_order(hs, node, floor=1e-15)) < 0.3
    assert order - 0.6 < fitted < order + 0.8
    assert np.all(error < 1.5 * node)


@pytest.mark.parametrize("e, k, hs", [
    (0.5, 2, (0.1, 0.05, 0.025)),
    (0.5, 4, (0.2, 0.1, 0.05)),
    (0.5, 6, (0.4, 0.28, 0.2)),
    (0.9, 4, (0.02, 0.01, 0.005)),
])
def test_refine_has_the_nodes_local_order_on_kepler(e, k, hs):
    """cG(k) on Kepler, one element straddling perihelion (from t = -h/3): the refined state at
    9 places inside errs by O(h^(2k + 1)), as z1 does, where the element polynomial errs by
    O(h^(k + 1)). Measured (e, k: fitted orders of the refined states, of z1, of the
    polynomial; refined error over z1's at the three h): 0.5, 2: 5.00, 5.01, 3.00; 1.00 1.00
    1.00. 0.5, 4: 9.25, 9.22, 4.92; 0.85 0.83 0.82. 0.5, 6: 13.18, 13.20, 6.62; 0.90 0.91 0.91.
    0.9, 4: 9.66, 9.67, 4.85; 0.85 0.97 0.87. The polynomial's error is 23 to 1.3e5 times z1's
    (bound: 10 times, and its order below k + 2)."""
    hs = np.asarray(hs)
    starts = -hs / 3
    z1, polynomial, refined, ends = elements(helpers.kepler(e)[0], k, jnp.asarray(kepler_states(starts, e)),
                                             jnp.asarray(hs))
    inside = np.stack([kepler_states(t + ALPHA * h, e) for t, h in zip(starts, hs)])
    node = np.max(np.abs(np.asarray(z1) - kepler_states(starts + hs, e)), axis=1)
    error = np.max(np.abs(np.asarray(refined) - inside), axis=(1, 2))
    assert_order_of_the_node(hs, error, node, 2 * k + 1)
    poly = np.max(np.abs(np.asarray(polynomial) - inside), axis=(1, 2))
    assert helpers.fitted_order(hs, poly) < k + 2 and np.all(poly > 10 * node)
    # through both nodes, to round-off
    np.testing.assert_allclose(np.asarray(ends[:, 0]), kepler_states(starts, e), rtol=0, atol=8 * np.finfo(float).eps)
    np.testing.assert_allclose(np.asarray(ends[:, 1]), np.asarray(z1), rtol=0, atol=8 * np.finfo(float).eps)


def test_refine_takes_any_h_that_jax_grad_takes():
    """H = |p|^2 / 2 + q arctan(q) - log(1 + q^2) / 2 (arctan: a primitive that Taylor mode,
    jax.experimental.jet, lacks), cG(3): against the exact flow (a cG(10) + Gauss 10 element
    over alpha h, local error O(h^21)), order 7 as z1's. Measured: fitted orders 7.04 and 7.04
    (z1), refined error over z1's 0.90, 0.91, 0.91."""
    H = lambda q, p: 0.5 * (p @ p) + jnp.sum(q * jnp.arctan(q) - 0.5 * jnp.log1p(q * q))
    k, hs = 3, np.array([0.4, 0.2, 0.1])
    z0 = jnp.array([1.5, -0.3, 0.2, 0.8])
    z1, _, refined, _ = elements(H, k, jnp.tile(z0, (3, 1)), jnp.asarray(hs))
    flow = jax.jit(jax.vmap(lambda tau: helpers.cg_element(10, H, z0, tau, sweeps=60)[0]))
    inside = np.stack([np.asarray(flow(jnp.asarray(ALPHA * h))) for h in hs])
    node = np.max(np.abs(np.asarray(z1) - np.asarray(flow(jnp.asarray(hs)))), axis=1)
    error = np.max(np.abs(np.asarray(refined) - inside), axis=(1, 2))
    assert_order_of_the_node(hs, error, node, 2 * k + 1)


def test_refine_on_the_time_transformed_kepler():
    """The run's problem with ``TimeTransform()`` (the default s, K with a custom derivative)
    on the extended state (q, t, p, p_t), Kepler e = 0.9 from t = -0.02 (an element in tau
    over perihelion), cG(4): the refined (q, p) against the exact orbit at the refined state's
    own time coordinate, order 9 in the step in tau as z1's. Measured: fitted orders 8.71 and
    8.71 (z1), refined error over z1's 0.97, 0.99, 0.97."""
    e, k, hs = 0.9, 4, np.array([0.02, 0.01, 0.005])
    He = helpers.kepler(e)[0]
    start = kepler_states(-0.02, e)
    # the unbounded density (s_max = inf): its order is asymptotic at these steps, the capped one's not yet
    K, qt0, pt0, args, _, clock = _adaptive.problem(He, gj.TimeTransform(s_max=float("inf")), jnp.asarray(start[:2]),
                                                    jnp.asarray(start[2:]), -0.02, None)
    z0 = jnp.concatenate([qt0, pt0])
    z1, _, refined, _ = elements(bind_args(K, args), k, jnp.tile(z0, (3, 1)), jnp.asarray(hs))
    user = lambda z: np.concatenate(_output.user_view(np.asarray(z), clock), axis=-1)
    inside = np.stack([kepler_states(np.asarray(r)[:, clock], e) for r in refined])
    node = np.max(np.abs(user(z1) - kepler_states(np.asarray(z1)[:, clock], e)), axis=1)
    error = np.max(np.abs(user(refined) - inside), axis=(1, 2))
    assert_order_of_the_node(hs, error, node, 2 * k + 1)


def test_interpolate_is_differentiable():
    """Forward and reverse mode of ``interpolate`` in (z0, z1, W, h, alpha) against central
    differences (cG(3) element on Kepler e = 0.5, alpha a vector)."""
    H = helpers.kepler(0.5)[0]
    z0 = jnp.asarray(kepler_states(0.3, 0.5))
    z1, W = jax.jit(helpers.cg_element, static_argnums=(0, 1))(3, H, z0, 0.1)
    f = lambda z0, z1, W, h, alpha: _interpolate.interpolate(H, z0, z1, W, h, alpha, order=7)
    helpers.check_first_derivatives(f, (z0, z1, W, 0.1, jnp.asarray([0.2, 0.5, 0.9])), eps=1e-6, atol=1e-8,
                                    rtol=1e-6)


def test_refine_needs_an_order_above_the_polynomials():
    with pytest.raises(ValueError, match="order 4 must exceed"):
        _interpolate.refine(helpers.kepler()[0], jnp.zeros(4), jnp.zeros(4), jnp.zeros((4, 4)), 0.1, order=4)
