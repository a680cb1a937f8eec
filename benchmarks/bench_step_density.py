"""Why the time transformation's default step density is less accurate than Kepler's own on
eccentric orbits (docs/adaptive.md, "The default step density"):

    python benchmarks/bench_step_density.py

Kepler e = 0.9 and e = 0.99 from apocentre over 5 orbits, cG(6) + Gauss 6 with
``TimeTransform(s)`` at h = 0.8 and 0.4 in tau, for densities s = (N(z0) / N(z))^(3/4):

* the default, N = |F| = (|dH/dq|^2 + |dH/dp|^2)^(1/2), Hamilton's field (with its cap
  s <= 3, which from apocentre only scales s by at most 1.02 near pericentre);
* N^2 = |dH/dq|^2 + lam |dH/dp|^2 for lam = 0.3, 0.1, 0.03 and 0 (the force alone);
* Kepler's own s = (r / r0)^(3/2).

For each: steps, the largest energy error over the nodes, and K = s (H - H0), the transformed
Hamiltonian, after the first step and at the end (the method conserves K near its start value,
and H - H0 = K / s, so an error of K made anywhere is divided by the small s of every later
pericentre). Writes results/step_density.json. No timings: the densities differ in accuracy,
not in cost per step (steps and iterations are recorded).
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
from galerkin_jax import scenes  # noqa: E402
from galerkin_jax._controllers import default_step_density, field_scale  # noqa: E402

H = scenes.kepler().H
ORBITS = 5


def blended(lam):
    """s from N^2 = |dH/dq|^2 + lam |dH/dp|^2, normalised to s(z0) = 1 (lam = 1 is the default's N)."""

    def make(q0, p0):
        def N(q, p):
            dq, dp = jax.grad(H, argnums=(0, 1))(q, p)
            return jnp.sqrt(dq @ dq + lam * (dp @ dp))

        N0 = N(q0, p0)
        return lambda q, p: (N0 / N(q, p)) ** 0.75

    return make


def kepler_own(q0, p0):
    r0 = jnp.sqrt(q0 @ q0)
    return lambda q, p: (jnp.sqrt(q @ q) / r0) ** 1.5


DENSITIES = {"default (lam = 1)": None, **{f"lam = {lam:g}": blended(lam) for lam in (0.3, 0.1, 0.03, 0.0)},
             "r^1.5": kepler_own}


def one(e, h, name):
    q0, p0 = jnp.asarray([1 + e, 0.0]), jnp.asarray([0.0, np.sqrt((1 - e) / (1 + e))])
    make = DENSITIES[name]
    s_user = None if make is None else make(q0, p0)
    sol = gj.integrate(H, q0, p0, method=gj.CG(6, gj.gauss_legendre(6)), h=h, t1=2 * np.pi * ORBITS,
                       controller=gj.TimeTransform(s_user), max_steps=100_000, dense=True, error_estimate=False)
    q, p = sol.dense.view(sol.dense.z)
    keep = np.isfinite(np.asarray(q[:, 0]))
    q, p = q[keep], p[keep]
    dH = np.asarray(jax.vmap(H)(q, p) - H(q0, p0))
    s = default_step_density(H, field_scale(H, q0, p0)) if make is None else s_user
    K = np.asarray(jax.vmap(s)(q, p)) * dH
    r = np.linalg.norm(np.asarray(q), axis=1)
    worst = int(np.argmax(np.abs(dH)))
    return dict(e=e, h=h, density=name, status=int(sol.status), steps=int(sol.stats["num_accepted_steps"]),
                iterations_per_step=int(sol.stats["num_newton_iterations"]) / int(sol.stats["num_accepted_steps"]),
                max_energy_error=float(np.abs(dH).max()), at_radius=float(r[worst]),
                K_after_first_step=float(K[1]), K_at_end=float(K[-1]))


def main():
    start = time.perf_counter()
    rows = []
    for e in (0.9, 0.99):
        for h in (0.8, 0.4):
            for name in DENSITIES:
                row = one(e, h, name)
                rows.append(row)
                print(f"e={e} h={h} {name:18s} steps {row['steps']:4d}  max |dH| {row['max_energy_error']:.1e} "
                      f"(r = {row['at_radius']:.3f})  K after step 1 {row['K_after_first_step']:+.1e}, "
                      f"at the end {row['K_at_end']:+.1e}", flush=True)
    write("step_density", dict(orbits=ORBITS, method="cG(6)+Gauss 6", runs=rows, total_s=time.perf_counter() - start))


if __name__ == "__main__":
    main()
