"""Time spans, error-per-step control, the time transformation, saving at chosen times and events."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

H, Q0, P0 = helpers.kepler(0.5)
T = 2 * np.pi
CG4 = gj.CG(4, gj.gauss_legendre(4))
CG3 = gj.CG(3, gj.gauss_legendre(3))


def pid(tol, **kw):
    return gj.PIDController(rtol=tol, atol=tol, **kw)


def error_after_one_orbit(sol):
    return float(np.max(np.abs(np.concatenate([sol.q[-1] - Q0, sol.p[-1] - P0]))))


def orbits_from_apocentre(e, orbits=2):
    """Kepler with eccentricity e over ``orbits`` orbits from apocentre: ``(H, q0, p0, T, z1)``,
    z1 the exact final state."""
    T = orbits * 2 * np.pi
    q0, p0 = (jnp.asarray(x) for x in helpers.kepler_exact(np.pi, e))
    return helpers.kepler(e)[0], q0, p0, T, np.concatenate(helpers.kepler_exact(np.pi + T, e))


def distance(sol, z1):
    """Max-norm distance of a run's final state from z1."""
    return float(np.max(np.abs(np.concatenate([sol.q[-1], sol.p[-1]]) - z1)))


def count_matrices(monkeypatch, log):
    """Append -1 to ``log`` for every Newton matrix, through an ordered host callback in
    ``_solve._Problem.jacobians``, the one function that computes them (cached traces cleared)."""
    from galerkin_jax import _solve

    jacobians = _solve._Problem.jacobians

    def counted(problem, Z):
        jax.debug.callback(lambda: log.append(-1), ordered=True)
        return jacobians(problem, Z)

    monkeypatch.setattr(_solve._Problem, "jacobians", counted)
    jax.clear_caches()


def matrices_of(monkeypatch, run):
    """``(run(), n)``, n the Newton matrices ``run`` computed (``count_matrices``; the hook is
    undone and the cached traces cleared before it returns)."""
    log = []
    count_matrices(monkeypatch, log)
    out = run()
    jax.effects_barrier()
    monkeypatch.undo()
    jax.clear_caches()
    return out, len(log)


def two_orbits_counting_matrices(monkeypatch, tol):
    """Kepler e = 0.9 over two orbits from apocentre, cG(8) + Gauss 8 under ``pid(tol)``:
    ``(sol, z1, matrices)`` (``matrices_of``)."""
    He, q0, p0, T2, z1 = orbits_from_apocentre(0.9)
    sol, matrices = matrices_of(monkeypatch, lambda: gj.integrate(
        He, q0, p0, method=gj.CG(8, gj.gauss_legendre(8)), h=1e-3 * T2, t1=T2, controller=pid(tol),
        error_estimate=False))
    return sol, z1, matrices


def test_error_falls_with_the_tolerance():
    """Kepler e = 0.5 over one orbit with cG(4): the error falls monotonically with rtol = atol.
    The embedded estimate has order 5 and the method's local error order 9, so the error falls
    faster than the tolerance (measured: 1.2e-9, 1.1e-12, 1.3e-14 at 1e-6, 1e-8, 1e-10) and the
    steps grow like tol^(-1/5) (41, 100, 251)."""
    sols = [gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=T, controller=pid(tol)) for tol in (1e-6, 1e-8, 1e-10)]
    errors = [error_after_one_orbit(s) for s in sols]
    steps = [int(s.stats["num_accepted_steps"]) for s in sols]
    assert all(int(s.status) == 0 for s in sols)
    assert errors[0] > 100 * errors[1] > 100 * 10 * errors[2] / 10  # each 100x tighter tolerance: >= 100x smaller
    assert errors[0] < 1e-6 and errors[2] < 1e-12
    # steps ~ tol^(-1/5): 2.5x per factor 100 (measured 2.44, 2.51); 1.8 and 3.5 bracket it
    assert all(1.8 < b / a < 3.5 for a, b in zip(steps, steps[1:]))
    assert sols[2].t[-1] == T


def test_a_first_step_of_half_a_period_is_rejected_not_fatal():
    """h0 = pi (half the orbit): the controller rejects and shrinks it, the run is as accurate as
    with a reasonable first step (measured 4.6e-13 against 1.1e-12 from h0 = 0.1)."""
    sol = gj.integrate(H, Q0, P0, method=CG4, h=np.pi, t1=T, controller=pid(1e-8))
    assert int(sol.status) == 0
    # at least 0.2 (factormin; 0.5 after a failed solve) per rejection: pi -> 0.13 needs two or more (measured 5)
    assert int(sol.stats["num_rejected_steps"]) >= 2
    assert float(sol.stats["max_step"]) < 0.5
    assert error_after_one_orbit(sol) < 1e-10


def starting_step(field, z0, order, tol, span):
    """Hairer, Norsett and Wanner's starting step (Solving ODEs I, Sec. II.4), in NumPy, with the
    scale tol + tol |z0| (rtol = atol = tol) and the RMS norm: h0' = 0.01 d0 / d1 from
    d0 = ||z0||, d1 = ||f(z0)||; d2 = ||f(z0 + h0' f(z0)) - f(z0)|| / h0' from one explicit
    Euler step; h1 = (0.01 / max(d1, d2))^(1 / order); h0 = min(100 h0', h1, span).
    ``(h0, 100 h0', h1)``."""
    norm = lambda x: np.sqrt(np.mean((x / (tol + tol * np.abs(z0))) ** 2))
    f0 = field(z0)
    d0, d1 = norm(z0), norm(f0)
    h = 0.01 * d0 / d1
    d2 = norm(field(z0 + h * f0) - f0) / h
    h1 = (0.01 / max(d1, d2)) ** (1.0 / order)
    return min(100 * h, h1, span), 100 * h, h1


def kepler_field(z):
    """Hamilton's field of H = |p|^2 / 2 - 1 / |q|, z = (q, p)."""
    q, p = z[:2], z[2:]
    return np.concatenate([p, -q / np.linalg.norm(q) ** 3])


@pytest.mark.parametrize("e, tol, k, binding", [(0.5, 1e-8, 4, "h1"), (0.9, 1e-6, 6, "100 h0'")])
def test_a_controller_picks_hairer_norsett_wanners_first_step(e, tol, k, binding):
    """h=None under a PIDController: the first step the run takes is Hairer, Norsett and
    Wanner's starting step, computed here in NumPy from Kepler's field (``starting_step``) with
    the order of the embedded estimate, cG(k)'s k + 1 coefficients. Read from a run stopped
    after one element (``max_steps=1``, that one accepted and none rejected, so it is the first
    attempt's h). Kepler e = 0.5, cG(4), tol 1e-8: h1 = 8.10136e-3 binds (100 h0' = 0.164);
    e = 0.9, cG(6), tol 1e-6: 100 h0' = 8.17683e-3 binds (h1 = 0.0305). Measured: equal to the
    last digit printed (the same formula, in float64); asserted to 1e-12 relative, where a step
    2x off fails by 1 and the order k in place of k + 1 (2.43e-3 at e = 0.5) by 0.7."""
    H, q0, p0 = helpers.kepler(e)
    z0 = np.concatenate([np.asarray(q0), np.asarray(p0)])
    expected, h_euler, h_order = starting_step(kepler_field, z0, k + 1, tol, T)
    assert expected == {"h1": h_order, "100 h0'": h_euler}[binding]
    sol = gj.integrate(H, q0, p0, method=gj.CG(k, gj.gauss_legendre(k)), t1=T, controller=pid(tol), max_steps=1)
    assert int(sol.status) == gj.Status.MAX_STEPS
    assert int(sol.stats["num_accepted_steps"]) == 1 and int(sol.stats["num_rejected_steps"]) == 0
    assert float(sol.stats["min_step"]) == float(sol.stats["max_step"]) == float(sol.t[-1] - sol.t[0])
    assert float(sol.t[-1] - sol.t[0]) == pytest.approx(expected, rel=1e-12, abs=0)


def test_the_predictive_controller_follows_the_way_into_a_pericentre():
    """Kepler e = 0.9 over two orbits from apocentre, cG(6) + Gauss 6, rtol = atol = 1e-8. On
    the way into each pericentre the I controller grows h after every accepted step and has the
    next one rejected (measured: 54 rejections for 131 accepted steps); Gustafsson's predictive
    term follows the shrinking steps (4 rejections, the same 131 accepted steps, 1087 iterations
    against 1505) and both end within 1e-14 of the exact orbit. Margins: the rejections at most
    10 % of the steps against at least 30 % without the term; iterations at most 0.8x."""
    He, q0, p0, T2, z1 = orbits_from_apocentre(0.9)
    runs = {}
    for predictive in (True, False):
        sol = gj.integrate(He, q0, p0, method=gj.CG(6, gj.gauss_legendre(6)), h=1e-3 * T2, t1=T2,
                           controller=pid(1e-8, predictive=predictive), error_estimate=False)
        assert int(sol.status) == 0
        assert distance(sol, z1) < 1e-13
        runs[predictive] = {k: int(sol.stats[k]) for k in ("num_accepted_steps", "num_rejected_steps", "num_newton_iterations")}
    steps = runs[True]["num_accepted_steps"]
    assert abs(steps - runs[False]["num_accepted_steps"]) <= 0.05 * steps
    assert runs[True]["num_rejected_steps"] <= 0.1 * steps
    assert runs[False]["num_rejected_steps"] >= 0.3 * runs[False]["num_accepted_steps"]
    assert runs[True]["num_newton_iterations"] <= 0.8 * runs[False]["num_newton_iterations"]


def test_a_loose_tolerance_keeps_to_the_fixed_point(monkeypatch):
    """Kepler e = 0.9 over two orbits from apocentre, cG(8) + Gauss 8 (32 unknowns, a small
    system), rtol = atol = 1e-6: the first long steps need Newton, and a small system's policy
    (kept with Newton for good) took a fresh matrix in 46 of the 54 attempts, its h changing in
    every one. Under a controller a small system follows a large one's policy (back to the
    fixed point after ``newton_stretch`` elements): measured 1 matrix, the same 50 steps and
    the same final error, 3.4e-12. Matrices counted through a host callback in
    ``_solve._Problem.jacobians``, the one function that computes them; bound 4."""
    sol, z1, matrices = two_orbits_counting_matrices(monkeypatch, 1e-6)
    assert int(sol.status) == 0
    assert distance(sol, z1) < 1e-10
    assert 1 <= matrices <= 4


def test_a_step_too_long_for_the_solve_fails_after_two_matrices(monkeypatch):
    """Kepler e = 0.9 over two orbits from apocentre, cG(8) + Gauss 8, rtol = atol = 1e-4: near
    apocentre the controller proposes steps the fixed point cannot take, and Newton from the
    continued polynomial needed up to 13 fresh matrices in an attempt (the watchdog, damping,
    refreshes) before it failed or ended at another root of the element equations, which the
    estimate rejects. Under a controller an element that asks for a third matrix fails
    (``SolverOptions.attempt_matrices``) and the controller retries it shorter. With diffrax's
    cut after a failed solve (``failfactor=factormin``, 0.2), whose cycle of failures gives the
    cap the most to do (``test_a_failed_solve_halves_h`` has the default). Measured: 118
    matrices in 95 attempts (35 failed at the cap, at most 2 each), against 358 in 89 (at most
    13) with the cap at 48 (the iteration cap: no cap on matrices); final errors 2.1e-8 and
    3.6e-9. Bounds: at most 2 per attempt, at least 5 attempts that fail (status 1) on their
    second matrix (the cap is reached), at least 100 matrices in the uncapped run (the hooks
    counted), half of those with the cap, error 1e-7."""
    from galerkin_jax import _march, _solve

    log = []
    solve = _march.solve  # the root finder of every element (``_march.element``)

    def attempt(*args):
        out = solve(*args)
        jax.debug.callback(lambda status: log.append(int(status)), out[3], ordered=True)
        return out

    monkeypatch.setattr(_march, "solve", attempt)
    count_matrices(monkeypatch, log)  # clears the cached traces: both wrappers are traced
    He, q0, p0, T2, z1 = orbits_from_apocentre(0.9)
    runs = {}
    for cap in (2, 48):
        log.clear()
        sol = gj.integrate(He, q0, p0, method=gj.CG(8, gj.gauss_legendre(8)), h=1e-3 * T2, t1=T2,
                           controller=pid(1e-4, failfactor=0.2), error_estimate=False,
                           solver=gj.SolverOptions(attempt_matrices=cap))
        jax.effects_barrier()
        assert int(sol.status) == 0
        assert distance(sol, z1) < 1e-7
        per, matrices = [], 0
        for entry in log:  # -1: a matrix; else an attempt's solve status
            if entry < 0:
                matrices += 1
            else:
                per.append((matrices, entry))
                matrices = 0
        runs[cap] = per
    uncapped = sum(m for m, _ in runs[48])
    assert uncapped >= 100
    assert max(m for m, _ in runs[2]) <= 2
    assert sum(1 for m, status in runs[2] if status == _solve.Status.NEWTON_MAX_ITERATIONS and m == 2) >= 5
    assert sum(m for m, _ in runs[2]) <= 0.5 * uncapped
    monkeypatch.undo()
    jax.clear_caches()


def test_a_stretch_of_newton_ends_where_its_matrix_no_longer_serves(monkeypatch):
    """Kepler e = 0.9 over two orbits from apocentre, cG(8) + Gauss 8, rtol = atol = 1e-5: near
    apocentre some steps are beyond the fixed point's reach, and the element switches to
    Newton. Under a controller the next ``newton_stretch`` elements started with Newton too,
    each with a fresh matrix (the kept one was taken at another h and state) and often ending
    at another root that the estimate rejects, where the fixed point at the next h converges.
    Now an element of a stretch that needs a fresh matrix ends it
    (``_solve.Options.short_lived_matrices``). Measured: 7 matrices in 45 attempts, against 30
    in 45 before; the same 40 steps and final error, 1.9e-10. Bounds: 15 matrices (half the old
    count), error 1e-9."""
    sol, z1, matrices = two_orbits_counting_matrices(monkeypatch, 1e-5)
    assert int(sol.status) == 0
    assert distance(sol, z1) < 1e-9
    assert 1 <= matrices <= 15


def test_a_failed_solve_halves_h():
    """After a failed solve the factor is ``max(failfactor, factormin)``, 0.5 by default (Radau5
    after a Newton failure). Cutting by factormin = 0.2 left the estimate of the next, accepted
    step so small that the controller grew h about four times and failed again: on Kepler
    e = 0.9 over two orbits from apocentre, cG(8) + Gauss 8 at rtol = atol = 1e-4, measured 7
    rejections in 41 attempts with 0.5 against 37 in 95 with 0.2, final errors 1.6e-8 and
    2.1e-8. Bounds 0.6 and 0.8 of the 0.2 run's rejections and attempts, error 1e-7."""
    c = pid(1e-6)
    assert float(c.next_factor(jnp.inf, 0.5, 1.0, 5, False, 1.0)) == 0.5
    assert float(pid(1e-6, factormin=0.7).next_factor(jnp.inf, 0.5, 1.0, 5, False, 1.0)) == pytest.approx(0.7)
    He, q0, p0, T2, z1 = orbits_from_apocentre(0.9)
    run = jax.jit(lambda fail: gj.integrate(He, q0, p0, method=gj.CG(8, gj.gauss_legendre(8)), h=1e-3 * T2, t1=T2,
                                            controller=pid(1e-4, failfactor=fail), error_estimate=False))
    stats = {}
    for fail in (0.5, 0.2):
        sol = run(fail)
        assert int(sol.status) == 0
        assert distance(sol, z1) < 1e-7
        stats[fail] = (int(sol.stats["num_rejected_steps"]), int(sol.stats["num_accepted_steps"]) + int(sol.stats["num_rejected_steps"]))
    assert stats[0.5][0] <= 0.6 * stats[0.2][0]
    assert stats[0.5][1] <= 0.8 * stats[0.2][1]
    with pytest.raises(ValueError, match="failfactor"):
        gj.integrate(H, Q0, P0, method=CG3, h=0.1, t1=1.0, controller=pid(1e-6, failfactor=1.5))


def test_the_predictive_factor_is_gustafssons():
    """After an accepted step the factor is the smaller of the I controller's,
    safety err^(-1/q), and Gustafsson's, safety (h / h_prev) err^(-2/q) max(err_prev, 0.01)^(1/q)
    (Hairer and Wanner II, Sec. IV.8; Radau5's); after a rejection, and without a previous
    accepted step (h_ratio NaN), the I controller's alone."""
    c, q = pid(1e-6), 5
    factor = lambda err, err_prev, accepted, ratio: float(c.next_factor(err, err_prev, 1.0, q, accepted, ratio))
    shrinking = 0.9 * 0.7 * 0.5 ** (-2 / q) * 0.25 ** (1 / q)
    assert factor(0.5, 0.25, True, 0.7) == pytest.approx(shrinking, rel=1e-14)
    assert shrinking < 0.9 * 0.5 ** (-1 / q)
    assert factor(0.5, 1e-9, True, 3.0) == pytest.approx(0.9 * 0.5 ** (-1 / q), rel=1e-14)  # the I factor is smaller
    assert factor(0.5, 1e-9, True, 0.5) == pytest.approx(0.9 * 0.5 * 0.5 ** (-2 / q) * 0.01 ** (1 / q), rel=1e-14)
    assert factor(0.5, 0.25, True, np.nan) == pytest.approx(0.9 * 0.5 ** (-1 / q), rel=1e-14)
    assert factor(4.0, 0.25, False, 0.7) == pytest.approx(0.9 * 4.0 ** (-1 / q), rel=1e-14)
    off = pid(1e-6, predictive=False)
    assert float(off.next_factor(0.5, 0.25, 1.0, q, True, 0.7)) == pytest.approx(0.9 * 0.5 ** (-1 / q), rel=1e-14)
    with pytest.raises(TypeError, match="predictive"):
        gj.integrate(H, Q0, P0, method=CG3, h=0.1, t1=1.0, controller=pid(1e-6, predictive=1))


def test_a_vmapped_member_equals_its_single_run():
    """Each member of a vmap over tolerances and initial states takes its own steps and equals
    its single run (same steps, and the states to the last bits the batched solver may move)."""
    tols = jnp.array([1e-6, 1e-9])
    hs = jnp.array([0.1, 0.02])
    run = lambda tol, h: gj.integrate(H, Q0, P0, method=CG4, h=h, t1=T, controller=pid(tol))
    batch = jax.vmap(run)(tols, hs)
    for b in range(2):
        single = run(float(tols[b]), float(hs[b]))  # Python floats: the program of the tests above
        assert int(batch.stats["num_accepted_steps"][b]) == int(single.stats["num_accepted_steps"])
        assert int(batch.stats["num_rejected_steps"][b]) == int(single.stats["num_rejected_steps"])
        np.testing.assert_allclose(batch.q[b], single.q, rtol=0, atol=1e-13)
    assert int(batch.stats["num_accepted_steps"][0]) < int(batch.stats["num_accepted_steps"][1])


def test_a_sweep_over_tolerances_and_initial_states_equals_integrate():
    states = (jnp.stack([Q0, Q0 * 1.1]), jnp.stack([P0, P0]))
    configs = gj.Configs(method=gj.stack_methods([CG4, CG4]), h=jnp.array([0.1, 0.1]), q0=states[0], p0=states[1])
    tols = jnp.array([1e-7, 1e-10])
    result = gj.sweep(H, configs, t1=T, controller=gj.PIDController(rtol=tols, atol=tols))
    for b in range(2):
        single = gj.integrate(H, states[0][b], states[1][b], method=CG4, h=0.1, t1=T, controller=pid(float(tols[b])))
        assert int(result.num_accepted_steps[b]) == int(single.stats["num_accepted_steps"])
        np.testing.assert_allclose(result.q[b], single.q[-1], rtol=0, atol=1e-13)
        # energy error: the run's largest |H - H0| / |H0|, about the final state error here
        assert float(result.energy_error[b]) < [1e-7, 1e-10][b]


def test_a_controller_checked_at_construction_passes_jit_vmap_and_grad():
    """The range check runs where the user builds a PIDController, not where JAX rebuilds it:
    traced leaves under jit, axis specs of 0 (rtol = atol = 0) and None under vmap, zero
    cotangents; each run takes its own steps."""
    run = lambda c, x: gj.integrate(H, Q0.at[0].set(x), P0, method=CG3, h=0.1, t1=1.0, controller=c,
                                    error_estimate=False)
    c, x0 = pid(1e-8), Q0[0]
    eager, jitted = run(c, x0), jax.jit(run)(c, x0)
    assert int(jitted.stats["num_accepted_steps"]) == int(eager.stats["num_accepted_steps"]) > 10
    np.testing.assert_allclose(jitted.q[-1], eager.q[-1], rtol=0, atol=1e-13)
    tols = jnp.array([1e-5, 1e-9])
    batch = gj.PIDController(rtol=tols, atol=tols)
    axes = jax.tree.map(lambda x: 0 if jnp.ndim(x) else None, batch)
    assert axes.rtol == 0 and axes.pcoeff is None  # an axis spec, not a controller to check
    steps = jax.vmap(run, in_axes=(axes, None))(batch, x0).stats["num_accepted_steps"]
    assert int(steps[0]) < int(steps[1])
    grad = jax.grad(lambda x: run(c, x).q[-1, 0])(x0)
    assert np.isfinite(float(grad)) and float(grad) != 0.0
    zero = jax.tree.map(jnp.zeros_like, c)  # the shape of a controller's cotangent
    assert float(zero.rtol) == 0.0 and zero.predictive is True


def test_fixed_steps_to_t1_land_on_t1_and_a_sweep_reaches_it_with_every_h():
    """The last element is shortened: every run ends at t1 exactly, at the accuracy of cG(3)
    against the exact orbit (h = 0.1: 2.9e-6; the shortened element only helps). ``integrate``
    at h = 0.1 only (each h of a fixed run to t1 is its own compiled program); the sweep's
    member at h = 0.07 is checked by its step count and its error against the exact orbit."""
    hs = [0.1, 0.07]
    result = gj.sweep(H, gj.grid(method=CG3, h=hs, state=(Q0, P0)), t1=T)
    sol = gj.integrate(H, Q0, P0, method=CG3, h=hs[0], t1=T)
    assert float(sol.t[-1]) == T and int(sol.stats["num_accepted_steps"]) == int(np.ceil(T / hs[0]))
    np.testing.assert_allclose(result.q[0], sol.q[-1], rtol=0, atol=1e-14)
    for b, h in enumerate(hs):
        assert int(result.num_accepted_steps[b]) == int(np.ceil(T / h))
        error = np.max(np.abs(np.concatenate([result.q[b] - Q0, result.p[b] - P0])))
        assert error < 2e-4 * h**6 / 0.1**6 * 0.1  # order 6: 2.9e-6 at h = 0.1


def test_t0_shifts_time():
    """An autonomous H: starting at t0 = 5 gives the same states at times shifted by 5, and an
    event of g = t - 6 fires at t = 6."""
    base = gj.integrate(H, Q0, P0, method=CG3, h=0.1, n_steps=20)
    shifted = gj.integrate(H, Q0, P0, method=CG3, h=0.1, n_steps=20, t0=5.0)
    np.testing.assert_allclose(shifted.t, base.t + 5.0, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(shifted.q, base.q)
    sol = gj.integrate(H, Q0, P0, method=CG3, h=0.1, t0=5.0, t1=7.0,
                       events=gj.Event(lambda t, q, p: t - 6.0, capacity=2))
    assert int(sol.events.count) == 1 and abs(float(sol.events.t[0]) - 6.0) < 1e-13


def test_save_at_is_accurate_between_nodes():
    """States at times between the nodes come from the element polynomial refined to the nodes'
    accuracy (``_output.refined``): error O(h^(2k)) against the exact orbit, as the nodes', for
    fixed and adaptive runs (cG(3): measured slope 5.99 from h = 0.1 to 0.05; the element
    polynomial alone, of degree k, gave 3.37: 5.2 excludes it and order 5)."""
    ts = jnp.asarray(np.linspace(0.0, 1.0, 13)[1:] + 0.0123)
    exact = np.stack([np.concatenate(helpers.kepler_exact(float(t))) for t in ts])
    errors = []
    for h in (0.1, 0.05):  # max_steps: the elements reserved, one for both h (one compiled program)
        sol = gj.integrate(H, Q0, P0, method=CG3, h=h, t1=1.1, save_at=ts, max_steps=22)
        assert np.array_equal(np.asarray(sol.t), np.asarray(ts))
        errors.append(np.max(np.abs(np.concatenate([sol.q, sol.p], axis=1) - exact)))
    assert 5.2 < np.log2(errors[0] / errors[1]) < 6.8
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=1.1, save_at=ts, controller=pid(1e-10))
    assert np.max(np.abs(np.concatenate([sol.q, sol.p], axis=1) - exact)) < 1e-6


def _energy_error_by_quarter(sol, He, z0, T_end):
    """The largest |H - H0| at the nodes of each quarter of the run (dense output's nodes)."""
    n = int(sol.stats["num_accepted_steps"])
    t = np.asarray(sol.dense.t[: n + 1])
    q, p = sol.dense.view(sol.dense.z[: n + 1])
    energy = np.abs(np.asarray(jax.vmap(He)(q, p)) - float(He(*z0)))
    return [energy[(t >= a * T_end / 4) & (t <= (a + 1) * T_end / 4)].max() for a in range(4)]


def test_the_time_transformation_lands_on_t1_and_its_energy_error_does_not_drift():
    """Kepler e = 0.9 from pericentre over 20 orbits, cG(2) + Gauss 2 (symplectic, symmetric),
    the default density unbounded (``s_max=inf``: from pericentre the default's cap takes 7.1x
    the steps, 4301 against 605, energy error 1.07e-4 against 1.78e-4, tests/test_step_density.py):
    the energy error at the nodes is bounded (measured: the four quarters' maxima equal to 4
    digits, 1.78e-4 at h = 0.01, order 4 in h), while PID control drifts: over 100 orbits at
    rtol = 1e-5 the last quarter's maximum is 3.31x the first's (3.85x without the predictive
    term; over 20 orbits the drift is still hidden by the first orbit's error, 0.76x), where a
    bounded error gives 1 within a few per cent; the margin 2.5 is 3/4 of the measured drift."""
    He, q0, p0 = helpers.kepler(0.9)
    T_end = 20 * 2 * np.pi
    method = gj.CG(2, gj.gauss_legendre(2))
    sol = gj.integrate(He, q0, p0, method=method, h=0.01, t1=T_end, controller=gj.TimeTransform(s_max=float("inf")),
                       dense=True)
    assert int(sol.status) == 0 and float(sol.t[-1]) == T_end
    quarters = _energy_error_by_quarter(sol, He, (q0, p0), T_end)
    assert quarters[-1] <= 1.01 * quarters[0] and quarters[0] < 3e-4
    T_pid = 5 * T_end
    pid_sol = gj.integrate(He, q0, p0, method=method, h=0.01, t1=T_pid, controller=pid(1e-5), dense=True,
                           max_steps=30_000)
    assert int(pid_sol.status) == 0
    pid_quarters = _energy_error_by_quarter(pid_sol, He, (q0, p0), T_pid)
    assert pid_quarters[-1] > 2.5 * pid_quarters[0]


def test_a_time_transformed_small_system_keeps_its_fixed_point(monkeypatch):
    """Kepler e = 0.9 over 5 orbits from apocentre, cG(4) + Gauss 4, default s, h = 0.8 in tau:
    the extended element has 24 unknowns, a small system, whose policy (Newton once switched,
    for good, refreshed at a low rate) suits a fixed h. A time-transformed run's step is as
    long against the local time scale all along the orbit, so a matrix is out of date a few
    elements on (``_solve.Options.short_lived_matrices``). Measured: 6 matrices in 127 steps (4
    in 129 before the default density's cap, which lengthens the steps near pericentre by up to
    2 %: tests/test_step_density.py; 9 before a stretch of Newton ended at an element that needs
    a fresh matrix), against 106 with the small system's policy (2.3-2.7x the run time per step
    on 1000 orbits, ``benchmarks/bench_adaptive.py`` part c); largest energy error 4.0e-7 (4.1e-7
    each way before the cap: the same roots). Bounds: 25 matrices (a quarter of the old count),
    the energy error 1e-6."""
    He, q0, p0, T5, _ = orbits_from_apocentre(0.9, orbits=5)
    sol, matrices = matrices_of(monkeypatch, lambda: gj.integrate(
        He, q0, p0, method=CG4, h=0.8, t1=T5, controller=gj.TimeTransform(), dense=True, error_estimate=False))
    assert int(sol.status) == 0 and int(sol.stats["num_accepted_steps"]) == 127
    assert matrices <= 25
    energy = jax.vmap(He)(*sol.dense.view(sol.dense.z[:128])) - He(q0, p0)
    assert float(jnp.max(jnp.abs(energy))) < 1e-6


def test_events_lie_on_the_section_plane():
    """Henon-Heiles, section q1 = 0 upward: every event state has |q1| < 1e-10 (Newton on the
    element polynomial to round-off), and the events' times match a fine reference run."""
    hh = lambda q, p: 0.5 * (p @ p + q @ q) + q[0] ** 2 * q[1] - q[1] ** 3 / 3
    q0, p0 = jnp.array([0.0, 0.1]), jnp.array([0.35, 0.0])
    event = gj.Event(lambda t, q, p: q[0], direction=1, capacity=32)
    sol = gj.integrate(hh, q0, p0, method=CG4, h=0.1, t1=100.0, controller=pid(1e-10), events=event)
    n = int(sol.events.count)
    assert int(sol.status) == 0 and 10 < n <= 32
    assert np.max(np.abs(sol.events.q[:n, 0])) < 1e-10
    assert np.all(sol.events.p[:n, 0] > 0)  # upward
    assert np.all(np.isnan(sol.events.t[n:]))
    fine = gj.integrate(hh, q0, p0, method=CG4, h=0.01, t1=100.0, events=event)
    np.testing.assert_allclose(sol.events.t[:n], fine.events.t[:n], rtol=0, atol=1e-7)


def test_a_terminal_event_ends_the_run_there():
    event = gj.Event(lambda t, q, p: q[1], direction=-1, terminal=True)  # y crosses 0 downward: apocentre
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=T, controller=pid(1e-10), events=event, dense=True)
    assert int(sol.status) == 0 and int(sol.events.count) == 1
    assert abs(float(sol.events.t[0]) - np.pi) < 1e-9 and abs(float(sol.t[-1]) - np.pi) < 1e-9
    assert abs(float(sol.q[-1, 0]) + 1.5) < 1e-9
    assert np.all(np.isnan(sol.evaluate(jnp.array([4.0]))[0]))


def test_dense_output_of_a_controlled_run_and_outside_the_span():
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=T, controller=pid(1e-10), dense=True)
    n = int(sol.stats["num_accepted_steps"])
    nodes = sol.dense.t[: n + 1]
    assert float(nodes[0]) == 0.0 and float(nodes[-1]) == T and np.all(np.isinf(sol.dense.t[n + 1 :]))
    t = jnp.asarray([0.3, 2.0, 5.5])
    q, p = sol.evaluate(t)
    exact = np.stack([helpers.kepler_exact(float(s))[0] for s in t])
    assert np.max(np.abs(q - exact)) < 1e-6  # degree-4 polynomial between nodes
    with pytest.raises(ValueError, match=r"\[t0, t1\]"):
        sol.evaluate(T + 0.1)
    inside_jit = jax.jit(lambda s, t: s.evaluate(t)[0])(sol, jnp.asarray([-0.1, 1.0, T + 0.1]))
    assert np.isnan(inside_jit[0]).all() and np.isnan(inside_jit[2]).all() and np.isfinite(inside_jit[1]).all()


def test_dense_output_after_a_failure_is_nan():
    """A fixed run whose fifth element fails (a cap of 2 iterations at h omega ~ 1 fails at
    the first hard element): every time from the failing element on gives NaN."""
    hq, _, q0, p0 = helpers.quartic()
    sol = gj.integrate(hq, q0, p0, method=CG3, h=0.01, n_steps=40, dense=True, max_newton_iterations=4)
    assert int(sol.status) != 0
    good = int(sol.stats["num_accepted_steps"])
    assert good < 40
    t_fail = good * 0.01
    q, _ = sol.evaluate(jnp.asarray([0.5 * t_fail, t_fail + 0.005, 0.39]))
    assert np.isfinite(q[0]).all() and np.isnan(q[1:]).all()


def test_statuses_of_a_controlled_run():
    """A run stopped by max_steps or dtmin keeps the time and state where it stopped (as
    diffrax does); the state is the one a run to that time gives."""
    # 20 orbits at 1e-10 take ~5000 steps (251 an orbit), more than the default cap of 4096
    # attempts; the first two runs are the program of test_error_falls_with_the_tolerance
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=20 * T, controller=pid(1e-10))
    assert int(sol.status) == gj.Status.MAX_STEPS and int(sol.stats["num_steps"]) == 4096
    t_stop = float(sol.t[-1])
    assert 10 * T < t_stop < 20 * T and np.isfinite(sol.q[-1]).all()
    np.testing.assert_allclose(sol.q[-1], helpers.kepler_exact(t_stop)[0], atol=1e-7)
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=T, controller=pid(1e-10, dtmin=0.05))
    assert int(sol.status) == gj.Status.DTMIN and np.isfinite(sol.q[-1]).all() and float(sol.t[-1]) < T
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=T, controller=gj.TimeTransform(s=lambda q, p: -1.0 + 0 * q[0]))
    assert int(sol.status) == gj.Status.TIME_TRANSFORM  # s < 0: time would run backwards
    # the default s no longer fails at an equilibrium (s = 1 there): tests/test_step_density.py
    for status in (gj.Status.MAX_STEPS, gj.Status.DTMIN, gj.Status.TIME_TRANSFORM):
        assert len(gj.status_message(status)) > 40


@pytest.mark.parametrize("controller", [pid(1e-11), gj.TimeTransform()], ids=["pid", "time-transform"])
def test_derivatives_through_a_controlled_run(controller):
    """Reverse and forward mode through a controller's run (the steps constants of the
    trajectory, the elements differentiated by the implicit function theorem) agree to round-off
    and equal a central difference of the exact flow to the runs' accuracy; the time-transformed
    run's states are differentiated at fixed t (without that correction: -11.9 against -13.7)."""
    ts = jnp.array([0.0, 1.0, 3.3, T])

    def loss(x):
        sol = gj.integrate(H, Q0.at[0].set(x), P0, method=CG4, h=0.05, t1=T, controller=controller, save_at=ts)
        return jnp.sum(sol.q[-1] ** 2) + sol.p[2, 1]

    # the value, the forward-mode tangent and the reverse-mode gradient from one compiled
    # program, which the difference quotient's values come from too
    x0 = Q0[0]
    derivatives = helpers.first_derivatives(loss, (jnp.ones_like(x0),), jnp.ones_like(x0))
    _, tangent, (grad,) = derivatives((x0,))
    eps = 1e-5
    fd = (derivatives((x0 + eps,))[0] - derivatives((x0 - eps,))[0]) / (2 * eps)
    assert abs(float(grad - tangent)) < 1e-12 * abs(float(grad))
    # the difference quotient's runs take other steps: it errs by ~tol / eps of its size
    # (measured 2.4e-6 relative for both controllers)
    assert abs(float(grad - fd)) < 1e-5 * abs(float(fd))


def rebuilt_pid(**fields):
    """``pid(1e-6)`` with ``fields`` replaced as JAX rebuilds a node (``tree_unflatten``), past
    the check at construction: ``integrate`` checks the values again."""
    controller = pid(1e-6)
    names = [f.name for f in dataclasses.fields(controller) if not f.metadata.get("static")]
    return jax.tree.unflatten(jax.tree.structure(controller), [fields.get(n, getattr(controller, n)) for n in names])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n_steps=10, t1=1.0), "exactly one"),
        (dict(), "exactly one"),
        (dict(n_steps=10, controller=gj.PIDController(1e-6, 1e-6)), "not n_steps"),
        (dict(t1=1.0, controller=rebuilt_pid(rtol=0.0)), r"controller.rtol must be > 0, got 0.0\."),
        (dict(t1=1.0, controller=rebuilt_pid(atol=-1.0)), r"controller.atol must be > 0, got -1.0\."),
        (dict(t1=1.0, save_at=[0.5, 0.2]), "sorted"),
        (dict(t1=1.0, save_at=[0.5, 1.5]), r"\[t0, t1\]"),
        (dict(t1=1.0, events=gj.Event(lambda t, q, p: q)), "scalar"),
        (dict(t1=1.0, save_every=2), "save_at"),
    ],
)
def test_bad_time_span_input_raises_before_compilation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gj.integrate(H, Q0, P0, method=CG3, h=0.1, **kwargs)


@pytest.mark.parametrize("scene", ["kepler", "chain"])
def test_the_embedded_estimate_against_the_full_one(scene):
    """The controller's embedded estimate (the end-point defect, order k + 1) lies above the full a
    posteriori estimate (order 2k + 1) on every element, their ratio growing like h^(-k)
    (measured on Kepler cG(2): 201, 795, 3361 at h = 0.1, 0.05, 0.025); and the default
    ``error_estimate``, the full estimate on the elements where the embedded one peaks, equals
    the full estimate's maximum over every element (measured: 0.976 to 1.0 of it)."""
    from galerkin_jax import scenes
    from galerkin_jax._controllers import embedded_error
    from galerkin_jax._defect import local_error

    if scene == "kepler":
        Hs, q0, p0, hs = H, Q0, P0, (0.1, 0.05)
    else:
        chain = scenes.get("fput", n=8)
        Hs, q0, p0, hs = chain.H, chain.q0, chain.p0, (0.2, 0.1)
    method = gj.CG(2, gj.gauss_legendre(2))
    ratios = []

    @jax.jit
    def estimates(z, h):  # on each element of the run, re-solved from its node
        def one(z0, z1):
            W = helpers.cg_element(2, Hs, z0, h)[1]
            q, p = jnp.split(z0, 2)
            return jnp.max(jnp.abs(embedded_error(Hs, q, p, W, h, z1 - z0))), local_error(Hs, q, p, W, z1 - z0, h)

        return jax.vmap(one)(z[:-1], z[1:])

    for h in hs:
        sol = gj.integrate(Hs, q0, p0, method=method, h=h, n_steps=60, dense=True)
        every = gj.integrate(Hs, q0, p0, method=method, h=h, n_steps=60, error_estimate="full")
        assert 0.9 * float(every.error_estimate) <= float(sol.error_estimate) <= float(every.error_estimate)
        embedded, full = estimates(sol.dense.z, h)
        assert np.all(embedded >= full)
        ratios.append(float(embedded.max() / full.max()))
    assert 2 ** 1.5 < ratios[1] / ratios[0] < 2 ** 2.5  # h^(-k), k = 2: a factor 4 per halving


def test_the_loop_carries_only_the_parts_a_run_asks_for():
    """The loop's carry (``_adaptive.Carry``) is made of named parts, each None where the run
    does not ask for it: a PID run with no outputs carries no saves, dense output, events,
    checkpoints, diagnostics or peak elements (``estimate=False``), and its leaves are the node,
    the rule's state, the status, the counts and the record (measured: 27 leaves for CG(3), the
    record's largest relative error among them); save times, two events and dense output add
    their buffers of the asked sizes (measured: 46 leaves). Traced by ``jax.eval_shape``: nothing compiles."""
    from galerkin_jax import _adaptive
    from galerkin_jax._march import solver_options

    options = solver_options(CG3)
    ts = jnp.linspace(0.5, 2.0, 4)
    events = (gj.Event(lambda t, q, p: q[1], capacity=5), gj.Event(lambda t, q, p: q[0], capacity=3))

    def carry(**outputs):
        return jax.eval_shape(lambda: _adaptive.run(CG3, H, Q0, P0, 0.0, 2.0, 0.01, None, pid(1e-8), options=options,
                                                    max_steps=64, **outputs))

    plain = carry()
    assert all(part is None for part in (plain.saves, plain.dense, plain.events, plain.checkpoints, plain.acc,
                                         plain.record.peak, plain.node.memo))
    assert set(plain.control.memory) == {"err1", "err2"} and plain.counts.steps.dtype == jnp.int32
    assert len(jax.tree.leaves(plain)) == 27
    full = carry(ts=ts, events=events, dense=True)
    assert full.saves.states.shape == (4, 4) and full.saves.elements.shape == (4,)
    assert [z.shape for z in full.events.z] == [(5, 4), (3, 4)] and full.events.count.shape == (2,)
    assert full.dense.node_z.shape == (65, 4) and full.dense.W.shape[:1] == (64,)
    assert len(jax.tree.leaves(full)) == 46


@pytest.mark.parametrize("rule, ratio", [(gj.trapezoid(), 10.9), (gj.midpoint(), 27.0)])
def test_a_controller_drives_galerkin_vi_of_degree_one(rule, ratio):
    """GalerkinVI(1, rule) (Stormer-Verlet in closed form with the trapezoid, iterated with the
    midpoint rule) under a PIDController on Kepler (e = 0.5) to t = 10: its embedded estimate,
    the defect of the polynomial whose momentum runs from p0 to p1, is O(h^2), so h falls like
    tol^(1/2) (10x the steps for 1/100 of the tolerance, 1782 and 17781 measured) and the error at
    t = 10 like tol (10.9 tol with the trapezoid, 27.0 tol with the midpoint rule, at both). Its
    momentum's constant polynomial had the defect -h F_p(z1), of order one: h fell with the
    tolerance (3.9e-7 at 1e-6) and the run ended MAX_STEPS near t = 0.1."""
    H, q0, p0 = helpers.kepler()
    qe, pe = helpers.kepler_exact(10.0)
    steps, errors = [], []
    for tol in (1e-5, 1e-7):
        sol = gj.integrate(H, q0, p0, method=gj.GalerkinVI(1, rule), t1=10.0,
                           controller=gj.PIDController(rtol=tol, atol=tol), max_steps=40000)
        assert int(sol.status) == 0 and float(sol.t[-1]) == 10.0
        steps.append(int(sol.stats["num_accepted_steps"]))
        errors.append(max(np.abs(sol.q[-1] - qe).max(), np.abs(sol.p[-1] - pe).max()) / tol)
        assert float(sol.error_estimate) < 0.05 * tol  # the true local error is O(h^3)
    assert 9 < steps[1] / steps[0] < 11, steps
    np.testing.assert_allclose(errors, ratio, rtol=0.2)
