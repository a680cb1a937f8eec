"""States between the nodes (project issue 36, item 1): the element polynomial against
``_interpolate.refine`` (Picard sweeps on the polynomial) and two-point Hermite interpolation
with the flow's derivatives at both nodes (Taylor mode, ``jax.experimental.jet``, or nested
``jax.jvp``), the candidates compared in docs/accuracy.md.

    python benchmarks/bench_interpolate.py              # all parts (~9 min)
    python benchmarks/bench_interpolate.py --only cost --name interpolate_cost  # some of: orders, pid, transformed, cost

* orders: Kepler e = 0.5 and 0.9 over one orbit from perihelion, cG(k) + Gauss k (k = 2, 4, 6),
  fixed steps, three h each. At 7 places alpha inside every element: the error against the
  exact orbit ("global") and against the exact flow from the element's start node
  ("local", f and g functions); at the nodes the global error and the local error of z1.
  Fitted orders over the three h, and each candidate's error over the nodes' error.
* pid: cG(6) + PIDController(1e-8, 1e-8) (and 1e-5 at e = 0.9), one orbit, 3999 equally
  spaced times: the error against the exact orbit (the issue's case).
* transformed: Kepler e = 0.99 from apocentre with TimeTransform (cG(6), h = 0.4 in tau,
  the default s and s = (r / r0)^(3/2); cG(4), h = 0.8, s = (r / r0)^(3/2)), ``--orbits``
  orbits, 4001 equally spaced times (those in the last, shortened, element left out): the
  largest |H - H0| at the nodes and at the times, and the largest over the orbits of the
  ratio of the times' largest error in an orbit to the nodes' in that orbit.
* cost: microseconds per interpolated time, 4000 times in random elements of a cG(k) run on
  Kepler e = 0.5 (and of the time-transformed cG(6) run, default s, whose field holds H's
  Hessian): vmapped over the times, and one after another in a ``lax.fori_loop`` (as a
  run's loop writes them); compile time of the vmapped program.

Writes results/interpolate.json.
"""

import argparse
import functools
import pathlib
import sys
from fractions import Fraction
from math import comb, factorial

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import jet

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))
sys.path.insert(0, str(pathlib.Path(__file__).parent.parent / "tests"))

import galerkin_jax as gj  # noqa: E402
import helpers  # noqa: E402
from _common import best_time, compiled, element_polynomials, write  # noqa: E402
from galerkin_jax import _adaptive, _basis, _interpolate, _output  # noqa: E402
from galerkin_jax._defect import symplectic_field  # noqa: E402
from galerkin_jax._march import bind_args  # noqa: E402

ALPHA = np.array([0.1, 0.25, 0.4, 0.5, 0.6, 0.75, 0.9])


# ---------------------------------------------------------------------------------------------
# candidate (a): two-point Hermite interpolation, degree 2r + 1, error O(h^(2r + 2))


def taylor_jet(H, z, h, r):
    """(r + 1, 2d): z^(j)(0) / j! of the flow through z in master time (z' = h F(z)), by Taylor
    mode: jet of order j gives z^(j + 1) from z', ..., z^(j)."""
    g = lambda z: h * symplectic_field(H)(z)
    derivatives = [g(z)]
    for _ in range(1, r):
        derivatives.append(jet.jet(g, (z,), (tuple(derivatives),))[1][-1])
    return jnp.stack([z] + [d / factorial(j + 1) for j, d in enumerate(derivatives)])


def taylor_jvp(H, z, h, r):
    """As ``taylor_jet``, by j nested ``jax.jvp`` of F along the Taylor polynomial known so far
    (the fallback where jet lacks a primitive of H)."""
    g = lambda z: h * symplectic_field(H)(z)
    coefficients = [z, g(z)]
    for j in range(1, r):
        known = jnp.stack(coefficients)

        def along(a, known=known):
            u = known[-1]
            for c in known[-2::-1]:  # Horner: no a ** 0, whose derivative at 0 is NaN
                u = c + a * u
            return g(u)

        f = along
        for _ in range(j):
            f = _derivative(f)
        coefficients.append(f(jnp.zeros((), z.dtype)) / factorial(j + 1))
    return jnp.stack(coefficients)


def _derivative(f):
    """a -> f'(a), forward mode."""
    return lambda a: jax.jvp(f, (a,), (jnp.ones_like(a),))[1]


@functools.lru_cache(maxsize=None)
def hermite_matrix(r):
    """B, (2r + 2, 2r + 2): Legendre coefficients on [0, 1] of the polynomial with Taylor
    coefficients a_0..a_r at 0 and b_0..b_r at 1, from (a, b); exact rationals rounded once."""
    n = 2 * r + 2
    A = [[Fraction(0)] * n for _ in range(n)]
    for j in range(r + 1):
        A[j][j] = Fraction(1)
        for k in range(n):
            A[r + 1 + j][k] = Fraction(comb(k, j))
    M = [row + [Fraction(int(i == j)) for j in range(n)] for i, row in enumerate(A)]
    for c in range(n):  # Gauss-Jordan in rationals: monomial coefficients from the data
        p = next(i for i in range(c, n) if M[i][c] != 0)
        M[c], M[p] = M[p], M[c]
        M[c] = [x / M[c][c] for x in M[c]]
        for i in range(n):
            if i != c and M[i][c] != 0:
                M[i] = [x - M[i][c] * y for x, y in zip(M[i], M[c])]
    # (2i + 1) int_0^1 P_i(2a - 1) a^k da, P_i(2a - 1) = sum_s (-1)^(i + s) C(i, s) C(i + s, s) a^s
    L = [[Fraction(2 * i + 1) * sum(Fraction((-1) ** (i + s) * comb(i, s) * comb(i + s, s), k + s + 1)
                                    for s in range(i + 1)) for k in range(n)] for i in range(n)]
    return np.array([[float(sum(L[i][k] * M[k][n + j] for k in range(n))) for j in range(n)] for i in range(n)])


def hermite(H, z0, z1, h, r, taylor=taylor_jet):
    """Legendre coefficients of the Hermite interpolant minus z0, (2r + 2, 2d)."""
    c = jax.vmap(lambda z: taylor(H, z, h, r))(jnp.stack([z0, z1]))
    data = jnp.concatenate([c[0].at[0].add(-z0), c[1].at[0].add(-z0)])
    return _basis.combine(jnp.asarray(hermite_matrix(r), z0.dtype), data)


def candidates(H, k):
    """name -> (z0, z1, W, h) -> Legendre coefficients minus z0."""
    return {
        "polynomial": lambda z0, z1, W, h: W,
        "refine 2k": lambda z0, z1, W, h: _interpolate.refine(H, z0, z1, W, h, order=2 * k),
        "refine 2k+1": lambda z0, z1, W, h: _interpolate.refine(H, z0, z1, W, h, order=2 * k + 1),
        "Hermite r=k-1": lambda z0, z1, W, h: hermite(H, z0, z1, h, k - 1),
        "Hermite r=k": lambda z0, z1, W, h: hermite(H, z0, z1, h, k),
    }


# ---------------------------------------------------------------------------------------------
# references


def kepler_flow(z, t):
    """The exact Kepler flow (mu = 1, bound) of states z (n, 4) over times t (n,): f and g
    functions, Kepler's equation in the eccentric anomaly's increment by Newton."""
    q, p = z[:, :2], z[:, 2:]
    r0 = np.linalg.norm(q, axis=1)
    a = 1.0 / (2.0 / r0 - np.sum(p * p, axis=1))
    n = a**-1.5
    es, ec = np.sum(q * p, axis=1) / np.sqrt(a), 1.0 - r0 / a  # e sin E0, e cos E0
    dE = n * t
    for _ in range(60):
        dE = dE - (dE + es * (1 - np.cos(dE)) - ec * np.sin(dE) - n * t) / (1 + es * np.sin(dE) - ec * np.cos(dE))
    c, s = np.cos(dE), np.sin(dE)
    r = a * (1 - ec * c + es * s)
    f, g = 1 - a / r0 * (1 - c), t + (s - dE) / n
    fd, gd = -np.sqrt(a) / (r * r0) * s, 1 - a / r * (1 - c)
    return np.concatenate([f[:, None] * q + g[:, None] * p, fd[:, None] * q + gd[:, None] * p], axis=1)


def exact(t, e):
    return np.concatenate(helpers.kepler_exact(np.asarray(t, float), e)).T


def fit(hs, errors):
    return float(np.polyfit(np.log(hs), np.log(errors), 1)[0])


# ---------------------------------------------------------------------------------------------
# parts

STEPS = {(0.5, 2): (0.1, 0.05, 0.025), (0.5, 4): (0.2, 0.1, 0.05), (0.5, 6): (0.4, 0.28, 0.2),
         (0.9, 2): (0.005, 0.0025, 0.00125), (0.9, 4): (0.02, 0.01, 0.005), (0.9, 6): (0.04, 0.02, 0.01)}


def orders():
    rows = []
    for (e, k), hs in STEPS.items():
        H, q0, p0 = helpers.kepler(e)
        per_h = []
        hs = [2 * np.pi / round(2 * np.pi / h) for h in hs]  # whole elements per orbit
        for h in hs:
            n = round(2 * np.pi / h)
            sol = gj.integrate(H, q0, p0, method=gj.CG(k, gj.gauss_legendre(k)), h=h, n_steps=n, dense=True)
            d = sol.dense
            z, t = np.asarray(d.z), np.asarray(d.t)
            ts = (t[:-1, None] + ALPHA[None, :] * h).ravel()
            local_reference = kepler_flow(np.repeat(z[:-1], ALPHA.size, axis=0), np.tile(ALPHA * h, n))
            errors = dict(nodes=(np.abs(z - exact(t, e)).max(),
                                 np.abs(z[1:] - kepler_flow(z[:-1], np.full(n, h))).max()))
            for name, f in candidates(H, k).items():
                values = jax.jit(jax.vmap(lambda z0, z1, W: _output.on_polynomial(z0, f(z0, z1, W, h),
                                                                                  jnp.asarray(ALPHA))))
                v = np.asarray(values(d.z[:-1], d.z[1:], d.W)).reshape(-1, z.shape[1])
                errors[name] = (np.abs(v - exact(ts, e)).max(), np.abs(v - local_reference).max())
            per_h.append(errors)
        for name in per_h[0]:
            g = [x[name][0] for x in per_h]
            loc = [x[name][1] for x in per_h]
            row = dict(e=e, k=k, candidate=name, h=list(hs), global_error=g, global_order=fit(hs, g),
                       global_ratio=[a / x["nodes"][0] for a, x in zip(g, per_h)], local_error=loc,
                       local_order=fit(hs, loc), local_ratio=[a / x["nodes"][1] for a, x in zip(loc, per_h)])
            rows.append(row)
            print(f"e = {e} cG({k}) {name:14s} global " + " ".join(f"{x:.1e}" for x in g)
                  + f" order {row['global_order']:5.2f} ratio " + " ".join(f"{x:.2g}" for x in row["global_ratio"])
                  + " | local " + " ".join(f"{x:.1e}" for x in loc) + f" order {row['local_order']:5.2f} ratio "
                  + " ".join(f"{x:.2g}" for x in row["local_ratio"]))
    return rows


def pid():
    rows = []
    for e, k, tol in ((0.5, 6, 1e-8), (0.9, 6, 1e-8), (0.9, 6, 1e-5)):
        H, q0, p0 = helpers.kepler(e)
        sol = gj.integrate(H, q0, p0, method=gj.CG(k, gj.gauss_legendre(k)), h=0.01, t1=2 * np.pi,
                           controller=gj.PIDController(tol, tol), dense=True, max_steps=2000)
        n = int(sol.stats["num_accepted_steps"])
        t, z = np.asarray(sol.dense.t[: n + 1]), sol.dense.z[: n + 1]
        W = element_polynomials(gj.CG(k, gj.gauss_legendre(k)), H, z[:n], np.diff(t))
        ts = np.linspace(0, 2 * np.pi, 4001)[1:-1]
        el = np.clip(np.searchsorted(t, ts, side="right") - 1, 0, n - 1)
        hs, alphas = jnp.asarray(np.diff(t)[el]), jnp.asarray((ts - t[el]) / np.diff(t)[el])
        row = dict(e=e, k=k, tol=tol, steps=n, nodes=float(np.abs(np.asarray(z) - exact(t, e)).max()))
        for name, f in candidates(H, k).items():
            one = lambda z0, z1, W, h, a: _output.on_polynomial(z0, f(z0, z1, W, h), a[None])[0]
            v = jax.jit(jax.vmap(one))(z[el], z[el + 1], W[el], hs, alphas)
            row[name] = float(np.abs(np.asarray(v) - exact(ts, e)).max())
        rows.append(row)
        print(row)
    return rows


def transformed(orbits):
    rows = []
    e = 0.99
    He = helpers.kepler(e)[0]
    q0, p0 = (jnp.asarray(x) for x in helpers.kepler_exact(np.pi, e))
    r0 = float(np.linalg.norm(np.asarray(q0)))
    own = lambda q, p: (jnp.sum(q * q) / r0**2) ** 0.75
    T = orbits * 2 * np.pi
    H0 = float(He(q0, p0))
    for k, h, density in ((6, 0.4, None), (6, 0.4, "(r/r0)^1.5"), (4, 0.8, "(r/r0)^1.5")):
        controller = gj.TimeTransform(None if density is None else own)
        sol = gj.integrate(He, q0, p0, method=gj.CG(k, gj.gauss_legendre(k)), h=h, t1=T, controller=controller,
                           dense=True, max_steps=200 * orbits + 1000, error_estimate=False)
        n, d = int(sol.stats["num_accepted_steps"]), sol.dense
        K, _, _, args, _, clock = _adaptive.problem(He, controller, q0, p0, 0.0, None)
        Kb = bind_args(K, args)
        z, t = d.z[: n + 1], np.asarray(d.t[: n + 1])
        # the last element's h is not h: it is left out below
        W = element_polynomials(gj.CG(k, gj.gauss_legendre(k)), Kb, z[:n], h)
        energy = jax.jit(lambda z: jnp.abs(jax.vmap(lambda x: He(*_output.user_view(x, clock)))(z) - H0))
        nodes = np.asarray(energy(z))
        ts = np.linspace(0, T, 4001)[1:-1]
        el = np.clip(np.searchsorted(t, ts, side="right") - 1, 0, n - 1)
        keep = el < n - 1  # the last element is shortened in tau to land on T: its h is not h
        ts, el = ts[keep], el[keep]
        orbit_of_nodes = np.minimum(t // (2 * np.pi), orbits - 1)
        orbit_of_saves = np.minimum(ts // (2 * np.pi), orbits - 1)
        row = dict(k=k, h=h, s=density or "default", orbits=orbits, steps=n, saves=int(ts.size),
                   nodes=float(nodes.max()))
        for name, f in candidates(Kb, k).items():
            def one(z0, z1, W, tt):
                refined = f(z0, z1, W, h)
                alpha = _output.alpha_at_time(z0, refined, tt, 0.0, h, clock)
                return _output.on_polynomial(z0, refined, alpha[None])[0]

            v = jax.jit(jax.vmap(one))(z[el], z[el + 1], W[el], jnp.asarray(ts))
            saved = np.asarray(energy(v))
            per_orbit = [saved[orbit_of_saves == i].max() / nodes[orbit_of_nodes == i].max() for i in range(orbits)]
            row[name] = dict(max=float(saved.max()), worst_orbit_ratio=float(max(per_orbit)),
                             time_error=float(np.abs(np.asarray(v[:, clock]) - ts).max()))
        rows.append(row)
        print(row)
    return rows


def cost(count=4000):
    rows = []
    rng = np.random.default_rng(0)
    H, q0, p0 = helpers.kepler(0.5)
    e = 0.99
    He = helpers.kepler(e)[0]
    qa, pa = (jnp.asarray(x) for x in helpers.kepler_exact(np.pi, e))
    K, _, _, args, _, _ = _adaptive.problem(He, gj.TimeTransform(), qa, pa, 0.0, None)
    cases = [(f"Kepler, cG({k})", H, k, dict(h=0.05, n_steps=126), (q0, p0)) for k in (2, 4, 6)]
    cases.append(("Kepler e = 0.99 time-transformed (default s), cG(6)", bind_args(K, args), 6,
                  dict(h=0.4, t1=4 * np.pi, controller=gj.TimeTransform(), max_steps=400), (qa, pa)))
    for label, Hb, k, kw, (qs, ps) in cases:
        sol = gj.integrate(He if "transformed" in label else H, qs, ps, method=gj.CG(k, gj.gauss_legendre(k)),
                           dense=True, **kw)
        n = int(sol.stats["num_accepted_steps"]) - 1
        el = rng.integers(0, n, count)
        h = kw["h"]
        W = element_polynomials(gj.CG(k, gj.gauss_legendre(k)), Hb, sol.dense.z[el], h)
        data = (sol.dense.z[el], sol.dense.z[el + 1], W, jnp.asarray(rng.uniform(0, 1, count)))
        row = dict(case=label)
        named = dict(candidates(Hb, k))
        del named["Hermite r=k-1"]
        named["Hermite r=k (nested jvp)"] = lambda z0, z1, W, h, k=k, Hb=Hb: hermite(Hb, z0, z1, h, k, taylor_jvp)
        for name, f in named.items():
            one = lambda z0, z1, W, a, f=f: _output.on_polynomial(z0, f(z0, z1, W, h), a[None])[0]

            def loop(z0, z1, W, a, one=one):
                body = lambda i, acc: acc + one(z0[i], z1[i], W[i], a[i])
                return jax.lax.fori_loop(0, count, body, jnp.zeros_like(z0[0]))

            compile_s, vmapped = compiled(jax.vmap(one), *data)
            _, looped = compiled(loop, *data)
            row[name] = dict(compile_s=compile_s, vmapped_us=best_time(vmapped, *data) / count * 1e6,
                             loop_us=best_time(looped, *data) / count * 1e6)
            print(label, name, {key: round(v, 3) for key, v in row[name].items()})
        rows.append(row)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="*", default=["orders", "pid", "transformed", "cost"])
    parser.add_argument("--orbits", type=int, default=100)
    parser.add_argument("--name", default="interpolate")
    options = parser.parse_args()
    parts = dict(orders=orders, pid=pid, transformed=lambda: transformed(options.orbits), cost=cost)
    results = {name: parts[name]() for name in options.only}
    write(options.name, results)


if __name__ == "__main__":
    main()
