"""galerkin_jax against its peers: diffrax, SciPy ``solve_ivp``, and integrators written in JAX.

    python -m benchmarks peers [--quick] [--only kepler quartic fput batch long explicit]

Six parts, in one process (``_peers.py`` holds the peers):
  kepler    work-precision, e = 0.6, T = 20, final error against the exact orbit;
  quartic   work-precision on the quartic central force of [GBS] (c = 1000), T = 1, final error
            relative to max|z| against SciPy DOP853 at rtol = atol = 1e-14;
  fput      microseconds per step on the beta-FPUT chain, N = 64 and 512, thermal start, h = 0.05;
  batch     256 Kepler orbits (e = 0.1 .. 0.7) at once, 1000 steps of h = 0.01;
  long      Kepler e = 0.6, 1e5 steps of h = 0.01: microseconds per step, energy error;
  explicit  Stormer-Verlet through ``gj.integrate`` (``GalerkinVI(1, trapezoid())``, explicit on a
            separable H) against the hand-written leapfrog, 10^4 steps on LJ13 and FPUT N = 64,
            the two programs timed alternately (not in the default set: ``--only explicit``).
A JAX run is compiled ahead of time (compile_s) and timed as the best of several calls
(run_s); a SciPy run is warmed up once. A run whose status is nonzero is recorded as failed
and not timed. Writes results/peers.json, results/peers.md (the summary table) and
results/peers_work_precision.png; ``--quick`` and ``--only`` add a suffix unless ``--name``.
"""

import argparse
import warnings

from _common import RESULTS, best_time, compiled, figure, machine, markdown_table, show, write  # first: one BLAS thread

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import _moderate as systems  # noqa: E402
import _peers as peers  # noqa: E402
import galerkin_jax as gj  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

# SciPy raises rtol = 1e-14 to 100 eps and says so; the reference asks for it on purpose.
warnings.filterwarnings("ignore", message="At least one element of `rtol` is too small")


def galerkin(method):
    """galerkin_jax as a peer factory (see ``_peers``): ``n`` elements of ``h = T / n``, only
    the final state stored."""

    def make(H, T, n):
        def run(z0):
            q0, p0 = jnp.split(z0, 2)
            sol = gj.integrate(H, q0, p0, method=method, h=T / n, n_steps=n, save_every=n)
            return jnp.concatenate([sol.q[-1], sol.p[-1]]), sol.status

        return run

    return make


LIBRARY = {"cG(1)+midpoint": galerkin(gj.CG(1, gj.midpoint()))} | {
    f"cG({k})+Gauss {k}": galerkin(gj.CG(k, gj.gauss_legendre(k))) for k in (2, 3, 4, 6)
}  # cG(k) with k Gauss points is Gauss collocation: symplectic, order 2k
PEERS = {
    "diffrax Tsit5": peers.diffrax_peer(diffrax.Tsit5()),
    "diffrax Dopri8": peers.diffrax_peer(diffrax.Dopri8()),
    "diffrax Dopri8+PID": peers.diffrax_peer(diffrax.Dopri8(), pid=True),
    "diffrax Kvaerno5": peers.diffrax_peer(peers.kvaerno5()),
    "scipy DOP853": peers.scipy_ivp("DOP853"),
    "scipy Radau": peers.scipy_ivp("Radau"),
    "leapfrog": peers.leapfrog,
    "Gauss RK s=3": peers.gauss_rk,
}
SOLVERS = LIBRARY | PEERS
ADAPTIVE = {"diffrax Dopri8+PID", "scipy DOP853", "scipy Radau"}  # their knob is rtol = atol
THRESHOLDS = ("1e-6", "1e-8", "1e-10", "1e-12")


def doubling(n, count, factor=2):
    return [int(round(n * factor**i)) for i in range(count)]


def tolerances(first, last, per_decade=1):
    return [10.0 ** (-e / per_decade) for e in range(first * per_decade, last * per_decade + 1)]


ROOT2 = 2**0.5  # the finer grid of the contenders for the cheapest run at 1e-10 and 1e-12


# Knobs chosen so that the errors span about 1e-4 .. 1e-13 (measured on this scene).
KEPLER_KNOBS = {
    "cG(1)+midpoint": doubling(2000, 7), "cG(2)+Gauss 2": doubling(500, 7), "cG(3)+Gauss 3": doubling(200, 6),
    "cG(4)+Gauss 4": doubling(100, 11, ROOT2), "cG(6)+Gauss 6": doubling(50, 9, ROOT2),
    "diffrax Tsit5": doubling(250, 7), "diffrax Dopri8": doubling(125, 9, ROOT2),
    "diffrax Dopri8+PID": tolerances(6, 14, per_decade=2),
    "diffrax Kvaerno5": doubling(1000, 6), "scipy DOP853": tolerances(6, 13), "scipy Radau": tolerances(5, 11)[::2],
    "leapfrog": doubling(1000, 7, 4), "Gauss RK s=3": doubling(200, 6),
}
QUARTIC_KNOBS = {
    "cG(1)+midpoint": doubling(4000, 5, 4), "cG(2)+Gauss 2": doubling(1000, 5), "cG(3)+Gauss 3": doubling(500, 5),
    "cG(4)+Gauss 4": doubling(250, 5), "cG(6)+Gauss 6": doubling(250, 4),
    "diffrax Tsit5": doubling(500, 6), "diffrax Dopri8": doubling(125, 5), "diffrax Dopri8+PID": tolerances(6, 14)[::2],
    "diffrax Kvaerno5": doubling(1000, 3, 4), "scipy DOP853": tolerances(6, 12)[::2], "scipy Radau": tolerances(5, 9)[::2],
    "leapfrog": doubling(4000, 6, 4), "Gauss RK s=3": doubling(250, 5),
}


def state(scene):
    return jnp.concatenate([jnp.asarray(scene.q0), jnp.asarray(scene.p0)])


def measure(run, z0, quick):
    """Compile (JAX) or warm up (SciPy) ``run``, call it, and time it only if it succeeded:
    ``(row, z1, retime)``, row with compile_s, run_s (None when failed), status (the largest
    code), failed (members with a nonzero status) and ok; ``retime()`` times it again."""
    compile_s, call = (0.0, run) if getattr(run, "is_python", False) else compiled(run, z0)
    z1, status = call(z0)
    status = np.asarray(status)
    ok = bool(np.all(status == 0))
    retime = lambda: best_time(call, z0, repeat=1 if quick else 3, budget_s=1.0 if quick else 3.0)
    row = {"compile_s": compile_s, "run_s": retime() if ok else None, "status": int(status.max()),
           "failed": int((status != 0).sum()), "ok": ok}
    return row, np.asarray(z1), retime


def fixed_run(solver, H, z0, h, n, quick):
    """One fixed-step run of ``n`` steps of ``h``: the measured row with the per-step time and
    the relative energy change at the end (batched ``z0``: the largest over members)."""
    row, z1, retime = measure(SOLVERS[solver](H, n * h, n), z0, quick)
    row.update(solver=solver, n_steps=n, h=h, us_per_step=1e6 * row["run_s"] / n if row["ok"] else None)
    H0, H1 = (np.array([float(H(*np.split(np.asarray(x), 2))) for x in np.atleast_2d(z)]) for z in (z0, z1))
    row["energy_error"] = float(np.max(np.abs(H1 - H0) / np.abs(H0)))
    return row, z1, retime


def work_precision(scene, T, reference, scale, knobs, quick):
    """Every solver over its knobs: run time and final error ``max|z1 - reference| / scale``."""
    z0, rows, retimes = state(scene), [], []
    for solver, values in knobs.items():
        for knob in [values[len(values) // 2]] if quick else values:
            if solver in ADAPTIVE:
                row, z1, retime = measure(SOLVERS[solver](scene.H, T, knob), z0, quick)
                row.update(solver=solver, tol=knob)
            else:
                row, z1, retime = fixed_run(solver, scene.H, z0, T / knob, knob, quick)
            row["error"] = float(np.max(np.abs(z1 - reference)) / scale) if row["ok"] else None
            show(row["solver"], row)
            rows.append(row)
            retimes.append(retime)
    # a second pass, minutes after the first: a machine's speed drifts for seconds at a time,
    # and the cheapest run at a threshold is a comparison of single timings
    for row, retime in zip(rows, retimes):
        if row["ok"]:
            row["run_s"] = min(row["run_s"], retime())
            if "n_steps" in row:
                row["us_per_step"] = 1e6 * row["run_s"] / row["n_steps"]
    return {"T": T, "runs": rows, "cheapest": {e: cheapest(rows, float(e)) for e in THRESHOLDS}}


def cheapest(rows, threshold):
    """Per solver the fastest run with error <= threshold; the best of the library and of the
    peers, and their ratio (> 1: the library is slower)."""
    best = {}
    for row in sorted((r for r in rows if r["ok"] and r["error"] <= threshold), key=lambda r: r["run_s"]):
        best.setdefault(row["solver"], {k: row.get(k) for k in ("solver", "n_steps", "tol", "run_s", "error")})
    library = min((r for s, r in best.items() if s in LIBRARY), key=lambda r: r["run_s"], default=None)
    peer = min((r for s, r in best.items() if s in PEERS), key=lambda r: r["run_s"], default=None)
    times = (r["run_s"] if r else None for r in (library, peer))
    return {"per_solver": best, "galerkin_jax": library, "peer": peer, "ratio": ratio(*times)}


def kepler_part(quick):
    scene, T = scenes.kepler(0.6), 20.0
    print(f"Kepler e = 0.6, T = {T:g}: work-precision against the exact orbit", flush=True)
    result = work_precision(scene, T, np.concatenate(scene.exact(T)), 1.0, KEPLER_KNOBS, quick)
    return {"e": 0.6, "reference": "exact orbit (scenes.kepler_orbit)", "error": "max |z1 - exact|"} | result


def quartic_part(quick):
    scene, T = scenes.quartic(), 1.0
    z0 = state(scene)
    reference, _ = peers.scipy_ivp("DOP853")(scene.H, T, 1e-14)(z0)
    check, _ = jax.jit(SOLVERS["cG(6)+Gauss 6"](scene.H, T, 8000))(z0)
    scale = float(np.max(np.abs(reference)))
    print(f"quartic c = 1000, T = {T:g}: work-precision against SciPy DOP853, rtol = atol = 1e-14", flush=True)
    result = work_precision(scene, T, reference, scale, QUARTIC_KNOBS, quick)
    return {
        "reference": "scipy DOP853, rtol = atol = 1e-14 (SciPy raises rtol to 2.2e-14)",
        "reference_vs_cG6_8000_steps": float(np.max(np.abs(np.asarray(check) - reference)) / scale),
        "error": "max |z1 - reference| / max |reference|", "scale": scale,
    } | result


def calibrated_run(solver, H, z0, h, target_s, quick, probe=10):
    """A fixed-step run of about ``target_s``: a probe of ``probe`` steps sets the step count
    (each count is a new compilation); with ``quick`` the probe is the run."""
    row, _, _ = fixed_run(solver, H, z0, h, probe, quick)
    if quick or not row["ok"] or row["run_s"] >= target_s / 4:
        return row
    n = int(float(f"{probe * target_s / row['run_s']:.2g}"))  # two significant digits
    return fixed_run(solver, H, z0, h, n, quick)[0]


def fput_part(quick):
    solvers = ("cG(3)+Gauss 3", "cG(1)+midpoint", "diffrax Tsit5", "leapfrog")
    result = {}
    for N in (64, 512):
        scene = scenes.fput(N)
        print(f"FPUT N = {N}, h = {scene.h:g}: microseconds per step", flush=True)
        rows = {s: calibrated_run(s, scene.H, state(scene), scene.h, 0.5, quick) for s in solvers}
        for row in rows.values():
            show(row["solver"], row)
        result[str(N)] = rows
    result["growth_512_over_64"] = {
        s: ratio(result["512"][s]["us_per_step"], result["64"][s]["us_per_step"]) for s in solvers
    }
    return result


def ratio(a, b):
    return a / b if a is not None and b is not None else None


def batch_part(quick, size=256, h=0.01, n=1000):
    """256 Kepler orbits: ``gj.sweep``, ``vmap(integrate)``, vmapped diffrax Tsit5."""
    e = np.linspace(0.1, 0.7, size)
    orbit = lambda t: np.stack([np.concatenate(scenes.kepler_orbit(np.array([t]), x), axis=-1)[0] for x in e])
    z0, exact = jnp.asarray(orbit(0.0)), orbit(n * h)
    H, method = scenes.kepler().H, gj.CG(2, gj.gauss_legendre(2))

    def sweep(z0):
        q0, p0 = jnp.split(z0, 2, axis=1)
        configs = gj.Configs(method=gj.stack_methods([method] * size), q0=q0, p0=p0, h=jnp.full(size, h))
        result = gj.sweep(H, configs, n_steps=n)
        return jnp.concatenate([result.q, result.p], axis=1), result.status

    runs = {
        "cG(2)+Gauss 2 sweep": sweep,
        "cG(2)+Gauss 2 vmap(integrate)": jax.vmap(galerkin(method)(H, n * h, n)),
        "diffrax Tsit5 vmap": jax.vmap(SOLVERS["diffrax Tsit5"](H, n * h, n)),
    }
    print(f"{size} Kepler orbits, e = 0.1 .. 0.7, {n} steps of h = {h:g}: microseconds per member-step", flush=True)
    rows = {}
    for name, run in runs.items():
        row, z1, _ = measure(run, z0, quick)
        row.update(solver=name, members=size, n_steps=n, h=h)
        row["us_per_member_step"] = 1e6 * row["run_s"] / (size * n) if row["ok"] else None
        row["error"] = float(np.max(np.abs(z1 - exact)))
        show(row["solver"], row)
        rows[name] = row
    return rows


def long_part(quick, h=0.01):
    n = 10_000 if quick else 100_000
    scene = scenes.kepler(0.6)
    exact = np.concatenate(scene.exact(n * h))
    print(f"Kepler e = 0.6, {n} steps of h = {h:g}: microseconds per step", flush=True)
    rows = {}
    for solver in ("cG(3)+Gauss 3", "cG(1)+midpoint", "Gauss RK s=3", "diffrax Dopri8", "leapfrog"):
        row, z1, _ = fixed_run(solver, scene.H, state(scene), h, n, quick)
        row["error"] = float(np.max(np.abs(z1 - exact)))
        show(row["solver"], row)
        rows[solver] = row
    return rows


def explicit_part(quick, n=10_000, rounds=30):
    """Explicit Stormer-Verlet through ``gj.integrate`` against the hand-written leapfrog (the
    same steps): the two compiled programs run alternately, ``rounds`` times, the best of each
    (a loaded machine slows both alike); their largest difference in the end state."""
    lj, chain = systems.lennard_jones(13), scenes.fput(64)
    verlet = galerkin(gj.GalerkinVI(1, gj.trapezoid()))
    n, rounds = (1000, 3) if quick else (n, rounds)
    rows = {}
    for label, H, z0, h in (("LJ13", lj.H, np.concatenate([lj.q0, lj.p0]), 0.005),
                            ("FPUT N = 64", chain.H, state(chain), chain.h)):
        z0 = jnp.asarray(z0)
        calls = {name: compiled(make(H, n * h, n), z0) for name, make in (("galerkin_jax", verlet),
                                                                          ("leapfrog", peers.leapfrog))}
        ends = {name: np.asarray(call(z0)[0]) for name, (_, call) in calls.items()}
        best = dict.fromkeys(calls, np.inf)
        for _ in range(rounds):
            for name, (_, call) in calls.items():
                best[name] = min(best[name], best_time(call, z0, repeat=1, min_s=0.0))
        rows[label] = dict(n_steps=n, h=h, unknowns=int(z0.size) // 2,
                           **{f"{name}_us_per_step": 1e6 * best[name] / n for name in calls},
                           **{f"{name}_compile_s": calls[name][0] for name in calls},
                           ratio=best["galerkin_jax"] / best["leapfrog"],
                           max_difference=float(np.max(np.abs(ends["galerkin_jax"] - ends["leapfrog"]))))
        show(label, rows[label])
    return rows


PARTS = {"kepler": kepler_part, "quartic": quartic_part, "fput": fput_part, "batch": batch_part, "long": long_part,
         "explicit": explicit_part}
DEFAULT = ("kepler", "quartic", "fput", "batch", "long")


def fmt(x, unit=""):
    return "n/a" if x is None else f"{x:.3g}{unit}"


def describe(best):
    """'cG(4)+Gauss 4, n = 800: 0.0123 s' for a ``cheapest`` entry."""
    if best is None:
        return "none reached it"
    knob = f"tol {best['tol']:.0e}" if best["tol"] is not None else f"n = {best['n_steps']}"
    return f"{best['solver']}, {knob}: {fmt(best['run_s'])} s (error {best['error']:.1e})"


def table(results):
    """The summary in markdown, one row per part and target (those that were run)."""
    rows, x = [], lambda a, b: fmt(ratio(a, b), "x")
    pair = lambda values, a, b, unit="": f"{a}: {fmt(values[a], unit)}; {b}: {fmt(values[b], unit)}"
    if "fput" in results:
        us = {s: row["us_per_step"] for s, row in results["fput"]["64"].items()}
        growth = results["fput"]["growth_512_over_64"]
        ours, theirs = ("cG(3)+Gauss 3", "cG(1)+midpoint"), ("diffrax Tsit5", "leapfrog")
        rows += [["beta-FPUT chain, N = 64 (state 128), h = 0.05: µs per step", pair(us, *ours), pair(us, *theirs),
                  f"{x(us[ours[0]], us[theirs[0]])}; {x(us[ours[1]], us[theirs[0]])}"],
                 ["FPUT N = 512 against N = 64: growth of time per step", pair(growth, *ours, "x"),
                  pair(growth, *theirs, "x"), ""]]
    for part, title, thresholds in (("kepler", "Kepler e = 0.6, T = 20", ("1e-10", "1e-12")),
                                    ("quartic", "quartic central force c = 1000, T = 1 (relative)", ("1e-8", "1e-10"))):
        for i, threshold in enumerate(thresholds if part in results else ()):
            entry = results[part]["cheapest"][threshold]
            rows.append([f"{'same' if i else title}, cheapest run with final error <= {threshold}",
                         describe(entry["galerkin_jax"]), describe(entry["peer"]), fmt(entry["ratio"], "x")])
    if "batch" in results:
        us = {name: row["us_per_member_step"] for name, row in results["batch"].items()}
        sweep, vmapped, tsit5 = us["cG(2)+Gauss 2 sweep"], us["cG(2)+Gauss 2 vmap(integrate)"], us["diffrax Tsit5 vmap"]
        rows.append(["256 Kepler orbits at once, 1000 steps of h = 0.01: µs per member-step",
                     f"cG(2)+Gauss 2 (sweep / vmap(integrate)): {fmt(sweep)} / {fmt(vmapped)}",
                     f"diffrax Tsit5: {fmt(tsit5)}", f"{x(sweep, tsit5)} / {x(vmapped, tsit5)}"])
    if "long" in results:
        us = {solver: row["us_per_step"] for solver, row in results["long"].items()}
        rows.append([f"Kepler e = 0.6, {results['long']['cG(3)+Gauss 3']['n_steps']:,} steps of h = 0.01: µs per step",
                     pair(us, "cG(3)+Gauss 3", "cG(1)+midpoint"),
                     f"hand-written Gauss RK s=3: {fmt(us['Gauss RK s=3'])}; {pair(us, 'diffrax Dopri8', 'leapfrog')}",
                     f"{x(us['cG(3)+Gauss 3'], us['Gauss RK s=3'])} (cG(3) / Gauss RK)"])
    for label, r in results.get("explicit", {}).items():
        rows.append([f"{label}, {r['n_steps']:,} Stormer-Verlet steps: µs per step",
                     f"GalerkinVI(1, trapezoid): {fmt(r['galerkin_jax_us_per_step'])}",
                     f"leapfrog: {fmt(r['leapfrog_us_per_step'])}", fmt(r["ratio"], "x")])
    return markdown_table(["scene", "galerkin_jax", "best comparable peer", "ratio"], rows) + "\n"


def plot(results, path):
    """Error against run time, log-log, one line per solver (library solid, peers dashed)."""
    import matplotlib.pyplot as plt

    parts = [p for p in ("kepler", "quartic") if p in results]
    colors = list(plt.cm.tab10.colors) + ["black", "navy", "maroon"]  # one per solver
    with figure(path, ncols=len(parts), size=(6.5, 5)) as axes:
        for ax, part in zip(axes, parts):
            for i, solver in enumerate(SOLVERS):
                runs = [r for r in results[part]["runs"] if r["solver"] == solver and r["ok"]]  # in knob order
                ax.loglog([r["run_s"] for r in runs], [r["error"] for r in runs], "-" if solver in LIBRARY else "--",
                          marker="osD^v<>pPX*hd"[i], color=colors[i], label=solver, ms=4)
            ax.set_xlabel("run time [s] (compile excluded)")
            ax.set_ylabel(results[part]["error"])
            ax.set_title({"kepler": "Kepler e = 0.6, T = 20", "quartic": "quartic central force, c = 1000, T = 1"}[part])
            ax.grid(True, which="major", alpha=0.3)
        axes[-1].legend(fontsize=7, loc="best")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="smoke pass: thinner sweeps, one timed call, 1e4 long steps")
    parser.add_argument("--only", nargs="+", choices=list(PARTS), default=list(DEFAULT), metavar="PART",
                        help=f"run only these parts ({', '.join(PARTS)})")
    parser.add_argument("--name", help="output name (default peers, with _quick and the parts run when not all)")
    options = parser.parse_args()
    suffix = ("_quick" if options.quick else "") + ("" if options.only == list(DEFAULT) else "_" + "_".join(options.only))
    name = options.name or "peers" + suffix
    before = machine()
    results = {part: PARTS[part](options.quick) for part in options.only}
    if {"kepler", "quartic"} & set(results):
        RESULTS.mkdir(parents=True, exist_ok=True)
        plot(results, RESULTS / f"{name}_work_precision.png")
    markdown = table(results)
    write(name, {"machine_before": before, "quick": options.quick, "versions": before["versions"], **results}, markdown)
    print(markdown)


if __name__ == "__main__":
    main()
