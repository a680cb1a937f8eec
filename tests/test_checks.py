"""Input checks of grid, sweep, ModifiedMidpoint, the controllers and events: clear errors naming
the argument, before tracing."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _checks, scenes

KEPLER = scenes.kepler(0.5)
H = KEPLER.H
Q0, P0 = jnp.asarray(KEPLER.q0), jnp.asarray(KEPLER.p0)
CG1 = gj.CG(1, gj.midpoint())
CONFIGS = gj.grid(method=CG1, h=[0.05, 0.1], state=(Q0, P0))


def assert_same_configs(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)


def test_grid_takes_a_single_value_as_one_point_of_its_axis():
    listed = gj.grid(method=[CG1], h=[0.01], state=[(Q0, P0)])
    assert listed.size == 1
    assert_same_configs(gj.grid(method=CG1, h=0.01, state=(Q0, P0)), listed)
    # a pair of 1-D sequences is one state too, a list of pairs the axis
    assert_same_configs(gj.grid(method=CG1, h=0.01, state=(list(KEPLER.q0), list(KEPLER.p0))), listed)
    two = gj.grid(method=CG1, h=np.array([0.01, 0.02]), state=[(Q0, P0), (0.9 * Q0, P0)])
    assert two.size == 4 and two.q0.shape == (4, 2)
    np.testing.assert_array_equal(two.h, [0.01, 0.01, 0.02, 0.02])  # order: method, h, state


def test_grid_args_a_list_is_the_axis_anything_else_one_pytree():
    assert gj.grid(method=CG1, h=0.01, state=(Q0, P0), args=1.5).args.shape == (1,)
    axis = gj.grid(method=CG1, h=0.01, state=(Q0, P0), args=[1.0, 2.0, 3.0])
    assert axis.size == 3
    np.testing.assert_array_equal(axis.args, [1.0, 2.0, 3.0])
    pair = gj.grid(method=CG1, h=0.01, state=(Q0, P0), args=(1.0, 2.0))  # a tuple is one pytree
    assert pair.size == 1 and len(pair.args) == 2
    wrapped = gj.grid(method=CG1, h=0.01, state=(Q0, P0), args=[[1.0, 2.0]])  # one list as args
    assert wrapped.size == 1 and isinstance(wrapped.args, list) and len(wrapped.args) == 2


BAD_GRIDS = [
    (dict(h=0.0), ValueError, r"h must be finite and > 0, got h\[0\] = 0.0"),
    (dict(h=[0.1, -0.1]), ValueError, r"h must be finite and > 0, got h\[1\] = -0.1"),
    (dict(h=[0.1, np.inf]), ValueError, r"h must be finite"),
    (dict(h=[]), ValueError, "h: no step sizes given"),
    (dict(h="0.1"), TypeError, "h must be a step size > 0 or a list"),
    (dict(h=[[0.1, 0.2]]), TypeError, r"h must be a step size .* got shape \(1, 2\)"),
    (dict(method=[]), ValueError, "method: no methods given"),
    (dict(method="cg"), TypeError, "method must be a galerkin_jax method"),
    (dict(method=[CG1, 0.5]), TypeError, r"method\[1\]"),
    (dict(method=[CG1, gj.DG(1, gj.midpoint())]), ValueError, r"one kind and degree.*CG\(k=1\).*DG\(k=1\)"),
    (dict(method=[CG1, gj.CG(2, gj.midpoint())]), ValueError, r"CG\(k=1\) \(method\[0\]\) and CG\(k=2\) \(method\[1\]\)"),
    (dict(state=[]), ValueError, "state: no states given"),
    (dict(state=Q0), ValueError, r"state must be one state \(q0, p0\).*got an array of shape \(2,\)"),
    (dict(state=(Q0, P0, P0)), ValueError, "state must be one state"),
    (dict(state=[(Q0, P0), Q0]), ValueError, r"state\[1\] is an array of shape \(2,\)"),
    (dict(state=(Q0, jnp.ones(3))), ValueError, "state: q0 and p0 need one length d >= 1, got 2 and 3"),
    (dict(state=[(Q0, P0), (jnp.ones(3), jnp.ones(3))]), ValueError, r"one dimension d; state\[0\] has d = 2, state\[1\] has d = 3"),
    (dict(state=(Q0, P0 * np.nan)), ValueError, "state must be finite"),
    (dict(args=[]), ValueError, "args: an empty list"),
    (dict(args=[1.0, jnp.ones(2)]), ValueError, r"args: every entry .* same structure and shapes.*args=\[\[a, b\]\]"),
]


@pytest.mark.parametrize("kwargs, error, match", BAD_GRIDS, ids=[m[:30] for _, _, m in BAD_GRIDS])
def test_grid_rejects_bad_axes_naming_the_argument(kwargs, error, match):
    call = dict(method=CG1, h=0.1, state=(Q0, P0))
    call.update(kwargs)
    with pytest.raises(error, match=match):
        gj.grid(**call)


def test_stack_methods_and_pad_rule_reject_bad_input():
    with pytest.raises(ValueError, match="methods: no methods given"):
        gj.stack_methods([])
    with pytest.raises(ValueError, match=r"CG\(k=1\) \(methods\[0\]\) and CG\(k=2\)"):
        gj.stack_methods([CG1, gj.CG(2, gj.midpoint())])
    with pytest.raises(ValueError, match="n must be an integer >= the rule's 3 points, got 2"):
        gj.pad_rule(gj.gauss_legendre(3), 2)
    with pytest.raises(TypeError, match="rule must be a QuadratureRule"):
        gj.pad_rule([0.5], 2)


def replaced(**fields):
    return gj.Configs(**{**{k: getattr(CONFIGS, k) for k in ("method", "q0", "p0", "h", "args")}, **fields})


BAD_SWEEPS = [
    (dict(H="H"), TypeError, "H must be a callable"),
    (dict(H=lambda q, p: q), ValueError, "H must return a scalar"),
    (dict(configs={"h": 0.1}), TypeError, r"configs must be gj.Configs \(see gj.grid\), got dict"),
    (dict(configs=replaced(h=jnp.array(0.1))), ValueError, r"configs.h must have shape \(B,\)"),
    (dict(configs=replaced(h=jnp.array([0.1, -0.1]))), ValueError, r"configs.h: every h must be finite and > 0, got \[-0.1\] in configuration 1"),
    (dict(configs=replaced(q0=Q0)), ValueError, r"configs.q0 must have shape \(B, d\) with B = 2"),
    (dict(configs=replaced(p0=jnp.ones((2, 3)))), ValueError, "configs.q0 and configs.p0 must have the same shape"),
    (dict(configs=replaced(p0=CONFIGS.p0.at[1, 0].set(np.nan))), ValueError, "configs.p0: every p0 must be finite"),
    (dict(configs=replaced(method=CG1)), ValueError, r"configs.method.quadrature.points needs shape \(B, n_q\).*stack_methods"),
    (dict(configs=replaced(method="cg")), TypeError, "configs.method must be a galerkin_jax method"),
    (dict(configs=replaced(args={"k": jnp.ones(3)})), ValueError, r"configs.args\['k'\] needs a leading axis of size B = 2"),
    (dict(n_steps=0), ValueError, "n_steps must be an integer >= 1, got 0"),
    (dict(n_steps=2.5), ValueError, "n_steps must be an integer"),
    (dict(save_every=0), ValueError, "save_every must be an integer >= 1"),
    (dict(n_steps=10, save_every=3), ValueError, r"n_steps \(10\) must be a multiple of save_every \(3\)"),
    (dict(invariants=lambda q, p: q[0]), TypeError, r"invariants must be a dict \{name: I\(q, p\)\}, got function"),
    (dict(invariants=[lambda q, p: q[0]]), TypeError, r"invariants must be a dict .* got list"),
    (dict(invariants={"L": 1.0}), TypeError, r"invariants\['L'\] must be a function I\(q, p\), got float"),
    (dict(invariants={"L": lambda q: q[0]}), TypeError, r"invariants\['L'\] could not be called as I\(q, p\)"),
    (dict(invariants={"L": lambda q, p: q[0] > 0}), TypeError, r"invariants\['L'\] must return a real floating array"),
    (dict(reference=(Q0, P0)), ValueError, r"reference must be \(q_ref, p_ref\), each of shape \(B, d\) = \(2, 2\), got \[\(2,\), \(2,\)\]"),
    (dict(reference=CONFIGS.q0), ValueError, r"reference must be \(q_ref, p_ref\)"),
]


@pytest.mark.parametrize("kwargs, error, match", BAD_SWEEPS, ids=[m[:30] for _, _, m in BAD_SWEEPS])
def test_check_sweep_rejects_bad_input_naming_the_argument(kwargs, error, match):
    """``_checks.check_sweep``, which ``gj.sweep`` runs before anything is traced."""
    call = dict(H=H, configs=CONFIGS, n_steps=10, save_every=None, invariants=None, reference=None)
    call.update(kwargs)
    with pytest.raises(error, match=match):
        _checks.check_sweep(**call)


def test_check_sweep_accepts_good_input_and_casts_to_the_state_dtype():
    configs = gj.Configs(method=CONFIGS.method, q0=CONFIGS.q0, p0=CONFIGS.p0, h=[0.05, 0.1])
    angular = {"L": lambda q, p: q[0] * p[1] - q[1] * p[0]}
    checked = _checks.check_sweep(H, configs, 10, 5, angular, (CONFIGS.q0, CONFIGS.p0))
    assert checked.h.dtype == checked.q0.dtype == jnp.float64 and checked.h.shape == (2,)
    # traced configs (sweep under jit or grad) pass the shape checks; their values are not read
    jax.jit(lambda c: _checks.check_sweep(H, c, 10, None, None, None).h)(CONFIGS)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(configs={"h": 0.1}), TypeError, "Configs"),
        (dict(n_steps=10, save_every=0), ValueError, "save_every"),
        (dict(n_steps=10, reference=(Q0, P0)), ValueError, "reference"),
    ],
)
def test_sweep_rejects_bad_input(kwargs, error, match):
    call = dict(configs=CONFIGS, n_steps=10)
    call.update(kwargs)
    with pytest.raises(error, match=match):
        gj.sweep(H, **call)


CENTRAL = {
    "kepler": KEPLER.H,
    "quartic": scenes.quartic().H,
    "oscillator": scenes.oscillator().H,
    "log potential, m = 3": lambda q, p: p @ p / 6.0 + jnp.log(q @ q),
    "unequal masses": lambda q, p: 0.5 * p[0] ** 2 + 0.25 * p[-1] ** 2 - 1.0 / jnp.sqrt(q @ q),
}
NOT_CENTRAL = {
    "anisotropic V": (lambda q, p: 0.5 * (p @ p) + 0.5 * q[0] ** 2 + 2.0 * q[-1] ** 2, "V is not a function of \\|q\\|"),
    "V + 1e-9 q0": (lambda q, p: KEPLER.H(q, p) + 1e-9 * q[0], "V is not a function of \\|q\\|"),
    "mass depends on q": (lambda q, p: 0.5 * (1.0 + 0.1 * (q @ q)) * (p @ p) - 1.0 / jnp.sqrt(q @ q), "kinetic energy depends on q"),
    "relativistic": (lambda q, p: jnp.sqrt(1.0 + p @ p) - 1.0 / jnp.sqrt(q @ q), "not a quadratic form in p"),
    "linear term in p": (lambda q, p: KEPLER.H(q, p) + 0.1 * p[0], "not a quadratic form in p"),
}
STATES = {"2-D": (Q0, P0), "3-D": (jnp.array([2.0, 0.1, -0.3]), jnp.array([0.1, 77.0, 0.0]))}


@pytest.mark.parametrize("d", STATES)
def test_central_force_check_accepts_central_forces(d):
    """Round-off of H at the probes is a few eps d; the bound, 100 d eps times the scale, has no false alarm."""
    for H_central in CENTRAL.values():
        _checks.check_central_force(H_central, *STATES[d])
    _checks.check_central_force(lambda q, p: 0.5 * (p @ p) - jnp.cos(q[0]), jnp.array([1.2]), jnp.array([0.3]))  # even V in 1-D


@pytest.mark.parametrize("name", NOT_CENTRAL)
@pytest.mark.parametrize("d", STATES)
def test_central_force_check_rejects_other_hamiltonians_naming_the_property(name, d):
    H_other, match = NOT_CENTRAL[name]
    with pytest.raises(ValueError, match=f"ModifiedMidpoint needs H = .*{match}.*gj.DiscreteGradient"):
        _checks.check_central_force(H_other, *STATES[d])


def test_central_force_check_runs_for_modified_midpoint_only_and_skips_traced_values():
    H_other = NOT_CENTRAL["anisotropic V"][0]
    with pytest.raises(ValueError, match="ModifiedMidpoint needs"):
        _checks.check_premise(gj.ModifiedMidpoint(), H_other, Q0, P0)
    _checks.check_premise(gj.DiscreteGradient(), H_other, Q0, P0)
    jax.jit(lambda q: _checks.check_central_force(H_other, q, P0) or q)(Q0)
    args_traced = lambda a: _checks.check_central_force(lambda q, p: H_other(q, p) * a, Q0, P0) or a
    jax.vmap(args_traced)(jnp.ones(2))
    configs = gj.grid(method=gj.ModifiedMidpoint(), h=0.1, state=(Q0, P0))
    with pytest.raises(ValueError, match="ModifiedMidpoint needs"):
        _checks.check_sweep(H_other, configs, 10, None, None, None)


BAD_CONTROLLERS = [
    (dict(rtol=0), ValueError, "PIDController: rtol must be > 0, got 0.0."),
    (dict(atol=-1e-9), ValueError, "PIDController: atol must be > 0, got -1e-09."),
    (dict(rtol=float("nan")), ValueError, "PIDController: rtol must be > 0, got nan."),
    (dict(rtol=np.array([1e-6, 0.0])), ValueError, "PIDController: rtol must be > 0, got 0.0 (entry 1 of 2)."),
    (dict(dtmin=1.0, dtmax=0.5), ValueError, "PIDController: dtmin must be < dtmax, got dtmin = 1.0 and dtmax = 0.5."),
    (dict(dtmin=-0.1), ValueError, "PIDController: dtmin must be >= 0, got -0.1."),
    (dict(dtmax=0.0), ValueError, "PIDController: dtmax must be > 0, got 0.0."),
    (dict(safety=1.5), ValueError, "PIDController: safety must be in (0, 1], got 1.5."),
    (dict(factormin=1.0), ValueError, "PIDController: factormin must be in (0, 1), got 1.0."),
    (dict(factormax=1.0), ValueError, "PIDController: factormax must be > 1, got 1.0."),
    (dict(failfactor=0.0), ValueError, "PIDController: failfactor must be in (0, 1), got 0.0."),
    (dict(pcoeff=np.inf), ValueError, "PIDController: pcoeff must be finite, got inf."),
    (dict(predictive=1), TypeError, "PIDController: predictive must be a bool, got 1."),
]


@pytest.mark.parametrize("kwargs, error, message", BAD_CONTROLLERS, ids=[m[15:45] for _, _, m in BAD_CONTROLLERS])
def test_a_pid_controller_out_of_range_raises_at_construction(kwargs, error, message):
    with pytest.raises(error) as caught:
        gj.PIDController(**{"rtol": 1e-6, "atol": 1e-6, **kwargs})
    assert str(caught.value) == message


def test_a_pid_controller_checks_concrete_values_only_and_replace_checks_too():
    import dataclasses

    # a traced tolerance is not read (integrate reports what it can through the status)
    assert float(jax.jit(lambda tol: gj.PIDController(tol, tol).rtol)(0.0)) == 0.0
    good = gj.PIDController(rtol=jnp.array([1e-6, 1e-9]), atol=1e-9)  # a sweep's tolerances
    assert good.rtol.shape == (2,)
    with pytest.raises(ValueError, match=r"PIDController: rtol must be > 0, got 0.0\.$"):
        dataclasses.replace(good, rtol=0.0)


def test_a_time_transform_takes_a_callable_and_no_modified_midpoint():
    with pytest.raises(TypeError, match="TimeTransform: s must be a callable s\\(q, p\\), got float"):
        gj.TimeTransform(s=1.0)
    with pytest.raises(ValueError, match=r"ModifiedMidpoint needs H = \|p\|\^2 / 2m \+ V\(\|q\|\).*K = s\(q, p\) "
                                         r"\(H \+ p_t\).*use fixed steps or a PIDController"):
        gj.integrate(H, Q0, P0, method=gj.ModifiedMidpoint(), h=0.1, t1=1.0, controller=gj.TimeTransform())


def test_an_event_function_of_a_vector_names_itself_and_the_shape():
    def section(t, q, p):
        return q  # should be q[0]

    with pytest.raises(ValueError) as caught:
        gj.integrate(H, Q0, P0, method=CG1, h=0.1, t1=1.0, events=gj.Event(section))
    assert str(caught.value) == ("Event.g (section) must return a scalar, got an array of shape (2,) (q0 of shape "
                                 "(2,)): one number whose sign changes at the event, e.g. q[0] rather than q.")
    with pytest.raises(ValueError, match=r"Event.g \(<lambda>\) must return a scalar, got tuple"):
        gj.integrate(H, Q0, P0, method=CG1, h=0.1, t1=1.0, events=gj.Event(lambda t, q, p: (q[0], p[0])))


@pytest.mark.parametrize(
    "fields, error, message",
    [
        (dict(terminal="yes"), TypeError, "Event: terminal must be a bool, got 'yes'."),
        (dict(terminal=1), TypeError, "Event: terminal must be a bool, got 1."),
        (dict(direction=2), ValueError, "Event: direction must be -1, 0 or 1, got 2."),
        (dict(direction="up"), TypeError, "Event: direction must be the integer -1, 0 or 1, got 'up'."),
        (dict(direction=True), TypeError, "Event: direction must be the integer -1, 0 or 1, got True."),
        (dict(capacity=0), ValueError, "Event: capacity must be an integer >= 1, got 0."),
        (dict(capacity=2.0), TypeError, "Event: capacity must be an integer >= 1, got 2.0."),
        (dict(g=1.0), TypeError, "Event: g must be a callable g(t, q, p), got float."),
    ],
)
def test_an_event_checks_its_fields_where_it_is_built(fields, error, message):
    """A field of the wrong kind raises at ``gj.Event(...)``, naming the field (terminal="yes"
    used to raise ``bad operand type for unary ~`` inside the traced run, terminal=1 to run as if
    terminal were -2)."""
    fields = dict(dict(g=lambda t, q, p: q[0]), **fields)
    with pytest.raises(error) as caught:
        gj.Event(**fields)
    assert str(caught.value) == message
    good = gj.Event(lambda t, q, p: q[0], direction=np.int64(-1), terminal=np.bool_(True), capacity=np.int32(3))
    assert (good.direction, good.terminal, good.capacity) == (-1, True, 3)


def test_the_time_transform_status_advises_the_default_s_and_a_users_s_apart():
    message = gj.status_message(gj.Status.TIME_TRANSFORM)
    default, own = message.split(". ")[1:3]
    # the default s fails only where the field overflows (or, unbounded, vanishes): there, a density of one's own helps
    assert default.startswith("The default s (TimeTransform()) fails only where Hamilton's field overflows, at a "
                              "collision, or with s_max=inf where the field vanishes on the way") \
        and "pass a TimeTransform(s=...) of your own there" in default
    # one's own s failed: it must stay positive and finite, not be replaced by another of one's own
    assert own.startswith("A TimeTransform(s=...) of your own must stay positive and finite at every state the "
                          "orbit reaches") and "pass" not in own
