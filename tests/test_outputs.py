"""What a run gives back: save times, node states, events, the stop of a run short of t1, runs
backwards, the first step a controller picks, and diffrax's counts and bounds."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers
from galerkin_jax import _output

H, Q0, P0 = helpers.kepler(0.9)
CG4 = gj.CG(4, gj.gauss_legendre(4))
TWO_PI = 2 * np.pi


def test_fixed_steps_with_save_at_reach_t1_for_every_count_of_steps():
    """h = 2 pi / n to t1 = 2 pi with save_at, n = 1 .. 1000 (one vmapped program): every run
    takes exactly n elements and ends with status 0. Adding up the steps used to leave t a
    sliver short of t1 after n of them, so that the run reserved for n failed with MAX_STEPS
    (n = 100, 399, 400 among others)."""
    n = jnp.arange(1, 1001)
    oscillator = lambda q, p: 0.5 * (q @ q + p @ p)
    run = lambda h: gj.integrate(oscillator, Q0, P0, method=gj.CG(1, gj.midpoint()), h=h, t1=TWO_PI, max_steps=1000,
                                 save_at=jnp.array([np.pi, TWO_PI]), error_estimate=False)
    sol = jax.vmap(run)(TWO_PI / n)
    assert np.all(np.asarray(sol.status) == 0)
    np.testing.assert_array_equal(sol.stats["num_accepted_steps"], n)


def test_every_crossing_inside_an_element_is_found_in_order():
    """g = sin(10 t) on Kepler e = 0.9, cG(8), PID 1e-8 over two orbits: 40 crossings, of which
    the elements near apocentre hold two or three each. Every one is found, at k pi / 10 to
    round-off (19 of the 40 when only the elements' ends were compared)."""
    event = gj.Event(lambda t, q, p: jnp.sin(10.0 * t), capacity=64)
    sol = gj.integrate(H, Q0, P0, method=gj.CG(8, gj.gauss_legendre(8)), h=0.1, t1=2 * TWO_PI - 0.05,
                       controller=gj.PIDController(1e-8, 1e-8), events=event, save_at="steps")
    count = int(sol.events.count)
    assert count == 39
    np.testing.assert_allclose(sol.events.t[:count], np.arange(1, count + 1) * np.pi / 10, rtol=0, atol=1e-13)
    assert np.isnan(sol.events.t[count:]).all()
    nodes = np.asarray(sol.t[: int(sol.stats["num_accepted_steps"]) + 1])
    per_element = np.diff(np.floor(nodes * 10 / np.pi))
    assert per_element.max() >= 2  # elements near apocentre hold two or three crossings


def test_a_list_of_events_each_with_its_direction_capacity_and_which_one_ended_the_run():
    """Three events: pericentre passages (q_y up through 0, not terminal, capacity 2), the
    crossings of x = 0 (any direction) and a terminal one at q_y = -0.3 going down, which ends
    the run at its time; the others stop counting there."""
    events = [gj.Event(lambda t, q, p: q[1], direction=1, capacity=2),
              gj.Event(lambda t, q, p: q[0], capacity=8),
              gj.Event(lambda t, q, p: q[1] + 0.3, direction=-1, terminal=True)]
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=3 * TWO_PI, controller=gj.PIDController(1e-10, 1e-10),
                       events=events)
    pericentre, axis, stop = sol.events
    assert [bool(e.ended) for e in sol.events] == [False, False, True]
    assert int(stop.count) == 1 and float(sol.t[-1]) == float(stop.t[0])
    np.testing.assert_allclose(sol.q[-1, 1], -0.3, atol=1e-13)
    # before the stop (on the way back to the first pericentre, still at x < 0) x = 0 is crossed
    # once, just after the start; the pericentre (t = 0, the start) not at all
    assert int(axis.count) == 1 and int(pericentre.count) == 0
    assert float(axis.t[0]) < float(stop.t[0])


def test_locate_keeps_a_root_it_has_reached():
    """A Newton step that lands on the root must stay there: with an open bracket the iteration
    bisected away from it for the rest of its iterations, and returned alphas off by ~1e-7."""
    f = lambda a: a - 0.3
    alpha = _output.locate(f, jnp.zeros(()), jnp.ones(()), f(jnp.zeros(())), iterations=24)
    assert float(alpha) == 0.3


def test_a_run_stopped_short_keeps_its_state_and_its_later_save_times_are_nan():
    pid = gj.PIDController(1e-10, 1e-10)
    ts = jnp.linspace(0.0, TWO_PI, 5)
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.01, t1=TWO_PI, controller=pid, max_steps=60, save_at=ts)
    assert int(sol.status) == gj.Status.MAX_STEPS
    assert np.isfinite(sol.q[0]).all() and np.isnan(sol.q[-1]).all()
    end = gj.integrate(H, Q0, P0, method=CG4, h=0.01, t1=TWO_PI, controller=pid, max_steps=60)
    assert int(end.status) == gj.Status.MAX_STEPS and 0.0 < float(end.t[-1]) < TWO_PI
    reference = gj.integrate(H, Q0, P0, method=CG4, h=0.01, t1=float(end.t[-1]), controller=pid)
    np.testing.assert_allclose(end.q[-1], reference.q[-1], atol=1e-9)


def test_diffrax_counts_and_the_step_bounds():
    """``num_steps`` counts every attempt, ``num_accepted_steps`` and ``num_rejected_steps`` the
    two kinds; dtmin and dtmax bound every step the controller proposes (the last, which lands
    on t1, may be shorter), and a step rejected at dtmin ends the run there (DTMIN)."""
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=TWO_PI, controller=gj.PIDController(1e-8, 1e-8))
    stats = {k: int(v) for k, v in sol.stats.items() if "steps" in k}
    assert stats["num_steps"] == stats["num_accepted_steps"] + stats["num_rejected_steps"]
    assert stats["num_rejected_steps"] > 0
    bounded = gj.PIDController(1e-8, 1e-8, dtmin=0.0005, dtmax=0.05)
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=TWO_PI, controller=bounded, save_at="steps")
    n = int(sol.stats["num_accepted_steps"])
    steps = np.diff(np.asarray(sol.t[: n + 1]))
    assert int(sol.status) == 0 and steps[:-1].min() >= 0.0005 and steps.max() <= 0.05 + 1e-15
    sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=TWO_PI, controller=gj.PIDController(1e-8, 1e-8, dtmin=0.05))
    assert int(sol.status) == gj.Status.DTMIN and np.isfinite(sol.q[-1]).all()


def counts(sol):
    """The step counts of ``sol.stats``, as ints."""
    return {k: int(sol.stats[k]) for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")}


def test_every_attempt_is_accepted_or_rejected():
    """num_steps = num_accepted_steps + num_rejected_steps in every controlled run: one ended by
    dtmin (its last attempt, rejected at dtmin, used to count in num_steps alone: 2, 0, 1) and
    a time-transformed one (its tries at the last element, shortened to land on t1, are the
    rejected attempts)."""
    floor = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=TWO_PI, controller=gj.PIDController(1e-10, 1e-10, dtmin=0.05))
    assert int(floor.status) == gj.Status.DTMIN
    assert counts(floor) == dict(num_steps=2, num_accepted_steps=0, num_rejected_steps=2)
    landed = gj.integrate(H, Q0, P0, method=CG4, h=0.05, t1=TWO_PI, controller=gj.TimeTransform())
    n = counts(landed)
    assert int(landed.status) == 0 and n["num_rejected_steps"] >= 1
    assert n["num_steps"] == n["num_accepted_steps"] + n["num_rejected_steps"]


def test_force_dtmin_accepts_the_steps_at_dtmin_and_goes_on():
    """``PIDController(force_dtmin=True)`` (diffrax's rule): a step of h = dtmin whose error
    exceeds the tolerance is accepted, so a run that ends with DTMIN by default (Kepler e = 0.5,
    tolerance 1e-12, dtmin 0.05: at its first step) reaches t1 with status 0, every step but the
    last (shortened to land on t1) at dtmin, each counted in num_accepted_steps."""
    H5, q0, p0 = helpers.kepler(0.5)
    run = lambda force: gj.integrate(H5, q0, p0, method=CG4, h=0.1, t1=TWO_PI, save_at="steps",
                                     controller=gj.PIDController(1e-12, 1e-12, dtmin=0.05, force_dtmin=force))
    strict, forced = run(False), run(True)
    assert int(strict.status) == gj.Status.DTMIN
    assert counts(strict) == dict(num_steps=2, num_accepted_steps=0, num_rejected_steps=2)
    n = counts(forced)
    assert int(forced.status) == 0 and float(forced.t[n["num_accepted_steps"]]) == TWO_PI
    assert n["num_steps"] == n["num_accepted_steps"] + n["num_rejected_steps"]
    steps = np.diff(np.asarray(forced.t[: n["num_accepted_steps"] + 1]))
    assert n["num_accepted_steps"] == math.ceil(TWO_PI / 0.05) == steps.size
    np.testing.assert_allclose(steps[:-1], 0.05, rtol=1e-12)
    with pytest.raises(TypeError, match=r"PIDController: force_dtmin must be a bool, got 1\.$"):
        gj.PIDController(1e-6, 1e-6, force_dtmin=1)


def test_save_at_steps_gives_every_node_in_the_users_shapes():
    """``save_at="steps"``: the accepted nodes (the dense output's), t = inf and NaN states past
    them; a time-transformed run's in the user's (q, p), without its clock and p_t; fixed steps
    the same as saving every element."""
    for controller in (gj.PIDController(1e-8, 1e-8), gj.TimeTransform()):
        sol = gj.integrate(H, Q0, P0, method=CG4, h=0.02, t1=TWO_PI, controller=controller, save_at="steps")
        dense = gj.integrate(H, Q0, P0, method=CG4, h=0.02, t1=TWO_PI, controller=controller, dense=True)
        n = int(sol.stats["num_accepted_steps"])
        assert sol.q.shape == (sol.t.shape[0], 2) and float(sol.t[n]) == TWO_PI and np.isinf(sol.t[n + 1:]).all()
        np.testing.assert_array_equal(sol.t[: n + 1], dense.dense.t[: n + 1])
        np.testing.assert_array_equal(sol.q[: n + 1], dense.dense.view(dense.dense.z[: n + 1])[0])
    fixed = gj.integrate(H, Q0, P0, method=CG4, h=0.05, n_steps=20, save_at="steps")
    np.testing.assert_array_equal(fixed.q, gj.integrate(H, Q0, P0, method=CG4, h=0.05, n_steps=20).q)
    with pytest.raises(ValueError, match="steps"):
        gj.integrate(H, Q0, P0, method=CG4, h=0.05, t1=1.0, save_at="step")
    with pytest.raises(ValueError, match="not both"):
        gj.integrate(H, Q0, P0, method=CG4, h=0.05, t1=1.0, save_at=["steps", 0.5])


@pytest.mark.parametrize("kind", ["fixed", "pid", "time-transform", "fixed, events"])
def test_a_run_backwards_in_time_returns_to_the_start(kind):
    """t1 < t0 integrates backwards (Hamilton's flow is reversible: -H forwards in -t): half an
    orbit out and back again ends at the initial state to the runs' accuracy, with decreasing
    times, and its dense output, saves and events in the user's time."""
    kwargs = {"fixed": dict(h=0.005), "pid": dict(h=0.01, controller=gj.PIDController(1e-12, 1e-12)),
              "time-transform": dict(h=0.02, controller=gj.TimeTransform()),
              "fixed, events": dict(h=0.005, events=gj.Event(lambda t, q, p: q[1] - 0.3, capacity=4))}[kind]
    out = gj.integrate(H, Q0, P0, method=gj.CG(6, gj.gauss_legendre(6)), t1=np.pi, **kwargs)
    back = gj.integrate(H, out.q[-1], out.p[-1], method=gj.CG(6, gj.gauss_legendre(6)), t0=np.pi, t1=0.0,
                        save_at=jnp.array([np.pi, 1.0, 0.0]), **kwargs)
    assert int(back.status) == 0
    np.testing.assert_array_equal(back.t, [np.pi, 1.0, 0.0])
    np.testing.assert_allclose(back.q[-1], Q0, atol=1e-9)
    np.testing.assert_allclose(back.q[1], helpers.kepler_exact(1.0, 0.9)[0], atol=1e-8)
    if kind == "fixed, events":  # y = 0.3 twice on the way back, where the way out crossed it
        assert int(back.events.count) == int(out.events.count) == 2
        np.testing.assert_allclose(back.events.t[:2], out.events.t[1::-1], atol=1e-9)


def test_a_run_backwards_saves_every_node():
    """save_at="steps" backwards: the accepted nodes in the user's time, decreasing from t0 to
    t1, the last the run's end state; save_every with it raises as it does forwards."""
    pid = dict(h=0.01, controller=gj.PIDController(1e-10, 1e-10), max_steps=400)
    sol = gj.integrate(H, Q0, P0, method=CG4, t1=-1.0, save_at="steps", **pid)
    end = gj.integrate(H, Q0, P0, method=CG4, t1=-1.0, **pid)
    n = int(sol.stats["num_accepted_steps"])
    assert int(sol.status) == 0 and float(sol.t[0]) == 0.0 and float(sol.t[n]) == -1.0
    assert np.all(np.diff(np.asarray(sol.t[: n + 1])) < 0)
    np.testing.assert_array_equal(sol.q[n], end.q[-1])
    with pytest.raises(ValueError, match="save_every"):
        gj.integrate(H, Q0, P0, method=CG4, t1=-1.0, save_at="steps", save_every=2, **pid)


def test_a_run_backwards_takes_its_save_times_in_its_direction():
    """In a run backwards (t1 < t0) save_at runs from t0 down to t1: increasing times raise a
    ValueError that names the direction (it said "must be sorted (non-decreasing)", of the
    negated times), times outside [t1, t0] one in the user's time; decreasing ones are saved."""
    pid = dict(h=0.01, controller=gj.PIDController(1e-10, 1e-10))
    with pytest.raises(ValueError) as caught:
        gj.integrate(H, Q0, P0, method=CG4, t1=-1.0, save_at=[-1.0, -0.5, 0.0], **pid)
    assert str(caught.value) == ("save_at must be sorted in the run's direction: non-increasing in a run backwards "
                                 "(t1 < t0), got -1.0 before -0.5.")
    with pytest.raises(ValueError) as caught:
        gj.integrate(H, Q0, P0, method=CG4, t1=-1.0, save_at=[0.0, -1.5], **pid)
    assert str(caught.value) == "save_at must lie in [t1, t0] = [-1.0, 0.0], got [-1.5, 0.0]."
    with pytest.raises(ValueError, match=r"non-decreasing in a run forwards \(t1 > t0\), got 0.5 before 0.2\.$"):
        gj.integrate(H, Q0, P0, method=CG4, t1=1.0, save_at=[0.5, 0.2], **pid)
    sol = gj.integrate(H, Q0, P0, method=CG4, t1=-1.0, save_at=jnp.array([0.0, -0.5, -1.0]), **pid)
    assert int(sol.status) == 0
    np.testing.assert_array_equal(sol.t, [0.0, -0.5, -1.0])
    for t, q in zip((-0.5, -1.0), sol.q[1:]):
        np.testing.assert_allclose(q, helpers.kepler_exact(t, 0.9)[0], atol=1e-8)


def test_h_none_needs_a_pid_controller():
    """h=None picks a PIDController's first step (``test_a_controller_picks_hairer_norsett_wanners_first_step``);
    fixed steps need h."""
    with pytest.raises(ValueError, match="h=None"):
        gj.integrate(H, Q0, P0, method=CG4, t1=1.0)


def test_save_times_have_the_nodes_accuracy():
    """Between the nodes a run reads its element polynomial refined to the nodes' accuracy
    (``_output.refined``). Kepler e = 0.9, cG(6) + Gauss 6, PID 1e-8 over one orbit: the largest
    error at 200 save times against the exact orbit is 0.73x the nodes' (measured: 5.0e-14 and
    6.8e-14; the element polynomial alone gave 5.8e-10 against 9.1e-14). Bound: 10x."""
    method, pid = gj.CG(6, gj.gauss_legendre(6)), gj.PIDController(1e-8, 1e-8)
    ts = jnp.linspace(0.01, TWO_PI - 0.01, 200)
    saved = gj.integrate(H, Q0, P0, method=method, h=0.01, t1=TWO_PI, controller=pid, save_at=ts)
    nodes = gj.integrate(H, Q0, P0, method=method, h=0.01, t1=TWO_PI, controller=pid, save_at="steps")
    n = int(nodes.stats["num_accepted_steps"])
    exact = lambda ts: np.stack([helpers.kepler_exact(float(t), 0.9)[0] for t in ts])
    between = np.max(np.abs(np.asarray(saved.q) - exact(ts)))
    at_nodes = np.max(np.abs(np.asarray(nodes.q[1: n + 1]) - exact(nodes.t[1: n + 1])))
    assert between < 10 * at_nodes


def test_a_time_transformed_runs_save_times_keep_its_energy():
    """Kepler e = 0.99 from apocentre over 10 orbits, TimeTransform (s = r^1.5), cG(4) + Gauss 4,
    h = 0.4 in tau (287 steps): the largest energy error at 2000 save times is 0.57x the nodes'
    (measured: 2.0e-8 and 3.5e-8; the element polynomial alone: 5e2-5e3x, docs/accuracy.md).
    Bound: 10x."""
    He, q0, p0 = helpers.kepler(0.99)
    q0, p0 = -q0 * (1 + 0.99) / (1 - 0.99), -p0 * (1 - 0.99) / (1 + 0.99)  # apocentre
    T = 10 * TWO_PI
    run = lambda save_at: gj.integrate(He, q0, p0, method=CG4, h=0.4, t1=T, save_at=save_at, max_steps=20_000,
                                       controller=gj.TimeTransform(s=lambda q, p: (q @ q) ** 0.75))
    saved, nodes = run(jnp.linspace(0.0, T, 2000)), run("steps")
    n = int(nodes.stats["num_accepted_steps"])
    energy = lambda sol, rows: np.max(np.abs(np.asarray(jax.vmap(He)(sol.q[rows], sol.p[rows])) - float(He(q0, p0))))
    assert int(saved.status) == 0 and energy(saved, slice(None)) < 10 * energy(nodes, slice(0, n + 1))


@pytest.mark.parametrize("terminal", [False, True])
def test_a_member_that_finishes_first_keeps_every_output_of_its_single_run(terminal):
    """Under ``vmap`` the loop goes on while any member does, and a finished member's body leaves
    its outputs as they are (``_adaptive._any_member``: no select of the carried buffers guards
    them). Two members, PID 1e-5 and 1e-10 over one orbit of Kepler e = 0.9, with save times, a
    crossing event and dense output (the terminal variant: the loose member ends at its first
    crossing, long before the other): every output of each member, its save times, events,
    nodes, evaluations, counts, status and estimate, equals its single run. Measured: equal to
    the last bit; asserted to 1e-13 (the batched root finder may stop an update apart)."""
    event = gj.Event(lambda t, q, p: q[1] - 0.3, direction=-1 if terminal else 0, terminal=terminal, capacity=4)
    ts = jnp.linspace(0.3, TWO_PI - 0.3, 7)

    def run(tol):
        sol = gj.integrate(H, Q0, P0, method=CG4, h=0.1, t1=TWO_PI, controller=gj.PIDController(tol, tol),
                           save_at=ts, events=event, dense=True)
        return sol, sol.evaluate(jnp.linspace(0.1, 2.0, 5))

    tols = jnp.array([1e-5, 1e-10])
    batch = jax.vmap(run)(tols)
    for b, tol in enumerate(tols):
        single = run(float(tol))
        leaves, single_leaves = jax.tree_util.tree_leaves_with_path(batch), jax.tree.leaves(single)
        assert len(leaves) == len(single_leaves) > 20
        for (path, x), y in zip(leaves, single_leaves):
            if "batch_newton_iterations" not in jax.tree_util.keystr(path):  # the batch's, by definition
                np.testing.assert_allclose(np.asarray(x)[b], np.asarray(y), rtol=0, atol=1e-13)
    steps = np.asarray(batch[0].stats["num_accepted_steps"])
    assert steps.tolist() == ([25, 216] if terminal else [51, 474])
