"""Hard first elements: the solver against plain Newton.

Each case is one element from the constant guess, where the predictor has no history: large
h omega, large momenta, near-collisions, a non-separable H, every method family. The reference
is plain Newton written here, independently of ``_solve``: a fresh dense Jacobian
(``jax.jacfwd`` of ``method.residual``) every iteration, full steps. The solver must reach the
same root within the default cap, in at most ``BOUND_FACTOR`` times plain Newton's iterations
plus ``BOUND_SLACK`` (its matrix is refreshed only when it contracts too slowly, and a far
step may be tried twice). ``benchmarks/bench_stress.py`` records the counts.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _march, _tangent, scenes

jax.config.update("jax_enable_x64", True)

BOUND_FACTOR, BOUND_SLACK = 3, 3


def quartic_L(m=2.0, c=1000.0):
    """The quartic central force's Lagrangian, for ``LagrangianVI``."""
    return lambda q, v: 0.5 * m * (v @ v) - 0.5 * c * (q @ q - 1.0) ** 2


def stiff_duffing(omega=10.0):
    """H = |p|^2 / 2 + omega^2 |q|^2 / 2 + |q|^4 / 4: a stiff nonlinear spring."""
    return lambda q, p: 0.5 * (p @ p) + 0.5 * omega**2 * (q @ q) + 0.25 * (q @ q) ** 2


def nonseparable(q, p):
    """H = |p|^2 (1 + |q|^2) / 2 + |q|^2 / 2: the mass depends on the position."""
    return 0.5 * (p @ p) * (1.0 + q @ q) + 0.5 * (q @ q)


QUARTIC = scenes.quartic().H
HIGH = (np.array([1.0, 0.0, 0.0]), np.array([100.0, 70.99, 94.66]))  # the quartic force at high momentum
KEPLER_95 = scenes.kepler(0.95)
PERICENTRE = (np.asarray(KEPLER_95.q0), np.asarray(KEPLER_95.p0))  # |q| = 0.05, |p| = 6.2
FPUT = scenes.fput(16)
CHAIN_SCENE = scenes.pendulum_chain(10, angle=1.0, momenta=1.0, seed=2)
CHAIN = (CHAIN_SCENE.H, CHAIN_SCENE.q0, CHAIN_SCENE.p0)
G2, L2, G3 = gj.gauss_legendre(2), gj.gauss_lobatto(2), gj.gauss_legendre(3)

# name: (H, q0, p0, method, h, solver keywords)
CASES = {
    "quartic high momentum, cG(1) + Lobatto 2": (QUARTIC, *HIGH, gj.CG(1, L2), 0.01, {}),
    "quartic high momentum, cG(2) + Gauss 2": (QUARTIC, *HIGH, gj.CG(2, G2), 0.01, {}),
    "quartic high momentum, dG(1) + Gauss 2": (QUARTIC, *HIGH, gj.DG(1, G2), 0.01, {}),
    "quartic high momentum, cG(3) + Gauss 3": (QUARTIC, *HIGH, gj.CG(3, G3), 0.01, {}),
    "quartic high momentum, dG(0) + Gauss 2": (QUARTIC, *HIGH, gj.DG(0, G2), 0.005, {}),
    "quartic high momentum, GalerkinVI(2) + Gauss 2": (QUARTIC, *HIGH, gj.GalerkinVI(2, G2), 0.01, {}),
    "quartic high momentum, LagrangianVI(2) + Gauss 2": (quartic_L(), *HIGH, gj.LagrangianVI(2, G2), 0.01, {}),
    "quartic high momentum, ModifiedMidpoint": (QUARTIC, *HIGH, gj.ModifiedMidpoint(), 0.01, {}),
    "quartic high momentum, DiscreteGradient": (QUARTIC, *HIGH, gj.DiscreteGradient(), 0.01, {}),
    "Kepler e = 0.95 pericentre, cG(2) + Gauss 2": (KEPLER_95.H, *PERICENTRE, gj.CG(2, G2), 0.01, {}),
    "Kepler e = 0.95 pericentre, dG(1) + Gauss 2": (KEPLER_95.H, *PERICENTRE, gj.DG(1, G2), 0.01, {}),
    "Kepler e = 0.95 pericentre, DiscreteGradient": (KEPLER_95.H, *PERICENTRE, gj.DiscreteGradient(), 0.005, {}),
    "stiff spring h omega = 5, cG(2) + Gauss 2": (stiff_duffing(), np.array([1.0, 0.5]), np.array([0.0, 3.0]),
                                                 gj.CG(2, G2), 0.5, {}),
    "stiff spring h omega = 5, GalerkinVI(2) + Gauss 3": (stiff_duffing(), np.array([1.0, 0.5]),
                                                          np.array([0.0, 3.0]), gj.GalerkinVI(2, G3), 0.5, {}),
    "pendulum near the separatrix h = 1, cG(3) + Gauss 3": (scenes.pendulum().H, np.array([0.0]), np.array([1.99]),
                                                            gj.CG(3, G3), 1.0, {}),
    "non-separable H, cG(2) + Gauss 3": (nonseparable, np.array([1.5, -1.0]), np.array([2.0, 1.0]),
                                        gj.CG(2, G3), 0.3, {}),
    "non-separable H, dG(1) + Gauss 2": (nonseparable, np.array([1.5, -1.0]), np.array([2.0, 1.0]),
                                        gj.DG(1, G2), 0.3, {}),
    "non-separable H, DiscreteGradient": (nonseparable, np.array([1.5, -1.0]), np.array([2.0, 1.0]),
                                         gj.DiscreteGradient(), 0.3, {}),
    "pendulum chain of 10 links h = 0.5, cG(3) + Gauss 3": (*CHAIN, gj.CG(3, G3), 0.5, {}),
    "pendulum chain of 10 links h = 0.5, GalerkinVI(2) + Gauss 2": (*CHAIN, gj.GalerkinVI(2, G2), 0.5, {}),
    "pendulum chain of 10 links h = 0.25, cG(3) + Gauss 3": (*CHAIN, gj.CG(3, G3), 0.25, {}),
    "FPUT N = 16 at 10x momenta h = 0.5, cG(2) + Gauss 2 (fixed point first)": (
        FPUT.H, FPUT.q0, 10 * FPUT.p0, gj.CG(2, G2), 0.5, {}),
    "FPUT N = 16 at 10x momenta h = 0.5, GalerkinVI(2) + Gauss 2 (fixed point first)": (
        FPUT.H, FPUT.q0, 10 * FPUT.p0, gj.GalerkinVI(2, G2), 0.5, {}),
    "FPUT N = 48 h = 1, cG(3) + Gauss 3, krylov (no dense matrix)": (
        scenes.fput(48).H, scenes.fput(48).q0, 3 * scenes.fput(48).p0, gj.CG(3, G3), 1.0, {"krylov": True}),
}


def plain_newton(method, H, q, p, h, max_iterations=100):
    """The root of ``method.residual`` by Newton with a fresh dense Jacobian every iteration and
    full steps, from the constant guess. Returns ``(Z, iterations)``: the updates until the
    first below sqrt(eps) of the state, which leaves the error at round-off, plus that one;
    the iterate is then polished by two more updates."""
    q, p = jnp.asarray(q, jnp.float64), jnp.asarray(p, jnp.float64)
    Z0 = method.initial_guess(q, p)
    residual = lambda z: method.residual(H, q, p, z.reshape(Z0.shape), h).reshape(-1)
    update = jax.jit(lambda z: jnp.linalg.solve(jax.jacfwd(residual)(z), residual(z)))  # one compilation
    scale = float(jnp.max(jnp.abs(jnp.concatenate([q, p]))))
    z, floor = Z0.reshape(-1), np.sqrt(np.finfo(np.float64).eps)
    for iteration in range(1, max_iterations + 1):
        dz = update(z)
        z = z - dz
        if not np.all(np.isfinite(z)):
            return None, None
        if float(jnp.sqrt(jnp.mean(dz**2))) <= floor * (scale + float(jnp.sqrt(jnp.mean(z**2)))):
            for _ in range(2):
                z = z - update(z)
            return z.reshape(Z0.shape), iteration
    return None, None


@functools.cache
def plain_newton_of(name):
    """``plain_newton`` of a case, computed once per case (the watchdog test reads it again)."""
    H, q, p, method, h, _ = CASES[name]
    return plain_newton(method, H, q, p, h)


def solver_element(method, H, q, p, h, keywords):
    """The library's element from the constant guess: ``(Z, iterations, status)``."""
    q, p = jnp.asarray(q, jnp.float64), jnp.asarray(p, jnp.float64)
    options = _march.solver_options(method, **keywords)
    run = jax.jit(lambda q, p: _march.solve_element(method, H, q, p, h, None, options)[2:])
    Z, iterations, status = run(q, p)
    return Z, int(iterations), int(status)


def compare(name):
    """``(plain iterations, ours, relative root difference, status)`` of a case: the difference
    in units of eps times the state's size."""
    H, q, p, method, h, keywords = CASES[name]
    Z_ref, plain = plain_newton_of(name)
    Z, ours, status = solver_element(method, H, q, p, h, keywords)
    scale = float(np.max(np.abs(np.concatenate([q, p]))))
    difference = float(jnp.max(jnp.abs(Z - Z_ref))) / (np.finfo(np.float64).eps * scale)
    return plain, ours, difference, status


# Cases over the bound, each with its measured reason: a strict xfail, so that one brought within it fails here.
OVER_BOUND = {
    "pendulum chain of 10 links h = 0.25, cG(3) + Gauss 3": (
        "26 updates against plain Newton's 5 (20 with the Gauss-Seidel sweep, which a non-separable H no longer "
        "takes): the fixed point uses up its patience for a large system (24 updates) before Newton's two"),
}


@pytest.mark.parametrize("name", [pytest.param(name, marks=pytest.mark.xfail(strict=True, reason=OVER_BOUND[name]))
                                  if name in OVER_BOUND else name for name in CASES])
def test_hard_first_element_reaches_plain_newtons_root_within_a_small_multiple_of_its_iterations(name):
    """Status 0 at the default cap (48), the root of plain Newton to within 100 eps of the
    state (measured at most 15 eps: the two iterations stop at different round-off; a different
    root would differ by O(h |z|), above 1e10 eps here), and at most 3 x plain Newton's
    iterations + 3 (measured at most 2.7 x, ``bench_stress.py``)."""
    plain, ours, difference, status = compare(name)
    assert plain is not None, "plain Newton must converge on every case of the set"
    assert status == 0
    assert difference <= 100, difference
    assert ours <= BOUND_FACTOR * plain + BOUND_SLACK, (ours, plain)


@pytest.mark.parametrize("name", [name for name in CASES if name.startswith("quartic high momentum, ") and
                                  name.split(", ")[1] in ("cG(1) + Lobatto 2", "cG(2) + Gauss 2", "dG(1) + Gauss 2")])
def test_the_quartic_high_momentum_elements_need_the_watchdog_for_the_bound(name):
    """The quartic force's elements at high momentum: with ``watch=0`` (halving from the first full step that raises the
    residual) the solver exceeds the bound of 3 x plain Newton's 4 iterations + 3 (measured
    26 to 32 iterations, ``bench_stress.py``); the watchdog keeps them within it."""
    H, q, p, method, h, _ = CASES[name]
    _, without, status = solver_element(method, H, q, p, h, {"solver": gj.SolverOptions(watch=0)})
    _, plain = plain_newton_of(name)
    assert without > BOUND_FACTOR * plain + BOUND_SLACK


def tangents_at_the_root(name):
    """At plain Newton's root of a case: the tangent of its root along a random (dq0, dp0), and
    the cotangent of (q0, p0) for a random cotangent of the root, each by the matrix-free solve
    (Richardson's iteration, then GMRES where it does not contract) and by LU on the jacfwd
    matrix, and that matrix's condition number."""
    H, q, p, method, h, _ = CASES[name]
    Z, _ = plain_newton_of(name)
    q, p = jnp.asarray(q, jnp.float64), jnp.asarray(p, jnp.float64)
    residual = _march.element_residual(H)
    fn = lambda Z, start: residual(Z, (method, *start, jnp.asarray(h), None))
    rng = np.random.default_rng(0)
    d_start = (jnp.asarray(rng.normal(size=q.shape)), jnp.asarray(rng.normal(size=p.shape)))
    cotangent = jnp.asarray(rng.normal(size=Z.shape))

    @jax.jit
    def both():
        out = []
        for limit in (0, 10**9):  # matrix-free, dense
            tangent = lambda d: _tangent.tangent(fn, (q, p), Z, jnp.asarray(True), d, dense_limit=limit)
            out.append((tangent(d_start), jnp.concatenate(jax.vjp(tangent, d_start)[1](cotangent)[0])))
        J = jax.jacfwd(lambda z: fn(z.reshape(Z.shape), (q, p)).reshape(-1))(Z.reshape(-1))
        return out, J

    (free, dense), J = both()
    return free, dense, float(np.linalg.cond(np.asarray(J)))


def tangent_error(name):
    """The largest relative difference between the matrix-free and the LU tangent of a case
    (``tangents_at_the_root``), in units of eps cond(dR/dZ)."""
    free, dense, cond = tangents_at_the_root(name)
    error = max(float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b))) for a, b in zip(free, dense))
    return error / (np.finfo(np.float64).eps * cond)


# a case of each kind for the tangents (each compiles its own solves; ``bench_stress.py`` runs all):
# Richardson's iteration alone (the pendulum), GMRES after it (the rest: FPUT's Gauss-Seidel sweep,
# a time-symmetric method, a method without a fixed point, a discrete gradient, a non-separable H)
TANGENT_CASES = ["pendulum near the separatrix h = 1, cG(3) + Gauss 3",
                 "FPUT N = 48 h = 1, cG(3) + Gauss 3, krylov (no dense matrix)",
                 "FPUT N = 16 at 10x momenta h = 0.5, GalerkinVI(2) + Gauss 2 (fixed point first)",
                 "quartic high momentum, dG(1) + Gauss 2", "Kepler e = 0.95 pericentre, DiscreteGradient",
                 "non-separable H, cG(2) + Gauss 3"]


@pytest.mark.parametrize("name", TANGENT_CASES)
def test_the_matrix_free_tangent_at_a_hard_root_equals_lu(name):
    """The element tangents that derivatives solve (``_tangent``), forced matrix-free at a
    case's root, equal LU's, forward and reverse, within 2 TOLERANCE eps cond(dR/dZ) relative: the
    solve stops at a residual of TOLERANCE eps |b|, an error of at most cond TOLERANCE eps, and
    LU's own is about cond eps. Measured at most 6.9 cond eps over the whole set (cond from 1.1 to
    7e3; ``bench_stress.py``)."""
    assert tangent_error(name) <= 2 * _tangent.TOLERANCE
