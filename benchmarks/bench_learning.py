"""A training step of a learned Hamiltonian through cG(2) + Gauss 2 against diffrax Tsit5.

run: python benchmarks/bench_learning.py

The problem of notebooks/07_learning_hamiltonian.ipynb: a tanh network H_theta(q, p) (4-32-32-1,
its parameters a pytree passed as ``args``), a batch of 16 trajectories of a charged particle in
a magnetic field (two degrees of freedom), 10 steps of h = 0.1 each, loss the mean squared error
of (q, p) at the 11 data times. A training step is ``jax.value_and_grad`` of the loss and an
optax Adam update, jitted; through ``gj.integrate`` under ``jax.vmap`` (gradients by the implicit
function theorem) and through ``diffrax.diffeqsolve(Tsit5(), ConstantStepSize())`` at the same h
(its default adjoint, RecursiveCheckpointAdjoint), the same batch, model and optimiser. The
forward run (the loss alone) is timed too, and steps through cG(2) with a loose
``SolverOptions(tolerance=...)``: their time, the fixed-point updates per element, and the loss
after ``--train`` Adam steps from the same start. Compile and run times apart; the run times are
the best of ``--rounds`` rounds that time every variant in turn (a shared machine's load falls on
all alike); results/learning.json.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import galerkin_jax as gj
from _common import best_time, compiled, write

jax.config.update("jax_enable_x64", True)

H_STEP, N_DATA, BATCH = 0.1, 10, 16


def H_true(q, p):
    v = p - 0.5 * jnp.array([-q[1], q[0]])
    return 0.5 * v @ v + 0.5 * q @ q + 0.1 * q[0] ** 4


def H_model(q, p, params):
    x = jnp.concatenate([q, p])
    for layer in params[:-1]:
        x = jnp.tanh(x @ layer["W"] + layer["b"])
    return (x @ params[-1]["W"] + params[-1]["b"])[0]


def init(key, sizes=(4, 32, 32, 1)):
    params = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        key, sub = jax.random.split(key)
        params.append({"W": jax.random.normal(sub, (a, b)) / np.sqrt(a), "b": jnp.zeros(b)})
    return params


def data(n):
    z0 = jax.random.uniform(jax.random.PRNGKey(0), (n, 4), minval=-1.0, maxval=1.0)
    ref = gj.CG(4, gj.gauss_legendre(4))
    run = lambda z: gj.integrate(H_true, z[:2], z[2:], method=ref, h=H_STEP / 10, n_steps=10 * N_DATA,
                                 save_every=10)
    sol = jax.jit(jax.vmap(run))(z0)
    return sol.q, sol.p


def galerkin_predict(solver):
    method = gj.CG(2, gj.gauss_legendre(2))

    def predict(params, q0, p0):
        sol = gj.integrate(H_model, q0, p0, method=method, h=H_STEP, n_steps=N_DATA, args=params, solver=solver)
        return sol.q, sol.p, sol.stats["num_newton_iterations"]

    return predict


def tsit5_predict():
    import diffrax

    ts = jnp.arange(N_DATA + 1) * H_STEP

    def field(t, z, params):
        dq, dp = jax.grad(H_model, argnums=(0, 1))(z[0], z[1], params)
        return dp, -dq

    def predict(params, q0, p0):
        sol = diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Tsit5(), t0=0.0, t1=ts[-1], dt0=H_STEP,
                                  y0=(q0, p0), args=params, saveat=diffrax.SaveAt(ts=ts),
                                  stepsize_controller=diffrax.ConstantStepSize())
        return sol.ys[0], sol.ys[1], jnp.zeros((), jnp.int32)

    return predict


def training(predict, optimiser):
    def loss(params, Qb, Pb):
        q, p, iterations = jax.vmap(predict, in_axes=(None, 0, 0))(params, Qb[:, 0], Pb[:, 0])
        return jnp.mean((q - Qb) ** 2) + jnp.mean((p - Pb) ** 2), jnp.sum(iterations)

    def update(params, state, Qb, Pb):
        (value, _), grads = jax.value_and_grad(loss, has_aux=True)(params, Qb, Pb)
        updates, state = optimiser.update(grads, state, params)
        return optax.apply_updates(params, updates), state, value

    return loss, update


def prepare(predict, Q, P, optimiser):
    """The loss and the training step compiled for one batch, their compile times."""
    params = init(jax.random.PRNGKey(1))
    state = optimiser.init(params)
    Qb, Pb = Q[:BATCH], P[:BATCH]
    loss, update = training(predict, optimiser)
    forward_compile_s, forward = compiled(loss, params, Qb, Pb)
    step_compile_s, step = compiled(update, params, state, Qb, Pb)
    iterations = int(forward(params, Qb, Pb)[1])
    return dict(forward=forward, step=step, args=(params, state, Qb, Pb),
                row=dict(forward_compile_s=forward_compile_s, step_compile_s=step_compile_s,
                         updates_per_element=iterations / (BATCH * N_DATA) if iterations else None))


def final_loss(prepared, Q, P, train_steps):
    """The loss over all trajectories after ``train_steps`` Adam steps on random batches, and
    the fixed-point updates per element of the trained model on the first batch."""
    params, state, _, _ = prepared["args"]
    step, forward, rng = prepared["step"], prepared["forward"], np.random.default_rng(0)
    for _ in range(train_steps):
        i = rng.choice(len(Q), BATCH, replace=False)
        params, state, _ = step(params, state, Q[i], P[i])
    loss = float(np.mean([forward(params, Q[j:j + BATCH], P[j:j + BATCH])[0] for j in range(0, len(Q), BATCH)]))
    prepared["trained_args"] = (params, state, Q[:BATCH], P[:BATCH])
    return loss, int(forward(params, Q[:BATCH], P[:BATCH])[1]) / (BATCH * N_DATA)


def interleaved(prepared, rounds):
    """Best forward and step times of each variant, at the initial parameters and at the
    trained ones (``trained_*``), timed in turn over ``rounds`` rounds, so that a shared
    machine's load falls on all of them alike."""
    for p in prepared.values():
        p["row"].update({f"{at}{what}_s": np.inf for at in ("", "trained_") for what in ("forward", "step")})
    for _ in range(rounds):
        for p in prepared.values():
            for at in ("", "trained_"):
                params, state, Qb, Pb = p[f"{at}args"]
                row = p["row"]
                row[f"{at}forward_s"] = min(row[f"{at}forward_s"], best_time(p["forward"], params, Qb, Pb, repeat=10))
                row[f"{at}step_s"] = min(row[f"{at}step_s"], best_time(p["step"], params, state, Qb, Pb, repeat=10))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--train", type=int, default=500, help="Adam steps for the final loss")
    parser.add_argument("--tolerances", type=float, nargs="*", default=[1e-8, 1e-6])
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    parser.add_argument("--name", default="learning")
    args = parser.parse_args()
    Q, P = data(128)
    optimiser = optax.adam(optax.exponential_decay(1e-2, transition_steps=500, decay_rate=0.3))
    variants = {"tsit5": ("diffrax Tsit5", tsit5_predict()),
                "cg2": ("cG(2)+Gauss 2", galerkin_predict(gj.SolverOptions()))}
    for tol in args.tolerances:
        variants[f"cg2_tol{tol:g}"] = (f"cG(2)+Gauss 2, tol {tol:g}", galerkin_predict(gj.SolverOptions(tolerance=tol)))
    prepared = {key: prepare(predict, Q, P, optimiser) for key, (_, predict) in variants.items()}
    rows = {}
    for key in variants:
        row = rows[key] = prepared[key]["row"]
        loss, trained_updates = final_loss(prepared[key], Q, P, args.train)
        row.update(final_loss=loss, train_steps=args.train, trained_updates_per_element=trained_updates or None)
    interleaved(prepared, args.rounds)
    for key, (label, _) in variants.items():
        row = rows[key]
        print(f"{label:28s} step {1e3 * row['step_s']:5.2f} ms, trained {1e3 * row['trained_step_s']:5.2f} ms "
              f"(compile {row['step_compile_s']:4.1f} s)  forward {1e3 * row['forward_s']:4.2f} ms, trained "
              f"{1e3 * row['trained_forward_s']:4.2f} ms (compile {row['forward_compile_s']:4.1f} s)  updates/element "
              f"{row['updates_per_element'] or 0:4.1f}, trained {row['trained_updates_per_element'] or 0:4.1f}  "
              f"loss after {args.train} steps {row['final_loss']:.9g}")
    base = rows["tsit5"]
    for row in rows.values():
        for what in ("step", "forward", "trained_step", "trained_forward"):
            row[f"{what}_over_tsit5"] = row[f"{what}_s"] / base[f"{what}_s"]
    for name, row in rows.items():
        print(f"{name:16s} step / Tsit5 {row['step_over_tsit5']:.2f}x (trained {row['trained_step_over_tsit5']:.2f}x), "
              f"forward / Tsit5 {row['forward_over_tsit5']:.2f}x (trained {row['trained_forward_over_tsit5']:.2f}x)")
    write(args.name, dict(problem=dict(h=H_STEP, steps=N_DATA, batch=BATCH, model="tanh MLP 4-32-32-1",
                                       system="charged particle in a uniform magnetic field, 2 dof"),
                          target="training step <= 0.5x Tsit5's", results=rows))


if __name__ == "__main__":
    main()
