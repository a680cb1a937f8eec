"""Newton-Krylov for systems too large for a dense Newton matrix (more than 256 unknowns).

The scene: a chain of N unit masses with stiff linear springs, fixed ends, H = |p|^2 / 2 +
k sum (q_{i+1} - q_i)^2 / 2, highest frequency omega = 2 sqrt(k) = 20. At h = 0.5, h omega =
10: the fixed-point iteration diverges, and only Newton solves the element equations. For a
linear system cG(k) with k Gauss points is k-stage Gauss collocation and dG(1), integrating
exactly here, is the 2-stage Radau IIA method: their one-step maps come from one dense
NumPy solve each, an independent reference.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

N, K_SPRING, H_STEP, STEPS = 50, 100.0, 0.5, 20
GAUSS3 = helpers.collocation_tableau(np.asarray(gj.gauss_legendre(3).points))
RADAU2 = helpers.collocation_tableau(np.asarray(gj.gauss_radau(2).points))  # Radau IIA: nodes 1/3, 1


def chain(n=N, k=K_SPRING):
    def H(q, p):
        strain = jnp.diff(jnp.concatenate([jnp.zeros(1, q.dtype), q, jnp.zeros(1, q.dtype)]))
        return 0.5 * (p @ p) + 0.5 * k * (strain @ strain)

    laplacian = 2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-k * laplacian, np.zeros((n, n))]])  # z' = A z
    rng = np.random.default_rng(1)
    return H, A, jnp.asarray(rng.normal(size=n)), jnp.asarray(rng.normal(size=n))


def runge_kutta_map(A, tableau, h):
    """The one-step matrix of the Runge-Kutta method ``tableau`` on z' = A z (dense solve)."""
    a, b = tableau
    s, m = len(b), A.shape[0]
    stages = np.linalg.solve(np.eye(s * m) - h * np.kron(a, A), np.kron(np.ones((s, 1)), A))
    return np.eye(m) + h * np.kron(b[None, :], np.eye(m)) @ stages


def reference(A, tableau, z0, h, n_steps):
    step = runge_kutta_map(A, tableau, h)
    z = np.asarray(z0)
    for _ in range(n_steps):
        z = step @ z
    return z


def test_stiff_large_cg_by_newton_krylov_equals_gauss_collocation():
    """cG(3), 3 Gauss points: 300 unknowns, h omega = 10. Without ``krylov`` the fixed point
    cannot converge (status 1); with it, every element converges (3.15 Newton updates per
    element, on the Gauss-Seidel sweep's residual), the states equal 3-stage Gauss
    collocation (measured 1.0e-13 relative to max|z| after 20 steps; 1e-11 leaves room for a
    GMRES tolerance of 1e-7 per Newton direction, refined by the next) and the energy is
    conserved to round-off (Theorem 3.1; measured 4e-16)."""
    H, A, q0, p0 = chain()
    method = gj.CG(3, gj.gauss_legendre(3))
    without = gj.integrate(H, q0, p0, method=method, h=H_STEP, n_steps=2)
    assert int(without.status) == gj.Status.NEWTON_MAX_ITERATIONS
    sol = gj.integrate(H, q0, p0, method=method, h=H_STEP, n_steps=STEPS, krylov=True)
    assert int(sol.status) == 0
    z = np.concatenate([sol.q[-1], sol.p[-1]])
    expected = reference(A, GAUSS3, np.concatenate([q0, p0]), H_STEP, STEPS)
    assert np.abs(z - expected).max() / np.abs(expected).max() < 1e-11
    energy = np.asarray(jax.vmap(H)(sol.q, sol.p))
    assert np.abs(energy / energy[0] - 1).max() < 1e-13


@pytest.mark.parametrize("path", ["integrate", "sweep"])
def test_large_dg_solves_by_newton_krylov_without_asking_and_equals_radau_iia(path):
    """dG(1) has no fixed point (its residual's Jacobian at h = 0 is not I): at 2 * 2 * 70 =
    280 unknowns, more than a dense matrix is kept for, it uses Newton-Krylov unasked. Exact
    quadrature (Gauss 2 on a quadratic H) makes it 2-stage Radau IIA (measured 1.6e-14)."""
    H, A, q0, p0 = chain(n=70)
    method = gj.DG(1, gj.gauss_legendre(2))
    if path == "integrate":
        sol = gj.integrate(H, q0, p0, method=method, h=H_STEP, n_steps=STEPS, save_every=STEPS)
        status, q, p = sol.status, sol.q[-1], sol.p[-1]
    else:
        result = gj.sweep(H, gj.grid(method=method, h=[H_STEP], state=(q0, p0)), n_steps=STEPS)
        status, q, p = result.status[0], result.q[0], result.p[0]
    assert int(status) == 0
    expected = reference(A, RADAU2, np.concatenate([q0, p0]), H_STEP, STEPS)
    assert np.abs(np.concatenate([q, p]) - expected).max() / np.abs(expected).max() < 1e-11
