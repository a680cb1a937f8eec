"""Explicit Stormer-Verlet through ``gj.integrate`` against velocity Verlet in plain JAX.

run: python benchmarks/bench_explicit.py

Per step, on a 13-atom Lennard-Jones cluster (39 unknowns, h = 0.005) and an FPUT chain of
N = 64 masses (alpha = 0.25, h = 0.05), 10,000 steps each: ``gj.integrate(H, ..., method=
GalerkinVI(1, trapezoid()), n_steps, save_every=n_steps, error_estimate=False)`` (the element
in closed form, ``_explicit``) against a lax.scan of kick-drift-kick with the force carried.
The two compiled programs run alternately, ``ROUNDS`` times each, and the best of each is
kept (a loaded machine slows both alike). Compile times apart: the library's run (also with
the default error estimate), the plain Verlet, and diffrax's Tsit5 with the same 10,000 fixed
steps (the compile baseline of issue 44). results/explicit.json.
"""

import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import galerkin_jax as gj
from _common import RESULTS, compiled, machine

jax.config.update("jax_enable_x64", True)

N_STEPS = 10_000
ROUNDS = 30


def lennard_jones():
    """13 atoms near the icosahedral minimum, epsilon = sigma = 1, unit masses."""
    golden = (1 + 5 ** 0.5) / 2
    vertices = [(0, s1, s2 * golden) for s1 in (-1, 1) for s2 in (-1, 1)]
    vertices = [v[i:] + v[:i] for v in vertices for i in range(3)]
    x = np.array([(0.0, 0.0, 0.0)] + vertices) * (1.12 / np.linalg.norm(vertices[0]))
    i, j = np.triu_indices(13, 1)

    def V(q):
        q = q.reshape(13, 3)
        r2 = jnp.sum((q[i] - q[j]) ** 2, axis=1)
        inv6 = r2 ** -3
        return jnp.sum(4.0 * (inv6 ** 2 - inv6))

    rng = np.random.default_rng(0)
    return V, jnp.asarray(x.ravel()), jnp.asarray(0.1 * rng.standard_normal(39)), 0.005


def fput(n=64, alpha=0.25):
    def V(q):
        dq = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return jnp.sum(dq ** 2 / 2 + alpha * dq ** 3 / 3)

    q0 = jnp.asarray(np.sin(np.pi * np.arange(1, n + 1) / (n + 1)))
    return V, q0, jnp.zeros(n), 0.05


def plain_verlet(V, h):
    """Velocity Verlet, kick-drift-kick, one force per step (carried)."""
    force = lambda q: -jax.grad(V)(q)

    def run(q, p):
        def step(c, _):
            q, p, f = c
            p = p + 0.5 * h * f
            q = q + h * p
            f = force(q)
            return (q, p + 0.5 * h * f, f), None

        (q, p, _), _ = jax.lax.scan(step, (q, p, force(q)), None, length=N_STEPS)
        return q, p

    return run


def library_verlet(V, h, error_estimate=False):
    H = lambda q, p: 0.5 * (p @ p) + V(q)
    method = gj.GalerkinVI(1, gj.trapezoid())

    def run(q, p):
        sol = gj.integrate(H, q, p, method=method, h=h, n_steps=N_STEPS, save_every=N_STEPS,
                           error_estimate=error_estimate)
        return sol.q[-1], sol.p[-1], sol.error_estimate

    return run


def diffrax_tsit5(V, h):
    """diffrax's Tsit5 with N_STEPS constant steps of h on Hamilton's equations, the end state."""
    import diffrax

    force = jax.grad(V)

    def run(q, p):
        term = diffrax.ODETerm(lambda t, y, args: (y[1], -force(y[0])))
        sol = diffrax.diffeqsolve(term, diffrax.Tsit5(), 0.0, N_STEPS * h, h, (q, p),
                                  stepsize_controller=diffrax.ConstantStepSize(), max_steps=N_STEPS,
                                  saveat=diffrax.SaveAt(t1=True))
        return sol.ys[0][-1], sol.ys[1][-1]

    return run


def alternating(calls, args, rounds=ROUNDS):
    """The best time of each compiled call, the calls run alternately ``rounds`` times."""
    best = [float("inf")] * len(calls)
    for call in calls:
        jax.block_until_ready(call(*args))
    for _ in range(rounds):
        for i, call in enumerate(calls):
            t0 = time.perf_counter()
            jax.block_until_ready(call(*args))
            best[i] = min(best[i], time.perf_counter() - t0)
    return best


def main():
    results = dict(machine(), n_steps=N_STEPS, rounds=ROUNDS, scenes={})
    for name, scene in (("lennard_jones_13", lennard_jones), ("fput_64", fput)):
        V, q0, p0, h = scene()
        ours_compile, ours = compiled(library_verlet(V, h), q0, p0)
        default_compile, default = compiled(library_verlet(V, h, error_estimate=True), q0, p0)
        base_compile, base = compiled(plain_verlet(V, h), q0, p0)
        tsit5_compile, _ = compiled(diffrax_tsit5(V, h), q0, p0)
        ours_run, default_run, base_run = alternating([ours, default, base], (q0, p0))
        a, b = ours(q0, p0), base(q0, p0)
        results["scenes"][name] = dict(
            unknowns=int(q0.size), h=h, run_s=ours_run, per_step_us=1e6 * ours_run / N_STEPS,
            plain_run_s=base_run, plain_per_step_us=1e6 * base_run / N_STEPS, ratio=ours_run / base_run,
            error_estimate_run_s=default_run, error_estimate_ratio=default_run / base_run,
            compile_s=ours_compile, error_estimate_compile_s=default_compile, plain_compile_s=base_compile,
            tsit5_compile_s=tsit5_compile, compile_over_tsit5=ours_compile / tsit5_compile,
            error_estimate_compile_over_tsit5=default_compile / tsit5_compile,
            max_difference=float(max(jnp.max(jnp.abs(a[0] - b[0])), jnp.max(jnp.abs(a[1] - b[1])))))
        print(name, json.dumps(results["scenes"][name]))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "explicit.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
