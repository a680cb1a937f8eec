"""Derivatives of every output of every run kind against central differences of the whole run.

Outputs: the states at ``save_at`` times and at the end, ``Solution.evaluate(t)``, event times
and states, a terminal event's final state and time. Inputs: q0, p0, args, h (fixed steps), t0,
t1, the save times and the rule's points and weights. Each check draws a random direction over
all the inputs at once and compares the forward-mode product J t and the reverse-mode product
<J^T c, t> with the central difference along t (``helpers.check_first_derivatives``: one
compiled program). The steps of a controlled run are constants of the trajectory (as in
diffrax), so its derivative leaves out how the controller's steps move with the inputs;
central differences of the whole run include that, at the size of the tolerance, which is why
the tolerances below are tight and the rule's points and weights (whose effect on the states is
the discretisation error itself) are left out of the PID run's direction.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

E = 0.5
Q0 = jnp.array([1.0 - E, 0.0])
P0 = jnp.array([0.0, np.sqrt((1.0 + E) / (1.0 - E))])
T1 = 5.0
SAVE = jnp.array([0.6, 1.7, 3.3, 4.4])
GAUSS = gj.gauss_legendre(4)


def H(q, p, args):
    return 0.5 * (p @ p) - args["gm"] / jnp.sqrt(q @ q) + args["j2"] / (q @ q) ** 1.5


def pack(q0, p0, gm, j2, t0, t1, ts, h, points, weights):
    return jnp.concatenate([q0, p0, jnp.array([gm, j2, t0, t1]), ts, jnp.array([h]), points, weights])


def unpack(x):
    sizes = [2, 2, 1, 1, 1, 1, SAVE.size, 1, 4, 4]
    q0, p0, gm, j2, t0, t1, ts, h, points, weights = jnp.split(x, np.cumsum(sizes)[:-1])
    return q0, p0, dict(gm=gm[0], j2=j2[0]), t0[0], t1[0], ts, h[0], gj.QuadratureRule(points, weights)


X0 = pack(Q0, P0, 1.0, 1e-3, 0.1, T1, SAVE, 0.047, GAUSS.points, GAUSS.weights)  # 104.3 elements of h


def outputs(controller, event, x, frozen=(), **kwargs):
    """Every output of one run, flattened; ``frozen``: inputs held at X0 (not differentiated)."""
    x = jnp.where(jnp.isin(jnp.arange(X0.size), jnp.asarray(frozen, int)), X0, x)
    q0, p0, args, t0, t1, ts, h, rule = unpack(x)
    h = unpack(X0)[6] if H_INDEX in frozen else h  # a controller's h is no input to differentiate (it raises)
    sol = gj.integrate(H, q0, p0, method=gj.CG(4, rule), h=h, t0=t0, t1=t1, args=args, controller=controller,
                       save_at=ts, events=event, dense=True, **kwargs)
    q, p = sol.evaluate(jnp.array([1.2, 2.9]))
    found = jnp.arange(event.capacity) < 3  # the first three events (the run has five)
    return jnp.concatenate([sol.q.ravel(), sol.p.ravel(), q.ravel(), p.ravel(),
                            jnp.where(found, sol.events.t, 0.0),
                            jnp.where(found[:, None], jnp.concatenate([sol.events.q, sol.events.p], 1), 0.0).ravel()])


# indices of the inputs in X0
RULE = list(range(X0.size - 8, X0.size))
H_INDEX = X0.size - 9
SECTION = gj.Event(lambda t, q, p: jnp.sin(3.0 * t) - 0.5 * q[0], capacity=8)


@pytest.mark.parametrize("kind", ["fixed", "pid", "time-transform"])
def test_every_output_of_a_run_against_central_differences(kind):
    """The measured agreement (``helpers.first_derivative_errors``: forward, max |J t - D|
    relative to max |D|; reverse, |<J^T c, t> - <c, D>| relative to sum |c D|): fixed steps
    1.0e-9 and 1.2e-10, PID 5.5e-10 and 8.8e-11, the time-transformed run 1.4e-10 and 1.6e-11
    (central differences of step 2e-7: the runs' round-off over the step; a controlled run's
    steps, which move with the inputs, add their effect at the tolerance, 1e-13). Bounds about
    20x each; the former atol 1e-7 and rtol 2e-6 were 500x to 5000x the agreement. Reverse
    mode takes the PID run's 635 elements in 10 stretches solved again from checkpoints
    (``checkpoint=True``: sqrt(max_steps) = 64 each), the time-transformed run's 50 from the
    roots the forward run kept."""
    controller = {"fixed": None, "pid": gj.PIDController(1e-13, 1e-13), "time-transform": gj.TimeTransform()}[kind]
    frozen = {"fixed": [], "pid": RULE + [H_INDEX], "time-transform": [H_INDEX]}[kind]
    kwargs = dict(checkpoint=True) if kind == "pid" else {}
    forward, reverse = {"fixed": (2e-8, 3e-9), "pid": (1e-8, 2e-9), "time-transform": (3e-9, 3e-10)}[kind]
    helpers.check_first_derivatives_within(lambda x: outputs(controller, SECTION, x, frozen, **kwargs), (X0,),
                                           eps=2e-7, forward=forward, reverse=reverse)


TERMINAL = gj.Event(lambda t, q, p: q[1] + 0.2, direction=-1, terminal=True)


@pytest.mark.parametrize("kind", ["pid", "time-transform"])
def test_a_terminal_events_time_and_state_end_the_run_and_move_with_the_inputs(kind):
    """The run ends at the event: its last state and time are the event's, and they move with
    the inputs as the implicit function theorem on g(t*, z(t*)) = 0 says (central differences of
    the run include the moving event time). Reverse mode takes the PID run's 528 elements from
    the kept roots, the time-transformed run's 37 in stretches of sqrt(max_steps) = 10 solved
    again from checkpoints. Measured (as in the test above, forward and reverse): PID 3.1e-10 and
    2.0e-10, time-transformed 5.3e-11 and 4.0e-11; bounds 20x."""
    controller = {"pid": gj.PIDController(1e-13, 1e-13), "time-transform": gj.TimeTransform()}[kind]
    kwargs = dict(checkpoint=True, max_steps=100) if kind == "time-transform" else {}

    def end(x):
        q0, p0, args, t0, t1, _, _, rule = unpack(jnp.where(jnp.isin(jnp.arange(X0.size), jnp.asarray(RULE)), X0, x))
        sol = gj.integrate(H, q0, p0, method=gj.CG(4, rule), h=0.05, t0=t0, t1=t1, args=args, controller=controller,
                           events=TERMINAL, **kwargs)
        return jnp.concatenate([sol.q[-1], sol.p[-1], sol.t[-1:], sol.events.t[:1], sol.events.q[0]])

    sol = gj.integrate(H, Q0, P0, method=gj.CG(4, GAUSS), h=0.05, t0=0.1, t1=T1, args=dict(gm=1.0, j2=1e-3),
                       controller=controller, events=TERMINAL)
    assert int(sol.events.count) == 1 and float(sol.t[-1]) == float(sol.events.t[0]) < T1
    np.testing.assert_array_equal(sol.q[-1], sol.events.q[0])
    forward, reverse = {"pid": (6e-9, 4e-9), "time-transform": (1e-9, 8e-10)}[kind]
    helpers.check_first_derivatives_within(end, (X0,), eps=2e-7, forward=forward, reverse=reverse)


def test_the_end_state_moves_with_t1_as_hamiltons_field():
    """d z(t1) / d t1 is Hamilton's field at z(t1) (to the run's accuracy), for every run kind,
    and d z(t1) / d t0 its negative (H does not depend on t): no silent zero. Measured, the
    largest entry's distance from the field (|field| = 0.89): PID 1e-12 6.5e-14, time-transformed
    3.5e-15, fixed steps reserved 3.3e-16 (3 ulp), fixed steps with events 7.8e-15; bounds
    (``atol``) 23x to 30x those. Reverse mode's d z(t1) / d t1 agrees with forward mode's to
    6.4e-14 (PID) and less; bound 1e-12."""
    H0 = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
    runs = {"pid": dict(h=0.05, controller=gj.PIDController(1e-12, 1e-12)),
            "time-transform": dict(h=0.05, controller=gj.TimeTransform()),
            "fixed, reserved": dict(h=0.01, max_steps=600),
            "fixed, events": dict(h=0.01, events=gj.Event(lambda t, q, p: q[0] - 10.0))}
    atol = {"pid": 1.5e-12, "time-transform": 1e-13, "fixed, reserved": 1e-14, "fixed, events": 2e-13}
    for name, kwargs in runs.items():
        def end(t0, t1):
            sol = gj.integrate(H0, Q0, P0, method=gj.CG(4, GAUSS), t0=t0, t1=t1, **kwargs)
            return jnp.concatenate([sol.q[-1], sol.p[-1]])

        # outside jit (t0 and t1 known while the run is traced, as under jax.jacfwd): the end state,
        # its Jacobian in (t0, t1) by forward mode and its column d z / d t1 by reverse mode
        z, forward, reverse = helpers.jacobians(lambda x: end(x[0], x[1]), jnp.array([0.0, T1]))
        (d_t0, d_t1), q, p = forward.T, z[:2], z[2:]
        field = jnp.concatenate([p, -q / jnp.sqrt(q @ q) ** 3])
        np.testing.assert_allclose(d_t1, field, rtol=0, atol=atol[name], err_msg=name)
        np.testing.assert_allclose(d_t0, -field, rtol=0, atol=atol[name], err_msg=name)
        assert np.allclose(reverse[:, 1], d_t1, rtol=1e-12, atol=1e-12), name


def test_derivatives_that_do_not_exist_raise_naming_the_input():
    """A controller's first step, its tolerances and a second derivative raise; they are never
    a silent zero."""
    H0 = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
    run = lambda h, rtol=1e-8, q0=Q0: gj.integrate(H0, q0, P0, method=gj.CG(2, gj.gauss_legendre(2)), h=h, t1=1.0,
                                                   controller=gj.PIDController(rtol, 1e-8)).q[-1, 0]
    with pytest.raises(ValueError, match="h has no derivative"):
        jax.grad(run)(0.05)
    with pytest.raises(ValueError, match="tolerances"):
        jax.grad(lambda rtol: run(0.05, rtol))(1e-8)
    with pytest.raises(NotImplementedError, match="Second derivatives"):
        jax.hessian(lambda q0: run(0.05, q0=q0))(Q0)


def test_a_gradient_over_a_million_steps_of_128_unknowns_fits_in_a_bound():
    """Reverse mode keeps one step size per attempt slot (8 bytes x max_steps), the state every
    sqrt(max_steps) nodes and the roots of one stretch of sqrt(max_steps) elements (more than 512
    elements: ``_adjoint.Spec.stretch``), one buffer for the forward run and the adjoint: XLA's temporary
    buffers of the compiled gradient of a controlled run of the FPUT chain of 64 masses (128
    unknowns, 512 per element) at max_steps = 10^6 measure 14.6 MB; the bound, 8 bytes x
    max_steps plus 8 MB, holds with room, where storing every element would take 4 GB."""
    from galerkin_jax import scenes

    scene = scenes.fput(64)
    p0 = jnp.asarray(scene.p0)

    def loss(q0):
        sol = gj.integrate(scene.H, q0, p0, method=gj.CG(4, GAUSS), h=0.05, t1=1e4, max_steps=10**6,
                           controller=gj.PIDController(1e-6, 1e-6))
        return jnp.sum(sol.q[-1] ** 2)

    memory = jax.jit(jax.grad(loss)).lower(jnp.asarray(scene.q0)).compile().memory_analysis()
    assert memory.temp_size_in_bytes < 8 * 10**6 + 8e6


def test_a_sweeps_gradient_from_the_kept_roots_equals_one_from_roots_found_again():
    """A controller's sweep keeps each member's roots for reverse mode (its diagnostics folded
    along, ``_sweep._diagnostics``); with ``checkpoint=True`` each member's run (164 and 158
    elements) is cut into stretches of sqrt(max_steps) = 20 solved again from checkpoints. The
    two Jacobians of the final states and of a diagnostic, the invariant error of the Runge-Lenz
    vector's x component (not conserved under the J2 term: 0.023 and 0.021, a maximum over the
    nodes whose derivative is that node's, entries up to 22), agree to round-off: measured 3.3e-15
    relative (1.5e-15 in the states' rows); bound 1e-13, 30x. (The energy error, 8e-16 for
    cG(4) + Gauss 4 at 1e-10, is round-off, and so would its derivative be: it is left out.)"""
    controller = gj.PIDController(1e-10, 1e-10)
    lenz_x = lambda q, p: p[1] * (q[0] * p[1] - q[1] * p[0]) - q[0] / jnp.sqrt(q @ q)

    def run(x, checkpoint):
        q0, p0, args, _, t1, _, _, rule = unpack(x)
        configs = gj.Configs(method=gj.stack_methods([gj.CG(4, rule)] * 2), h=jnp.array([0.047, 0.047]),
                             q0=jnp.stack([q0, 1.01 * q0]), p0=jnp.stack([p0, p0]),
                             args=jax.tree.map(lambda a: jnp.stack([a, a]), args))
        result = gj.sweep(H, configs, t1=t1, controller=controller, max_steps=400, checkpoint=checkpoint,
                          invariants=dict(A=lenz_x))
        return jnp.concatenate([result.q.ravel(), result.p.ravel(), result.invariant_errors["A"]])

    kept, again = (jax.jacrev(lambda x: run(x, checkpoint))(X0) for checkpoint in (False, True))
    assert np.all(np.isfinite(kept)) and float(jnp.max(jnp.abs(kept))) > 1.0
    assert float(jnp.max(jnp.abs(kept[-2:]))) > 1.0  # the diagnostic's rows, far from round-off
    assert float(jnp.max(jnp.abs(again - kept)) / jnp.max(jnp.abs(kept))) < 1e-13


def test_a_vmapped_gradient_takes_each_members_own_elements_backwards(monkeypatch):
    """Under ``vmap`` on a CPU the adjoint sweep runs the members one after another
    (``_adjoint._apart``): the backward elements taken, counted by a callback, are the members'
    own accepted steps summed (58 + 314), not the batch's longest member's twice (628). The gradients
    equal each member's own, and so do those of a vmapped ``jax.vjp``, whose residuals (the
    sweep's constants among them) come batched. Measured: equal to the last bit; asserted to
    1e-12 relative (the batched and lone forward runs may stop an update apart)."""
    from galerkin_jax import _adjoint

    count = dict(elements=0)
    element = _adjoint._element

    def counted(*args):
        jax.debug.callback(lambda: count.__setitem__("elements", count["elements"] + 1))
        return element(*args)

    monkeypatch.setattr(_adjoint, "_element", counted)
    jax.clear_caches()  # a program compiled before the patch would not count
    tols = jnp.array([1e-6, 1e-9])
    run = lambda q0, tol: gj.integrate(H, q0, P0, method=gj.CG(3, gj.gauss_legendre(3)), h=0.1, t1=T1,
                                       args=dict(gm=1.0, j2=1e-3), controller=gj.PIDController(tol, tol))
    loss = lambda q0, tol: jnp.sum(run(q0, tol).q[-1] ** 2)
    steps = [int(run(Q0, tol).stats["num_accepted_steps"]) for tol in tols]
    assert steps == [58, 314]
    batched = jax.jit(jax.vmap(jax.grad(loss), in_axes=(None, 0)))(Q0, tols)
    assert count["elements"] == sum(steps)
    monkeypatch.undo()
    jax.clear_caches()  # nor leave counting programs behind
    alone = jnp.stack([jax.grad(loss)(Q0, tol) for tol in tols])
    np.testing.assert_allclose(batched, alone, rtol=1e-12, atol=0)
    _, vjps = jax.vmap(lambda tol: jax.vjp(lambda q0: loss(q0, tol), Q0))(tols)
    np.testing.assert_allclose(jax.vmap(lambda f: f(jnp.ones(()))[0])(vjps), alone, rtol=1e-12, atol=0)


def test_a_jacobian_of_one_run_takes_its_cotangents_backwards_together():
    """A batch of cotangents of one run (``jacrev``) shares its elements' roots and linearisations:
    ``_apart`` keeps it one batch, where the members of a ``vmap`` of ``grad``, which took their
    own steps, go one after another (a ``lax.map``, a scan as long as the batch, in the program;
    7 outputs and 3 members, lengths no other loop of the program has). Mapped one after another,
    the cotangents of a 6-output Jacobian took 4x as long. (A ``vmap`` of ``jacrev`` batches the
    cotangents first, and its members stay together.)"""
    import re

    run = lambda x: jnp.concatenate([gj.integrate(H, x[:2], P0 * x[2], method=gj.CG(3, gj.gauss_legendre(3)), h=0.1,
                                                  t1=2.0, args=dict(gm=1.0, j2=1e-3),
                                                  controller=gj.PIDController(1e-8, 1e-8)).q[-1], jnp.zeros(5)])
    x0 = jnp.concatenate([Q0, jnp.ones(1)])
    lengths = lambda f, *args: set(re.findall(r"length=(\d+)", str(jax.make_jaxpr(f)(*args))))
    assert "7" not in lengths(jax.jacrev(run), x0)
    assert "3" in lengths(jax.vmap(jax.grad(lambda x: jnp.sum(run(x)))), jnp.stack([x0, 1.01 * x0, 0.99 * x0]))
