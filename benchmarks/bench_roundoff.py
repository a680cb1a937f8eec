"""Energy round-off over long runs: |H_n - H_0| / |H_0| against n, with sqrt(n) and n guides.

    python benchmarks/bench_roundoff.py [--steps 10000000]

Kepler e = 0.6, h = 0.01, for the energy-conserving schemes (DiscreteGradient,
ModifiedMidpoint, cG(k) with exact quadrature) and a symplectic one (cG(4) + Gauss 4, whose
energy error also has a bounded O(h^8) part). Each run stores 1000 states; the maximum of
the relative energy error up to n is reported at each decade. Brouwer's law: round-off that
is unbiased grows like sqrt(n) eps; a biased stop or lost low bits grow like n eps.
Writes results/roundoff.json and results/roundoff.png.
"""

import argparse
import pathlib
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import RESULTS, figure, write  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

METHODS = {
    "DiscreteGradient": gj.DiscreteGradient(),
    "ModifiedMidpoint": gj.ModifiedMidpoint(),
    "cG(3) + Gauss 6 (exact for Kepler to ~1e-16)": gj.CG(3, gj.gauss_legendre(6)),
    "cG(4) + Gauss 4 (symplectic)": gj.CG(4, gj.gauss_legendre(4)),
}


def energy_growth(method, n_steps, scene):
    save_every = n_steps // 1000
    start = time.perf_counter()
    sol = gj.integrate(scene.H, scene.q0, scene.p0, method=method, h=0.01, n_steps=n_steps, save_every=save_every)
    energy = np.asarray(jax.vmap(scene.H)(sol.q, sol.p))
    seconds = time.perf_counter() - start
    error = np.maximum.accumulate(np.abs(energy / energy[0] - 1))
    return {"status": int(sol.status), "n": (np.arange(len(energy)) * save_every).tolist(), "max_error": error.tolist(),
            "seconds_with_compile": seconds}


def plot(results, path):
    eps = np.finfo(float).eps
    with figure(path, size=(6.5, 4.5)) as (ax,):
        for name, r in results.items():
            n, e = np.asarray(r["n"][1:]), np.asarray(r["max_error"][1:])
            ax.loglog(n, np.maximum(e, 1e-17), label=name)
        n = np.logspace(3, np.log10(max(r["n"][-1] for r in results.values())), 20)
        ax.loglog(n, eps * np.sqrt(n), "k--", lw=1, label="eps sqrt(n)")
        ax.loglog(n, eps * n / 100, "k:", lw=1, label="eps n / 100")
        ax.set_xlabel("elements n")
        ax.set_ylabel("max |H_m - H_0| / |H_0|, m <= n")
        ax.set_title("Kepler e = 0.6, h = 0.01: energy round-off")
        ax.legend(fontsize=7)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=10_000_000)
    options = parser.parse_args()
    scene = scenes.kepler(0.6)
    results = {}
    for name, method in METHODS.items():
        results[name] = energy_growth(method, options.steps, scene)
        r = results[name]
        marks = [m for m in (10**4, 10**5, 10**6, 10**7) if m <= options.steps]
        row = "  ".join(f"1e{int(np.log10(m))}: {r['max_error'][m // (options.steps // 1000)]:.1e}" for m in marks)
        print(f"{name:<46} status {r['status']}  {row}  ({r['seconds_with_compile']:.0f} s)", flush=True)
    plot(results, RESULTS / "roundoff.png")
    write("roundoff", {"h": 0.01, "scene": "kepler e=0.6", "n_steps": options.steps, "runs": results})


if __name__ == "__main__":
    main()
