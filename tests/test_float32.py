"""float32: the library computes in the dtype it is given, warns once, and stays accurate to it.

The suite enables x64 (conftest.py); float32 arrays passed explicitly still compute in
float32. Tolerances follow eps32 = 1.2e-7.
"""

import os
import subprocess
import sys
import textwrap
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _checks, _state, scenes
from galerkin_jax._checks import Float32Warning

F32 = jnp.float32
EPS32 = float(jnp.finfo(F32).eps)
KEPLER = scenes.kepler(0.5)
Q32, P32 = jnp.asarray(KEPLER.q0, F32), jnp.asarray(KEPLER.p0, F32)


def energy_drift(H, sol):
    """max_n |H_n - H_0|, H evaluated in float64 so that only the run's own round-off shows."""
    E = np.asarray(jax.vmap(lambda q, p: H(q.astype(jnp.float64), p.astype(jnp.float64)))(sol.q, sol.p))
    return np.max(np.abs(E - E[0])), abs(E[0])


@pytest.fixture(autouse=True)
def silence_float32_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Float32Warning)
        yield


ONCE = textwrap.dedent(
    """
    import warnings
    import jax, jax.numpy as jnp
    import galerkin_jax as gj
    from galerkin_jax._checks import Float32Warning
    assert not jax.config.jax_enable_x64
    H = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
    q0, p0 = jnp.array([0.5, 0.0]), jnp.array([0.0, 3.0 ** 0.5])
    method = gj.CG(1, gj.midpoint())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            gj.integrate(H, q0, p0, method=method, h=0.1, n_steps=1)
            gj.step(H, q0, p0, method=method, h=0.1)
    ours = [w for w in caught if issubclass(w.category, Float32Warning)]
    print("count", len(ours))
    print("file", ours[0].filename)
    print("message", str(ours[0].message))
    """
)


def test_float32_warning_is_given_once_per_process_and_says_what_to_do():
    """JAX's default without x64 is float32: integrate and step, three times each, warn once."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    done = subprocess.run([sys.executable, "-c", ONCE], capture_output=True, text=True, timeout=300,
                          env=dict(env, JAX_PLATFORMS="cpu"))
    assert done.returncode == 0, done.stderr[-2000:]
    out = dict(line.split(" ", 1) for line in done.stdout.splitlines())
    assert out["count"] == "1"
    assert out["file"] == "<string>"  # points at the caller's line, not the library's
    message = out["message"]
    for expected in ("float32", "1e-06", 'jax.config.update("jax_enable_x64", True)',
                     'warnings.filterwarnings("ignore", category=gj.Float32Warning)'):
        assert expected in message


def test_float32_warning_can_be_silenced_and_is_not_given_for_float64(monkeypatch):
    monkeypatch.setattr(_state, "_warned_low_precision", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _checks.check_state(jnp.asarray(KEPLER.q0), jnp.asarray(KEPLER.p0))
        assert not [w for w in caught if issubclass(w.category, Float32Warning)]
        warnings.filterwarnings("ignore", category=Float32Warning)
        _checks.check_state(Q32, P32)
        assert not [w for w in caught if issubclass(w.category, Float32Warning)]
    monkeypatch.setattr(_state, "_warned_low_precision", False)
    with pytest.warns(Float32Warning, match="float32"):
        q1, p1 = gj.step(KEPLER.H, Q32, P32, method=gj.CG(1, gj.midpoint()), h=0.1)
    assert q1.dtype == p1.dtype == F32


# CG and DiscreteGradient: in the energy tests below; step: in the warning test above
METHODS = {
    "DG": gj.DG(1, gj.gauss_radau(2)),
    "GalerkinVI": gj.GalerkinVI(2, gj.gauss_lobatto(3)),
    "LagrangianVI": gj.LagrangianVI(1, gj.midpoint()),
    "ModifiedMidpoint": gj.ModifiedMidpoint(),
}


@pytest.mark.parametrize("name", METHODS)
def test_float32_inputs_compute_in_float32_with_x64_enabled(name):
    """No internal constant promotes a float32 run to float64; Newton reaches the float32 floor."""
    fn = KEPLER.H
    if name == "LagrangianVI":
        fn = lambda q, v: 0.5 * (v @ v) + 1.0 / jnp.sqrt(q @ q)
    sol = gj.integrate(fn, Q32, P32, method=METHODS[name], h=0.05, n_steps=4)
    assert sol.q.dtype == sol.p.dtype == sol.t.dtype == F32
    assert int(sol.status) == 0


def test_sweep_of_float32_states_runs_in_float32():
    """grid casts h to the states' dtype (a float64 h made the scan carry float64 and failed)."""
    configs = gj.grid(method=gj.CG(1, gj.midpoint()), h=[0.05, 0.1], state=(Q32, P32))
    assert configs.q0.dtype == configs.h.dtype == F32
    result = gj.sweep(KEPLER.H, configs, n_steps=10)
    assert result.q.dtype == result.energy_error.dtype == F32
    assert np.all(np.asarray(result.status) == 0)


def test_cg2_gauss3_conserves_kepler_energy_to_float32_round_off():
    """1000 steps of h = 0.01: measured 2.0 eps32 |H| (float64: 2.8e-13 relative, quadrature
    error). Bound 20 eps32 |H|: a Newton stop above the float32 floor (e.g. at sqrt(eps)) gives 1e-4."""
    sol = gj.integrate(KEPLER.H, Q32, P32, method=gj.CG(2, gj.gauss_legendre(3)), h=0.01, n_steps=1000,
                       save_every=10)
    assert int(sol.status) == 0 and sol.q.dtype == F32
    drift, H0 = energy_drift(KEPLER.H, sol)
    assert drift < 20 * EPS32 * H0, drift / (EPS32 * H0)


def test_nodal_order_of_cg2_is_visible_above_the_float32_floor():
    """cG(2) + 2 Gauss points (order 4) on Kepler e = 0.5 at t = 2: errors 2.1e-4 and 1.3e-5, both
    >= 100 eps32; slope 4.01 as in float64, so 0.1 is loose but not vacuous."""
    hs, ns = (0.1, 0.05), (20, 40)
    # one compiled run vmapped over h, each read at its step n (t = 2)
    method = gj.CG(2, gj.gauss_legendre(2))
    sol = jax.vmap(lambda h: gj.integrate(KEPLER.H, Q32, P32, method=method, h=h, n_steps=max(ns)))(jnp.asarray(hs, F32))
    assert np.all(np.asarray(sol.status) == 0) and sol.q.dtype == F32
    q, p = KEPLER.exact(np.array(2.0))
    errors = [np.max(np.abs(np.concatenate([np.asarray(sol.q[j, n]) - q, np.asarray(sol.p[j, n]) - p])))
              for j, n in enumerate(ns)]
    assert min(errors) > 100 * EPS32
    assert np.polyfit(np.log(hs), np.log(errors), 1)[0] == pytest.approx(4.0, abs=0.1)


def test_discrete_gradient_keeps_float32_energy_as_h_shrinks():
    """Pendulum, 20 000 steps of h = 0.001 in float32. With the excess H(z1) - H(z0) - DH.dz taken
    from H values (``line_points=0``) its cancellation, eps |H| / |dz|^2, costs 9.4e-6 relative
    (it made Newton fail here before the rounding of z1 was corrected); from the Gauss line
    integral (6 points, the default) 2.0e-7. Bounds 1e-6 (5x) and 3e-6 (3x below)."""
    scene = scenes.pendulum()
    q0, p0 = jnp.asarray(scene.q0, F32), jnp.asarray(scene.p0, F32)
    drifts = []
    for method in (gj.DiscreteGradient(), gj.DiscreteGradient(line_points=0)):
        sol = gj.integrate(scene.H, q0, p0, method=method, h=0.001, n_steps=20_000, save_every=100)
        assert int(sol.status) == 0 and sol.q.dtype == F32
        drift, H0 = energy_drift(scene.H, sol)
        drifts.append(drift / H0)
    assert drifts[0] < 1e-6 and drifts[1] > 3e-6, drifts


def test_rule_checks_follow_the_dtype():
    """float32 weights are rounded to eps32: accepted to 32 eps32, not beyond."""
    for n in (2, 5, 12):
        rule = gj.gauss_legendre(n)
        gj.QuadratureRule(jnp.asarray(rule.points, F32), jnp.asarray(rule.weights, F32))
    gj.QuadratureRule(jnp.array([0.3, 0.7], F32), jnp.array([0.5, 0.5 + 1e-6], F32))
    with pytest.raises(ValueError, match="weights must sum to 1"):
        gj.QuadratureRule(jnp.array([0.3, 0.7], F32), jnp.array([0.5, 0.5 + 1e-5], F32))


def test_central_force_check_has_no_false_alarm_in_float32():
    for scene in (KEPLER, scenes.quartic(), scenes.oscillator()):
        _checks.check_central_force(scene.H, jnp.asarray(scene.q0, F32), jnp.asarray(scene.p0, F32))
    with pytest.raises(ValueError, match="DiscreteGradient"):
        H = lambda q, p: 0.5 * (p @ p) + 0.5 * q[0] ** 2 + 2.0 * q[1] ** 2
        _checks.check_central_force(H, Q32, P32)


@pytest.mark.parametrize("scale", [1e30, 1e-30])
def test_float32_states_far_from_one_converge_and_keep_float32_accuracy(scale):
    """Sizes are taken of the unknowns over the state's size, so their squares neither overflow
    (|x| > 1e19) nor underflow (< 1e-19) in float32: a scaled linear oscillator, 50 steps of
    cG(2) + Gauss 2, converges and keeps 1e-6 of the exact solution relative to the scale
    (measured 5e-7 at both scales; before, 1e30 failed with status 2 and 1e-30 stopped after
    one block with 2.6e-4)."""
    H = lambda q, p: 0.5 * (p @ p) + 0.5 * (q @ q)
    q0, p0 = jnp.array([1.0, 0.5], F32) * scale, jnp.array([0.0, 1.0], F32) * scale
    sol = gj.integrate(H, q0, p0, method=gj.CG(2, gj.gauss_legendre(2)), h=0.1, n_steps=50)
    t = 5.0
    exact = np.array([np.cos(t), 0.5 * np.cos(t) + np.sin(t)])
    assert int(sol.status) == 0
    assert np.abs(np.asarray(sol.q[-1], np.float64) / scale - exact).max() < 1e-6
