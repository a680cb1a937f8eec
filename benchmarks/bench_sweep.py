"""Throughput of batched sweeps against one-by-one runs (Kepler, cG(2), Gauss 3).

    python benchmarks/bench_sweep.py [--steps 10000] [--sizes 1 64 256 1024]

Configurations vary the eccentricity (0.1 ... 0.7) and h (0.005 ... 0.02). For each batch
size B: compile time, run time, and the per-configuration speed-up over running the same
configurations one by one with the compiled B = 1 sweep. Also measured: Newton iterations
per member against the batch maximum (a vmapped while_loop runs until its slowest member
has converged).
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
from galerkin_jax._integrate import solve_element  # noqa: E402

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
    """Mean Newton iterations per member and per step, against the batch maximum per step."""

    def member(q0, p0, h):
        def one(carry, _):
            q, p, previous = carry
            q1, p1, Z, iterations, _ = solve_element(METHOD, kepler, q, p, h, previous, 32)
            return (q1, p1, (q, p, Z)), iterations

        return jax.lax.scan(one, (q0, p0, (q0, p0, METHOD.initial_guess(q0, p0))), None, length=n_steps)[1]

    c = configs(size, seed=1)
    iterations = np.asarray(jax.jit(jax.vmap(member))(c.q0, c.p0, c.h))  # (size, n_steps)
    mean, batch_max = iterations.mean(), iterations.max(axis=0).mean()
    return {"mean_iterations_per_member": float(mean), "mean_batch_max_per_step": float(batch_max),
            "wasted_fraction": float(1 - mean / batch_max)}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 256, 1024])
    parser.add_argument("--one-by-one", type=int, default=8, help="configurations timed one by one")
    options = parser.parse_args()
    fn = run(options.steps)
    rows = {}
    for size in options.sizes:
        compile_s, run_s = timed(fn, configs(size), repeat=1 if size > 64 else 3)
        rows[size] = {"compile_s": compile_s, "run_s": run_s, "run_s_per_config": run_s / size}
        print(f"B={size:5d} compile {compile_s:6.2f} s  run {run_s:8.3f} s  per config {1e3 * run_s / size:8.3f} ms", flush=True)
    single = jax.jit(fn).lower(configs(1)).compile()
    sample = configs(options.one_by_one, seed=2)
    pieces = [jax.tree.map(lambda x: x[i : i + 1], sample) for i in range(options.one_by_one)]
    jax.block_until_ready(single(pieces[0]))
    t0 = time.perf_counter()
    for piece in pieces:
        jax.block_until_ready(single(piece))
    one_by_one = (time.perf_counter() - t0) / options.one_by_one
    for size, row in rows.items():
        row["speedup_per_config_vs_one_by_one"] = one_by_one / row["run_s_per_config"]
        row["run_ratio_to_B1"] = row["run_s"] / rows[options.sizes[0]]["run_s"]
    print(f"one by one: {1e3 * one_by_one:.3f} ms per config")
    for size, row in rows.items():
        print(f"B={size:5d} speed-up per config vs one by one: {row['speedup_per_config_vs_one_by_one']:6.1f}x")
    waste = iteration_waste(256, 1000)
    print(f"Newton iterations (B=256, 1000 steps): {waste}")
    write("sweep", {"n_steps": options.steps, "method": "cG(2), gauss_legendre(3)", "one_by_one_s_per_config": one_by_one,
                    "sizes": rows, "newton_iterations": waste})


if __name__ == "__main__":
    main()
