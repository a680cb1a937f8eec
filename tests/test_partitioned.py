"""The Gauss-Seidel sweep of partitioned methods (``_march.element_residual``).

A partitioned method on a separable H of more than ``SolverOptions.sweep_dimension`` degrees of freedom is solved
through R~ = Z - G(Z), G the sweep that updates the p columns from R_p(Z), then the q columns
from R_q at that update. For a separable quadratic H the Jacobi iteration matrix I - dR/dZ
couples q only to p and p only to q: it is 2-cyclic, and by Young's theorem the sweep's
matrix I - dR~/dZ has exactly the squared spectral radius. R~ must have R's roots: a step
equals Newton on R itself. Any other H keeps R: the square rate is not its, and where each
half is a gradient through all of H an update of the sweep costs two plain ones.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _march, scenes

METHODS = [gj.CG(1, gj.midpoint()), gj.CG(3, gj.gauss_legendre(3)), gj.CG(2, gj.gauss_lobatto(3)),
           gj.DG(0, gj.gauss_legendre(1)), gj.GalerkinVI(2, gj.gauss_legendre(2))]


def linear_chain(n=24, k=4.0):
    def H(q, p):
        strain = jnp.diff(jnp.concatenate([jnp.zeros(1, q.dtype), q, jnp.zeros(1, q.dtype)]))
        return 0.5 * (p @ p) + 0.5 * k * (strain @ strain)

    rng = np.random.default_rng(3)
    return H, jnp.asarray(rng.normal(size=n)), jnp.asarray(rng.normal(size=n))


def iteration_matrices(method, H, q0, p0, h):
    """I - dR/dZ (Jacobi, the plain residual) and I - dR~/dZ (the sweep), at Z = 0."""
    Z = method.initial_guess(q0, p0)
    plain = lambda Z: method.residual(H, q0, p0, Z, h)
    swept = lambda Z: _march.element_residual(H)(Z, (method, q0, p0, h, None))
    eye = np.eye(Z.size)
    jacobians = jax.jit(lambda z: [jax.jacfwd(lambda z: R(z.reshape(Z.shape)).reshape(-1))(z) for R in (plain, swept)])
    return [eye - np.asarray(J) for J in jacobians(Z.reshape(-1))]


def radius(M):
    return np.max(np.abs(np.linalg.eigvals(M)))


@pytest.mark.parametrize("method", METHODS, ids=lambda m: type(m).__name__ + str(getattr(m, "k", getattr(m, "s", ""))))
def test_sweep_contracts_at_the_square_of_the_jacobi_rate(method):
    H, q0, p0 = linear_chain()
    jacobi, sweep = iteration_matrices(method, H, q0, p0, h=0.2)
    assert q0.shape[0] > gj.SolverOptions().sweep_dimension
    rho = radius(jacobi)
    assert 0.05 < rho < 1.0  # a rate worth squaring, below 1
    # Young's theorem holds exactly; the eigenvalues' round-off is ~1e-15
    assert radius(sweep) == pytest.approx(rho**2, rel=1e-10)


def test_small_states_keep_the_plain_residual():
    H, q0, p0 = linear_chain(n=gj.SolverOptions().sweep_dimension)
    method = gj.CG(6, gj.gauss_legendre(6))  # 96 unknowns, but a state of 8
    jacobi, sweep = iteration_matrices(method, H, q0, p0, h=0.2)
    np.testing.assert_array_equal(jacobi, sweep)


V_CHAIN = lambda q: jnp.sum(1.0 - jnp.cos(jnp.diff(q))) + 0.5 * q @ q
MASS = lambda q: jnp.eye(q.shape[0]) + 0.1 * jnp.cos(q[:, None] - q[None, :])
HAMILTONIANS = {  # name: (H, whether the solver is handed the sweep)
    "separable": (lambda q, p: 0.5 * (p @ p) + 0.1 * jnp.sum(p**4) + V_CHAIN(q), True),
    "scalar mass m(q)": (lambda q, p: 0.5 * (p @ p) / (1.0 + 0.25 * (q @ q)) + V_CHAIN(q), False),
    "mass matrix M(q)": (lambda q, p: 0.5 * p @ jnp.linalg.solve(MASS(q), p) + V_CHAIN(q), False),
}
ONE_OF_EACH = (METHODS[1], METHODS[3], METHODS[4])  # CG(3) + Gauss 3, DG(0), GalerkinVI(2)


def start(n=20):
    """A generator and the start state (q0, p0) it drew, n degrees of freedom."""
    rng = np.random.default_rng(5)
    return rng, jnp.asarray(rng.normal(size=n)), jnp.asarray(rng.normal(size=n))


@pytest.mark.parametrize("kind", HAMILTONIANS)
def test_the_sweep_is_taken_for_a_separable_H_alone(kind):
    """On 20 degrees of freedom, for every partitioned method class: a separable H is handed the
    sweep's R~ (not R), any other keeps R itself (the same array, to the bit)."""
    (H, sweeps), (rng, q0, p0) = HAMILTONIANS[kind], start()
    assert gj.structure(H, q0, p0).separable is sweeps
    for method in ONE_OF_EACH:
        Z = jnp.asarray(rng.normal(size=method.initial_guess(q0, p0).shape)) * 0.01
        handed = _march.element_residual(H)(Z, (method, q0, p0, 0.1, None))
        assert bool(jnp.array_equal(handed, method.residual(H, q0, p0, Z, 0.1))) is not sweeps


@pytest.mark.parametrize("kind", ["separable", "mass matrix M(q)"])
def test_a_step_is_newtons_root_with_either_residual(kind):
    """A step, through the sweep (separable) or R itself (the mass matrix), is the root of
    Newton's method on R, to a few ulps of the state. One method of each class: CG(1), CG(2)
    and CG(3) share their equations whatever the rule."""
    (H, _), (_, q0, p0) = HAMILTONIANS[kind], start()
    h = 0.1
    for method in ONE_OF_EACH:
        shape = method.initial_guess(q0, p0).shape
        R = lambda z: method.residual(H, q0, p0, z.reshape(shape), h).reshape(-1)

        @jax.jit  # one compilation per method: 8 plain Newton steps on R, and the library's step
        def newton_and_step(q0, p0):
            z = jax.lax.fori_loop(0, 8, lambda _, z: z - jnp.linalg.solve(jax.jacfwd(R)(z), R(z)),
                                  jnp.zeros(np.prod(shape)))
            return method.increment(H, q0, p0, z.reshape(shape), h), gj.step(H, q0, p0, method=method, h=h)

        (dq, dp), (q1, p1) = newton_and_step(q0, p0)
        # both are converged to round-off: a few ulps of the state
        np.testing.assert_allclose(q1, q0 + dq, rtol=0, atol=2e-15 * float(jnp.max(jnp.abs(q0))))
        np.testing.assert_allclose(p1, p0 + dp, rtol=0, atol=2e-15 * float(jnp.max(jnp.abs(p0))))


def test_iterations_per_element_on_the_fput_chain():
    """cG(1) + midpoint on the 64-mass chain at h = 0.05 (h omega = 0.1): the plain fixed
    point needs about 12 iterations per element, the sweep about 6.5 (the one-off ``solver`` study).
    Asserted with room, an upper bound between the two: at most four blocks of two."""
    scene = scenes.fput(64)
    sol = gj.integrate(scene.H, scene.q0, scene.p0, method=gj.CG(1, gj.midpoint()), h=0.05, n_steps=1000,
                       save_every=1000)
    assert int(sol.status) == 0
    per_element = float(sol.stats["num_newton_iterations"]) / 1000
    assert per_element <= 8.0


def fput_cg3(n_steps, **kwargs):
    scene = scenes.fput(64)
    method = gj.CG(3, gj.gauss_legendre(3))
    sol = gj.integrate(scene.H, scene.q0, scene.p0, method=method, h=0.05, n_steps=n_steps, **kwargs)
    assert int(sol.status) == 0
    return scene, method, sol


@pytest.fixture(scope="module")
def fput_run():
    """1000 elements of ``fput_cg3``, every node saved, shared by the two tests below."""
    return fput_cg3(1000)


def test_a_large_system_stops_at_the_round_off_floor_after_five_updates(fput_run):
    """cG(3) + Gauss 3 on the 64-mass chain (384 unknowns), h = 0.05: the fixed point's rate,
    judged by the last two updates of a block, stops most elements after four updates and the
    polish (the one-off ``solver`` study: about five per element), and the unknowns it accepts are the
    root: solved by the same stopping rule from every third node of the run (from the constant
    predictor, about seven updates), 200 more sweeps move them by 0.01 eps of their size on
    average, at most 0.9 eps. Margins: one update per element; 3 eps."""
    scene, method, sol = fput_run
    assert float(sol.stats["num_newton_iterations"]) / 1000 <= 6.0
    fn, d = _march.element_residual(scene.H), scene.q0.shape[0]
    options = _march.solver_options(method)

    @jax.jit
    @jax.vmap
    def distance_to_root(z):
        q, p = z[:d], z[d:]
        C, params = _march.solve_element(method, scene.H, q, p, 0.05, None, options)[2], (method, q, p, 0.05, None)
        root = jax.lax.fori_loop(0, 200, lambda _, Z: Z - fn(Z, params), C)
        return jnp.sqrt(jnp.mean((C - root) ** 2) / jnp.mean(root**2)) / jnp.finfo(C.dtype).eps

    distances = np.asarray(distance_to_root(jnp.concatenate([sol.q, sol.p], axis=1)[1:1000:3]))
    assert distances.size == 333 and distances.max() <= 3.0


def test_the_first_block_of_four_changes_no_number(fput_run):
    """A system of more than 32 unknowns starts each element with a block of four updates, not
    two (``SolverOptions.first_block``): the check after two, which on the chain never accepts,
    is skipped (the one-off ``solver`` study). The iterates, the counts and the result are those of
    blocks of two, bitwise."""
    _, _, first = fput_run
    _, _, pairs = fput_cg3(1000, solver=gj.SolverOptions(first_block=2))
    assert int(first.stats["num_newton_iterations"]) == int(pairs.stats["num_newton_iterations"])
    np.testing.assert_array_equal(np.concatenate([first.q, first.p]), np.concatenate([pairs.q, pairs.p]))
