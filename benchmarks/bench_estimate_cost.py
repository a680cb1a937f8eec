"""The price of ``Solution.error_estimate``: a run with it off, the default, and "full".

    python benchmarks/bench_estimate_cost.py

The outer solar system of Hairer, Lubich and Wanner (GNI, Sec. I.2.4: the Sun and the inner
planets as one body, Jupiter, Saturn, Uranus, Neptune, Pluto; d = 18) with cG(6) + Gauss 6,
h = 50 days, 400 steps, and Kepler e = 0.6 with cG(3) + Gauss 3, h = 0.05, 400 steps. Each
variant is compiled ahead of time (compile_s) and timed by the best of alternating repeats
(run_s), so that the three share the machine's state; writes results/estimate_cost.json.
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
from _common import compiled, write  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

G = 2.95912208286e-4
MASSES = np.array([1.00000597682, 0.000954786104043, 0.000285583733151, 0.0000437273164546, 0.0000517759138449,
                   1 / 1.3e8])
POSITIONS = np.array([[0, 0, 0], [-3.5023653, -3.8169847, -1.5507963], [9.0755314, -3.0458353, -1.6483708],
                      [8.3101420, -16.2901086, -7.2521278], [11.4707666, -25.7294829, -10.8169456],
                      [-15.5387357, -25.2225594, -3.1902382]])
VELOCITIES = np.array([[0, 0, 0], [0.00565429, -0.00412490, -0.00190589], [0.00168318, 0.00483525, 0.00192462],
                       [0.00354178, 0.00137102, 0.00055029], [0.00288930, 0.00114527, 0.00039677],
                       [0.00276725, -0.00170702, -0.00136504]])
PAIRS = np.triu_indices(6, 1)


def outer_solar_system(q, p):
    """H of six bodies (q, p flat, shape (18,)): kinetic energy minus the pairs' potential."""
    q, p = q.reshape(6, 3), p.reshape(6, 3)
    i, j = PAIRS
    r = jnp.sqrt(jnp.sum((q[i] - q[j]) ** 2, axis=1))
    return 0.5 * jnp.sum(jnp.sum(p**2, axis=1) / MASSES) - G * jnp.sum(MASSES[i] * MASSES[j] / r)


def cases():
    kepler = scenes.kepler(0.6)
    solar = (outer_solar_system, jnp.asarray(POSITIONS.ravel()), jnp.asarray((MASSES[:, None] * VELOCITIES).ravel()))
    return {
        "outer solar system, cG(6) Gauss 6, h = 50, 400 steps": (*solar, gj.CG(6, gj.gauss_legendre(6)), 50.0),
        "Kepler e = 0.6, cG(3) Gauss 3, h = 0.05, 400 steps": (kepler.H, kepler.q0, kepler.p0,
                                                               gj.CG(3, gj.gauss_legendre(3)), 0.05),
    }


def main(repeats=15):
    results = {}
    for name, (H, q0, p0, method, h) in cases().items():
        calls, row = {}, {}
        for variant in (False, True, "full"):
            run = lambda q0, p0, variant=variant: gj.integrate(H, q0, p0, method=method, h=h, n_steps=400,
                                                               error_estimate=variant)
            compile_s, calls[variant] = compiled(run, q0, p0)
            sol = calls[variant](q0, p0)
            row[str(variant)] = {"compile_s": compile_s, "estimate": float(sol.error_estimate), "runs": []}
        for _ in range(repeats):  # alternating, so that a slow moment of the machine hits all three
            for variant, call in calls.items():
                t0 = time.perf_counter()
                jax.block_until_ready(call(q0, p0))
                row[str(variant)]["runs"].append(time.perf_counter() - t0)
        base = min(row["False"]["runs"])
        for variant in row.values():
            variant["run_s"] = min(variant.pop("runs"))
            variant["ratio_to_no_estimate"] = variant["run_s"] / base
        results[name] = row
        print(name)
        for variant, values in row.items():
            print(f"  error_estimate={variant:5s}  run {1e3 * values['run_s']:7.2f} ms  "
                  f"({values['ratio_to_no_estimate']:.2f}x)  compile {values['compile_s']:.2f} s  "
                  f"estimate {values['estimate']:.3e}")
    write("estimate_cost", {"cases": results})


if __name__ == "__main__":
    main()
