"""Variable steps that keep the structure, two ways (issue 22, item 4): the Poincare time
transformation (``gj.TimeTransform``, symplectic) against Hairer and Soderlind's reversible
step-size control, with the same method and the same step density.

    python benchmarks/bench_reversible.py [--orbits 1000]

Kepler e = 0.9 from apocentre, cG(4)+Gauss 4, step density sigma = (r / r0)^(3/2) (the orbit's
dynamical time scale, sigma(z0) = 1), fictive step eps:

* TimeTransform: K = sigma (H + p_t) on the extended state, the constant step eps in tau;
* Hairer-Soderlind [E. Hairer, G. Soderlind, Explicit, time reversible, adaptive step size
  control, SIAM J. Sci. Comput. 26 (2005) 1838-1851]: rho_{n+1/2} = rho_{n-1/2} + eps G(z_n),
  h_n = eps / rho_{n+1/2}, z_{n+1} = Phi_{h_n}(z_n) with G = -(grad sigma . f) / sigma, so that
  rho follows 1 / sigma; symmetric (reversible) because the method is, not symplectic. Here a
  ``lax.scan`` of ``gj.step`` (each element from the constant guess: no predictor, so its run
  time is not comparable; the steps and the errors are).

Reports, per eps: steps, the largest energy error over the nodes, in the first and the last
quarter of the run, and the run time. Writes results/reversible.json.
"""

import argparse
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import energy_quarters, write  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

METHOD = gj.CG(4, gj.gauss_legendre(4))
EPS = (0.8, 0.4, 0.2)


def problem(e, orbits):
    scene = scenes.kepler(e)
    q0, p0 = (jnp.asarray(x) for x in scene.exact(np.pi))
    r0 = float(np.linalg.norm(np.asarray(q0)))
    sigma = lambda q, p: (jnp.sum(q * q) / r0**2) ** 0.75
    return scene.H, q0, p0, 2 * np.pi * orbits, sigma


def quarters(t, dH, T):
    ok = np.isfinite(t) & np.isfinite(dH)
    return energy_quarters(t[ok], np.abs(dH[ok]), T)


def time_transform(H, q0, p0, T, sigma, eps):
    max_steps = int(40 * T / eps) + 64

    def run(q0, p0, eps):
        sol = gj.integrate(H, q0, p0, method=METHOD, h=eps, t1=T, controller=gj.TimeTransform(sigma),
                           max_steps=max_steps, dense=True, error_estimate=False)
        q, p = sol.dense.view(sol.dense.z)
        return sol.dense.t, jax.vmap(H)(q, p) - H(q0, p0), sol.stats["num_accepted_steps"], sol.status

    return jax.jit(run)


def hairer_soderlind(H, q0, p0, sigma, n_steps):
    """The reversible controller's run of ``n_steps`` steps: ``(t, energy error)`` at its nodes."""
    def G(q, p):
        dq, dp = jax.grad(H, argnums=1)(q, p), -jax.grad(H, argnums=0)(q, p)
        gq, gp = jax.grad(sigma, argnums=(0, 1))(q, p)
        return -(gq @ dq + gp @ dp) / sigma(q, p)

    def run(q0, p0, eps):
        def body(c, _):
            q, p, t, rho = c
            rho = rho + eps * G(q, p)  # rho_{n+1/2} from rho_{n-1/2}
            h = eps / rho
            q, p, status = gj.step(H, q, p, method=METHOD, h=h, return_status=True)
            return (q, p, t + h, rho), (t + h, H(q, p) - H(q0, p0), status)

        rho = 1.0 / sigma(q0, p0) - 0.5 * eps * G(q0, p0)  # rho_{-1/2}: rho_{1/2} = 1/sigma + eps G / 2
        _, (t, dH, status) = jax.lax.scan(body, (q0, p0, 0.0 * eps, rho), None, length=n_steps)
        return t, dH, jnp.max(status)

    return jax.jit(run)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--orbits", type=int, default=1000)
    opts = parser.parse_args()
    H, q0, p0, T, sigma = problem(0.9, opts.orbits)
    rows = []
    tt = time_transform(H, q0, p0, T, sigma, EPS[0])
    for eps in EPS:
        t0 = time.perf_counter()
        t, dH, steps, status = jax.block_until_ready(tt(q0, p0, eps))
        run_s = time.perf_counter() - t0  # compile included on the first eps
        row = dict(kind="TimeTransform", eps=eps, steps=int(steps), status=int(status), wall_s=run_s,
                   **quarters(np.asarray(t), np.asarray(dH), T))
        rows.append(row)
        n = int(steps)
        hs = hairer_soderlind(H, q0, p0, sigma, n)
        t0 = time.perf_counter()
        t, dH, status = jax.block_until_ready(hs(q0, p0, eps))
        hs_s = time.perf_counter() - t0
        t = np.asarray(t)
        rows.append(dict(kind="Hairer-Soderlind", eps=eps, steps=n, status=int(status), wall_s=hs_s,
                         reached_t=float(t[-1]), **quarters(t, np.asarray(dH), min(T, float(t[-1])))))
        for r in rows[-2:]:
            print(f"{r['kind']:17s} eps {eps:4.2f}: steps {r['steps']:7d} status {r['status']} "
                  f"max|dH| {r['max_energy_error']:.2e} last/first quarter {r['last_over_first']:.2f} "
                  f"({r['wall_s']:.1f} s with compilation)", flush=True)
    write("reversible", dict(e=0.9, orbits=opts.orbits, method="cG(4)+Gauss 4", density="(r/r0)^(3/2)", rows=rows))


if __name__ == "__main__":
    main()
