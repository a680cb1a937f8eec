"""Time to the first answer: where a run's first call goes, beside diffrax's equivalent.

    python -m benchmarks compile [--only kepler fput explicit] [--kinds KIND ...] [--name compile]

For every public entry point and run kind, on Kepler (d = 2, cG(6) + Gauss 6, one orbit) and on
the beta-FPUT chain (N = 64, cG(4) + Gauss 4), the first call of a fresh function in one
process, split as JAX reports it (``jax.monitoring``): tracing and lowering (the first call's
wall time less XLA's compilation and less the run), XLA's compilation (every backend compile
the call triggers, the library's eager checks included), and the run (the second call). The
program's size: StableHLO operations of the lowered module (``lowered.as_text()``, the count
``tests/test_program.py`` budgets) and the kernels (fusions) XLA compiled, which set the
compile time (about 4-8 ms each on this CPU). diffrax's equivalent runs in the same process,
with the same state and span: Dopri8 with a constant step or with its PID controller (and
Tsit5 for the forward run kinds). Part ``explicit``: methods in closed form on Kepler beside the
same steps written by hand (``explicit``). Results: ``results/compile.json``. (The CLI and the README's
tour with the compilation cache were measured once by parts ``cli`` and ``tour``, since removed,
in ``results/compile_cli.json`` and ``results/compile_tour.json``:
notes/README.md.)
"""

import argparse
import re
import time

from _common import best_time, show, write  # first: one BLAS thread

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import galerkin_jax as gj  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

_EVENTS = {"compile": "/jax/core/compile/backend_compile_duration"}
_durations = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **_: _durations.append(duration) if event == _EVENTS["compile"] else None)


def program_size(fn, *args):
    """``(stablehlo_ops, kernels, parts)`` of ``jax.jit(fn)`` at ``args``: operations of the
    lowered module, fusions of the compiled one, and those fusions by part (``kernels_by_part``),
    from one lowering and one compilation."""
    lowered = jax.jit(fn).lower(*args)
    ops = sum(1 for line in lowered.as_text().splitlines() if re.match(r"\s*(%\S+ = )?\"?[a-z_]+\.[a-z_]", line))
    parts = kernels_by_part(lowered.compile().as_text())
    return ops, sum(parts.values()), parts


# the parts of a program (``jax.named_scope`` in the library: the root finder's phases, the
# element, its predictor, the error estimate, a step rule and the writers); a kernel counts in
# the innermost part its operation lies in, and in "loop" where it lies in none
PARTS = ("start", "fixed_point", "settle", "newton", "krylov", "element", "predictor", "estimate", "step_rule",
         "save_at", "events", "dense", "checkpoints")


def kernels_by_part(compiled_text):
    """``{part: kernels}`` of a compiled program's text (``PARTS``), by the operation each
    fusion's result comes from (XLA's ``op_name`` metadata)."""
    counts = dict.fromkeys(PARTS + ("loop",), 0)
    for line in compiled_text.splitlines():
        if " fusion(" not in line:
            continue
        name = re.search(r'op_name="([^"]+)"', line)
        inner = [p for p in (name.group(1).split("/") if name else ()) if p in PARTS]
        counts[inner[-1] if inner else "loop"] += 1
    return {part: n for part, n in counts.items() if n}


def first_call(make, sized=True):
    """The first call of a fresh program (``make()`` builds the function and its arguments):
    ``dict(total, trace_and_lower, compile, run, stablehlo_ops, kernels)`` in seconds; without
    ``sized`` (a function that is not one jittable program) no sizes."""
    jax.clear_caches()
    fn, args = make()
    _durations.clear()
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    total = time.perf_counter() - t0
    compile_s = sum(_durations)
    run = best_time(fn, *args, repeat=3, min_s=0.0)
    ops, kernels, parts = program_size(fn, *args) if sized else (None, None, None)
    return dict(total=total, trace_and_lower=max(total - compile_s - run, 0.0), compile=compile_s, run=run,
                stablehlo_ops=ops, kernels=kernels, parts=parts)


PROBLEMS = {  # (scene, span, method, tolerance)
    "kepler": lambda: (scenes.kepler(0.6), 2 * np.pi, gj.CG(6, gj.gauss_legendre(6)), 1e-10),
    "fput": lambda: (scenes.fput(64), 10.0, gj.CG(4, gj.gauss_legendre(4)), 1e-8),
}


def ours(problem):
    """``{kind: make}``: the library's entry points on ``problem``."""
    scene, T, method, tol = problem
    H, q0, p0 = scene.H, jnp.asarray(scene.q0), jnp.asarray(scene.p0)
    n = 1000
    h = T / n
    pid = lambda: gj.PIDController(rtol=tol, atol=tol)
    ts = jnp.linspace(0.0, T, 21)
    event = gj.Event(lambda t, q, p: q[0], capacity=8)

    def run(**kw):
        return lambda: (lambda q0, p0: gj.integrate(H, q0, p0, method=method, **kw), (q0, p0))

    def grad(**kw):
        loss = lambda q0, p0: jnp.sum(gj.integrate(H, q0, p0, method=method, **kw).q[-1] ** 2)
        return lambda: (jax.grad(loss), (q0, p0))

    def sweep():
        configs = gj.grid(method=method, h=[h, 2 * h], state=[(q0, p0), (0.99 * q0, p0)])
        return lambda configs: gj.sweep(H, configs, n_steps=n), (configs,)

    return {
        "step": lambda: (lambda q, p: gj.step(H, q, p, method=method, h=h), (q0, p0)),
        "amplification_matrix": lambda: (lambda q, p: gj.amplification_matrix(H, q, p, method=method, h=h), (q0, p0)),
        "suggest_step_size": lambda: (lambda q, p: gj.suggest_step_size(H, q, p, method=method, tolerance=tol, h=h,
                                                                        span=T)[0], (q0, p0)),
        "integrate fixed": run(h=h, n_steps=n),
        "integrate PID": run(h=h, t1=T, controller=pid()),
        "integrate TimeTransform": run(h=h, t1=T, controller=gj.TimeTransform()),
        "integrate save_at + events": run(h=h, t1=T, controller=pid(), save_at=ts, events=event),
        "integrate dense": run(h=h, n_steps=n, dense=True),
        "sweep": sweep,
        "grad fixed": grad(h=h, n_steps=n),
        "grad PID": grad(h=h, t1=T, controller=pid()),
    }


def peers(problem):
    """``{kind: {peer: make}}``: diffrax's equivalents (the same H, state and span)."""
    import diffrax

    scene, T, _, tol = problem
    H, q0, p0, n = scene.H, jnp.asarray(scene.q0), jnp.asarray(scene.p0), 1000
    dH = jax.grad(H, argnums=(0, 1))
    term = diffrax.ODETerm(lambda t, y, args: (dH(*y)[1], -dH(*y)[0]))
    ts = jnp.linspace(0.0, T, 21)

    def solve(solver, pid, **kw):
        controller = diffrax.PIDController(rtol=tol, atol=tol) if pid else diffrax.ConstantStepSize()
        return lambda q0, p0: diffrax.diffeqsolve(term, solver, 0.0, T, T / n, (q0, p0), stepsize_controller=controller,
                                                  max_steps=4096, **kw)

    def made(fn, *args):
        return lambda: (fn, args or (q0, p0))

    def step(solver):
        def one(q0, p0):
            state = solver.init(term, 0.0, T / n, (q0, p0), None)
            return solver.step(term, 0.0, T / n, (q0, p0), None, state, made_jump=False)[0]
        return one

    def grad(solver, pid):
        run = solve(solver, pid)
        return jax.grad(lambda q0, p0: jnp.sum(run(q0, p0).ys[0][-1] ** 2), argnums=(0, 1))

    dopri8, tsit5 = diffrax.Dopri8(), diffrax.Tsit5()
    event = diffrax.Event(lambda t, y, args, **kw: y[0][0])
    vsolve = jax.vmap(solve(dopri8, False))
    return {
        "step": {"Dopri8": made(step(dopri8))},
        "amplification_matrix": {"Dopri8": made(lambda q, p: jax.jacrev(
            lambda z: jnp.concatenate(step(dopri8)(z[: q.size], z[q.size:])))(jnp.concatenate([q, p])))},
        "integrate fixed": {"Dopri8": made(solve(dopri8, False)), "Tsit5": made(solve(tsit5, False))},
        "integrate PID": {"Dopri8": made(solve(dopri8, True)), "Tsit5": made(solve(tsit5, True))},
        "integrate save_at + events": {"Dopri8": made(solve(dopri8, True, saveat=diffrax.SaveAt(ts=ts), event=event))},
        "integrate dense": {"Dopri8": made(solve(dopri8, False, saveat=diffrax.SaveAt(dense=True)))},
        "sweep": {"Dopri8": made(vsolve, jnp.stack([q0] * 4), jnp.stack([p0] * 4))},
        "grad fixed": {"Dopri8": made(grad(dopri8, False))},
        "grad PID": {"Dopri8": made(grad(dopri8, True)), "Tsit5": made(grad(tsit5, True))},
    }


def explicit():
    """``{kind: {solver: make}}``: methods computed in closed form (``_explicit``: a separable H)
    beside the same steps written by hand in plain JAX (``_peers.leapfrog``: velocity Verlet,
    composed for the triple jump), on Kepler, 1000 fixed steps over one orbit. The library's
    runs return the whole ``Solution`` (so the error estimate is compiled where it is on)."""
    from _peers import leapfrog

    scene = scenes.kepler(0.6)
    H, q0, p0, T, n = scene.H, jnp.asarray(scene.q0), jnp.asarray(scene.p0), 2 * np.pi, 1000
    z0 = jnp.concatenate([q0, p0])
    verlet = gj.GalerkinVI(1, gj.trapezoid())
    triple = gj.Composition(verlet, "yoshida4").coefficients

    def run(method, **kw):
        return lambda: (lambda q0, p0: gj.integrate(H, q0, p0, method=method, h=T / n, n_steps=n, **kw), (q0, p0))

    by_hand = lambda weights: lambda: (jax.jit(leapfrog(H, T, n, weights)), (z0,))
    return {
        "Verlet": {"galerkin_jax": run(verlet), "by hand": by_hand((1.0,))},
        "Verlet, no estimate": {"galerkin_jax": run(verlet, error_estimate=False), "by hand": by_hand((1.0,))},
        "triple jump": {"galerkin_jax": run(gj.Composition(verlet, "yoshida4")), "by hand": by_hand(triple)},
        "kahan_li8": {"galerkin_jax": run(gj.Composition(verlet, "kahan_li8")), "by hand": by_hand(triple)},
        "blanes_moan_rkn6": {"galerkin_jax": run(gj.Splitting("blanes_moan_rkn6")), "by hand": by_hand(triple)},
    }


def explicit_part(kinds=None):
    """The ``explicit()`` kinds: the first call of each, and the library's compile (trace, lower
    and XLA) less and over the hand-written one's (``extra_s``, ``ratio``)."""
    rows = {}
    for kind, makes in explicit().items():
        if kinds and kind not in kinds:
            continue
        row = {solver: first_call(make) for solver, make in makes.items()}
        mine, theirs = ((row[k]["trace_and_lower"] + row[k]["compile"]) for k in ("galerkin_jax", "by hand"))
        rows[kind] = row | {"extra_s": mine - theirs, "ratio": mine / theirs}
        show(f"explicit {kind}", row["galerkin_jax"] | {"by hand compile": theirs, "extra_s": mine - theirs,
                                                        "ratio": mine / theirs})
    return rows


EAGER = ("suggest_step_size",)  # pilot runs chosen in Python: several programs, no single one to lower


def problem_part(name, problem, kinds=None):
    rows = {}
    theirs = peers(problem)
    for kind, make in ours(problem).items():
        if kinds and kind not in kinds:
            continue
        row = {"galerkin_jax": first_call(make, sized=kind not in EAGER)}
        for peer, peer_make in theirs.get(kind, {}).items():
            row[f"diffrax {peer}"] = first_call(peer_make)
        mine = row["galerkin_jax"]["trace_and_lower"] + row["galerkin_jax"]["compile"]
        if "diffrax Dopri8" in row:
            dopri8 = row["diffrax Dopri8"]
            row["ratio_to_dopri8"] = mine / (dopri8["trace_and_lower"] + dopri8["compile"])
        rows[kind] = row
        show(f"{name} {kind}", row["galerkin_jax"] | {f"{k} compile": v["trace_and_lower"] + v["compile"]
                                                     for k, v in row.items() if k.startswith("diffrax")}
             | {"ratio_to_dopri8": row.get("ratio_to_dopri8")})
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=[*PROBLEMS, "explicit"], default=[*PROBLEMS, "explicit"])
    parser.add_argument("--kinds", nargs="*", help="run kinds to measure (default: all), e.g. 'integrate PID'")
    parser.add_argument("--name", default="compile")
    options = parser.parse_args()
    write(options.name, {name: explicit_part(options.kinds) if name == "explicit"
                         else problem_part(name, PROBLEMS[name](), options.kinds) for name in options.only})


if __name__ == "__main__":
    main()
