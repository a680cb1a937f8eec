"""The main job: the paper's scenes in one short run.  ``python -m galerkin_jax.demo``

Prints, for the isotropic oscillator of [GBS, Figs. 4.1-4.2] and the Kepler problem,
the energy and angular-momentum behaviour of cG(k) and dG(k) with several rules, the
nodal convergence orders, and one batched sweep over quadrature rules and step sizes. Runs in well under a minute on a laptop CPU.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np


def _scenes():
    m, c = 2.0, -0.25
    oscillator = (
        lambda q, p: p @ p / (2 * m) - 0.5 * c * (q @ q),
        jnp.array([1.0, 0.0, 0.0]),
        jnp.array([0.0, 0.4 * np.sqrt(2.0), 0.3 * np.sqrt(2.0)]),
    )
    e = 0.5
    kepler = (
        lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q),
        jnp.array([1.0 - e, 0.0]),
        jnp.array([0.0, np.sqrt((1.0 + e) / (1.0 - e))]),
    )
    return oscillator, kepler


def _conservation_table(gj, H, q0, p0, h, n_steps):
    methods = {
        "cG(1) exact (Gauss 2)": gj.CG(1, gj.gauss_legendre(2)),
        "cG(1) midpoint": gj.CG(1, gj.midpoint()),
        "cG(1) trapezoid": gj.CG(1, gj.trapezoid()),
        "cG(1) one point at 0.3": gj.CG(1, gj.QuadratureRule([0.3], [1.0])),
        "dG(1) exact (Gauss 2)": gj.DG(1, gj.gauss_legendre(2)),
        "dG(1) midpoint": gj.DG(1, gj.midpoint()),
        "dG(1) Lobatto 3": gj.DG(1, gj.gauss_lobatto(3)),
        "cG(3) Gauss 3": gj.CG(3, gj.gauss_legendre(3)),
    }
    print(f"\nIsotropic oscillator m=2, c=-0.25, H0=0.25, h={h}, {n_steps} steps [GBS, Figs. 4.1-4.5]")
    print(f"{'method':<26}{'H_end/H_0 - 1':>16}{'|L|_end/|L|_0 - 1':>20}{'status':>8}")
    for name, method in methods.items():
        sol = gj.integrate(H, q0, p0, method=method, h=h, n_steps=n_steps)
        energy = jax.vmap(H)(sol.q, sol.p)
        L = jnp.linalg.norm(jnp.cross(sol.q, sol.p), axis=-1)
        print(f"{name:<26}{float(energy[-1] / energy[0] - 1):>16.3e}{float(L[-1] / L[0] - 1):>20.3e}"
              f"{int(sol.status):>8}")


def _order_table(gj, H, q0, p0):
    T = 2 * np.pi
    print("\nKepler e=0.5, error at t = 2 pi against the exact orbit")
    print(f"{'method':<18}{'n=64':>12}{'n=128':>12}{'order':>8}")
    for name, method in {
        "cG(1) Gauss 3": gj.CG(1, gj.gauss_legendre(3)),
        "cG(2) Gauss 4": gj.CG(2, gj.gauss_legendre(4)),
        "dG(1) Gauss 3": gj.DG(1, gj.gauss_legendre(3)),
        "dG(2) Gauss 4": gj.DG(2, gj.gauss_legendre(4)),
    }.items():
        errors = []
        for n in (64, 128):
            sol = gj.integrate(H, q0, p0, method=method, h=T / n, n_steps=n, save_every=n)
            errors.append(float(jnp.max(jnp.abs(jnp.concatenate([sol.q[-1] - q0, sol.p[-1] - p0])))))
        print(f"{name:<18}{errors[0]:>12.3e}{errors[1]:>12.3e}{np.log2(errors[0] / errors[1]):>8.2f}")


def _sweep_table(gj, H, q0, p0):
    rules = {"Gauss 2": gj.gauss_legendre(2), "Gauss 3": gj.gauss_legendre(3), "Lobatto 3": gj.gauss_lobatto(3),
             "midpoint": gj.midpoint()}
    steps = [0.005, 0.01, 0.02, 0.05]
    configs = gj.grid(method=[gj.CG(2, r) for r in rules.values()], h=steps, state=[(q0, p0)])
    angular = {"L": lambda q, p: q[0] * p[1] - q[1] * p[0]}
    start = time.perf_counter()
    result = gj.sweep(H, configs, n_steps=2000, invariants=angular)
    seconds = time.perf_counter() - start
    print(f"\nKepler e=0.5, cG(2): one sweep of {configs.size} configurations x 2000 steps "
          f"({seconds:.1f} s with compilation): max relative energy error")
    print(f"{'rule':<12}" + "".join(f"{f'h={h}':>12}" for h in steps) + f"{'max L error':>14}")
    energy = np.asarray(result.energy_error).reshape(len(rules), len(steps))
    angular_error = np.asarray(result.invariant_errors["L"]).reshape(len(rules), len(steps)).max(axis=1)
    for name, row, L in zip(rules, energy, angular_error):
        print(f"{name:<12}" + "".join(f"{e:>12.2e}" for e in row) + f"{L:>14.1e}")
    print(f"statuses {sorted(set(np.asarray(result.status).tolist()))}, Newton iterations per step and "
          f"configuration {float(np.mean(result.num_newton_iterations)) / 2000:.1f}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="oscillator steps (default 200)")
    parser.add_argument("--h", type=float, default=1.0, help="oscillator step size (default 1.0)")
    options = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    import galerkin_jax as gj

    start = time.perf_counter()
    (H_osc, q_osc, p_osc), (H_kep, q_kep, p_kep) = _scenes()
    _conservation_table(gj, H_osc, q_osc, p_osc, options.h, options.steps)
    _order_table(gj, H_kep, q_kep, p_kep)
    _sweep_table(gj, H_kep, q_kep, p_kep)
    print(f"\ndone in {time.perf_counter() - start:.1f} s on {jax.devices()[0].platform}")


if __name__ == "__main__":
    main()
