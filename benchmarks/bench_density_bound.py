"""The time transformation's default step density where Hamilton's field vanishes (issue 36,
item 5; docs/adaptive.md, "Where Hamilton's field vanishes"):

    python benchmarks/bench_density_bound.py

The default s = ((1 + k^2) / (|F|^2 / |F(z0)|^2 + k^2))^(3/8), F Hamilton's field, is at most
s_max = ((1 + k^2) / k^2)^(3/8) (``TimeTransform(s_max=...)``, default 3); s_max = inf is the
unbounded density (|F(z0)| / |F|)^(3/4) of earlier versions. cG(4) + Gauss 4 throughout.

a. The four cases: the pendulum H = p^2/2 - cos q at rest (q0 = p0 = 0), at its saddle
   (q0 = pi, p0 = 0) and near its separatrix (q0 = 0, p0 = 1.99999), to t = 40 at h = 0.2 in
   tau, and Henon-Heiles near its equilibrium (energy 1e-4, to t = 100): status, steps, the
   longest step in t, the largest error at 401 (201) times against SciPy DOP853 at
   rtol = 1e-13, and the same for fixed steps (s = 1) with as many elements.
b. s_max swept (2, 3, 5, 8, inf) near the separatrix: p0 = 1.99, 1.99999, 2.00001 (outside,
   a rotation) at h = 0.2, and p0 = 1.99999 at h = 0.1 and 0.4.
c. Kepler from apocentre (e = 0.9 at h = 0.8, 0.4; e = 0.99 at h = 1.6, 0.8 in tau; 100
   orbits; part c of bench_adaptive.py) and from pericentre (h scaled by the ratio of the
   unbounded density's values at pericentre and apocentre, so that the unbounded runs take
   the apocentre runs' steps; 10 orbits), s_max = 3, 5, 10 and inf: steps, the largest
   energy error at the nodes, root-finder iterations per step; microseconds per step for
   s_max = 3 against inf (e = 0.9, h = 0.4, best of 3).

Writes results/density_bound.json.
"""

import os
import pathlib
import sys
import time

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS", "VECLIB_MAXIMUM_THREADS"):
    os.environ[_var] = "1"  # as bench_adaptive.py: one BLAS thread on a busy machine

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import write  # noqa: E402
from galerkin_jax._controllers import field_norm  # noqa: E402

CG4 = gj.CG(4, gj.gauss_legendre(4))
INF = float("inf")


def pendulum(q, p):
    return 0.5 * (p @ p) - jnp.cos(q[0])


def henon_heiles(q, p):
    return 0.5 * (p @ p + q @ q) + q[0] ** 2 * q[1] - q[1] ** 3 / 3


def kepler(q, p):
    return 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)


def pendulum_field(t, z):
    return [z[1], -np.sin(z[0])]


def henon_heiles_field(t, z):
    x, y, px, py = z
    return [px, py, -x - 2 * x * y, -y - x * x + y * y]


def reference(field, z0, times):
    sol = solve_ivp(field, (0, times[-1]), z0, method="DOP853", rtol=1e-13, atol=1e-16, t_eval=times)
    return sol.y.T


def transformed(H, q0, p0, h, t1, s_max, max_steps=50_000):
    return gj.integrate(H, jnp.asarray(q0, float), jnp.asarray(p0, float), method=CG4, h=h, t1=t1,
                        controller=gj.TimeTransform(s_max=s_max), dense=True, max_steps=max_steps,
                        error_estimate=False)


def error_at(sol, times, ref):
    if int(sol.status) != 0:
        return float("nan")
    q, p = sol.evaluate(jnp.asarray(times))
    return float(np.max(np.abs(np.c_[q, p] - ref)))


def nodes(sol):
    n = int(sol.stats["num_accepted_steps"])
    return n, np.asarray(sol.dense.t[: n + 1]), sol.dense.view(sol.dense.z[: n + 1])


def case(name, H, field, q0, p0, h, t1, s_max, n_times=401):
    times = np.linspace(0.0, t1, n_times)
    ref = reference(field, list(q0) + list(p0), times)
    sol = transformed(H, q0, p0, h, t1, s_max)
    n, t, (q, p) = nodes(sol)
    H0 = float(H(jnp.asarray(q0, float), jnp.asarray(p0, float)))
    fixed = gj.integrate(H, jnp.asarray(q0, float), jnp.asarray(p0, float), method=CG4, h=t1 / n, t1=t1, dense=True,
                         error_estimate=False)
    row = dict(case=name, s_max=s_max, h=h, status=int(sol.status), steps=n,
               longest_step=float(np.max(np.diff(t))) if n else float("nan"), error=error_at(sol, times, ref),
               max_energy_error=float(np.max(np.abs(np.asarray(jax.vmap(H)(q, p)) - H0))) if n else float("nan"),
               final_q=np.asarray(sol.q[-1]).tolist(), final_p=np.asarray(sol.p[-1]).tolist(),
               fixed_steps_error=error_at(fixed, times, ref))
    print(f"{name:28s} s_max={s_max:<4g} h={h:<4g} status {row['status']} steps {n:5d} "
          f"longest {row['longest_step']:.3g} error {row['error']:.2e} "
          f"(fixed steps, as many: {row['fixed_steps_error']:.2e})", flush=True)
    return row


def part_a():
    rows = []
    for s_max in (3.0, INF):
        rows.append(case("pendulum at rest", pendulum, pendulum_field, [0.0], [0.0], 0.2, 40.0, s_max))
        rows.append(case("pendulum at its saddle", pendulum, pendulum_field, [np.pi], [0.0], 0.2, 40.0, s_max))
        rows.append(case("pendulum p0 = 1.99999", pendulum, pendulum_field, [0.0], [1.99999], 0.2, 40.0, s_max))
        rows.append(case("Henon-Heiles, energy 1e-4", henon_heiles, henon_heiles_field, [0.0, 0.0],
                         [np.sqrt(2e-4), 0.0], 0.2, 100.0, s_max, n_times=201))
    return rows


def part_b():
    rows = []
    for p0, h in ((1.99999, 0.2), (2.00001, 0.2), (1.99, 0.2), (1.99999, 0.1), (1.99999, 0.4)):
        for s_max in (2.0, 3.0, 5.0, 8.0, INF):
            rows.append(case(f"pendulum p0 = {p0}", pendulum, pendulum_field, [0.0], [p0], h, 40.0, s_max))
    return rows


def kepler_start(e, at):
    if at == "apocentre":
        return jnp.asarray([1 + e, 0.0]), jnp.asarray([0.0, np.sqrt((1 - e) / (1 + e))])
    return jnp.asarray([1 - e, 0.0]), jnp.asarray([0.0, np.sqrt((1 + e) / (1 - e))])


def part_c():
    rows = []
    for at, orbits in (("apocentre", 100), ("pericentre", 10)):
        for e, hs in ((0.9, (0.8, 0.4)), (0.99, (1.6, 0.8))):
            q0, p0 = kepler_start(e, at)
            # the unbounded density's value at apocentre, over its value at the start
            scale = float((field_norm(kepler, *kepler_start(e, "apocentre")) / field_norm(kepler, q0, p0)) ** 0.75)
            for h in hs:
                for s_max in (3.0, 5.0, 10.0, INF):
                    sol = transformed(kepler, q0, p0, h * scale, 2 * np.pi * orbits, s_max, max_steps=200_000)
                    n, t, (q, p) = nodes(sol)
                    dH = np.abs(np.asarray(jax.vmap(kepler)(q, p)) - float(kepler(q0, p0)))
                    row = dict(start=at, e=e, h=h, h_tau=h * scale, orbits=orbits, s_max=s_max, status=int(sol.status),
                               steps=n, max_energy_error=float(dH.max()),
                               iterations_per_step=int(sol.stats["num_newton_iterations"]) / n)
                    rows.append(row)
                    print(f"Kepler from {at:10s} e={e} h={h} s_max={s_max:<4g} status {row['status']} steps {n:6d} "
                          f"max |dH| {row['max_energy_error']:.2e} it/step {row['iterations_per_step']:.1f}",
                          flush=True)
    return rows


def part_c_time():
    q0, p0 = kepler_start(0.9, "apocentre")
    out = {}
    for s_max in (3.0, INF):
        run = jax.jit(lambda q0, p0, s_max=s_max: gj.integrate(
            kepler, q0, p0, method=CG4, h=0.4, t1=2 * np.pi * 100, controller=gj.TimeTransform(s_max=s_max),
            max_steps=20_000, error_estimate=False))
        sol = jax.block_until_ready(run(q0, p0))
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            jax.block_until_ready(run(q0, p0))
            best = min(best, time.perf_counter() - t)
        out[str(s_max)] = dict(steps=int(sol.stats["num_accepted_steps"]), run_s=best,
                               us_per_step=1e6 * best / int(sol.stats["num_accepted_steps"]))
        print(f"Kepler e=0.9 h=0.4 100 orbits s_max={s_max:g}: {out[str(s_max)]['us_per_step']:.1f} us/step",
              flush=True)
    return out


def main():
    start = time.perf_counter()
    out = dict(method="cG(4)+Gauss 4", a=part_a(), b=part_b(), c=part_c(), c_time=part_c_time())
    write("density_bound", dict(**out, total_s=time.perf_counter() - start))


if __name__ == "__main__":
    main()
