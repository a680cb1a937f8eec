"""``gj.SolverOptions``: one frozen options object for the implicit
solve, its shorthands, ``throw=``, ``step``'s status and the count of elements accepted short
of the round-off criterion."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _solve, scenes

KEPLER = scenes.kepler(0.6)
CG2 = gj.CG(2, gj.gauss_legendre(2))


def kepler(n_steps=50, **kwargs):
    return gj.integrate(KEPLER.H, KEPLER.q0, KEPLER.p0, method=CG2, h=0.05, n_steps=n_steps, **kwargs)


def test_options_are_frozen_hashable_and_the_shorthands_build_the_same_object():
    solver = gj.SolverOptions(max_iterations=20, krylov=True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        solver.max_iterations = 3
    assert hash(solver) == hash(gj.SolverOptions(max_iterations=20, krylov=True))
    assert _solve.solver_from(None, 20, True) == solver
    # a shorthand replaces its field of the object passed
    assert _solve.solver_from(gj.SolverOptions(max_iterations=5, patience=3), 20, None) == gj.SolverOptions(
        max_iterations=20, patience=3)
    a, b = kepler(max_newton_iterations=20), kepler(solver=gj.SolverOptions(max_iterations=20))
    np.testing.assert_array_equal(a.q, b.q)
    assert int(a.stats["num_newton_iterations"]) == int(b.stats["num_newton_iterations"])


@pytest.mark.parametrize("bad, error, name", [
    (dict(max_iterations=0), ValueError, "max_iterations"),
    (dict(patience=1.5), ValueError, "patience"),
    (dict(attempt_matrices=0), ValueError, "attempt_matrices"),
    (dict(theta_newton=(0.03,)), ValueError, "theta_newton"),
    (dict(min_damping=0.0), ValueError, "min_damping"),
    (dict(krylov=1), TypeError, "krylov"),
    (dict(miss_orders=()), ValueError, "miss_orders"),
    (dict(tolerance=-1e-9), ValueError, "tolerance"),
    (dict(tolerance=1.0), ValueError, "tolerance"),
    (dict(tolerance=True), ValueError, "tolerance"),
])
def test_bad_options_raise_naming_the_field(bad, error, name):
    with pytest.raises(error, match=name):
        gj.SolverOptions(**bad)


def test_solver_must_be_an_options_object():
    with pytest.raises(TypeError, match="solver"):
        kepler(solver={"max_iterations": 5})
    with pytest.raises(ValueError, match="max_newton_iterations"):
        kepler(max_newton_iterations=0)


def test_the_fixed_point_patience_leaves_newton_half_the_cap():
    """The patience of a fixed-point member (12 and 24 iterations by default) is at most half
    the cap, so that a member that contracts too slowly always reaches Newton."""
    assert gj.SolverOptions().fixed_point_patience_for(True) == 24
    assert gj.SolverOptions(max_iterations=20).fixed_point_patience_for(True) == 10
    assert gj.SolverOptions(max_iterations=20).fixed_point_patience_for(False) == 10
    assert gj.SolverOptions(max_iterations=1).fixed_point_patience_for(False) == 1


def test_every_entry_point_takes_the_same_options():
    """``solver=`` on step, integrate, sweep and amplification_matrix: the same element."""
    solver = gj.SolverOptions(max_iterations=30, patience=4)
    q0, p0 = jnp.asarray(KEPLER.q0), jnp.asarray(KEPLER.p0)
    q1, p1 = gj.step(KEPLER.H, q0, p0, method=CG2, h=0.05, solver=solver)
    sol = gj.integrate(KEPLER.H, q0, p0, method=CG2, h=0.05, n_steps=1, solver=solver)
    swept = gj.sweep(KEPLER.H, gj.grid(method=CG2, h=0.05, state=(q0, p0)), n_steps=1, solver=solver)
    np.testing.assert_array_equal(q1, sol.q[-1])
    np.testing.assert_array_equal(q1, swept.q[0])
    A = gj.amplification_matrix(KEPLER.H, q0, p0, method=CG2, h=0.05, solver=solver)
    assert np.all(np.isfinite(A))


def failing(**kwargs):
    """A Kepler element of h = 0.05 with a cap of 1: status 1."""
    return kepler(n_steps=4, max_newton_iterations=1, **kwargs)


def test_throw_raises_the_status_message_outside_jit():
    assert int(failing().status) == 1  # no throw: a status
    with pytest.raises(gj.SolverError, match="status 1 .*did not converge within max_newton_iterations") as info:
        failing(throw=True)
    assert int(info.value.status) == 1
    assert int(kepler(n_steps=500, throw=True).status) == 0  # status 0: no error (the run of the last test)


def test_throw_under_jit_says_it_cannot():
    with pytest.raises(TypeError, match="throw=True needs a concrete status"):
        jax.jit(lambda q: gj.integrate(KEPLER.H, q, KEPLER.p0, method=CG2, h=0.05, n_steps=2, throw=True).q)(
            jnp.asarray(KEPLER.q0))


def test_step_exposes_its_status():
    q0, p0 = jnp.asarray(KEPLER.q0), jnp.asarray(KEPLER.p0)
    q1, p1, status = gj.step(KEPLER.H, q0, p0, method=CG2, h=0.05, max_newton_iterations=1, return_status=True)
    assert int(status) == 1 and np.all(np.isnan(q1))
    *_, status = jax.jit(lambda q: gj.step(KEPLER.H, q, p0, method=CG2, h=0.05, return_status=True))(q0)
    assert int(status) == 0
    with pytest.raises(gj.SolverError, match="status 1"):
        gj.step(KEPLER.H, q0, p0, method=CG2, h=0.05, max_newton_iterations=1, throw=True)


def test_sweep_throw_names_the_failed_configurations():
    q0, p0 = jnp.asarray(KEPLER.q0), jnp.asarray(KEPLER.p0)
    configs = gj.grid(method=CG2, h=[0.05, 2.0, 0.01], state=(q0, p0))
    result = gj.sweep(KEPLER.H, configs, n_steps=20)
    failed = np.flatnonzero(np.asarray(result.status))
    assert failed.tolist() == [1]  # h = 2 on an orbit of period 2 pi and pericentre 0.4
    with pytest.raises(gj.SolverError, match=r"configurations \[1\]"):
        gj.sweep(KEPLER.H, configs, n_steps=20, throw=True)


def measurements(**values):
    one = lambda v: jnp.asarray([v], jnp.float64)
    m = dict(step=1e-20, before=1e-20, rate=1.0, theta=1.0, z_size=1.0, r_size=1e-12, bad=False, patience=False,
             stale=False)
    m.update(values)
    return {k: jnp.asarray([v]) if isinstance(v, bool) else one(v) for k, v in m.items()}


@pytest.mark.parametrize("case, values, previous_r, accepted, lenient", [
    # the error left is below the round-off of the unknowns: the strict rule
    ("converged", dict(step=1e-15, before=1e-10, rate=1e-5, theta=1e-5), 1e-10, True, False),
    # updates that stopped shrinking at sqrt(eps) with a fresh Newton matrix: the stall floor
    ("stalled, fresh matrix", dict(step=1e-9, before=1e-9, rate=1.0, theta=1.0), 1e-9, False, True),
    # ... not with a stale one (it is refreshed instead)
    ("stalled, stale matrix", dict(step=1e-9, before=1e-9, rate=1.0, theta=1.0, stale=True), 1e-9, None, None),
    # round-off-sized updates that still shrink, by less than half, past the patience
    ("settled noise", dict(step=1e-15, before=1.5e-15, rate=0.7, theta=0.7, patience=True), 1e-12, True, True),
    # ... not before the patience is used up
    ("noise, patient", dict(step=1e-15, before=1.5e-15, rate=0.7, theta=0.7), 1e-12, None, None),
])
def test_the_stopping_rule_marks_acceptances_short_of_round_off(case, values, previous_r, accepted, lenient):
    """``_solve._converged``: which rule accepts, and whether ``num_accepted_stalled`` counts it."""
    problem = type("P", (), {"scale": jnp.ones(1), "tolerance": jnp.zeros(1), "solver": gj.SolverOptions()})()
    c = {"step": jnp.asarray([values.get("before", 1e-20)]), "r_size": jnp.asarray([previous_r])}
    done, accept_here, is_lenient, _, _ = _solve._converged(problem, c, measurements(**values))
    if accepted is None:
        assert not bool(done[0]), case
        return
    assert bool(done[0]) and bool(accept_here[0]) == accepted, case
    assert bool(is_lenient[0]) == lenient, case


def test_smooth_runs_count_no_element_accepted_short_of_round_off():
    """Kepler at h = 0.05: every element meets the strict rule (``Status.SUCCESS``'s message
    names the count a user reads)."""
    sol = kepler(n_steps=500)
    assert int(sol.status) == 0 and int(sol.stats["num_accepted_stalled"]) == 0
    assert "num_accepted_stalled" in gj.status_message(0)


def test_a_tolerance_stops_the_iteration_early_at_an_error_of_that_size():
    """FPUT with 64 masses (the Gauss-Seidel sweep), cG(3), h = 0.1, 1000 elements: iterating to
    1e-13, 1e-11 and 1e-9 of the unknowns instead of their round-off takes 6.0, 5.1 and 4.0
    updates an element instead of 7.9 (measured), and moves the final state by 1.2e-12,
    1.3e-10 and 2.8e-10 (|z| ~ 1; bound: 10 x tolerance x elements, the iteration errors added up)
    while the relative energy error, the discretisation's 7.9e-9, moves by less than 1e-13."""
    scene = scenes.fput(64)
    q0, p0 = jnp.asarray(scene.q0), jnp.asarray(scene.p0)
    runs = {tol: gj.integrate(scene.H, q0, p0, method=gj.CG(3, gj.gauss_legendre(3)), h=0.1, n_steps=1000,
                              save_every=100, solver=gj.SolverOptions(tolerance=tol))
            for tol in (0.0, 1e-13, 1e-11, 1e-9)}
    updates = {tol: float(sol.stats["num_newton_iterations"]) / 1000 for tol, sol in runs.items()}
    energy = {tol: float(jnp.max(jnp.abs(jax.vmap(scene.H)(sol.q, sol.p) - scene.H(q0, p0))))
              for tol, sol in runs.items()}
    end = lambda sol: jnp.concatenate([sol.q[-1], sol.p[-1]])
    assert 7.5 < updates[0.0] < 8.5 and updates[0.0] > updates[1e-13] > updates[1e-11] > updates[1e-9]
    assert updates[1e-9] < 0.6 * updates[0.0]
    for tol, sol in runs.items():
        assert int(sol.status) == 0
        assert float(jnp.max(jnp.abs(end(sol) - end(runs[0.0])))) <= max(10 * tol, 1e-15) * 1000
        assert abs(energy[tol] - energy[0.0]) < 1e-13 * abs(float(scene.H(q0, p0))) + 1e-12 * energy[0.0]


@pytest.mark.parametrize("k, h, newton, sweep", [(6, 0.1, 3.86, 4.12), (2, 0.05, 3.91, 4.80)])
def test_newton_and_the_sweep_save_updates_at_large_h_and_reach_the_same_root(k, h, newton, sweep):
    """Kepler e = 0.6, cG(k) + Gauss k, 400 elements at h omega far from small: the default
    (fixed point with R, d = 2 <= sweep_dimension) takes 6.24 (cG(6), h = 0.1) and 6.34 (cG(2),
    h = 0.05) updates an element; simplified Newton with a kept matrix (``theta_fixed_point``
    tiny) 3.86 and 3.91, the Gauss-Seidel sweep (the position-only form of a separable H,
    ``sweep_dimension=1``) 4.12 and 4.80 (measured), and both end within 3.3e-14 of the default's
    state (|z| ~ 1; asserted 1e-12: round-offs of 400 elements). Neither is the default: fewer
    updates, not less time (notes/solver-design.md, "Fewer updates")."""
    method = gj.CG(k, gj.gauss_legendre(k))
    runs = {name: gj.integrate(KEPLER.H, KEPLER.q0, KEPLER.p0, method=method, h=h, n_steps=400, solver=solver)
            for name, solver in (("default", gj.SolverOptions()), ("newton", gj.SolverOptions(theta_fixed_point=1e-12)),
                                 ("sweep", gj.SolverOptions(sweep_dimension=1)))}
    updates = {name: float(sol.stats["num_newton_iterations"]) / 400 for name, sol in runs.items()}
    end = lambda sol: jnp.concatenate([sol.q[-1], sol.p[-1]])
    assert 5.9 < updates["default"] < 6.7
    assert abs(updates["newton"] - newton) < 0.3 and abs(updates["sweep"] - sweep) < 0.3
    for sol in runs.values():
        assert int(sol.status) == 0
        assert float(jnp.max(jnp.abs(end(sol) - end(runs["default"])))) < 1e-12
