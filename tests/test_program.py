"""The compiled program: its size against a recorded budget, and no compilation where only values change.

Compile time is a cost a user pays on every new configuration, and XLA's part of it grows with
the program (about 4-8 ms per kernel on the two-core machine: ``benchmarks/bench_compile.py``).
A timing would be noisy; the size of the lowered program is not: lowering is deterministic, so
``test_programs_stay_within_their_budget`` fails wherever a change bloats a standard program.
"""

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import scenes
from conftest import COMPILE_FLAGS
from helpers import kepler

# StableHLO operations (SSA definitions of the lowered module) of five standard programs, as
# measured with JAX 0.10.2 (benchmarks/results/compile.json has the first four programs' kernels),
# and the margin a change may add before the test asks for a look (and a new budget, if the
# growth is wanted). "kepler PID gradient": reverse mode through a controlled run with save
# times and an event (the adjoint sweep, the save times' and the event's parts), 12838 operations
# when recorded, 3x the fixed steps' gradient. "fput explicit": Stormer-Verlet's closed form
# (``_explicit``), no root finder: 787 operations (205 of them without the error estimate),
# against 3311 for the same elements iterated.
BUDGETS = {"fput fixed": 2821, "kepler PID": 4196, "kepler fixed": 4141, "kepler gradient": 4312,
           "kepler PID gradient": 12838, "fput explicit": 787}
MARGIN = 1.10


def operations(fn, *args):
    """The operations of ``jax.jit(fn)`` lowered at ``args``."""
    return sum(" = " in line for line in jax.jit(fn).lower(*args).as_text().splitlines())


def _programs():
    H, q0, p0 = kepler(0.6)
    cg6 = gj.CG(6, gj.gauss_legendre(6))
    fput = scenes.fput(64)
    fixed = lambda H, method: lambda q0, p0: gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=1000)
    pid = lambda q0, p0: gj.integrate(H, q0, p0, method=cg6, h=0.01, t1=6.0, controller=gj.PIDController(1e-10, 1e-10))
    gradient = jax.grad(lambda q0, p0: jnp.sum(fixed(H, cg6)(q0, p0).q[-1] ** 2))
    # save_at ends at t1, so q[-1] is the final state; the event (the crossings of the x axis, one
    # within t1) is found in the forward run that the gradient's program holds
    controlled = lambda q0, p0: gj.integrate(H, q0, p0, method=gj.CG(4, gj.gauss_legendre(4)), h=0.01, t1=6.0,
                                             controller=gj.PIDController(1e-10, 1e-10),
                                             save_at=jnp.linspace(1.0, 6.0, 6),
                                             events=gj.Event(lambda t, q, p: q[1], capacity=4))
    pid_gradient = jax.grad(lambda q0, p0: jnp.sum(controlled(q0, p0).q[-1] ** 2))
    return {"kepler fixed": (fixed(H, cg6), q0, p0), "kepler PID": (pid, q0, p0),
            "fput fixed": (fixed(fput.H, gj.CG(4, gj.gauss_legendre(4))), jnp.asarray(fput.q0), jnp.asarray(fput.p0)),
            "fput explicit": (fixed(fput.H, gj.GalerkinVI(1, gj.trapezoid())), jnp.asarray(fput.q0),
                              jnp.asarray(fput.p0)),
            "kepler gradient": (gradient, q0, p0), "kepler PID gradient": (pid_gradient, q0, p0)}


@pytest.mark.parametrize("name", sorted(BUDGETS))
def test_programs_stay_within_their_budget(name):
    fn, *args = _programs()[name]
    within_budget(name, operations(fn, *args), BUDGETS[name], "operations")


def within_budget(name, count, budget, unit):
    """``count`` at most ``MARGIN`` times ``budget``, and at least 0.8 times it: a budget far above
    the program hides the next bloat, so a program that shrinks records its new size."""
    assert count <= MARGIN * budget, f"{name}: {count} {unit}, budget {budget} (+10 %)"
    assert count >= 0.8 * budget, f"{name}: {count} {unit}, budget {budget}: record the new size"


def kernels(fn, *args):
    """The kernels (fusions) XLA compiles for ``jax.jit(fn)`` at ``args``: what sets its compile time."""
    return jax.jit(fn).lower(*args).compile().as_text().count(" fusion(")


def _kernel_programs():
    """Every run kind on Kepler (cG(4) + Gauss 4, the whole ``Solution`` returned, so nothing
    it computes is left out), a gradient of each step rule, a sweep, and methods in closed
    form with and without their error estimate."""
    H, q0, p0 = kepler(0.6)
    cg4 = gj.CG(4, gj.gauss_legendre(4))
    verlet = gj.GalerkinVI(1, gj.trapezoid())
    pid = gj.PIDController(1e-10, 1e-10)
    run = lambda **kw: lambda q0, p0: gj.integrate(H, q0, p0, **({"method": cg4, "h": 0.01, "t1": 6.0} | kw))
    grad = lambda **kw: jax.grad(lambda q0, p0: jnp.sum(run(**kw)(q0, p0).q[-1] ** 2))
    configs = gj.grid(method=cg4, h=[0.01, 0.02], state=[(q0, p0), (q0, 0.99 * p0)])
    return {
        "fixed": (run(), q0, p0),
        "PID": (run(controller=pid), q0, p0),
        "TimeTransform": (run(controller=gj.TimeTransform(), h=0.05), q0, p0),
        "PID, save_at, event": (run(controller=pid, save_at=jnp.linspace(1.0, 6.0, 6),
                                    events=gj.Event(lambda t, q, p: q[1], capacity=4)), q0, p0),
        "dense": (run(dense=True), q0, p0),
        "sweep": (lambda configs: gj.sweep(H, configs, n_steps=600), configs),
        "fixed gradient": (grad(), q0, p0),
        "PID gradient": (grad(controller=pid), q0, p0),
        "Verlet": (run(method=verlet), q0, p0),
        "Verlet, no estimate": (run(method=verlet, error_estimate=False), q0, p0),
        "kahan_li8": (run(method=gj.Composition(verlet, "kahan_li8")), q0, p0),
        "kahan_li8, no estimate": (run(method=gj.Composition(verlet, "kahan_li8"), error_estimate=False), q0, p0),
        "Tao kahan_li8": (run(method=gj.Composition(gj.Tao(), "kahan_li8")), q0, p0),
    }


# Kernels of each ``_kernel_programs`` program, as measured with JAX 0.10.2 on CPU under the suite's
# compile options (``conftest.COMPILE_FLAGS``; XLA's defaults fuse differently: 164 kernels for
# "fixed", ``benchmarks/results/compile.json``). XLA compiles each kernel in about 4-8 ms. A method
# in closed form with its default error estimate (the embedded estimate per element, the full
# one on the four elements where it peaks) compiles 37 kernels more than without (Verlet 55
# against 18); a composition builds its elements' Hermite cubics from the increments it has
# (``polynomial_with``), so its estimate costs about what Verlet's does (kahan_li8 119 against
# 76; with the default options 282 against 97 when the stages were computed again for it).
KERNELS = {"fixed": 141, "PID": 155, "TimeTransform": 262, "PID, save_at, event": 228, "dense": 170,
           "sweep": 220, "fixed gradient": 140, "PID gradient": 263, "Verlet": 55, "Verlet, no estimate": 18,
           "kahan_li8": 119, "kahan_li8, no estimate": 76, "Tao kahan_li8": 212}


@pytest.mark.skipif(not all(flag in os.environ.get("XLA_FLAGS", "") for flag in COMPILE_FLAGS),
                    reason="the kernels were counted under the suite's compile options")
@pytest.mark.parametrize("name", sorted(KERNELS))
def test_every_run_kind_compiles_within_its_kernel_budget(name):
    fn, *args = _kernel_programs()[name]
    within_budget(name, kernels(fn, *args), KERNELS[name], "kernels")


def test_a_direction_known_when_traced_is_a_constant_of_the_program():
    """A run's direction sigma = sign(t1 - t0) is a Python constant where t0 and t1 are known when
    the run is traced, so a run forwards compiles as it did before a traced direction could run
    (a controlled run with save times, an event and dense output, and its gradient: 4635 and
    9770 operations, JAX 0.10.2; 4631 and 9763 before ``SolverOptions.tolerance`` became a
    value of the program, 4618 and 9745 before the one element computation,
    ``_march.element``, and the increments of the estimate's peak elements); the run's record
    of its largest relative error, which decides
    ``Status.INACCURATE``, is 28 and 30 of them); a traced t1 carries sigma through the run
    and its program is larger (measured: +1 % and +1 %)."""
    q0, p0 = jnp.array([1.0]), jnp.array([0.0])
    H = lambda q, p: 0.5 * (p @ p + q @ q)
    event = gj.Event(lambda t, q, p: q[0] - 0.3 * t, capacity=4)

    def run(q0, p0, t1):
        return gj.integrate(H, q0, p0, method=gj.CG(3, gj.gauss_legendre(3)), h=0.1, t1=t1, events=event,
                            dense=True, controller=gj.PIDController(1e-8, 1e-8), save_at=t1 * jnp.array([0.25, 0.5]))

    gradient = lambda t1: jax.grad(lambda q0, p0: run(q0, p0, t1).q[-1, 0])
    for fn, recorded in [(lambda q0, p0: run(q0, p0, 2.0), 4635), (gradient(2.0), 9770)]:
        count = operations(fn, q0, p0)
        assert 0.98 * recorded <= count <= recorded, (count, recorded)
    traced = operations(lambda q0, p0, t1: run(q0, p0, t1), q0, p0, 2.0)
    assert 1.0 < traced / operations(lambda q0, p0: run(q0, p0, 2.0), q0, p0) < 1.05


class Compilations:
    """Counts XLA compilations (``jax.monitoring``'s backend-compile events)."""

    def __init__(self):
        self.count = 0
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            self.count += 1

    def of(self, run):
        before = self.count
        jax.block_until_ready(run())
        return self.count - before


COMPILATIONS = Compilations()


def _run(H, q0, p0, **kwargs):
    return lambda: gj.integrate(H, q0, p0, **kwargs)


@pytest.mark.parametrize("case", ["method built anew", "other tolerances", "other t1", "other save_at",
                                  "other t1, time-transformed", "other t1, fixed steps reserved",
                                  "other n_steps, reserved", "other h, fixed steps", "other solver tolerance",
                                  "other solver tolerance, PID", "other state"])
def test_runs_that_differ_only_in_values_do_not_compile_again(case):
    H, q0, p0 = kepler(0.6)
    cg = lambda: gj.CG(4, gj.gauss_legendre(4))
    pid = lambda tol: gj.PIDController(rtol=tol, atol=tol)
    first, second = {
        "method built anew": (dict(method=cg(), h=0.01, n_steps=50), dict(method=cg(), h=0.01, n_steps=50)),
        "other tolerances": (dict(method=cg(), h=0.01, t1=2.0, controller=pid(1e-8)),
                             dict(method=cg(), h=0.02, t1=2.0, controller=pid(1e-6))),
        "other t1": (dict(method=cg(), h=0.01, t1=2.0, controller=pid(1e-8)),
                     dict(method=cg(), h=0.01, t1=3.0, controller=pid(1e-8))),
        "other save_at": (dict(method=cg(), h=0.01, t1=2.0, controller=pid(1e-8), save_at=jnp.linspace(0.0, 2.0, 5)),
                          dict(method=cg(), h=0.01, t1=2.0, controller=pid(1e-8), save_at=jnp.linspace(0.5, 1.5, 5))),
        "other t1, time-transformed": (dict(method=cg(), h=0.1, t1=2.0, controller=gj.TimeTransform()),
                                       dict(method=cg(), h=0.1, t1=3.0, controller=gj.TimeTransform())),
        "other t1, fixed steps reserved": (dict(method=cg(), h=0.01, t1=2.0, max_steps=400),
                                           dict(method=cg(), h=0.01, t1=3.5, max_steps=400)),
        "other n_steps, reserved": (dict(method=cg(), h=0.01, n_steps=120, max_steps=400),
                                    dict(method=cg(), h=0.01, n_steps=350, max_steps=400)),
        "other h, fixed steps": (dict(method=cg(), h=0.01, n_steps=50), dict(method=cg(), h=0.02, n_steps=50)),
        "other solver tolerance": (dict(method=cg(), h=0.01, n_steps=50),
                                   dict(method=cg(), h=0.01, n_steps=50, solver=gj.SolverOptions(tolerance=1e-8))),
        "other solver tolerance, PID": (dict(method=cg(), h=0.01, t1=2.0, controller=pid(1e-8),
                                             solver=gj.SolverOptions(tolerance=1e-10)),
                                        dict(method=cg(), h=0.01, t1=2.0, controller=pid(1e-8),
                                             solver=gj.SolverOptions(tolerance=1e-6))),
        "other state": (dict(method=cg(), h=0.01, n_steps=50), dict(method=cg(), h=0.01, n_steps=50)),
    }[case]
    COMPILATIONS.of(_run(H, q0, p0, **first))
    q1, p1 = (q0, 0.99 * p0) if case == "other state" else (q0, p0)
    jax.block_until_ready(p1)  # the scaling compiles a program of its own, which is not the run's
    assert COMPILATIONS.of(_run(H, q1, p1, **second)) == 0


def test_fixed_steps_to_t1_within_their_reserve_end_at_t1_and_beyond_it_stop_with_max_steps():
    """``max_steps`` with fixed steps to t1 reserves the elements (so that another t1 compiles
    nothing): within it the run equals the one without; beyond it, it stops after the reserve
    with status MAX_STEPS and the state there, where ``n_steps`` full elements end."""
    H, q0, p0 = kepler(0.6)
    method = gj.CG(4, gj.gauss_legendre(4))
    exact_count = gj.integrate(H, q0, p0, method=method, h=0.01, t1=3.005)
    reserved = gj.integrate(H, q0, p0, method=method, h=0.01, t1=3.005, max_steps=400)
    assert int(reserved.status) == 0 and float(reserved.t[-1]) == 3.005
    assert int(reserved.stats["num_accepted_steps"]) == int(exact_count.stats["num_accepted_steps"]) == 301
    np.testing.assert_allclose(reserved.q[-1], exact_count.q[-1], rtol=0, atol=1e-15)
    short = gj.integrate(H, q0, p0, method=method, h=0.01, t1=3.005, max_steps=200)
    full = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=200)
    assert int(short.status) == gj.Status.MAX_STEPS and int(short.stats["num_accepted_steps"]) == 200
    np.testing.assert_allclose(float(short.t[-1]), 2.0, rtol=1e-15)
    np.testing.assert_array_equal(short.q[-1], full.q[-1])


def test_a_sweep_to_another_t1_within_its_reserve_compiles_nothing_and_equals_the_sweep_without():
    """``sweep``'s ``max_steps`` with fixed steps to t1 reserves the elements, so another t1
    runs the program compiled for the first; each member ends where the sweep that counts its
    elements from t1 ends it (the same elements, the last shortened to land on t1)."""
    H, q0, p0 = kepler(0.6)
    configs = gj.grid(method=[gj.CG(3, gj.gauss_legendre(3))], h=[0.01, 0.02], state=[(q0, p0)])
    run = lambda t1, **kw: gj.sweep(H, configs, t1=t1, **kw)
    COMPILATIONS.of(lambda: run(1.005, max_steps=300).q)
    assert COMPILATIONS.of(lambda: run(2.5, max_steps=300).q) == 0
    np.testing.assert_allclose(run(2.5, max_steps=300).q, run(2.5).q, rtol=0, atol=1e-14)
    traced = jax.jit(lambda h: gj.sweep(H, dataclasses.replace(configs, h=h), t1=2.5, max_steps=300).q)
    np.testing.assert_allclose(traced(configs.h), run(2.5).q, rtol=0, atol=1e-14)  # traced step sizes


def test_n_steps_within_a_reserve_equal_the_run_without_and_beyond_it_stop_with_max_steps():
    """``n_steps`` with ``max_steps`` is a value (traced under jit and vmap, one program for
    every count): within the reserve the run equals the one of n_steps elements without it
    (the same elements, so to the last bit), its saves past the end repeat the end state at
    t0 + n_steps h; beyond it the run stops after the reserve with status MAX_STEPS; a negative
    traced count is INVALID_INPUT with NaN states."""
    H, q0, p0 = kepler(0.6)
    method = gj.CG(4, gj.gauss_legendre(4))
    plain = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=120)
    reserved = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=120, max_steps=200)
    assert reserved.q.shape == (201, 2) and int(reserved.status) == 0
    assert int(reserved.stats["num_accepted_steps"]) == 120
    np.testing.assert_array_equal(reserved.q[:121], plain.q)
    np.testing.assert_array_equal(reserved.q[121:], jnp.broadcast_to(plain.q[-1], (80, 2)))
    np.testing.assert_allclose(reserved.t[120:], 1.2, rtol=1e-15)
    short = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=300, max_steps=200)
    full = gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=200)
    assert int(short.status) == gj.Status.MAX_STEPS
    np.testing.assert_array_equal(short.q[-1], full.q[-1])
    end = jax.jit(jax.vmap(lambda n: gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=n, max_steps=200,
                                                  save_every=200)))(jnp.array([120, 200, -1]))
    np.testing.assert_array_equal(end.q[:2, -1], jnp.stack([plain.q[-1], full.q[-1]]))
    assert end.status.tolist() == [0, 0, gj.Status.INVALID_INPUT] and bool(jnp.isnan(end.q[2, -1]).all())
    count = lambda n, **kw: gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=n, **kw).q
    with pytest.raises(TypeError, match="integer scalar"):
        jax.jit(lambda n: count(n, max_steps=200))(120.0)
    with pytest.raises(ValueError, match="needs max_steps"):
        jax.jit(count)(120)


_CACHED_RUN = """
import sys, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import galerkin_jax as gj
gj.use_compilation_cache(sys.argv[1])
programs, hits = [], []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **kw: programs.append(event) if event == "/jax/core/compile/backend_compile_duration" else None)
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(event) if event == "/jax/compilation_cache/cache_hits" else None)
H = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
sol = gj.integrate(H, jnp.array([0.4, 0.0]), jnp.array([0.0, 2.0]), method=gj.CG(3, gj.gauss_legendre(3)), h=0.01,
                   t1=1.0, controller=gj.PIDController(1e-8, 1e-8))
print(len(programs), len(hits), int(sol.status))
"""


def test_a_second_process_with_the_compilation_cache_compiles_nothing(tmp_path):
    """``gj.use_compilation_cache(folder)``: the first process compiles its programs (the run,
    and the small ones of the checks before it) and keeps them; a second one loads them all."""
    import subprocess
    import sys

    runs = [subprocess.run([sys.executable, "-c", _CACHED_RUN, str(tmp_path)], capture_output=True, text=True,
                           timeout=600) for _ in range(2)]
    assert all(run.returncode == 0 for run in runs), runs[-1].stderr[-2000:]
    (programs, hits, status), (programs_again, hits_again, _) = (map(int, run.stdout.split()[-3:]) for run in runs)
    assert status == 0 and programs >= 1 and hits == 0
    assert programs_again == hits_again == programs  # each program of the second process loaded
    assert any(tmp_path.iterdir())


def test_the_suite_keeps_no_compiled_program_on_disk():
    """``conftest`` sets ``GALERKIN_JAX_CACHE`` empty: the README tour's
    ``gj.use_compilation_cache()`` (run by test_docs) then turns no cache on, where it wrote a
    worker's every later program into ~/.cache/galerkin_jax and loaded earlier runs' from it."""
    assert gj.use_compilation_cache() is None
    assert jax.config.jax_compilation_cache_dir is None
