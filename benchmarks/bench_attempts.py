"""Where a PID-controlled run's time goes (issue 22): per attempt, the root finder's iterations
and its fresh Newton matrices, split into accepted attempts, attempts rejected by the estimate
and attempts whose solve failed; and what one Newton matrix costs against one residual.

    python benchmarks/bench_attempts.py

Kepler e = 0.9 and e = 0.99 over 10 orbits from apocentre (as ``bench_adaptive.py`` part a),
cG(k) + Gauss k with ``PIDController(tol, tol)``, and the same run with ``predictive=False``
(diffrax's I controller: steps, rejections, iterations, error, run time). Two passes per run:
the timed one (compile apart, best of several calls) and a counting one, in which
``_solve.block_jacobians`` (the one function that computes Newton matrices) and the
controller's rule report to a host callback; the callbacks slow that pass, so it is not timed.
The cost of a matrix is timed apart, in a ``lax.fori_loop`` of 200, against the residual in
the same loop. Writes results/attempts.json.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS", "VECLIB_MAXIMUM_THREADS"):
    os.environ[_var] = "1"

import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import best_time, compiled, write  # noqa: E402
from galerkin_jax import _adaptive, _solve, scenes  # noqa: E402
from galerkin_jax._march import element_residual  # noqa: E402

RUNS = {6: (1e-4, 1e-5, 1e-6, 1e-8), 8: (1e-3, 1e-5, 1e-6, 1e-7, 1e-9)}
H = scenes.kepler().H


def kepler(e):
    q0, p0 = jnp.asarray([1 + e, 0.0]), jnp.asarray([0.0, np.sqrt((1 - e) / (1 + e))])
    return q0, p0, 2 * np.pi * 10


def run(method, q0, p0, T, tol, predictive=True):
    return gj.integrate(H, q0, p0, method=method, h=1e-3 * T, t1=T,
                        controller=gj.PIDController(tol, tol, predictive=predictive), max_steps=200_000,
                        error_estimate=False)


def final_error(sol, q0, p0):
    """Max-norm distance of the final state from the start: the orbit is closed after 10 periods."""
    return float(jnp.max(jnp.abs(jnp.concatenate([sol.q[-1] - q0, sol.p[-1] - p0]))))


class Counting:
    """A context in which every Newton matrix and every attempt's verdict reach the host:
    ``attempts`` rows ``(accepted, solved, the run's iterations before the attempt, the run's
    matrices after it)``."""

    def __enter__(self):
        self.matrices, self.attempts = 0, []
        self._jacobians, self._rule = _solve.block_jacobians, _adaptive._pid_rule

        def jacobians(residual, Z):
            jax.debug.callback(self._matrix, ordered=True)
            return self._jacobians(residual, Z)

        def rule_factory(*args):
            rule, memory = self._rule(*args)

            def rule_counted(c, step):
                verdict = rule(c, step)
                jax.debug.callback(self._attempt, verdict["accept"], step["solved"], c["total"], ordered=True)
                return verdict

            return rule_counted, memory

        _solve.block_jacobians, _adaptive._pid_rule = jacobians, rule_factory
        jax.clear_caches()  # trace again, through the wrappers
        return self

    def _matrix(self):
        self.matrices += 1

    def _attempt(self, accepted, solved, total):
        self.attempts.append((bool(accepted), bool(solved), int(total), self.matrices))

    def __exit__(self, *exc):
        _solve.block_jacobians, _adaptive._pid_rule = self._jacobians, self._rule
        jax.clear_caches()


def per_attempt(counting, total_iterations):
    """Iterations and matrices of each attempt, by category."""
    rows = np.asarray(counting.attempts, dtype=float)
    # an attempt reports after its solve, with the run's iterations before it and the matrices after it
    iterations = np.diff(np.append(rows[:, 2], total_iterations))
    matrices = np.diff(np.insert(rows[:, 3], 0, 0.0))
    accepted, solved = rows[:, 0] > 0, rows[:, 1] > 0
    out = {}
    for name, mask in (("accepted", accepted), ("rejected by the estimate", ~accepted & solved),
                       ("solve failed", ~solved)):
        out[name] = dict(attempts=int(mask.sum()),
                         iterations_per_attempt=float(iterations[mask].mean()) if mask.any() else None,
                         matrices_per_attempt=float(matrices[mask].mean()) if mask.any() else None)
    return out


def matrix_cost(k, e):
    """µs of one Newton matrix (n JVPs of the residual, and its inverse) and of one residual,
    each in a fori_loop of 200 (one dispatch), at the first element of the run."""
    q0, p0, T = kepler(e)
    method = gj.CG(k, gj.gauss_legendre(k))
    fn = element_residual(H)
    params = jax.tree.map(lambda x: jnp.asarray(x)[None], (method, q0, p0, jnp.asarray(1e-3 * T), None))
    residual = lambda Z: jax.vmap(fn)(Z, params)
    Z0 = method.initial_guess(q0, p0)[None]
    loops = 200

    def looped(work):
        return jax.jit(lambda Z: jax.lax.fori_loop(0, loops, lambda i, Z: Z + 1e-300 * work(Z), Z))

    pieces = {"residual": residual,
              "jacobian": lambda Z: jnp.sum(_solve.block_jacobians(residual, Z), axis=-1).reshape(Z.shape),
              "jacobian and inverse": lambda Z: jnp.sum(jnp.linalg.inv(_solve.block_jacobians(residual, Z)),
                                                        axis=-1).reshape(Z.shape),
              "nothing": lambda Z: Z}
    times = {name: best_time(looped(work), Z0, repeat=5, min_s=0.2) for name, work in pieces.items()}
    us = {name: 1e6 * (t - times["nothing"]) / loops for name, t in times.items() if name != "nothing"}
    return dict(unknowns=int(Z0[0].size), **{f"{name}_us": v for name, v in us.items()},
                matrix_over_residual=us["jacobian and inverse"] / us["residual"])


def main():
    start = time.perf_counter()
    records = []
    for e in (0.9, 0.99):
        q0, p0, T = kepler(e)
        for k, tols in RUNS.items():
            method = gj.CG(k, gj.gauss_legendre(k))
            compile_s, call = compiled(lambda q0, p0, tol: run(method, q0, p0, T, tol), q0, p0, jnp.asarray(tols[0]))
            _, call_i = compiled(lambda q0, p0, tol: run(method, q0, p0, T, tol, False), q0, p0, jnp.asarray(tols[0]))
            for tol in tols:
                sol = call(q0, p0, jnp.asarray(tol))
                run_s = best_time(call, q0, p0, jnp.asarray(tol), repeat=5, min_s=0.2)
                with Counting() as counting:
                    counted = jax.jit(lambda q0, p0, tol: run(method, q0, p0, T, tol))(q0, p0, jnp.asarray(tol))
                assert int(counted.stats["num_accepted_steps"]) == int(sol.stats["num_accepted_steps"])  # the same run
                attempts = int(sol.stats["num_accepted_steps"]) + int(sol.stats["num_rejected_steps"])
                error = final_error(sol, q0, p0)
                rec = dict(e=e, method=f"cG({k})+Gauss {k}", tol=tol, status=int(sol.status), attempts=attempts,
                           error=error, run_ms=1e3 * run_s, compile_s=compile_s, us_per_attempt=1e6 * run_s / attempts,
                           matrices=counting.matrices, iterations=int(sol.stats["num_newton_iterations"]),
                           by_category=per_attempt(counting, int(sol.stats["num_newton_iterations"])))
                sol_i = call_i(q0, p0, jnp.asarray(tol))
                rec["i_control"] = dict(  # the same run with predictive=False (diffrax's controller)
                    steps=int(sol_i.stats["num_accepted_steps"]), rejected=int(sol_i.stats["num_rejected_steps"]),
                    iterations=int(sol_i.stats["num_newton_iterations"]),
                    error=final_error(sol_i, q0, p0),
                    run_ms=1e3 * best_time(call_i, q0, p0, jnp.asarray(tol), repeat=5, min_s=0.2))
                records.append(rec)
                acc = rec["by_category"]["accepted"]
                print(f"e={e} cG({k}) tol {tol:.0e}: error {error:.1e}, {attempts} attempts, {1e3 * run_s:.2f} ms "
                      f"({rec['us_per_attempt']:.1f} µs/attempt), {counting.matrices} Newton matrices; accepted: "
                      f"{acc['iterations_per_attempt']:.1f} iterations, {acc['matrices_per_attempt']:.2f} matrices "
                      f"per attempt; rejected {int(sol.stats['num_rejected_steps'])}, I control: "
                      f"{rec['i_control']['rejected']} of {rec['i_control']['steps'] + rec['i_control']['rejected']}, "
                      f"{rec['i_control']['run_ms']:.2f} ms", flush=True)
    costs = {f"cG({k})": matrix_cost(k, 0.9) for k in RUNS}
    for name, c in costs.items():
        print(f"{name}: {c['unknowns']} unknowns, residual {c['residual_us']:.2f} µs, Newton matrix "
              f"{c['jacobian and inverse_us']:.1f} µs ({c['matrix_over_residual']:.0f} residuals)", flush=True)
    write("attempts", dict(runs=records, matrix_cost=costs, total_s=time.perf_counter() - start))


if __name__ == "__main__":
    main()
