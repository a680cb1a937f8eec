"""Learning a Hamiltonian: a training step and a long rollout through each method, beside diffrax Tsit5.

    python -m benchmarks learning [--only particle pendulum] [--iterations 500] [--name learning]

A 4-32-32-1 tanh network H_theta(q, p) (docs/learning.md's model) is fitted to 16 trajectories of
10 steps of h = 0.1 per Adam step (learning rate 1e-2), from data of cG(4) + Gauss 4 at h = 0.01:
particle: a charged particle in a magnetic field and an anharmonic potential (docs/learning.md);
pendulum: the double pendulum (unit masses and lengths, g = 1), H = p^T M(q)^-1 p / 2 - 2 cos q1 -
    cos q2, not separable.
Each method trains its own network for ``--iterations`` Adam steps from the same start and batches:
diffrax Tsit5 (its default adjoint), cG(1) (the implicit midpoint rule) and cG(2) + Gauss 2, each
iterated to round-off and with ``SolverOptions(tolerance=1e-8)``, and cG(2) with
``checkpoint=True``. Per method: the training step's compile time, its run time at the first and
at the trained parameters, the forward run alone, the solve's updates per element, the final
loss; then a rollout of 10^4 steps of h = 0.1 of the trained model from a held-out state (saved
every 10th node): its run time per step and its learned energy's largest change
max |H_theta(z_n) - H_theta(z_0)|. Ratios are against Tsit5's in the same process.
"""

import argparse
import functools

from _common import best_time, compiled, markdown_table, show, write  # first: one BLAS thread

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import galerkin_jax as gj  # noqa: E402

H_STEP, N_DATA, BATCH, ROLLOUT = 0.1, 10, 16, 10_000
LOOSE = gj.SolverOptions(tolerance=1e-8)
CG1, CG2 = gj.CG(1, gj.gauss_legendre(1)), gj.CG(2, gj.gauss_legendre(2))
METHODS = {  # name: integrate's options; None: diffrax Tsit5
    "diffrax Tsit5": None,
    "cG(1)": dict(method=CG1),
    "cG(1), tolerance=1e-8": dict(method=CG1, solver=LOOSE),
    "cG(2) + Gauss 2": dict(method=CG2),
    "cG(2) + Gauss 2, tolerance=1e-8": dict(method=CG2, solver=LOOSE),
    "cG(2) + Gauss 2, checkpoint=True": dict(method=CG2, checkpoint=True),
}


def particle(q, p):
    v = p - 0.5 * jnp.array([-q[1], q[0]])
    return 0.5 * v @ v + 0.5 * q @ q + 0.1 * q[0] ** 4


def pendulum(q, p):
    c = jnp.cos(q[0] - q[1])
    M = jnp.array([[2.0, c], [c, 1.0]])
    return 0.5 * p @ jnp.linalg.solve(M, p) - 2.0 * jnp.cos(q[0]) - jnp.cos(q[1])


SYSTEMS = {"particle": (particle, 1.0), "pendulum": (pendulum, 0.8)}  # H, the initial states' box


def data(H, box, n=64):
    z0 = jax.random.uniform(jax.random.PRNGKey(0), (n, 4), minval=-box, maxval=box)
    exact = jax.vmap(lambda z: gj.integrate(H, z[:2], z[2:], method=gj.CG(4, gj.gauss_legendre(4)), h=H_STEP / 10,
                                            n_steps=10 * N_DATA, save_every=10))(z0)
    assert int(jnp.max(exact.status)) == 0
    return exact.q, exact.p


def H_model(q, p, params):
    x = jnp.concatenate([q, p])
    for layer in params[:-1]:
        x = jnp.tanh(x @ layer["W"] + layer["b"])
    return (x @ params[-1]["W"] + params[-1]["b"])[0]


def init(key, sizes=(4, 32, 32, 1)):
    keys = jax.random.split(key, len(sizes) - 1)
    return [{"W": jax.random.normal(k, (a, b)) / np.sqrt(a), "b": jnp.zeros(b)}
            for k, a, b in zip(keys, sizes[:-1], sizes[1:])]


def tsit5(params, q0, p0, n_steps, every=1):
    """diffrax Tsit5 at constant steps h through H_theta's field: the states every ``every``-th node."""
    def field(t, z, params):
        dq, dp = jax.grad(H_model, argnums=(0, 1))(z[:2], z[2:], params)
        return jnp.concatenate([dp, -dq])

    ts = jnp.arange(0, n_steps + 1, every) * H_STEP
    sol = diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, n_steps * H_STEP, H_STEP,
                              jnp.concatenate([q0, p0]), args=params, saveat=diffrax.SaveAt(ts=ts),
                              max_steps=n_steps + 1)
    return sol.ys[:, :2], sol.ys[:, 2:], jnp.zeros((), jnp.int32)


def galerkin(options, params, q0, p0, n_steps, every=1):
    sol = gj.integrate(H_model, q0, p0, h=H_STEP, n_steps=n_steps, save_every=every, args=params, **options)
    return sol.q, sol.p, sol.stats["num_newton_iterations"]


def runner(options):
    return tsit5 if options is None else functools.partial(galerkin, options)


def training(options, Q, P):
    """The jitted Adam step ``(params, state, Qb, Pb) -> (params, state, loss)`` and the batch's
    forward run ``(params, Qb, Pb) -> (q, p, updates)``."""
    run = runner(options)
    batch_run = lambda params, Qb, Pb: jax.vmap(lambda q0, p0: run(params, q0, p0, N_DATA))(Qb[:, 0], Pb[:, 0])

    def loss(params, Qb, Pb):
        q, p, _ = batch_run(params, Qb, Pb)
        return jnp.mean((q - Qb) ** 2) + jnp.mean((p - Pb) ** 2)

    optimiser = optax.adam(1e-2)

    def update(params, state, Qb, Pb):
        value, grads = jax.value_and_grad(loss)(params, Qb, Pb)
        updates, state = optimiser.update(grads, state, params)
        return optax.apply_updates(params, updates), state, value

    return optimiser, update, batch_run


def measure(name, options, Q, P, iterations):
    optimiser, update, batch_run = training(options, Q, P)
    params = init(jax.random.PRNGKey(1))
    state = optimiser.init(params)
    batches = np.random.default_rng(0).choice(len(Q) - 1, (iterations, BATCH))  # the last state is held out
    Qb, Pb = Q[batches[0]], P[batches[0]]
    compile_s, step = compiled(update, params, state, Qb, Pb)
    _, forward = compiled(batch_run, params, Qb, Pb)
    row = dict(method=name, compile_s=compile_s, step_s=best_time(step, params, state, Qb, Pb),
               forward_s=best_time(forward, params, Qb, Pb))
    for i in batches:
        params, state, value = step(params, state, Q[i], P[i])
    row.update(trained_step_s=best_time(step, params, state, Qb, Pb), trained_forward_s=best_time(forward, params, Qb, Pb),
               final_loss=float(value))
    if options is not None:
        row["updates_per_element"] = float(jnp.mean(forward(params, Qb, Pb)[2])) / N_DATA
    q0, p0 = Q[-1, 0], P[-1, 0]
    rollout_compile_s, rollout = compiled(lambda params: runner(options)(params, q0, p0, ROLLOUT, every=10), params)
    q, p, _ = rollout(params)
    energy = jax.vmap(H_model, in_axes=(0, 0, None))(q, p, params)
    row.update(rollout_compile_s=rollout_compile_s, rollout_step_s=best_time(rollout, params) / ROLLOUT,
               learned_energy_change=float(jnp.max(jnp.abs(energy - energy[0]))))
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(prog="bench_learning.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=list(SYSTEMS), default=list(SYSTEMS))
    parser.add_argument("--iterations", type=int, default=500)
    parser.add_argument("--name", default="learning")
    args = parser.parse_args(argv)
    results, rows = dict(iterations=args.iterations, batch=BATCH, h=H_STEP, n_data=N_DATA, rollout=ROLLOUT), []
    for system in args.only:
        Q, P = data(*SYSTEMS[system])
        print(system, flush=True)
        measured = []
        for name, options in METHODS.items():
            measured.append(measure(name, options, Q, P, args.iterations))
            show(name, measured[-1])
        base = measured[0]
        for row in measured:
            for key in ("step_s", "trained_step_s", "forward_s", "trained_forward_s", "rollout_step_s"):
                row[key[:-2] + "_ratio"] = row[key] / base[key]
            rows.append([system, row["method"], f"{row['step_s'] * 1e3:.2f} ms ({row['step_ratio']:.2f}x)",
                         f"{row['trained_step_s'] * 1e3:.2f} ms ({row['trained_step_ratio']:.2f}x)",
                         f"{row['trained_forward_s'] * 1e3:.2f} ms ({row['trained_forward_ratio']:.2f}x)",
                         f"{row['compile_s']:.1f} s", f"{row.get('updates_per_element', float('nan')):.1f}",
                         f"{row['final_loss']:.3e}",
                         f"{row['rollout_step_s'] * 1e6:.2f} us ({row['rollout_step_ratio']:.2f}x)",
                         f"{row['learned_energy_change']:.1e}"])
        results[system] = measured
    table = markdown_table(["system", "method", "training step", "trained step", "trained forward run",
                            "compile (step)", "updates per element", "final loss", "rollout per step",
                            "learned energy change"], rows)
    print(table)
    write(args.name, results, table)


if __name__ == "__main__":
    main()
