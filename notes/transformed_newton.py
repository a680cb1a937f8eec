"""Simplified Newton on the transformed stage system of cG(k) + Gauss k, against the library's
root finder, on the planar 10-link pendulum (non-separable; ``benchmarks/_moderate.py``).

    python notes/transformed_newton.py        (writes notes/transformed_newton.md, ~3 min)

cG(k)'s element equations are R(C) = C - h M F(z0 + B C) row-wise (``_galerkin.CG``: B the
Legendre antiderivatives at the points, M = S V^T W B the k x k matrix of the tested integrals).
With the field's Jacobian J taken at one state, Newton's matrix is I - h M (x) J; M = T L T^-1
(complex eigenvalues: L's conjugate pairs share one factorisation) turns each update into
ceil(k/2) complex 2d x 2d solves (I - h l_j J) (Hairer and Wanner's Radau5, IRKGL16). Here J is
taken at the predicted mid-element state, every element or every fourth, the predictor is the
library's (the previous element's polynomial continued), and the iteration stops where the
library's does at a tolerance (the error left, step theta / (1 - theta), below 1e-10 of |C|).
The library runs cG(k) + Gauss k at ``SolverOptions(tolerance=1e-10)``. Both in one process,
best of 5 calls each, every 10th element saved; the same end state to 1e-9 (the tolerance's
accumulated error).
"""

import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "benchmarks"))
jax.config.update("jax_enable_x64", True)

import _moderate  # noqa: E402

import galerkin_jax as gj  # noqa: E402
from galerkin_jax import _basis  # noqa: E402
from galerkin_jax._defect import hamilton_field  # noqa: E402

TOLERANCE = 1e-10


def tested_matrix(k, rule):
    """M with dR/dC = I - h M (x) J for a field of constant Jacobian J."""
    with jax.ensure_compile_time_eval():
        alpha, w = jnp.asarray(rule.points), np.asarray(rule.weights)
        B = np.asarray(_basis.legendre_antiderivatives(alpha, k))
        V = np.asarray(_basis.legendre_values(alpha, k))
    return _basis.test_scale(k)[:, None] * (V.T @ (w[:, None] * B))


def transformed_run(H, q0, p0, k, h, n, refresh):
    """n elements of cG(k) + Gauss k by simplified Newton on the transformed stage system, J
    refreshed every ``refresh`` elements. Returns (end state, updates per element)."""
    method = gj.CG(k, gj.gauss_legendre(k))
    lam, T = np.linalg.eig(tested_matrix(k, method.quadrature))
    kept = [i for i in range(k) if lam[i].imag >= 0]  # one of each conjugate pair
    partner = [kept.index(i) if i in kept else kept.index(int(np.argmin(np.abs(lam - np.conj(lam[i])))))
               for i in range(k)]
    conjugate = jnp.asarray([i not in kept for i in range(k)])
    T, T_inv, lam_kept = jnp.asarray(T), jnp.asarray(np.linalg.inv(T)), jnp.asarray(lam[kept])
    d = q0.shape[0]
    jacobian = jax.jacfwd(lambda z: hamilton_field(H)(z[:d], z[d:]))
    mid = _basis.legendre_antiderivatives(jnp.asarray([0.5]), k)[0]

    def factor(z):
        matrices = jnp.eye(2 * d) - h * lam_kept[:, None, None] * jacobian(z)[None].astype(complex)
        return jax.vmap(jax.scipy.linalg.lu_factor)(matrices)

    def update(lu, r):
        r_hat = T_inv @ r.astype(complex)
        solved = jax.vmap(jax.scipy.linalg.lu_solve)(lu, r_hat[jnp.asarray(kept)])[jnp.asarray(partner)]
        return (T @ jnp.where(conjugate[:, None], jnp.conj(solved), solved)).real

    def element(carry, _):
        z0, previous, lu, age = carry
        q, p = z0[:d], z0[d:]
        C = method.initial_guess(q, p, previous=(previous[0][:d], previous[0][d:], previous[1]))
        lu = jax.lax.cond(age % refresh == 0, lambda: factor(z0 + mid @ C), lambda: lu)

        def body(s):
            C, updates, step, _ = s
            dC = update(lu, method.residual(H, q, p, C, h))
            new = jnp.sqrt(jnp.mean(dC**2))
            return C - dC, updates + 1, new, jnp.where(updates > 0, new / step, 1.0)  # a rate needs two

        def going(s):
            C, updates, step, theta = s
            left = jnp.where(theta < 1, step * theta / (1 - theta), jnp.inf)
            return (updates < 50) & ~(left <= TOLERANCE * jnp.sqrt(jnp.mean(C**2)))

        C, updates, _, _ = jax.lax.while_loop(going, body, (C, 0, jnp.inf, jnp.asarray(1.0)))
        return (z0 + C[0], (z0, C), lu, age + 1), updates

    z0 = jnp.concatenate([q0, p0])
    start = (z0, (z0, jnp.zeros((k, 2 * d))), factor(z0), 0)
    (z, _, _, _), updates = jax.lax.scan(element, start, None, length=n)
    return z, jnp.mean(updates)


def library_run(H, q0, p0, k, h, n):
    sol = gj.integrate(H, q0, p0, method=gj.CG(k, gj.gauss_legendre(k)), h=h, n_steps=n, save_every=n // 10,
                       error_estimate=False, solver=gj.SolverOptions(tolerance=TOLERANCE))
    return jnp.concatenate([sol.q[-1], sol.p[-1]]), sol.stats["num_newton_iterations"] / n, sol.status


def best(f, *args):
    jax.block_until_ready(f(*args))
    times = []
    for _ in range(5):
        start = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - start)
    return min(times)


def main():
    chain = _moderate.pendulum_chain(10, T=20.0)
    H, q0, p0 = chain.H, jnp.asarray(chain.q0), jnp.asarray(chain.p0)
    rows = ["| k, n (h) | library: ms, updates / element | transformed, J every element | transformed, J every 4th |",
            "| --- | --- | --- | --- |"]
    for k, n in [(3, 2000), (3, 760), (3, 320), (4, 540), (4, 230), (4, 120), (6, 130), (6, 60)]:
        h = chain.T / n
        library = jax.jit(lambda q0, p0: library_run(H, q0, p0, k, h, n))
        z_lib, it_lib, status = library(q0, p0)
        cells = [f"{best(library, q0, p0) * 1e3:.1f} ms, {float(it_lib):.2f} (status {int(status)})"]
        for refresh in (1, 4):
            run = jax.jit(lambda q0, p0: transformed_run(H, q0, p0, k, h, n, refresh))
            z, it = run(q0, p0)
            gap = float(jnp.max(jnp.abs(z - z_lib)))
            cells.append(f"{best(run, q0, p0) * 1e3:.1f} ms, {float(it):.2f} (end state off by {gap:.0e})")
        rows.append(f"| {k}, {n} ({h:.3g}) | " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    text = (f"`python notes/transformed_newton.py` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
            f"jax {jax.__version__}, {jax.devices()[0].platform})\n\n" + "\n".join(rows) + "\n")
    (pathlib.Path(__file__).parent / "transformed_newton.md").write_text(text)


if __name__ == "__main__":
    main()
