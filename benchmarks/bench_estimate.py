"""The a posteriori error estimate against the measured local error of one element.

    python benchmarks/bench_estimate.py

Kepler e = 0.6: one element of each method from six exact states of the orbit (perihelion,
aphelion and four points between), h = 0.1, 0.05, 0.025. The true local error is the
element's end state against the exact orbit (``scenes.kepler(0.6).exact``), max-norm over
(q, p); the estimate is ``Solution.error_estimate``. Prints a markdown table (largest true
error, largest estimate, range of estimate / true) and writes results/estimate.json.
"""

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import write  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

STARTS = np.linspace(0.0, 2 * np.pi, 7)[:-1]
STEPS = (0.1, 0.05, 0.025)
METHODS = {
    "cG(1) midpoint": gj.CG(1, gj.midpoint()),
    "cG(2) Gauss 2": gj.CG(2, gj.gauss_legendre(2)),
    "dG(1) Gauss 3": gj.DG(1, gj.gauss_legendre(3)),
    "GalerkinVI(2) Gauss 3": gj.GalerkinVI(2, gj.gauss_legendre(3)),
    "DiscreteGradient": gj.DiscreteGradient(),
}


def local_errors(scene, method, h):
    """(true, estimated) local errors of one element from each start state."""
    starts = [scene.exact(t) for t in STARTS]
    ends = np.array([np.concatenate(scene.exact(t + h)) for t in STARTS])
    q0s, p0s = (jnp.asarray(np.array(x)) for x in zip(*starts))
    sol = jax.vmap(lambda q, p: gj.integrate(scene.H, q, p, method=method, h=h, n_steps=1))(q0s, p0s)
    true = np.abs(np.concatenate([sol.q[:, -1], sol.p[:, -1]], axis=1) - ends).max(axis=1)
    return true, np.asarray(sol.error_estimate)


def main():
    scene = scenes.kepler(0.6)
    results, rows = {}, []
    for name, method in METHODS.items():
        cells = []
        for h in STEPS:
            true, estimate = local_errors(scene, method, h)
            ratio = estimate / true
            results.setdefault(name, []).append({"h": h, "true": true.tolist(), "estimate": estimate.tolist()})
            cells.append(f"{true.max():.2e} / {estimate.max():.2e} / {ratio.min():.3f}-{ratio.max():.3f}")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    header = "| method | " + " | ".join(f"h = {h}" for h in STEPS) + " |\n| --- |" + " --- |" * len(STEPS)
    table = header + "\n" + "\n".join(rows)
    print("largest true local error / largest estimate / estimate over true, 6 points of the orbit\n" + table)
    write("estimate", {"scene": "kepler e=0.6", "starts": STARTS.tolist(), "runs": results, "table": table})


if __name__ == "__main__":
    main()
