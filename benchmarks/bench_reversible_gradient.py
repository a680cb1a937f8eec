"""Memory and time of a long run's gradient by reversibility (``checkpoint="reversible"``)
against the stored gradient (``checkpoint=False``) and block checkpointing (``checkpoint=True``),
and the round-off of the states the reversible pass rebuilds (issue 45, item 3).

    python benchmarks/bench_reversible_gradient.py [--ns 1000 10000 100000]

Not to be confused with bench_reversible.py (a study at 1632fa2) (reversible step-size control, issue 22).

Problem: Kepler, H = |p|^2 / 2 - 1 / |q|, q0 = (1, 0), p0 = (0, 1.2) (e = 0.44, period
~ 8.2), the midpoint rule cG(1) + Gauss 1, h = 0.01; loss |q_N|^2 + sum p_N, its gradient
with respect to (q0, p0). ``checkpoint=False`` and ``"reversible"`` save the end state only
(save_every = N); ``checkpoint=True`` saves every B-th state, B the divisor of N nearest
sqrt(N) (its memory O(N / B + B) is least there). Reported per N and mode: XLA's temporary
buffer size of the compiled gradient (``memory_analysis().temp_size_in_bytes``), compile time,
best run time, and the gradient's largest difference from the stored one relative to its
largest entry. Rebuild: z_0 rebuilt from z_N by N elements of step -h (``_reversible.rebuild``,
exactly the backward pass's reconstruction), max-norm distance to the true z_0, for Kepler and
for the harmonic oscillator H = (q^2 + p^2) / 2 (no shear: the reference for a sqrt(N) walk).
Writes results/reversible_gradient.json.
"""

import argparse
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import compiled, timed, write  # noqa: E402
from galerkin_jax import _reversible  # noqa: E402
from galerkin_jax._march import solver_options  # noqa: E402

METHOD = gj.CG(1, gj.gauss_legendre(1))
H_STEP = 0.01
Q0, P0 = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.2])


def kepler(q, p):
    return 0.5 * jnp.sum(p**2) - 1.0 / jnp.linalg.norm(q)


def oscillator(q, p):
    return 0.5 * jnp.sum(q**2) + 0.5 * jnp.sum(p**2)


def block(n):
    divisors = [b for b in range(1, n + 1) if n % b == 0]
    return min(divisors, key=lambda b: abs(b - np.sqrt(n)))


def gradient(n, mode):
    save_every = block(n) if mode is True else n

    def loss(q0, p0):
        s = gj.integrate(kepler, q0, p0, method=METHOD, h=H_STEP, n_steps=n, save_every=save_every,
                         checkpoint=mode)
        return jnp.sum(s.q[-1] ** 2) + jnp.sum(s.p[-1])

    return jax.grad(loss, argnums=(0, 1)), save_every


def rebuilt(H, n):
    s = gj.integrate(H, Q0, P0, method=METHOD, h=H_STEP, n_steps=n, save_every=n)
    z_end = jnp.concatenate([s.q[-1], s.p[-1]])
    fn = jax.jit(lambda z: _reversible.rebuild(METHOD, H, z, jnp.asarray(H_STEP), None, solver_options(METHOD), n))
    z0, status = fn(z_end)
    assert int(status) == 0
    return float(jnp.max(jnp.abs(z0 - jnp.concatenate([Q0, P0]))))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--ns", type=int, nargs="+", default=[1000, 10000, 100000])
    ns = parser.parse_args().ns
    rows = []
    for n in ns:
        reference = None
        for mode in (False, True, "reversible"):
            fn, save_every = gradient(n, mode)
            compile_s, call = compiled(fn, Q0, P0)
            temp = call.memory_analysis().temp_size_in_bytes
            _, run_s = timed(fn, Q0, P0, repeat=3 if n <= 10000 else 1)
            g = np.concatenate([np.asarray(x) for x in call(Q0, P0)])
            reference = g if mode is False else reference
            row = dict(n_steps=n, checkpoint=mode, save_every=save_every, temp_bytes=int(temp),
                       compile_s=compile_s, run_s=run_s,
                       rel_diff_from_stored=float(np.max(np.abs(g - reference)) / np.max(np.abs(reference))))
            print(row, flush=True)
            rows.append(row)
    rebuild = [dict(n_steps=n, kepler=rebuilt(kepler, n), oscillator=rebuilt(oscillator, n)) for n in ns]
    for r in rebuild:
        print(r, flush=True)
    write("reversible_gradient", dict(problem="Kepler e=0.44, CG(1)+Gauss 1, h=0.01; loss |q_N|^2 + sum p_N",
                                      gradients=rows, rebuild_z0_error=rebuild))


if __name__ == "__main__":
    main()
