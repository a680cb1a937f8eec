"""Throughput of batched sweeps against one-by-one runs (Kepler, cG(2), Gauss 3).

    python benchmarks/bench_sweep.py [--steps 10000] [--sizes 1 64 256 1024]

Configurations vary the eccentricity (0.1 ... 0.7) and h (0.005 ... 0.02). For each batch
size B: compile time, run time, and the per-configuration speed-up over running the same
configurations one by one, (a) with the compiled B = 1 sweep (same solver, same diagnostics)
and (b) with the compiled ``gj.integrate`` (the single-trajectory Newton, final state only).
Also measured: Newton iterations per member against the batch's count (the batch's loop runs
until its slowest member has converged).
"""

import argparse
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import timed, write  # noqa: E402

METHOD = gj.CG(2, gj.gauss_legendre(3))


def kepler(q, p):
    return 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)


def configs(size, seed=0):
    rng = np.random.default_rng(seed)
    e = rng.uniform(0.1, 0.7, size)
    h = rng.uniform(0.005, 0.02, size)
    q0 = np.stack([1 - e, np.zeros(size)], axis=1)
    p0 = np.stack([np.zeros(size), np.sqrt((1 + e) / (1 - e))], axis=1)
    return gj.Configs(method=gj.stack_methods([METHOD] * size), q0=jnp.asarray(q0), p0=jnp.asarray(p0), h=jnp.asarray(h))


def run(n_steps):
    return lambda c: gj.sweep(kepler, c, n_steps=n_steps).energy_error


def iteration_waste(size, n_steps):
    """Mean Newton iterations per member and per element, against the batch's count per element."""
    result = jax.jit(lambda c: gj.sweep(kepler, c, n_steps=n_steps))(configs(size, seed=1))
    mean = float(result.num_newton_iterations.mean()) / n_steps
    batch = float(result.batch_newton_iterations[0]) / n_steps
    return {"mean_iterations_per_member": mean, "mean_batch_iterations_per_step": batch,
            "wasted_fraction": 1 - mean / batch}


def one_by_one(fn, sample, count, repeat=3):
    """Seconds per configuration, running ``count`` configurations one at a time, compiled
    once; the best of ``repeat`` passes."""
    pieces = [jax.tree.map(lambda x: x[i : i + 1], sample) for i in range(count)]
    compiled = jax.jit(fn).lower(pieces[0]).compile()
    jax.block_until_ready(compiled(pieces[0]))
    passes = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for piece in pieces:
            jax.block_until_ready(compiled(piece))
        passes.append((time.perf_counter() - t0) / count)
    return min(passes)


def integrate_final_state(n_steps):
    def run_one(c):
        method = jax.tree.map(lambda x: x[0], c.method)
        sol = gj.integrate(kepler, c.q0[0], c.p0[0], method=method, h=c.h[0], n_steps=n_steps, save_every=n_steps)
        return sol.q[-1]

    return run_one


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 256, 1024])
    parser.add_argument("--one-by-one", type=int, default=8, help="configurations timed one by one")
    options = parser.parse_args()
    fn = run(options.steps)
    rows = {}
    for size in options.sizes:
        compile_s, run_s = timed(fn, configs(size), repeat=2 if size > 256 else 3)
        rows[size] = {"compile_s": compile_s, "run_s": run_s, "run_s_per_config": run_s / size}
        print(f"B={size:5d} compile {compile_s:6.2f} s  run {run_s:8.3f} s  per config {1e3 * run_s / size:8.3f} ms", flush=True)
    sample = configs(options.one_by_one, seed=2)
    baselines = {"sweep_B1": one_by_one(fn, sample, options.one_by_one),
                 "integrate": one_by_one(integrate_final_state(options.steps), sample, options.one_by_one)}
    for size, row in rows.items():
        for name, seconds in baselines.items():
            row[f"speedup_per_config_vs_one_by_one_{name}"] = seconds / row["run_s_per_config"]
        row["run_ratio_to_B1"] = row["run_s"] / rows[options.sizes[0]]["run_s"]
    for name, seconds in baselines.items():
        print(f"one by one ({name}): {1e3 * seconds:.3f} ms per config")
    for size, row in rows.items():
        print(f"B={size:5d} speed-up per config vs one by one: "
              f"{row['speedup_per_config_vs_one_by_one_sweep_B1']:6.1f}x (sweep B=1), "
              f"{row['speedup_per_config_vs_one_by_one_integrate']:6.1f}x (integrate)")
    waste = iteration_waste(256, 1000)
    print(f"Newton iterations (B=256, 1000 steps): {waste}")
    write("sweep", {"n_steps": options.steps, "method": "cG(2), gauss_legendre(3)", "one_by_one_s_per_config": baselines,
                    "sizes": rows, "newton_iterations": waste})


if __name__ == "__main__":
    main()
