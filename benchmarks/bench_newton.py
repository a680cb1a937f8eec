"""Newton's matrix of cG(k) from the field's Jacobians at the quadrature points, against the
same matrix from one tangent of the element equations per unknown.

    python -m benchmarks newton [--only chain learned kepler]

Both give dR/dZ to round-off; they differ in cost. ``gj.CG`` builds it from 2d tangents of
Hamilton's field at each quadrature point (``CG.jacobian``); a subclass that redefines
``residual`` alone (``Tangents`` here, the same equations) takes one tangent of R per unknown,
k times as many, each through all the points. For each system (the 10-link pendulum chain and
a network H of ``_moderate``, Kepler e = 0.6) this times, in one process and alternating: the
matrix and its inverse alone (200 in one compiled loop), and whole runs and gradients at steps
where Newton's matrices are taken often (long elements, PID) and rarely; the best of several
calls each, with the updates and the end states' difference. Writes results/newton.json and
newton.md.
"""

import argparse
import sys

from _common import best_time, markdown_table, write  # first: one BLAS thread

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import _moderate  # noqa: E402
import galerkin_jax as gj  # noqa: E402
from galerkin_jax import _march, _solve, scenes  # noqa: E402

jax.config.update("jax_enable_x64", True)


@gj.pytree_dataclass
class Tangents(gj.CG):
    """cG(k) whose Newton matrix is taken by tangents of R: a redefined ``residual`` (the same
    equations) does not inherit ``CG.jacobian``."""

    def residual(self, H, q0, p0, C, h, part=None):
        return super().residual(H, q0, p0, C, h, part)


def systems():
    chain, learned, kepler = _moderate.pendulum_chain(10), _moderate.learned(), scenes.kepler(0.6)
    return {"chain": (chain.H, chain.q0, chain.p0, "Chain10"), "learned": (learned.H, learned.q0, learned.p0, "Learned2"),
            "kepler": (kepler.H, kepler.q0, kepler.p0, "Kepler e = 0.6")}


# (system, k, h, steps or None with t1 and a PID controller, gradient)
RUNS = [
    ("chain", 6, 1 / 3, 60, False), ("chain", 4, 1 / 6, 120, False), ("chain", 4, 1 / 6, 120, True),
    ("chain", 6, 20 / 130, 130, False), ("chain", 3, 1 / 16, 320, False),
    ("learned", 4, 0.1, 200, False), ("learned", 2, 0.02, 1000, False), ("learned", 2, 0.1, 200, True),
    ("kepler", 6, 0.05, 1000, False), ("kepler", 6, 0.05, None, False),
]


def matrix_loop(H, q0, p0, method):
    """200 Newton matrices and their inverses of one element, in one compiled loop, each taken
    as the root finder takes it (``_solve._Problem.jacobians``)."""
    fn = _march.element_residual(H)
    params = jax.tree.map(lambda x: jnp.asarray(x)[None], (method, q0, p0, 0.05, None))
    Z = 0.01 * jnp.ones_like(method.initial_guess(q0, p0))
    problem = _solve._Problem(fn, params, jnp.ones(1), jnp.zeros(1), gj.SolverOptions(), True, False)
    matrix = lambda Z: problem.jacobians(Z[None])[0]
    body = lambda i, total: total + jnp.linalg.inv(matrix(Z + i * 1e-12))
    return jax.jit(lambda Z: jax.lax.fori_loop(0, 200, body, jnp.zeros((Z.size, Z.size)))), Z


def run_fn(H, method, k, h, n, gradient):
    span = dict(n_steps=n, save_every=n) if n else dict(t1=20.0, controller=gj.PIDController(1e-10, 1e-10),
                                                        save_every=10**6)
    solve = lambda q0, p0: gj.integrate(H, q0, p0, method=method, h=h, **span)
    if gradient:
        return jax.jit(jax.grad(lambda q0, p0: jnp.sum(solve(q0, p0).q[-1] ** 2)))
    return jax.jit(solve)


def compare(make, args, rounds=2):
    """The best time of ``make(structured)`` and ``make(not structured)``, alternating, and their last outputs."""
    best, out = {True: np.inf, False: np.inf}, {}
    for _ in range(rounds):
        for structured in (False, True):
            call = make(structured)
            out[structured] = jax.block_until_ready(call(*args))
            best[structured] = min(best[structured], best_time(call, *args, repeat=7, min_s=0.2))
    return best, out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=["chain", "learned", "kepler"])
    options = parser.parse_args()
    chosen = {name: s for name, s in systems().items() if options.only is None or name in options.only}
    matrices, runs = [], []
    for name, (H, q0, p0, label) in chosen.items():
        q0, p0 = jnp.asarray(q0), jnp.asarray(p0)
        for k in (2, 4, 6):
            rule = gj.gauss_legendre(k)
            make = lambda structured: matrix_loop(H, q0, p0, (gj.CG if structured else Tangents)(k, rule))[0]
            best, _ = compare(make, (matrix_loop(H, q0, p0, gj.CG(k, rule))[1],))
            matrices.append([label, k, f"{best[False] / 200 * 1e6:.1f}", f"{best[True] / 200 * 1e6:.1f}",
                             f"{best[True] / best[False]:.2f}"])
            print(" | ".join(map(str, matrices[-1])), flush=True)
    for name, k, h, n, gradient in RUNS:
        if name not in chosen:
            continue
        H, q0, p0, label = chosen[name]
        rule = gj.gauss_legendre(k)
        make = lambda structured: run_fn(lambda q, p: H(q, p), (gj.CG if structured else Tangents)(k, rule), k, h, n,
                                         gradient)
        best, out = compare(make, (jnp.asarray(q0), jnp.asarray(p0)))
        if gradient:
            gap, updates = float(np.max(np.abs(out[True] - out[False]))), "-"
        else:
            gap = float(np.max(np.abs(out[True].q[-1] - out[False].q[-1])))
            updates = f"{int(out[False].stats['num_newton_iterations'])}, {int(out[True].stats['num_newton_iterations'])}"
        what = ("gradient of " if gradient else "") + (f"{n} steps, h = {h:.3g}" if n else "PID 1e-10 to t = 20")
        runs.append([label, f"cG({k})", what, f"{best[False] * 1e3:.2f}", f"{best[True] * 1e3:.2f}",
                     f"{best[True] / best[False]:.2f}", updates, f"{gap:.0e}"])
        print(" | ".join(map(str, runs[-1])), flush=True)
    table = ("Newton matrix and inverse, one element (us):\n\n"
             + markdown_table(["system", "k", "tangents of R", "field at the points", "ratio"], matrices)
             + "\n\nRuns (ms):\n\n"
             + markdown_table(["system", "method", "run", "tangents of R", "field at the points", "ratio",
                               "updates", "end states differ by"], runs) + "\n")
    write("newton", {"matrices": matrices, "runs": runs}, markdown=table)


if __name__ == "__main__":
    sys.exit(main())
