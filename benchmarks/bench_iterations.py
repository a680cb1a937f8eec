"""Fixed-point updates per element of cG(k) + Gauss k, and the levers that could lower them.

run: python benchmarks/bench_iterations.py [--rounds 3] [--only LJ13 Plummer32 Kepler learning misses] [--name iterations]

Issue 44 item 4 and issue 45 item 2: the implicit elements iterate 4-17 times an element on the
moderate systems (results/moderate.md) and 6-10 times on the learned Hamiltonian of
bench_learning.py. Each lever is a ``SolverOptions`` of the one solver (no second solver), run on
the same elements, and counted by ``stats["num_newton_iterations"]`` (deterministic) and timed
(run time apart from compile time; the variants of a case timed in turn over ``--rounds``
rounds, the best of each, so that a shared machine's load falls on all alike):

- ``default``: the library as it is: the Gauss-Seidel sweep above 8 degrees of freedom (for a
  separable H, T(p) + V(q), the sweep's map Q -> Q' is the position-only, second-order form of
  Gauss collocation that IRKGL16 iterates with ``second_order_ode``), the continued polynomial
  plus the extrapolated misses of order 2 or 6;
- ``first_order``: the sweep off (``sweep_dimension`` above d): the first-order form, q and p
  updated together;
- ``second_order_small``: the sweep on below 8 degrees of freedom too (Kepler);
- ``order2``: the misses extrapolated by order 2 alone (the predictor without its order 6);
- ``newton``: simplified Newton with a kept matrix instead of the fixed point
  (``theta_fixed_point`` tiny: a member leaves the fixed point after its first block, a small
  system keeps Newton for good and refreshes its matrix at ``theta_newton``);
- ``floor`` (learning only): ``tolerance=0.5``, each element accepted at its first check, not a
  run to use (its answer is not the root): the time a training step would take were the
  iteration as cheap as it can be.

``--only misses``: the predictor's miss on LJ13's first 60 elements at the 1e-6 step (each
element's root solved from its own start, the predictor built from the previous roots as
``_march.march`` builds it), and the sweep's updates from it to the round-off of the root.

IRKGL16's published counts (Antoñana, Makazaga, Murua; IRKGaussLegendre.jl's example notebooks,
the 16-body solar system at a fixed step of 5 days, float64) are written beside them.
Results: results/iterations.json.
"""

import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import galerkin_jax as gj
from galerkin_jax import scenes
from _common import best_time, compiled, write

jax.config.update("jax_enable_x64", True)

IRKGL16 = {"system": "16-body solar system, h = 5 days, 200 steps, 8-stage Gauss collocation",
           "first_order_per_step": 2087 / 200, "second_order_per_step": 1053 / 200}

VARIANTS = {"default": gj.SolverOptions(), "first_order": gj.SolverOptions(sweep_dimension=10**6),
            "second_order_small": gj.SolverOptions(sweep_dimension=1), "order2": gj.SolverOptions(miss_orders=(2,)),
            "newton": gj.SolverOptions(theta_fixed_point=1e-12)}
LONG_S = 3.0  # a variant whose first call takes longer is counted, not timed


def run_cases():
    """(system, label, H, q0, p0, k, h, n, variants) of the fixed-step runs: the moderate
    systems at the steps that meet max |dH/H| 1e-6 and 1e-10 (results/moderate.md), Kepler."""
    sys.path.insert(0, "benchmarks")
    import _moderate

    lj, sphere, kepler = _moderate.lennard_jones(13), _moderate.plummer(32), scenes.kepler(0.6)
    separable_large = ("default", "first_order", "order2", "newton")
    yield from (("LJ13", f"cG(3), n = {n}", lj.H, lj.q0, lj.p0, 3, lj.T / n, n, separable_large) for n in (1520, 5120))
    yield from (("Plummer32", f"cG({k}), n = {n}", sphere.H, sphere.q0, sphere.p0, k, sphere.T / n, n, separable_large)
                for k, n in ((4, 160), (3, 640)))
    small = ("default", "second_order_small", "order2", "newton")
    yield from (("Kepler", f"e = 0.6, cG({k}), h = {h}", kepler.H, kepler.q0, kepler.p0, k, h, 2000, small)
                for k, h in ((3, 0.01), (2, 0.05), (6, 0.1)))


def runs(only, rounds):
    rows = []
    for system, label, H, q0, p0, k, h, n, variants in run_cases():
        if only and system not in only:
            continue
        method, z = gj.CG(k, gj.gauss_legendre(k)), (jnp.asarray(q0), jnp.asarray(p0))
        case = {}
        for name in variants:
            solver = VARIANTS[name]
            run = lambda q, p, solver=solver: gj.integrate(H, q, p, method=method, h=h, n_steps=n, solver=solver)
            compile_s, call = compiled(run, *z)
            t0 = time.perf_counter()
            sol = jax.block_until_ready(call(*z))
            first_s = time.perf_counter() - t0
            case[name] = dict(call=call, row=dict(
                system=system, run=label, variant=name, updates_per_element=int(sol.stats["num_newton_iterations"]) / n,
                most=int(sol.stats["max_newton_iterations"]), status=int(sol.status), compile_s=compile_s,
                run_ms=None if first_s > LONG_S else np.inf))
            print(f"{system:10s} {label:26s} {name:20s} {case[name]['row']['updates_per_element']:6.2f} updates/element",
                  flush=True)
        for _ in range(rounds):
            for entry in case.values():
                if entry["row"]["run_ms"] is not None:
                    entry["row"]["run_ms"] = min(entry["row"]["run_ms"], 1e3 * best_time(entry["call"], *z))
        rows += [entry["row"] for entry in case.values()]
    return rows


def misses(n=1520, elements=60):
    """The predictor's relative miss |Z_pred - Z| / |Z| (rms) on LJ13, cG(3), h = 50 / n, and the
    continued polynomial's alone, per element, with the sweep's updates from Z_pred to |Z| eps."""
    sys.path.insert(0, "benchmarks")
    import _moderate
    from galerkin_jax._march import element_residual, miss_correction, solve_element, solver_options

    lj, method = _moderate.lennard_jones(13), gj.CG(3, gj.gauss_legendre(3))
    h, options = lj.T / n, solver_options(method)
    q, p = jnp.asarray(lj.q0), jnp.asarray(lj.p0)
    root = jax.jit(lambda q, p: solve_element(method, lj.H, q, p, h, None, options))
    sweep = jax.jit(lambda Z, q, p: element_residual(lj.H)(Z, (method, q, p, h, None)))
    rms = lambda x: float(jnp.sqrt(jnp.mean(x * x)))
    history, correction, previous, rows = None, None, None, []
    for j in range(elements):
        q1, p1, Z, _, _ = root(q, p)
        if previous is None:
            history = jnp.zeros((max(gj.SolverOptions().miss_orders),) + Z.shape)
            history, correction = miss_correction(history, jnp.zeros_like(Z), jnp.int32(0))
        else:
            continued = method.initial_guess(q, p, previous)
            guess, updates = continued + correction, 0
            while rms(guess - Z) > np.finfo(float).eps * rms(Z) and updates < 40:
                guess, updates = guess - sweep(guess, q, p), updates + 1
            rows.append(dict(element=j, continued=rms(continued - Z) / rms(Z),
                             predicted=rms(continued + correction - Z) / rms(Z), sweep_updates=updates))
            history, correction = miss_correction(history, Z - continued, jnp.int32(j))
        previous, q, p = (q, p, Z), q1, p1
    summary = {key: [float(np.min([r[key] for r in rows])), float(np.median([r[key] for r in rows])),
                     float(np.max([r[key] for r in rows]))] for key in ("continued", "predicted", "sweep_updates")}
    print("LJ13 misses (min, median, max):", summary)
    return dict(system="LJ13", run=f"cG(3), n = {n}", elements=rows, min_median_max=summary)


def learning(rounds):
    """The training step of bench_learning.py (batch 16, 10 steps of h = 0.1, cG(2) + Gauss 2),
    its forward run and updates per element, at the initial parameters and after 300 Adam steps."""
    import optax

    import bench_learning as bl

    Q, P = bl.data(128)
    optimiser = optax.adam(1e-2)
    solvers = {"default": VARIANTS["default"], "newton": VARIANTS["newton"], "floor": gj.SolverOptions(tolerance=0.5)}
    predicts = dict({"tsit5": bl.tsit5_predict()}, **{k: bl.galerkin_predict(s) for k, s in solvers.items()})
    prepared = {k: bl.prepare(predict, Q, P, optimiser) for k, predict in predicts.items()}
    params, state, Qb, Pb = prepared["default"]["args"]
    rng = np.random.default_rng(0)
    for _ in range(300):
        i = rng.choice(len(Q), bl.BATCH, replace=False)
        params, state, _ = prepared["default"]["step"](params, state, Q[i], P[i])
    at = {"initial": prepared["default"]["args"], "trained": (params, state, Qb, Pb)}
    rows = {}
    for key, p in prepared.items():
        rows[key] = dict(p["row"])
        for where, (w, s, q, pp) in at.items():
            updates = int(p["forward"](w, q, pp)[1]) / (bl.BATCH * bl.N_DATA)
            rows[key][f"{where}_updates_per_element"] = updates or None
            rows[key][f"{where}_forward_ms"] = rows[key][f"{where}_step_ms"] = np.inf
    for _ in range(rounds):
        for key, p in prepared.items():
            for where, (w, s, q, pp) in at.items():
                row = rows[key]
                row[f"{where}_forward_ms"] = min(row[f"{where}_forward_ms"], 1e3 * best_time(p["forward"], w, q, pp, repeat=10))
                row[f"{where}_step_ms"] = min(row[f"{where}_step_ms"], 1e3 * best_time(p["step"], w, s, q, pp, repeat=10))
    for key, row in rows.items():
        for where in at:
            for what in ("forward", "step"):
                row[f"{where}_{what}_over_tsit5"] = row[f"{where}_{what}_ms"] / rows["tsit5"][f"{where}_{what}_ms"]
        print(f"learning {key:8s} " + "  ".join(
            f"{where}: {row[f'{where}_updates_per_element'] or 0:5.2f} updates, forward {row[f'{where}_forward_ms']:.3f} ms "
            f"({row[f'{where}_forward_over_tsit5']:.2f}x), step {row[f'{where}_step_ms']:.3f} ms "
            f"({row[f'{where}_step_over_tsit5']:.2f}x)" for where in at), flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=3, help="timing rounds, the variants in turn")
    parser.add_argument("--only", nargs="*", default=None, help="LJ13 Plummer32 Kepler learning misses")
    parser.add_argument("--name", default="iterations")
    args = parser.parse_args()
    only = set(args.only or ())
    systems = only - {"learning", "misses"}
    rows = runs(systems, args.rounds) if not only or systems else []
    for row in rows:
        timing = "counted only" if row["run_ms"] is None else f"{row['run_ms']:8.1f} ms"
        print(f"{row['system']:10s} {row['run']:26s} {row['variant']:20s} {row['updates_per_element']:6.2f} "
              f"(most {row['most']:2d}, status {row['status']}) {timing}  compile {row['compile_s']:.1f} s")
    learned = learning(args.rounds) if not only or "learning" in only else None
    missed = misses() if not only or "misses" in only else None
    write(args.name, dict(variants={k: repr(v) for k, v in VARIANTS.items()}, irkgl16=IRKGL16, runs=rows,
                          learning=learned, misses=missed))


if __name__ == "__main__":
    main()
