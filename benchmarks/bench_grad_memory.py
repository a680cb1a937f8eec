"""Memory of reverse-mode gradients over long runs, with and without checkpointing.

    python benchmarks/bench_grad_memory.py

d/dq0 of |q_N|^2 for Kepler with cG(2), Gauss 3, h = 0.01. Without checkpointing the scan
stores, per element, the converged unknowns and what the implicit-function-theorem
adjoint needs (never the Newton iterates); with ``checkpoint=True`` and blocks of ~sqrt(N)
elements it stores one state per block and recomputes a block at a time. Reported: XLA's
temporary buffer size of the compiled gradient (``memory_analysis``), bytes per step, and
the run time of the checkpointed gradient.
"""

import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import write  # noqa: E402

METHOD = gj.CG(2, gj.gauss_legendre(3))
Q0, P0 = jnp.array([0.5, 0.0]), jnp.array([0.0, 3.0**0.5])


def kepler(q, p):
    return 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)


def block_size(n):
    b = max(1, int(np.sqrt(n)))
    while n % b:
        b += 1
    return b


def gradient(n_steps, checkpoint):
    block = block_size(n_steps) if checkpoint else n_steps
    loss = lambda q: jnp.sum(
        gj.integrate(kepler, q, P0, method=METHOD, h=0.01, n_steps=n_steps, save_every=block, checkpoint=checkpoint).q[-1] ** 2
    )
    return jax.jit(jax.grad(loss)).lower(Q0).compile()


def main():
    rows = []
    for n in (1_000, 10_000, 100_000):
        plain, checkpointed = gradient(n, False), gradient(n, True)
        t0 = time.perf_counter()
        jax.block_until_ready(checkpointed(Q0))
        run_s = time.perf_counter() - t0
        row = {
            "n_steps": n,
            "block": block_size(n),
            "temp_bytes_plain": plain.memory_analysis().temp_size_in_bytes,
            "temp_bytes_checkpointed": checkpointed.memory_analysis().temp_size_in_bytes,
            "checkpointed_gradient_run_s": run_s,
        }
        row["bytes_per_step_plain"] = row["temp_bytes_plain"] / n
        row["bytes_per_step_checkpointed"] = row["temp_bytes_checkpointed"] / n
        rows.append(row)
        print(f"N={n:7d}  plain {row['temp_bytes_plain'] / 1e6:8.2f} MB ({row['bytes_per_step_plain']:6.1f} B/step)"
              f"  checkpointed {row['temp_bytes_checkpointed'] / 1e6:6.3f} MB ({row['bytes_per_step_checkpointed']:5.2f} B/step)"
              f"  gradient run {run_s:.2f} s")
    write("grad_memory", {"method": "cG(2), gauss_legendre(3)", "rows": rows})


if __name__ == "__main__":
    main()
