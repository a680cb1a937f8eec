"""The implicit-function-theorem tangent of an element's root (``_tangent``): dense up to the
dense limit, matrix-free GMRES above it, NaN where GMRES does not converge.

The scene: the beta-FPUT chain (``scenes.fput``) with cG(3) and 3 Gauss points, 6 d unknowns
per element, so d = 50 masses give 300 unknowns, above the dense limit of 256, and d = 8 give
48, below it.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _solve, _tangent, scenes

METHOD = gj.CG(3, gj.gauss_legendre(3))
STEPS, H_STEP = 4, 0.5  # h omega = 1 at the chain's highest linear frequency, 2


def chain(d):
    scene = scenes.fput(d)
    q0 = 0.1 * jnp.asarray(np.random.default_rng(2).normal(size=d))
    direction = jnp.asarray(np.random.default_rng(3).normal(size=d))
    weights = jnp.arange(d) / d

    def loss(q):
        sol = gj.integrate(scene.H, q, jnp.asarray(scene.p0), method=METHOD, h=H_STEP, n_steps=STEPS,
                           save_every=STEPS, krylov=True, error_estimate=False)
        return jnp.sum(sol.q[-1] ** 2) + weights @ sol.p[-1], sol.status

    return loss, q0, direction


@functools.lru_cache(maxsize=None)
def compiled_gradient(d):
    """The value and gradient of ``chain(d)``'s loss, compiled once for the tests that read it
    (the central differences take their values from it too)."""
    loss, q0, _ = chain(d)
    return jax.jit(jax.value_and_grad(loss, has_aux=True)).lower(q0).compile()


@pytest.mark.parametrize("d", [8, 50], ids=["dense-48-unknowns", "gmres-300-unknowns"])
def test_gradient_through_integrate_equals_central_differences(d):
    """grad . v against Richardson-extrapolated central differences of the loss along v,
    (4 D(delta / 2) - D(delta)) / 3 with delta = 2e-4: the O(delta^2) truncation (measured
    8e-8 relative for D(1e-4)) cancels, leaving O(delta^4) ~ 1e-14 and the forward solves'
    round-off over the step, ~ eps / delta ~ 1e-12 relative. Measured agreement: 4e-13 to
    1e-11 for delta from 1e-4 to 8e-4. The bound 1e-9 leaves a factor of 100 over that and
    still catches a tangent solved to a looser tolerance than ~1e-10, or a wrong Jacobian."""
    loss, q0, v = chain(d)
    program = compiled_gradient(d)
    (_, status), gradient = program(q0)
    assert int(status) == 0
    value = lambda q: program(q)[0][0]
    D = lambda delta: (value(q0 + delta * v) - value(q0 - delta * v)) / (2 * delta)
    extrapolated = (4 * D(1e-4) - D(2e-4)) / 3
    exact = float(gradient @ v)
    assert abs(float(extrapolated) - exact) < 1e-9 * abs(exact)



def test_gradient_memory_stays_below_the_dense_tangents_factors():
    """XLA's temporary memory of the compiled gradient of 4 elements of 300 unknowns: below
    STEPS n^2 float64s (2.9 MB), the LU factors alone that a dense tangent stores for reverse
    mode, one per element (the dense tangent took 5.8 MB here; the matrix-free one 0.26 MB,
    a factor of 11 under the bound)."""
    n = 6 * 50
    memory = compiled_gradient(50).memory_analysis().temp_size_in_bytes
    assert memory < STEPS * n * n * 8


def element(d=50, h=2.0):
    """One cG(3) element of the FPUT chain, its unknowns near the root, and a tangent of
    (q0, p0). At h = 2 (h omega = 4) dR/dZ has condition number 124."""
    scene = scenes.fput(d)
    rng = np.random.default_rng(4)
    q0, p0 = 0.3 * jnp.asarray(rng.normal(size=d)), jnp.asarray(scene.p0)
    fn = lambda Z, params: METHOD.residual(scene.H, params[0], params[1], Z, h)
    Z = METHOD.initial_guess(q0, p0) + 0.01 * jnp.asarray(rng.normal(size=(3, 2 * d)))
    return fn, (q0, p0), Z, (jnp.asarray(rng.normal(size=d)), jnp.asarray(rng.normal(size=d)))


def assert_matrix_free_equals_dense(h):
    """The element's tangent (jvp) and cotangent (vjp, on the transposed products) by the
    matrix-free solve equal LU's on the jacfwd matrix within 1e-11 relative."""
    fn, params, Z, dparams = element(h=h)
    ok = jnp.asarray(True)
    solve = lambda limit: jax.jit(lambda dp: _tangent.tangent(fn, params, Z, ok, dp, dense_limit=limit))
    free, dense = solve(0), solve(10**9)
    assert Z.size > gj.SolverOptions().dense_limit
    forward, expected = free(dparams), dense(dparams)
    assert np.abs(forward - expected).max() < 1e-11 * np.abs(expected).max()
    cotangent = jnp.asarray(np.random.default_rng(5).normal(size=Z.shape))
    reverse = jax.vjp(free, dparams)[1](cotangent)
    expected = jax.vjp(dense, dparams)[1](cotangent)
    for a, b in zip(reverse[0], expected[0]):
        assert np.abs(a - b).max() < 1e-11 * np.abs(b).max()


def test_gmres_tangent_equals_the_dense_solve_forward_and_reverse():
    """The same tangent and cotangent as LU at 300 unknowns and condition number 124 (h = 2,
    where Richardson's iteration does not contract and GMRES solves). GMRES stops at a
    residual of 64 eps |b|, an error of at most cond 64 eps = 1.8e-12 relative; measured
    1.5e-14 (forward) and 3.4e-14 (reverse). The bound 1e-11 also covers LU's own error, ~cond eps."""
    assert_matrix_free_equals_dense(h=2.0)


def test_richardson_alone_reaches_the_tolerance_where_the_fixed_point_contracts(monkeypatch):
    """At h = 0.2 (h omega = 0.4) the element's fixed point contracts, and Richardson's
    iteration reaches 64 eps |b| without GMRES, forward and reverse: with GMRES replaced by
    NaN the tangents still equal LU's (measured within 1.2e-14 relative; the bound is the
    test above's). A first iteration that is judged against the residual of x = 0, which it
    equals, stops Richardson after one product and hands every element to GMRES."""
    monkeypatch.setattr(_tangent, "_gmres", lambda matvec, b, x0: jnp.full_like(b, jnp.nan))
    assert_matrix_free_equals_dense(h=0.2)


def blend(Z, params):
    """R = a Z + (1 - a) P Z - p, P the cyclic shift: dR/dZ is I for a = 1 and P for a = 0.
    GMRES on P stagnates until the Krylov space is all of R^n (the residual polynomial
    averages to p(0) = 1 over P's eigenvalues, the n-th roots of unity), so restarted GMRES
    never converges although P is orthogonal and LU solves it exactly."""
    a, p = params
    return a * Z + (1 - a) * jnp.roll(Z, 1) - p


@pytest.mark.parametrize("mode", ["jvp", "grad"])
def test_unconverged_gmres_gives_nan_per_member_not_a_wrong_tangent(mode):
    """Through ``implicit`` under vmap, 300 unknowns: a member whose GMRES converges gets the
    exact tangent, one whose GMRES does not gets NaN (forward and reverse mode), and a failed
    solve (ok False) gets zero, without running GMRES on its matrix."""
    n = 300
    p = jnp.asarray(np.random.default_rng(6).normal(size=(3, n)))
    a, ok = jnp.array([1.0, 0.0, 0.0]), jnp.array([True, True, False])
    roots = jnp.stack([p[0], jnp.roll(p[1], -1), p[2]])
    weights = jnp.asarray(np.random.default_rng(7).normal(size=n))

    def member(a, p, Z, ok):
        Z_of = lambda p: _solve.implicit(blend, 256, (a, p), Z, ok)
        if mode == "jvp":
            return jax.jvp(Z_of, (p,), (weights,))[1]
        return jax.grad(lambda p: weights @ Z_of(p))(p)

    out = jax.jit(jax.vmap(member))(a, p, roots, ok)
    np.testing.assert_allclose(out[0], weights, rtol=0, atol=1e-14)  # dR/dZ = I: dZ = dp
    assert np.all(np.isnan(out[1]))
    assert np.all(out[2] == 0)


@pytest.mark.parametrize("n", [10, 300], ids=["dense", "gmres"])
def test_second_derivatives_see_the_root_move(n):
    """R = Z^3 + Z - p elementwise: Z' = 1 / (3 Z^2 + 1), Z'' = -6 Z Z'^3. Forward over
    reverse and reverse over reverse equal them to round-off (measured 4e-14; the bound
    1e-12 leaves room for GMRES's 64 eps), so the rule's own derivative sees Z move with p."""
    fn = lambda Z, p: Z**3 + Z - p
    p = jnp.asarray(np.random.default_rng(8).normal(size=n))
    Z = jax.lax.fori_loop(0, 60, lambda _, Z: Z - fn(Z, p) / (3 * Z**2 + 1), p)
    first = 1 / (3 * Z**2 + 1)
    second = -6 * Z * first**3
    w = jnp.asarray(np.random.default_rng(9).normal(size=n))
    loss = lambda p: w @ _solve.implicit(fn, 256, p, Z, jnp.asarray(True))
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(p), w * first, rtol=0, atol=1e-12)
    forward_over_reverse = jax.jit(lambda p: jax.jvp(jax.grad(loss), (p,), (w,))[1])(p)
    reverse_over_reverse = jax.jit(jax.grad(lambda p: jax.grad(loss)(p) @ w))(p)
    for hvp in (forward_over_reverse, reverse_over_reverse):
        np.testing.assert_allclose(hvp, w * second * w, rtol=0, atol=1e-12)


@pytest.mark.parametrize("rate, products", [(1e-4, 3), (1e-2, 6), (0.3, 26)])
def test_richardson_stops_when_the_update_it_takes_leaves_the_tolerance(rate, products):
    """A = I - rate Q, Q orthogonal: Richardson's residuals contract by exactly ``rate`` a
    product, |r_k| = rate^k |b|. The rule stops at the first k with |r_k| rate / (1 - rate) below
    64 eps |b| = 1.4e-14 |b| and takes the update r_k without a product: k = 3, 6 and 26 products
    here, where a stop at |r_k| below the tolerance itself takes 4, 7 and 27. The result's
    residual, recomputed, is rate^(k + 1) |b| (1e-16, 1e-14 and 7.6e-15 relative), below the
    tolerance, as the rule's (1 - rate) guarantees for an exact contraction."""
    n = 40
    Q, _ = np.linalg.qr(np.random.default_rng(10).normal(size=(n, n)))
    A = jnp.asarray(np.eye(n) - rate * Q)
    b = jnp.asarray(np.random.default_rng(11).normal(size=n))
    count = [0]

    def matvec(x):
        jax.debug.callback(lambda: count.__setitem__(0, count[0] + 1))
        return A @ x

    x = jax.jit(lambda b: _tangent._iterated(matvec, b))(b)
    assert count[0] == products
    residual = float(jnp.linalg.norm(A @ x - b) / jnp.linalg.norm(b))
    assert residual <= _tangent.TOLERANCE * np.finfo(np.float64).eps
