"""The root finder's cost per element, its iterations, and the kernels its loops launch.

    python benchmarks/bench_solver.py

On XLA's CPU runtime each fused kernel of a loop body is a task of its own, so a loop's cost
follows its kernel count more than its arithmetic (docs/solver.md, "The implicit solve"). For a
few scenes (the FPUT chain, Kepler, a batch of Kepler orbits, a stiff linear chain with
``krylov=True``) this measures microseconds per element (compiled ahead, best of five calls;
states only returned, so no error estimate), Newton iterations and batch updates per element,
and the number of kernels in the body of every while loop of the compiled program, read from
its HLO: the fixed-point block, the Newton loops and the element. The chain's rows run
twice: with the Gauss-Seidel sweep of partitioned methods (the library's default for states
of more than 8 degrees of freedom) and with the plain fixed point ``Z <- Z - R(Z)`` (the
sweep's threshold, ``SolverOptions.sweep_dimension``, raised for that row), an A/B in one
run, and the contraction rate of either iteration at an element's root. Every row also counts the calls of H per element, by a callback
inside H (``h_calls``). Writes results/solver.json.
"""

import pathlib
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parent))

import galerkin_jax as gj  # noqa: E402
from _common import best_time, compiled, write  # noqa: E402
from galerkin_jax import _march, scenes  # noqa: E402

NOT_KERNELS = ("get-tuple-element", "constant", "bitcast", "parameter", "tuple")


def loop_kernels(hlo):
    """Kernels (instructions other than tuples, constants, bitcasts) in each while body."""
    bodies = {m.group(1): m.group(2) for m in re.finditer(r"\n%(\S+) \(.*?\) -> .*? \{\n(.*?)\n\}", hlo, re.S)}
    counts = []
    for body in re.findall(r"%\S+ = \S.*? while\(.*?body=%(\S+?),", hlo):
        ops = [m.group(2) for line in bodies.get(body, "").splitlines()
               if (m := re.match(r"\s*(ROOT )?%\S+ = \S+ ([\w-]+)\(", line))]
        counts.append(sum(op not in NOT_KERNELS for op in ops))
    return counts


def stiff_chain(n=50, k=100.0):
    def H(q, p):
        strain = jnp.diff(jnp.concatenate([jnp.zeros(1, q.dtype), q, jnp.zeros(1, q.dtype)]))
        return 0.5 * (p @ p) + 0.5 * k * (strain @ strain)

    return H, np.sin(np.arange(1, n + 1) / 8.0), np.zeros(n)


def kepler_batch(size=256):
    qs, ps = zip(*[scenes.kepler_orbit(np.zeros(1), e) for e in np.linspace(0.1, 0.7, size)])
    return np.concatenate(qs), np.concatenate(ps)


CASES = {  # name: (H, q0, p0, method, h, n_steps, members, options)
    "FPUT N = 64, cG(1) + midpoint": (scenes.fput(64), gj.CG(1, gj.midpoint()), 0.05, 10_000, 1, {}),
    "FPUT N = 64, cG(3) + Gauss 3": (scenes.fput(64), gj.CG(3, gj.gauss_legendre(3)), 0.05, 10_000, 1, {}),
    "FPUT N = 512, cG(3) + Gauss 3": (scenes.fput(512), gj.CG(3, gj.gauss_legendre(3)), 0.05, 2_000, 1, {}),
    "FPUT N = 64, GalerkinVI(3) + Gauss 3": (scenes.fput(64), gj.GalerkinVI(3, gj.gauss_legendre(3)), 0.05, 10_000,
                                             1, {}),
    "Kepler e = 0.6, cG(3) + Gauss 3, h = 0.01": (scenes.kepler(0.6), gj.CG(3, gj.gauss_legendre(3)), 0.01, 20_000,
                                                  1, {}),
    "Kepler e = 0.6, cG(6) + Gauss 6, h = 0.1": (scenes.kepler(0.6), gj.CG(6, gj.gauss_legendre(6)), 0.1, 2_000, 1, {}),
    "256 Kepler orbits, cG(2) + Gauss 2, h = 0.01": (scenes.kepler(0.6), gj.CG(2, gj.gauss_legendre(2)), 0.01, 1_000,
                                                     256, {}),
    "stiff chain N = 50, h omega = 10, cG(3) + Gauss 3, krylov": (None, gj.CG(3, gj.gauss_legendre(3)), 0.5, 20, 1,
                                                                   {"krylov": True}),
}


def measure(name, scene, method, h, n_steps, members, options, solver=None):
    if scene is None:
        H, q0, p0 = stiff_chain()
    else:
        H, q0, p0 = scene.H, scene.q0, scene.p0
    if members > 1:
        q0, p0 = kepler_batch(members)

    def runner(H, **extra):
        def run(q, p):
            sol = gj.integrate(H, q, p, method=method, h=h, n_steps=n_steps, save_every=n_steps, solver=solver,
                               **options, **extra)
            return sol.q[-1], sol.p[-1], sol.status, sol.stats

        return jax.vmap(run) if members > 1 else run

    fn = runner(H)
    args = (jnp.asarray(q0), jnp.asarray(p0))
    compile_s, call = compiled(fn, *args)
    kernels = loop_kernels(call.as_text())
    q, p, status, stats = call(*args)
    run_s = best_time(call, *args, repeat=5)
    stats = {k: float(np.mean(v)) / n_steps for k, v in stats.items()}
    row = {
        "compile_s": compile_s, "us_per_member_step": 1e6 * run_s / (n_steps * members), "status": int(np.max(status)),
        "iterations_per_element": stats["num_newton_iterations"],
        "batch_updates_per_element": stats["batch_newton_iterations"], "kernels_per_loop_body": kernels,
    }
    # the error estimate off: XLA drops it from the timed run, but not a callback's calls
    row["h_calls_per_element"] = h_calls(lambda H: runner(H, error_estimate=False), H, args) / n_steps
    print(f"{name:58} {row['us_per_member_step']:8.3f} us  status {row['status']}"
          f"  iterations {row['iterations_per_element']:5.2f}  batch updates {row['batch_updates_per_element']:5.2f}"
          f"  H calls {row['h_calls_per_element']:5.2f}  compile {compile_s:4.2f} s  kernels per loop body {kernels}",
          flush=True)
    return row


def h_calls(runner, H, args):
    """Calls of H in a run, ``runner(H)`` on ``args``, counted by a callback inside H. One call
    evaluates H at every quadrature point of every member, so for the batch it counts the
    batch's calls. Each residual of the Gauss-Seidel sweep calls H twice (its q half and its p
    half), any other residual once, and ``GalerkinVI``'s increment once more; so this checks,
    independently of the solver's own counts, that a step costs its updates and one residual more."""
    calls = []

    def counted(q, p):
        jax.debug.callback(lambda: calls.append(1))
        return H(q, p)

    jax.block_until_ready(jax.jit(runner(counted))(*args))
    return len(calls)


def contraction(scene, method, h, n_steps=300, solver=None):
    """The fixed-point iteration's asymptotic rate, the spectral radius of ``I - dR/dZ`` at an
    element's root after ``n_steps`` elements, for the residual the solver iterates (the
    Gauss-Seidel sweep's, or the plain one's with ``PLAIN_FIXED_POINT``): the factor by which
    each update shrinks once the predictor's error is spread over every mode."""
    sol = gj.integrate(scene.H, scene.q0, scene.p0, method=method, h=h, n_steps=n_steps, save_every=n_steps,
                       solver=solver)
    q, p = sol.q[-1], sol.p[-1]
    options = _march.solver_options(method, solver=solver)
    *_, Z, _, status = _march.solve_element(method, scene.H, q, p, h, None, options)
    fn, params = _march.element_residual(scene.H, options.solver.sweep_dimension), (method, q, p, h, None)
    assert int(status) == 0
    J = jax.jacfwd(lambda z: fn(z.reshape(Z.shape), params).reshape(-1))(Z.reshape(-1))
    return float(np.max(np.abs(np.linalg.eigvals(np.eye(J.shape[0]) - np.asarray(J)))))


# the Gauss-Seidel sweep off: no state is above its size threshold
PLAIN_FIXED_POINT = gj.SolverOptions(sweep_dimension=2**62)


def main():
    rows = {}
    for name, case in CASES.items():
        rows[name] = measure(name, *case)
        if name.startswith("FPUT"):
            rows[name]["contraction"] = contraction(*case[:3])
            plain = rows[name + ", plain fixed point"] = measure(name + ", plain fixed point", *case,
                                                                 solver=PLAIN_FIXED_POINT)
            plain["contraction"] = contraction(*case[:3], solver=PLAIN_FIXED_POINT)
            print(f"{'':58} contraction rate: sweep {rows[name]['contraction']:.2e}, plain {plain['contraction']:.2e}",
                  flush=True)
    write("solver", {"rows": rows})


if __name__ == "__main__":
    main()
