"""Per-step cost of cG/dG on Kepler against a plain jitted implicit midpoint rule.

    python benchmarks/bench_step.py [--steps 20000]

Compile time and run time are reported separately; the ratio is to the baseline timed
in the same run. A work-precision table (error at t = 2 pi against run time, over
several h) goes into the same JSON file, and a plot into results/step_work_precision.png.
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
from _common import RESULTS, figure, timed, write  # noqa: E402
from galerkin_jax import plot as gj_plot  # noqa: E402

E = 0.5
Q0 = jnp.array([1.0 - E, 0.0])
P0 = jnp.array([0.0, np.sqrt((1.0 + E) / (1.0 - E))])


def kepler(q, p):
    return 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)


def implicit_midpoint(q0, p0, h, n_steps):
    """The baseline: z1 = z0 + h J DH((z0 + z1) / 2), Newton with a dense Jacobian, lax.scan."""
    dH = jax.grad(kepler, argnums=(0, 1))
    d = q0.shape[0]

    def field(z):
        dq, dp = dH(z[:d], z[d:])
        return jnp.concatenate([dp, -dq])

    def one_step(z0, _):
        residual = lambda z1: z1 - z0 - h * field(0.5 * (z0 + z1))

        def body(c):
            z, _, i = c
            dz = jnp.linalg.solve(jax.jacfwd(residual)(z), residual(z))
            return z - dz, jnp.max(jnp.abs(dz)), i + 1

        cond = lambda c: (c[1] > 1e-14 * (1 + jnp.max(jnp.abs(c[0])))) & (c[2] < 32)
        z1, _, _ = jax.lax.while_loop(cond, body, (z0, jnp.inf, 0))
        return z1, None

    z, _ = jax.lax.scan(one_step, jnp.concatenate([q0, p0]), None, length=n_steps)
    return z


def library(method, n_steps):
    def run(q0, p0, h):
        sol = gj.integrate(kepler, q0, p0, method=method, h=h, n_steps=n_steps, save_every=n_steps)
        return jnp.concatenate([sol.q[-1], sol.p[-1]])

    return run


METHODS = {
    "cG(1) midpoint": gj.CG(1, gj.midpoint()),
    "cG(1) Gauss 2": gj.CG(1, gj.gauss_legendre(2)),
    "cG(3) Gauss 4": gj.CG(3, gj.gauss_legendre(4)),
    "dG(1) Gauss 2": gj.DG(1, gj.gauss_legendre(2)),
    "DiscreteGradient": gj.DiscreteGradient(),
    "DiscreteGradient, excess from H values": gj.DiscreteGradient(line_points=0),
}


def per_step(n_steps, h):
    rows = {}
    c, r = timed(lambda q, p, h: implicit_midpoint(q, p, h, n_steps), Q0, P0, h)
    rows["baseline: implicit midpoint"] = {"compile_s": c, "run_s": r, "us_per_step": 1e6 * r / n_steps}
    for name, method in METHODS.items():
        c, r = timed(library(method, n_steps), Q0, P0, h)
        rows[name] = {"compile_s": c, "run_s": r, "us_per_step": 1e6 * r / n_steps}
    base = rows["baseline: implicit midpoint"]["run_s"]
    for row in rows.values():
        row["ratio_to_baseline"] = row["run_s"] / base
    return rows


def work_precision(ns):
    """Error at t = 2 pi (exact state = initial state) against run time."""
    table = {}
    for name, method in {"baseline: implicit midpoint": None, **METHODS}.items():
        table[name] = []
        for n in ns:
            h = 2 * np.pi / n
            fn = (lambda q, p, h, n=n: implicit_midpoint(q, p, h, n)) if method is None else library(method, n)
            _, run_s = timed(fn, Q0, P0, h, repeat=3)
            z = jax.jit(fn)(Q0, P0, h)
            error = float(jnp.max(jnp.abs(z - jnp.concatenate([Q0, P0]))))
            table[name].append({"n_steps": n, "h": h, "run_s": run_s, "error": error})
    return table


def progress_cost(n_steps=100_000, h=0.01):
    """Run time of a long run with and without the progress bar (50 host callbacks)."""
    method = gj.CG(2, gj.gauss_legendre(2))
    rows = {}
    for progress in (False, True):
        fn = lambda q, p, h: gj.integrate(kepler, q, p, method=method, h=h, n_steps=n_steps, save_every=n_steps,
                                          progress=progress).q[-1]
        c, r = timed(fn, Q0, P0, h)
        rows[f"progress={progress}"] = {"compile_s": c, "run_s": r, "us_per_step": 1e6 * r / n_steps}
    rows["slowdown"] = rows["progress=True"]["run_s"] / rows["progress=False"]["run_s"] - 1
    return rows


def plot(table, path):
    runs = {name: ([r["run_s"] for r in rows], [r["error"] for r in rows]) for name, rows in table.items()}
    with figure(path) as (ax,):
        gj_plot.work_precision(runs, ax=ax)
        ax.set_xlabel("run time [s] (one period)")
        ax.set_ylabel("max error at t = 2 pi")
        ax.set_title("Kepler e = 0.5: work-precision")
        ax.legend(fontsize=8)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--h", type=float, default=0.01)
    options = parser.parse_args()
    rows = per_step(options.steps, options.h)
    print(f"{'method':<30}{'compile s':>10}{'us/step':>10}{'ratio':>8}")
    for name, row in rows.items():
        print(f"{name:<30}{row['compile_s']:>10.2f}{row['us_per_step']:>10.2f}{row['ratio_to_baseline']:>8.2f}")
    progress = progress_cost()
    print(f"progress bar on 1e5 steps: {100 * progress['slowdown']:+.1f} % run time "
          f"({progress['progress=False']['run_s']:.3f} s without)")
    table = work_precision([64, 128, 256, 512, 1024, 2048])
    plot(table, RESULTS / "step_work_precision.png")
    write("step", {"n_steps": options.steps, "h": options.h, "per_step": rows, "progress": progress,
                   "work_precision": table})


if __name__ == "__main__":
    main()
