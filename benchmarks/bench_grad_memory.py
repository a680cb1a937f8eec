"""Memory and time of reverse-mode gradients: the tangent solve of a large element, and
long runs with and without checkpointing.

    python benchmarks/bench_grad_memory.py [--only tangent checkpoint]

tangent: d/dq0 of |q_N|^2 + w . p_N for the beta-FPUT chain of 512 masses (``scenes.fput``,
thermal start, q0 perturbed by 0.1 N(0, 1)), cG(3) + Gauss 3, h = 0.05, ``krylov=True``:
3072 unknowns per element, above the solver's dense limit of 256. The element tangent of
the implicit function theorem by matrix-free GMRES on Jacobian-vector products (the
library's, ``_tangent``) against the dense tangent it replaces (jacfwd and LU per element,
``_tangent.tangent`` called with no dense limit), each compiled separately: XLA's temporary
buffer size of the compiled gradient, compile time, best run time, and the largest
difference between the two gradients relative to the largest entry.

checkpoint: d/dq0 of |q_N|^2 for Kepler with cG(2), Gauss 3, h = 0.01. Without checkpointing the scan
stores, per element, the converged unknowns and what the implicit-function-theorem
adjoint needs (never the Newton iterates); with ``checkpoint=True`` and blocks of ~sqrt(N)
elements it stores one state per block and recomputes a block at a time. Reported: XLA's
temporary buffer size of the compiled gradient (``memory_analysis``), bytes per step, and
the run time of the checkpointed gradient.
"""

import argparse
import pathlib
import sys
import time
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import best_time, compiled, write  # noqa: E402
from galerkin_jax import _solve, _tangent, scenes  # noqa: E402

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


CHAIN, CHAIN_METHOD, CHAIN_H = 512, gj.CG(3, gj.gauss_legendre(3)), 0.05


def chain_gradient(n_steps, dense):
    """The compiled gradient of the chain's loss and its argument; ``dense``: the dense tangent.
    A fresh scene (a fresh H) for each, so that no trace of the other tangent is reused."""
    scene = scenes.fput(CHAIN)
    q0 = jnp.asarray(scene.q0) + 0.1 * jnp.asarray(np.random.default_rng(2).normal(size=CHAIN))
    weights = jnp.arange(CHAIN) / CHAIN

    def loss(q):
        sol = gj.integrate(scene.H, q, jnp.asarray(scene.p0), method=CHAIN_METHOD, h=CHAIN_H, n_steps=n_steps,
                           save_every=n_steps, krylov=True, error_estimate=False)
        return jnp.sum(sol.q[-1] ** 2) + weights @ sol.p[-1], sol.status

    tangent = _tangent.tangent
    everywhere = lambda *args, dense_limit: tangent(*args, dense_limit=2**62)
    with mock.patch.object(_tangent, "tangent", everywhere if dense else tangent):
        compile_s, call = compiled(jax.grad(loss, has_aux=True), q0)
    return compile_s, call, q0


def tangent_part():
    rows = []
    for n_steps in (2, 6):
        row = {"n_steps": n_steps}
        gradients = {}
        for name, dense in (("gmres", False), ("dense", True)):
            compile_s, call, q0 = chain_gradient(n_steps, dense)
            gradient, status = call(q0)
            assert int(status) == 0, status
            gradients[name] = np.asarray(gradient)
            row[name] = {"temp_bytes": call.memory_analysis().temp_size_in_bytes, "compile_s": compile_s,
                         "run_s": best_time(call, q0, repeat=3, budget_s=10.0)}
        row["memory_ratio_dense_over_gmres"] = row["dense"]["temp_bytes"] / row["gmres"]["temp_bytes"]
        row["run_ratio_dense_over_gmres"] = row["dense"]["run_s"] / row["gmres"]["run_s"]
        row["gradient_difference"] = float(np.abs(gradients["gmres"] - gradients["dense"]).max()
                                           / np.abs(gradients["dense"]).max())
        rows.append(row)
        print(f"N = {n_steps}: temporary memory GMRES {row['gmres']['temp_bytes'] / 1e6:.2f} MB, dense "
              f"{row['dense']['temp_bytes'] / 1e6:.1f} MB; compile {row['gmres']['compile_s']:.1f} s and "
              f"{row['dense']['compile_s']:.1f} s; run {row['gmres']['run_s'] * 1e3:.1f} ms and "
              f"{row['dense']['run_s'] * 1e3:.0f} ms; gradients differ by {row['gradient_difference']:.1e}", flush=True)
    first, last = rows
    per_element = {name: (last[name]["temp_bytes"] - first[name]["temp_bytes"]) / (last["n_steps"] - first["n_steps"])
                   for name in ("gmres", "dense")}
    n = 6 * CHAIN
    print(f"per element: GMRES {per_element['gmres'] / 1e3:.0f} kB, dense {per_element['dense'] / 1e6:.0f} MB "
          f"(one n x n float64 matrix: {n * n * 8 / 1e6:.1f} MB)")
    return {"scene": f"beta-FPUT, {CHAIN} masses, cG(3) + Gauss 3, h = {CHAIN_H}, krylov=True",
            "unknowns_per_element": n, "dense_limit": gj.SolverOptions().dense_limit,
            "temp_bytes_per_element": per_element, "rows": rows}


def checkpoint_part():
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
              f"  gradient run {run_s:.2f} s", flush=True)
    return {"method": "cG(2), gauss_legendre(3)", "rows": rows}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--only", nargs="+", choices=("tangent", "checkpoint"), default=("tangent", "checkpoint"))
    only = parser.parse_args().only
    results = {}
    if "tangent" in only:
        results["tangent"] = tangent_part()
    if "checkpoint" in only:
        results["checkpoint"] = checkpoint_part()
    write("grad_memory", results)


if __name__ == "__main__":
    main()
