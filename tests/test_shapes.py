"""States of any shape: an N-body scene written naturally, q and p of shape (3, 2), against
the same scene written by hand on flat vectors of length 6, on every public path.

The two Hamiltonians are the same function computed in a different order (a norm against a
square root of a sum), so states agree to round-off, not bit for bit: the margins are a few
hundred eps of O(1) states over short runs.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _integrate, cli

MASSES = (1.0, 1.0, 1.0)
PAIRS = ((0, 1), (0, 2), (1, 2))
CG2 = gj.CG(2, gj.gauss_legendre(3))
CG1 = gj.CG(1, gj.gauss_legendre(1))  # the implicit midpoint rule: the cheapest to compile
CG2_GAUSS2 = gj.CG(2, gj.gauss_legendre(2))  # the command line's cG2
FAST = dict(method=CG1, error_estimate=False)
TOL = 1e-13  # states of size ~1 after at most ~60 elements: round-off accumulates to a few 1e-15


I, J = np.array(PAIRS).T


def H(q, p):
    """Three bodies in the plane, pairwise 1/r: q, p of shape (3, 2)."""
    m = jnp.asarray(MASSES)
    kinetic = jnp.sum(jnp.sum(p**2, axis=1) / (2 * m))
    return kinetic - jnp.sum(m[I] * m[J] / jnp.linalg.norm(q[I] - q[J], axis=1))


def H_flat(q, p):
    """The same H written by hand on flat vectors (x1, y1, x2, y2, x3, y3)."""
    m = jnp.asarray(MASSES)
    kinetic = jnp.sum((p[0::2] ** 2 + p[1::2] ** 2) / (2 * m))
    r = jnp.sqrt((q[2 * I] - q[2 * J]) ** 2 + (q[2 * I + 1] - q[2 * J + 1]) ** 2)
    return kinetic - jnp.sum(m[I] * m[J] / r)


def figure_eight():
    """Chenciner and Montgomery's figure-eight orbit of three equal masses (period ~6.3259)."""
    x1, v3 = np.array([0.97000436, -0.24308753]), np.array([-0.93240737, -0.86473146])
    return jnp.asarray([x1, -x1, [0.0, 0.0]]), jnp.asarray([-v3 / 2, -v3 / 2, v3])


Q0, P0 = figure_eight()
F0, G0 = Q0.ravel(), P0.ravel()


def flat(x):
    """States of shape (..., 3, 2) as (..., 6)."""
    return np.asarray(x).reshape(np.shape(x)[:-2] + (6,))


def assert_close(shaped, flat_states, tol=TOL):
    shaped = np.asarray(shaped)
    assert shaped.shape[-2:] == (3, 2)
    np.testing.assert_allclose(flat(shaped), np.asarray(flat_states), rtol=0, atol=tol)


def test_step_keeps_the_shape_and_equals_the_flat_step():
    q1, p1 = gj.step(H, Q0, P0, method=CG1, h=0.05)
    f1, g1 = gj.step(H_flat, F0, G0, method=CG1, h=0.05)  # compiled once: shared below
    assert q1.shape == p1.shape == (3, 2)
    assert_close(q1, f1), assert_close(p1, g1)


@pytest.fixture(scope="module")
def flat_run():
    """The flat scene with cG(2) + Gauss 2, h = 0.05, 40 elements, every state saved: one
    compiled program for the two tests that compare against it."""
    return gj.integrate(H_flat, F0, G0, method=CG2_GAUSS2, h=0.05, n_steps=40)


def test_fixed_steps_with_save_every_and_the_error_estimate(flat_run):
    sol = gj.integrate(H, Q0, P0, method=CG2_GAUSS2, h=0.05, n_steps=40, save_every=4)
    ref = flat_run  # save_every=1: every fourth state is the shaped run's
    assert sol.q.shape == sol.p.shape == (11, 3, 2) and int(sol.status) == 0
    assert_close(sol.q, ref.q[::4]), assert_close(sol.p, ref.p[::4])
    np.testing.assert_allclose(sol.error_estimate, ref.error_estimate, rtol=1e-6)
    # energy conserved by cG(2) on the naturally written H: cG(k) conserves H up to the
    # quadrature (two Gauss points: measured 2.2e-7; three: 8.7e-10)
    energy = jax.jit(jax.vmap(H))(sol.q, sol.p)
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 1e-6


def test_t1_with_save_at_and_dense_evaluate():
    ts = jnp.linspace(0.0, 1.0, 7)
    sol = gj.integrate(H, Q0, P0, **FAST, h=0.07, t1=1.0, save_at=ts, dense=True)
    ref = gj.integrate(H_flat, F0, G0, **FAST, h=0.07, t1=1.0, save_at=ts, dense=True)
    assert sol.q.shape == (7, 3, 2)
    assert_close(sol.q, ref.q), assert_close(sol.p, ref.p)
    times = jnp.asarray([0.0, 0.123, 0.5, 1.0])
    (q, p), (fq, fp) = sol.evaluate(times), ref.evaluate(times)
    assert q.shape == (4, 3, 2) and sol.evaluate(0.3)[0].shape == (3, 2)
    assert_close(q, fq), assert_close(p, fp)


def test_fixed_steps_to_t1_with_dense_output():
    sol = gj.integrate(H, Q0, P0, **FAST, h=0.07, t1=1.0, dense=True)
    ref = gj.integrate(H_flat, F0, G0, **FAST, h=0.07, t1=1.0, dense=True)
    assert sol.q.shape == (16, 3, 2)  # 15 elements: 14 of 0.07 and a last one of 0.02
    assert_close(sol.q, ref.q)
    assert_close(sol.evaluate(0.99)[1], ref.evaluate(0.99)[1])


def test_pid_controller():
    controller = gj.PIDController(rtol=1e-6, atol=1e-6)
    sol = gj.integrate(H, Q0, P0, **FAST, h=0.05, t1=1.0, controller=controller)
    ref = gj.integrate(H_flat, F0, G0, **FAST, h=0.05, t1=1.0, controller=controller)
    assert int(sol.status) == 0 and sol.q.shape == (2, 3, 2)
    # the same accepted steps: the controller sees the same flat errors (to round-off)
    assert int(sol.stats["num_accepted_steps"]) == int(ref.stats["num_accepted_steps"]) > 10
    assert_close(sol.q, ref.q, 1e-12), assert_close(sol.p, ref.p, 1e-12)


def s_shaped(q, p):
    """Step density: the smallest pair distance to the power 3/2 (Kepler's time scale)."""
    return jnp.min(jnp.stack([jnp.linalg.norm(q[i] - q[j]) for i, j in PAIRS])) ** 1.5


def s_flat(q, p):
    r = lambda i, j: jnp.sqrt((q[2 * i] - q[2 * j]) ** 2 + (q[2 * i + 1] - q[2 * j + 1]) ** 2)
    return jnp.min(jnp.stack([r(i, j) for i, j in PAIRS])) ** 1.5


def test_time_transform_with_a_step_density_of_the_users_shape():
    sol = gj.integrate(H, Q0, P0, **FAST, h=0.05, t1=1.0, controller=gj.TimeTransform(s_shaped), dense=True)
    ref = gj.integrate(H_flat, F0, G0, **FAST, h=0.05, t1=1.0, controller=gj.TimeTransform(s_flat), dense=True)
    assert int(sol.status) == 0 and int(sol.stats["num_accepted_steps"]) == int(ref.stats["num_accepted_steps"])
    assert_close(sol.q, ref.q, 1e-12), assert_close(sol.p, ref.p, 1e-12)
    assert_close(sol.evaluate(0.4)[0], ref.evaluate(0.4)[0], 1e-12)


def test_events_receive_and_return_the_users_shape():
    """Body 1 (y = -0.243 at t = 0) crosses y = 0 upwards; g reads q[0, 1] against flat q[1]."""
    event = gj.Event(lambda t, q, p: q[0, 1], direction=1, capacity=4)
    event_flat = gj.Event(lambda t, q, p: q[1], direction=1, capacity=4)
    sol = gj.integrate(H, Q0, P0, **FAST, h=0.05, t1=3.0, events=event)
    ref = gj.integrate(H_flat, F0, G0, **FAST, h=0.05, t1=3.0, events=event_flat)
    assert int(sol.events.count) == int(ref.events.count) >= 1
    assert sol.events.q.shape == sol.events.p.shape == (4, 3, 2)
    n = int(sol.events.count)
    np.testing.assert_allclose(sol.events.t[:n], ref.events.t[:n], rtol=0, atol=TOL)
    assert_close(sol.events.q[:n], ref.events.q[:n])
    assert abs(float(sol.events.q[0, 0, 1])) < 1e-12  # located on the root of g
    assert np.all(np.isnan(np.asarray(sol.events.q[n:])))


def test_vmap_over_initial_states_of_shape_3_by_2():
    scales = jnp.asarray([1.0, 0.98, 1.02])
    shaped = jax.vmap(lambda q0: gj.integrate(H, q0, P0, **FAST, h=0.05, n_steps=20, dense=True).q)(scales[:, None, None] * Q0[None])
    flat_runs = jax.vmap(lambda q0: gj.integrate(H_flat, q0, G0, **FAST, h=0.05, n_steps=20, dense=True).q)(scales[:, None] * F0[None])
    assert shaped.shape == (3, 21, 3, 2)
    assert_close(shaped, flat_runs)


def angular_momentum(q, p):
    return jnp.sum(q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0])


def angular_momentum_flat(q, p):
    return sum(q[2 * i] * p[2 * i + 1] - q[2 * i + 1] * p[2 * i] for i in range(3))


def test_sweep_over_grid_and_configs_of_shape_b_by_3_by_2():
    states = [(Q0, P0), (0.98 * Q0, P0)]
    configs = gj.grid(method=[CG1, gj.CG(1, gj.gauss_legendre(2))], h=[0.05, 0.1], state=states)
    assert configs.q0.shape == (8, 3, 2)
    flat_configs = gj.grid(method=[CG1, gj.CG(1, gj.gauss_legendre(2))], h=[0.05, 0.1],
                           state=[(F0, G0), (0.98 * F0, G0)])
    reference = (configs.q0, configs.p0)  # the final error is then the distance travelled
    result = gj.sweep(H, configs, n_steps=10, invariants={"L": angular_momentum}, reference=reference, save_every=5,
                      error_estimate=False)
    ref = gj.sweep(H_flat, flat_configs, n_steps=10, invariants={"L": angular_momentum_flat},
                   reference=(flat_configs.q0, flat_configs.p0), save_every=5, error_estimate=False)
    assert result.q.shape == (8, 3, 2) and result.solution.q.shape == (8, 3, 3, 2)
    assert_close(result.q, ref.q), assert_close(result.p, ref.p)
    assert_close(result.solution.p, ref.solution.p)
    np.testing.assert_allclose(result.final_error, ref.final_error, rtol=0, atol=TOL)
    np.testing.assert_allclose(result.invariant_errors["L"], ref.invariant_errors["L"], rtol=0, atol=TOL)
    np.testing.assert_allclose(result.energy_error, ref.energy_error, rtol=0, atol=1e-12)
    assert np.all(np.asarray(result.status) == 0)


def test_gradient_through_fixed_steps_has_the_states_shape():
    loss = lambda f, q0, p0: jnp.sum(gj.integrate(f, q0, p0, **FAST, h=0.05, n_steps=10).q[-1] ** 2)
    value_and_grad = jax.jit(jax.value_and_grad(lambda q0: loss(H, q0, P0)))  # the differences' values too
    grad = value_and_grad(Q0)[1]
    grad_flat = jax.jit(jax.grad(lambda q0: loss(H_flat, q0, G0)))(F0)
    assert grad.shape == (3, 2)
    np.testing.assert_allclose(np.asarray(grad).ravel(), grad_flat, rtol=0, atol=1e-12)
    # and against central differences in one entry (an independent check of the flattening)
    e = jnp.zeros((3, 2)).at[1, 0].set(1e-6)
    fd = (value_and_grad(Q0 + e)[0] - value_and_grad(Q0 - e)[0]) / 2e-6
    assert abs(float(fd) - float(grad[1, 0])) < 1e-7 * max(1.0, abs(float(fd)))


def test_amplification_matrix_is_in_flat_c_order():
    A = gj.amplification_matrix(H, Q0, P0, method=CG2, h=0.05)
    B = gj.amplification_matrix(H_flat, F0, G0, method=CG2, h=0.05)
    assert A.shape == (12, 12)
    np.testing.assert_allclose(A, B, rtol=0, atol=1e-13)


def H_dict(q, p):
    """The same H on states dict(x=(3,), y=(3,)): coordinates by axis."""
    return H(jnp.stack([q["x"], q["y"]], axis=1), jnp.stack([p["x"], p["y"]], axis=1))


def to_dict(x):
    return dict(x=x[..., 0], y=x[..., 1])


def test_pytree_state_dict_of_coordinates():
    sol = gj.integrate(H_dict, to_dict(Q0), to_dict(P0), **FAST, h=0.05, n_steps=20, dense=True)
    ref = gj.integrate(H_flat, F0, G0, **FAST, h=0.05, n_steps=20, dense=True)  # compiled once: shared below
    assert set(sol.q) == {"x", "y"} and sol.q["x"].shape == (21, 3)
    assert_close(jnp.stack([sol.q["x"], sol.q["y"]], axis=-1), ref.q)
    assert_close(jnp.stack([sol.p["x"], sol.p["y"]], axis=-1), ref.p)
    q, _ = sol.evaluate(jnp.asarray([0.5, 0.7]))
    assert_close(jnp.stack([q["x"], q["y"]], axis=-1), ref.evaluate(jnp.asarray([0.5, 0.7]))[0])
    q1, _ = gj.step(H_dict, to_dict(Q0), to_dict(P0), method=CG1, h=0.05)
    assert_close(jnp.stack([q1["x"], q1["y"]], axis=-1), gj.step(H_flat, F0, G0, method=CG1, h=0.05)[0])
    # a sweep over a grid of dict states (leaves of shape (B, 3)) runs the same elements
    configs = gj.grid(method=CG1, h=[0.05, 0.05], state=(to_dict(Q0), to_dict(P0)))
    assert configs.q0["x"].shape == (2, 3)
    result = gj.sweep(H_dict, configs, n_steps=20, error_estimate=False)
    assert result.q["y"].shape == (2, 3)
    assert_close(jnp.stack([result.q["x"], result.q["y"]], axis=-1), jnp.stack([ref.q[-1], ref.q[-1]]))


def test_pytree_of_leaves_of_different_shapes_and_dtypes():
    """dict(a=(2,), b=(2, 2)) in float32 and float64: one float64 vector of 6 entries; the
    leaves come back in float64 (the library computes in one dtype)."""
    q0 = dict(a=np.asarray(Q0[0], np.float32), b=Q0[1:])
    p0 = dict(a=np.asarray(P0[0], np.float32), b=P0[1:])
    stack = lambda x: jnp.concatenate([x["a"][..., None, :], x["b"]], axis=-2)
    sol = gj.integrate(lambda q, p: H(stack(q), stack(p)), q0, p0, **FAST, h=0.05, n_steps=20, dense=True)
    ref = gj.integrate(H_flat, jnp.concatenate([jnp.asarray(Q0[0], jnp.float32).astype(float), F0[2:]]),
                       jnp.concatenate([jnp.asarray(P0[0], jnp.float32).astype(float), G0[2:]]),
                       **FAST, h=0.05, n_steps=20, dense=True)
    assert sol.q["a"].shape == (21, 2) and sol.q["b"].shape == (21, 2, 2) and sol.q["a"].dtype == jnp.float64
    assert_close(stack(sol.q), ref.q)


def test_a_second_call_reuses_the_compiled_program():
    """H is a static argument of the jitted run: the wrapper around it must hash and compare
    by (H, layout), so that a second call with new values of the same shape finds the
    compiled program instead of tracing and compiling again. Traces of H are counted: the
    second call traces H only in the input checks (``eval_shape``), fewer times than the first."""
    traces = []

    def H_counted(q, p):
        traces.append(q.shape)
        return 0.5 * jnp.sum(p**2) + 0.5 * jnp.sum(q**2)

    size = _integrate._integrate._cache_size()
    gj.integrate(H_counted, Q0, P0, **FAST, h=0.05, n_steps=4)
    first = len(traces)
    assert _integrate._integrate._cache_size() == size + 1
    sol = gj.integrate(H_counted, 1.01 * Q0, P0, **FAST, h=0.05, n_steps=4)
    assert _integrate._integrate._cache_size() == size + 1
    second = len(traces) - first
    assert second < first and int(sol.status) == 0, (first, second)
    assert all(shape == (3, 2) for shape in traces)  # H only ever sees the user's shape


@pytest.mark.parametrize(
    "q0, p0, match",
    [
        (Q0, P0.T, r"q0 and p0 must have the same shape, got \(3, 2\) and \(2, 3\)"),
        (to_dict(Q0), P0, "q0 and p0 must have the same structure"),
        (to_dict(Q0), dict(x=P0[:, 0], z=P0[:, 1]), "q0 and p0 must have the same structure"),
        (to_dict(Q0), dict(x=P0[:, 0], y=P0[:2, 1]), r"q0\['y'\] and p0\['y'\] must have the same shape"),
        (Q0.at[2, 1].set(jnp.nan), P0, "q0 must be finite"),
        (to_dict(Q0), dict(x=P0[:, 0], y=P0[:, 1].at[0].set(jnp.inf)), r"p0\['y'\] must be finite"),
        (dict(x=Q0, y="a"), dict(x=P0, y="a"), r"q0\['y'\] must be an array of real numbers"),
        (Q0 + 0j, P0 + 0j, "q0 must hold real numbers"),
        (jnp.zeros((0, 3)), jnp.zeros((0, 3)), "q0 must have at least one element"),
    ],
)
def test_bad_states_raise_a_clear_value_error(q0, p0, match):
    with pytest.raises(ValueError, match=match):
        gj.integrate(H, q0, p0, method=CG2, h=0.05, n_steps=2)


def test_bad_batched_states_raise_a_clear_value_error():
    configs = gj.grid(method=CG2, h=[0.05, 0.1], state=(Q0, P0))
    with pytest.raises(ValueError, match=r"configs.q0 and configs.p0 must have the same shape \(B, ...\)"):
        gj.sweep(H, dataclasses.replace(configs, p0=configs.p0[:, :2]), n_steps=2)
    with pytest.raises(ValueError, match="configs.q0 and configs.p0 must have the same structure"):
        gj.sweep(H, dataclasses.replace(configs, q0=to_dict(configs.q0)), n_steps=2)
    with pytest.raises(ValueError, match=r"state: all states of one sweep need one shape"):
        gj.grid(method=CG2, h=0.1, state=[(Q0, P0), (Q0[:2], P0[:2])])
    with pytest.raises(ValueError, match=r"state: q0 and p0 must have the same shape"):
        gj.grid(method=CG2, h=0.1, state=(Q0, P0.T))


NBODY_SCENE = """
import jax.numpy as jnp
import numpy as np

def H(q, p):
    r = lambda i, j: jnp.linalg.norm(q[i] - q[j])
    return 0.5 * jnp.sum(p ** 2) - 1 / r(0, 1) - 1 / r(0, 2) - 1 / r(1, 2)

def L(q, p):
    return jnp.sum(q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0])

x1, v3 = np.array([0.97000436, -0.24308753]), np.array([-0.93240737, -0.86473146])
q0 = np.array([x1, -x1, [0.0, 0.0]])
p0 = np.array([-v3 / 2, -v3 / 2, v3])
h, n_steps = 0.05, 40
invariants = {"L": L}
"""


def test_command_line_runs_a_scene_of_shape_n_by_2(tmp_path, capsys, flat_run):
    scene = tmp_path / "eight.py"
    scene.write_text(NBODY_SCENE)
    assert cli.main(["run", str(scene), "--method", "cG2", "--out", str(tmp_path / "out")]) == 0
    text = capsys.readouterr().out
    assert "d = 6 degrees of freedom" in text
    saved = np.load(tmp_path / "out" / "eight_cG2-gauss2.npz")
    # the files hold rows of the flat state, and the state's shape beside them
    assert saved["q"].shape == (41, 6) and tuple(saved["state_shape"]) == (3, 2)
    assert_close(saved["q"].reshape(41, 3, 2), flat_run.q)
    np.testing.assert_allclose(saved["invariant_L"], saved["invariant_L"][0], rtol=0, atol=1e-12)
