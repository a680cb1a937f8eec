"""Gradients through runs whose steps a controller chooses: paid for by the steps taken.

    python -m benchmarks gradients [--only max_steps peers long members fixed] [--name gradients]

max_steps: the beta-FPUT chain of 6 masses, cG(4) + Gauss 4, PIDController(1e-6, 1e-6) to T = 10,
    d/dq0 of |q(T)|^2: forward and gradient time, XLA's temporary buffers of the compiled gradient
    and the peak resident memory of a fresh process that computes it, against ``max_steps``;
    diffrax Tsit5 + PID (its default adjoint, RecursiveCheckpointAdjoint) beside it.
peers: Kepler e = 0.9 over one orbit (cG(6) + Gauss 7) and FPUT N = 64 (cG(4) + Gauss 4, T = 10):
    forward and gradient time of a PID run (max_steps 10^5; the gradient also at the default
    max_steps, without and with ``checkpoint=True``), its final error against the same run at a
    tolerance 100 times tighter, and diffrax Dopri8 + PID at the tolerance that reaches that error.
long: the gradient's memory at max_steps = 10^6 for FPUT N = 64, and one gradient through ~10^5 steps.
members: a controller's sweep over 8 tolerances (1e-4 .. 1e-11) of Kepler e = 0.9 and of the 6-mass
    chain: d/dq0 of the sum of |q(T)|^2 (and a forward-mode product), all members at once and with
    ``batch_size`` 1 and 4, beside the members' gradients alone; compile and run times apart.
fixed: gradients through fixed steps (Kepler e = 0.5, cG(6), 126 steps; cG(2) + Gauss 3, 2000
    steps, ``checkpoint=True``; FPUT N = 64, cG(4), 286 steps): forward and gradient, compile and run.
"""

import argparse
import json
import pathlib
import subprocess
import sys
import textwrap

from _common import best_time, compiled, show, timed, write  # first: one BLAS thread

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import _peers as peers  # noqa: E402
import galerkin_jax as gj  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

_PROCESS = textwrap.dedent("""
    import json, resource, sys, time
    import jax, jax.numpy as jnp
    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, {here!r})
    import bench_gradients as b
    loss, x = b.{case}({max_steps})
    f = jax.jit(jax.grad(loss) if {gradient} else loss)
    jax.block_until_ready(f(x))
    print(json.dumps(dict(peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)))
""")


def peak_memory(case, max_steps, gradient=True):
    """Peak resident memory (MB) of a fresh process that compiles and computes one gradient (or
    the loss alone)."""
    code = _PROCESS.format(here=str(pathlib.Path(__file__).parent), case=case, max_steps=max_steps, gradient=gradient)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])["peak_mb"]


def fput_small(max_steps):
    scene = scenes.fput(6)
    loss = lambda q0: jnp.sum(gj.integrate(scene.H, q0, jnp.asarray(scene.p0), method=gj.CG(4, gj.gauss_legendre(4)),
                                           h=0.05, t1=10.0, controller=gj.PIDController(1e-6, 1e-6),
                                           max_steps=max_steps).q[-1] ** 2)
    return loss, jnp.asarray(scene.q0)


def fput_small_diffrax(max_steps):
    scene = scenes.fput(6)
    controller = diffrax.PIDController(rtol=1e-6, atol=1e-6)
    z = lambda q0: jnp.concatenate([q0, jnp.asarray(scene.p0)])
    loss = lambda q0: jnp.sum(peers.diffrax_solve(scene.H, 10.0, z(q0), diffrax.Tsit5(), 0.05, controller,
                                                  max_steps)[0][:6] ** 2)
    return loss, jnp.asarray(scene.q0)


def gradient_figures(loss, x, repeat=5):
    """``(run_s, temp_mb)`` of ``jax.grad(loss)`` at x, compiled once: the best of ``repeat`` runs
    and XLA's temporary buffers (``memory_analysis``)."""
    _, call = compiled(jax.grad(loss), x)
    jax.block_until_ready(call(x))
    return best_time(call, x, repeat=repeat), call.memory_analysis().temp_size_in_bytes / 1e6


def max_steps_part():
    rows = []
    for max_steps in (128, 4096, 20_000, 100_000, 1_000_000):
        row = dict(max_steps=max_steps)
        for name, case in (("galerkin_jax", "fput_small"), ("diffrax Tsit5", "fput_small_diffrax")):
            loss, x = globals()[case](max_steps)
            gradient_s, gradient_temp_mb = gradient_figures(loss, x)
            row[name] = dict(forward_s=timed(loss, x)[1], gradient_s=gradient_s,
                             gradient_temp_mb=gradient_temp_mb, peak_mb=peak_memory(case, max_steps),
                             forward_peak_mb=peak_memory(case, max_steps, gradient=False))
            row[name]["gradient_over_forward"] = row[name]["gradient_s"] / row[name]["forward_s"]
        rows.append(row)
        for name in ("galerkin_jax", "diffrax Tsit5"):
            show(f"max_steps {max_steps}, {name}", row[name])
    first, last = rows[1]["galerkin_jax"], rows[-1]["galerkin_jax"]
    return dict(scene="beta-FPUT, 6 masses, cG(4) + Gauss 4, PID 1e-6, T = 10", rows=rows,
                gradient_time_1e6_over_4096=last["gradient_s"] / first["gradient_s"],
                peak_memory_1e6_over_4096=last["peak_mb"] / first["peak_mb"],
                gradient_peak_over_forward_peak=max(r["galerkin_jax"]["peak_mb"] / r["galerkin_jax"]["forward_peak_mb"]
                                                    for r in rows))


def kepler():
    scene = scenes.kepler(0.9)
    return ("Kepler e = 0.9, one orbit, cG(6) + Gauss 7", scene.H, jnp.asarray(scene.q0), jnp.asarray(scene.p0),
            2 * np.pi, gj.CG(6, gj.gauss_legendre(7)), 1e-8)


def fput_large():
    scene = scenes.fput(64)
    return ("beta-FPUT, 64 masses, cG(4) + Gauss 4, T = 10", scene.H, jnp.asarray(scene.q0), jnp.asarray(scene.p0),
            10.0, gj.CG(4, gj.gauss_legendre(4)), 1e-8)


def peers_part():
    results = {}
    for problem in (kepler, fput_large):
        label, H, q0, p0, T, method, tol = problem()
        run = lambda q0, tol, max_steps=100_000, checkpoint=False: gj.integrate(
            H, q0, p0, method=method, h=0.01, t1=T, controller=gj.PIDController(tol, tol), max_steps=max_steps,
            checkpoint=checkpoint)
        reference = np.asarray(run(q0, tol / 100).q[-1])
        final = run(q0, tol)
        error = float(np.max(np.abs(final.q[-1] - reference)))
        loss = lambda q0, **kwargs: jnp.sum(run(q0, tol, **kwargs).q[-1] ** 2)
        ours = dict(steps=int(final.stats["num_accepted_steps"]), final_error=error,
                    forward_s=timed(lambda q0: run(q0, tol).q[-1], q0, repeat=20)[1])
        # also at the default max_steps (4096), and with the fewest roots kept (``checkpoint=True``)
        for key, kw in (("gradient", {}), ("gradient_default_max_steps", dict(max_steps=4096)),
                        ("gradient_checkpoint", dict(max_steps=4096, checkpoint=True))):
            ours[key + "_s"] = timed(jax.grad(lambda q0: loss(q0, **kw)), q0, repeat=20)[1]
            ours[key + "_over_forward"] = ours[key + "_s"] / ours["forward_s"]
        dopri8 = []
        for peer_tol in tol * 10.0 ** -np.arange(7):
            controller = diffrax.PIDController(rtol=peer_tol, atol=peer_tol)
            solve = lambda q0: peers.diffrax_solve(H, T, jnp.concatenate([q0, p0]), diffrax.Dopri8(), 0.01, controller,
                                                   100_000)
            z1, _, accepted, _ = solve(q0)
            peer_loss = lambda q0: jnp.sum(solve(q0)[0][: q0.size] ** 2)
            dopri8.append(dict(tol=float(peer_tol), steps=int(accepted),
                               final_error=float(np.max(np.abs(np.asarray(z1[: q0.size]) - reference))),
                               forward_s=timed(lambda q0: solve(q0)[0], q0)[1],
                               gradient_s=timed(jax.grad(peer_loss), q0)[1]))
            if dopri8[-1]["final_error"] <= ours["final_error"]:
                break
        best = dopri8[-1]  # the loosest tolerance whose error is at most ours (or the tightest tried)
        results[label] = dict(galerkin_jax=ours, dopri8=dopri8, dopri8_at_same_error=best,
                              gradient_ratio_to_dopri8=ours["gradient_s"] / best["gradient_s"])
        show(label, ours)
        show(f"{label}, Dopri8 at the same error", results[label] | best, "tol", "final_error", "gradient_s",
             "gradient_ratio_to_dopri8")
    return results


def long_part():
    label, H, q0, p0, T, method, tol = fput_large()
    out = {}
    for max_steps in (4096, 1_000_000):
        loss = lambda q0: jnp.sum(gj.integrate(H, q0, p0, method=method, h=0.01, t1=T, max_steps=max_steps,
                                               controller=gj.PIDController(tol, tol)).q[-1] ** 2)
        memory = jax.jit(jax.grad(loss)).lower(q0).compile().memory_analysis()
        out[f"gradient_temp_mb_at_max_steps_{max_steps}"] = memory.temp_size_in_bytes / 1e6
    span = 3000.0  # ~10^5 steps at PID 1e-6
    run = lambda q0: gj.integrate(H, q0, p0, method=method, h=0.05, t1=span, max_steps=1_000_000,
                                  controller=gj.PIDController(1e-6, 1e-6))
    gradient_s, gradient_temp_mb = gradient_figures(lambda q0: jnp.sum(run(q0).q[-1] ** 2), q0, repeat=1)
    out.update(scene=label + ", PID 1e-6", span=span, steps=int(run(q0).stats["num_accepted_steps"]),
               gradient_s=gradient_s, gradient_temp_mb=gradient_temp_mb)
    show("long", out)
    return out


def fixed_part():
    """Gradients through fixed steps, d/dq0 of |q_N|^2 + |p_N|^2: compile and run time of the
    forward run and of the gradient, and the gradient itself (a later tree must keep its digits;
    two trees compare by their result files, each records its commit)."""
    kepler, chain = ((s.H, jnp.asarray(s.q0), jnp.asarray(s.p0)) for s in (scenes.kepler(0.5), scenes.fput(64)))
    cases = {"kepler": (*kepler, gj.CG(6, gj.gauss_legendre(6)), 2 * np.pi / 126, 126, {}),
             "kepler_checkpoint": (*kepler, gj.CG(2, gj.gauss_legendre(3)), 0.01, 2000, dict(checkpoint=True)),
             "fput64": (*chain, gj.CG(4, gj.gauss_legendre(4)), 0.035, 286, {})}
    results = {}
    for case, (H, q0, p0, method, h, n, extra) in cases.items():
        def loss(q0):
            sol = gj.integrate(H, q0, p0, method=method, h=h, n_steps=n, save_every=n, **extra)
            return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.p[-1] ** 2)

        row = results[case] = {}
        for name, f in (("forward", loss), ("gradient", jax.grad(loss))):
            row[name + "_compile_s"], row[name + "_s"] = timed(f, q0, repeat=20)
        row["gradient"] = np.asarray(jax.grad(loss)(q0)).tolist()
        show(case, row)
    return results


def members_part(tolerances=tuple(10.0 ** -np.arange(4, 12))):
    results = {}
    fput = scenes.fput(6)
    problems = (kepler()[1:], (fput.H, jnp.asarray(fput.q0), jnp.asarray(fput.p0), 10.0,
                                gj.CG(4, gj.gauss_legendre(4)), None))
    for label, (H, q0, p0, T, method, _) in zip(("kepler", "fput_6"), problems):
        B, tols = len(tolerances), jnp.asarray(tolerances)
        configs = lambda q0s: gj.Configs(method=gj.stack_methods([method] * B), h=jnp.full(B, 0.05), q0=q0s,
                                         p0=jnp.stack([p0] * B))
        q0s = jnp.stack([q0] * B)

        def loss(q0s, batch_size):
            result = gj.sweep(H, configs(q0s), t1=T, controller=gj.PIDController(tols, tols), batch_size=batch_size)
            return jnp.sum(result.q ** 2)

        steps = gj.sweep(H, configs(q0s), t1=T, controller=gj.PIDController(tols, tols)).num_accepted_steps
        alone = lambda q0, tol: jnp.sum(gj.integrate(H, q0, p0, method=method, h=0.05, t1=T,
                                                     controller=gj.PIDController(tol, tol)).q[-1] ** 2)
        _, grad_alone = compiled(jax.grad(alone), q0, tols[0])
        jax.block_until_ready(grad_alone(q0, tols[0]))
        case = dict(steps=[int(n) for n in steps],
                    alone_gradient_s=[best_time(grad_alone, q0, tol, repeat=5) for tol in tols])
        case["alone_gradient_sum_s"] = sum(case["alone_gradient_s"])
        for batch_size in (None, 1, 4):
            key = "vmap" if batch_size is None else f"batch_size_{batch_size}"
            f = lambda x: loss(x, batch_size)
            case[key] = {}
            for what, fn in (("forward", f), ("gradient", jax.grad(f)),
                             ("tangent", lambda x: jax.jvp(f, (x,), (jnp.ones_like(x),))[1])):
                case[key][what + "_compile_s"], case[key][what + "_s"] = timed(fn, q0s)
        show(label, case)
        results[label] = case
    return results


PARTS = {"max_steps": max_steps_part, "peers": peers_part, "long": long_part, "members": members_part,
         "fixed": fixed_part}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=list(PARTS), default=list(PARTS))
    parser.add_argument("--name", default="gradients")
    options = parser.parse_args()
    write(options.name, {part: PARTS[part]() for part in options.only})


if __name__ == "__main__":
    main()
