"""Adaptive steps: galerkin_jax's PIDController and TimeTransform against
diffrax Dopri8 + PID and Tsit5 + PID, and against uniform steps over long runs.

    python -m benchmarks adaptive [--quick] [--only a b c] [--orbits 1000] [--e 0.9]

Three parts, in one process:
  a  Kepler e = 0.9 and e = 0.99, 10 orbits from apocentre: work-precision (run time, steps and
     field evaluations against the final error, max-norm against the exact orbit) of cG(k)+Gauss
     k with a PIDController (k = 4, 6, 8; one run per decade of rtol = atol), cG(6)+Gauss 7 with
     it (one quadrature point more, docs/adaptive.md), cG(6)+Gauss 6 with the TimeTransform (h in
     tau swept), diffrax Dopri8 and Tsit5 with PID (1e-6 .. 1e-15); at each target final error the
     cost of each solver interpolated on its log-log curve, and the ratio ours / best peer;
  b  the Pythagorean three-body problem (masses 3, 4, 5 at rest, G = 1), t in [0, 5]: the same
     against a reference (cG(8)+Gauss 8 with the TimeTransform at a small step, checked against
     SciPy DOP853 and against a change of 1e-14 in q0; no target below its resolution);
  c  Kepler e = 0.9 (``--e 0.99``) over ``--orbits`` orbits (1000; 100 with --quick), cG(4)+Gauss 4
     with the TimeTransform (its default s, and Kepler's own s = (r / r0)^(3/2)), the
     PIDController and uniform steps: the maximum energy error over the nodes against run time,
     the first quarter's against the last quarter's, the uniform cost at the TimeTransform's error.
Compile time (ahead of time) apart from run time (best of several calls). Writes
results/adaptive.json, adaptive_work_precision.png and adaptive_energy.png (``--quick`` and
``--only`` add a suffix unless ``--name`` is given).
"""

import argparse
import time
import warnings

from _common import RESULTS, best_time, compiled, energy_quarters, figure, show, write  # first: one BLAS thread

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.integrate  # noqa: E402

import _peers as peers  # noqa: E402
import galerkin_jax as gj  # noqa: E402
from galerkin_jax import scenes  # noqa: E402

warnings.filterwarnings("ignore", message="At least one element of `rtol` is too small")

TARGETS = (1e-8, 1e-10, 1e-12)
MAX_STEPS = 200_000
PEERS = {"diffrax Dopri8+PID": diffrax.Dopri8(), "diffrax Tsit5+PID": diffrax.Tsit5()}
# new field evaluations per attempt (first-same-as-last): Dopri8 13 stages, Tsit5 7
PEER_STAGES = {"diffrax Dopri8+PID": 12, "diffrax Tsit5+PID": 6}


def gauss(k):
    return gj.CG(k, gj.gauss_legendre(k))


KEPLER_H = scenes.kepler().H  # one function, so that both eccentricities share a compilation


def kepler_problem(e, orbits=10):
    """Kepler from apocentre (a = 1, period 2 pi) over ``orbits`` periods; the end is an apocentre
    too, where the state is well conditioned (at pericentre dp/dt = 1/r^2 turns a phase error
    of 1e-13 into a momentum error of 1e-11 at e = 0.9)."""
    scene = scenes.kepler(e)
    q0, p0 = scene.exact(np.pi)
    T = 2 * np.pi * orbits
    q1, p1 = scene.exact(np.pi + T)
    return dict(H=KEPLER_H, q0=jnp.asarray(q0), p0=jnp.asarray(p0), T=T, z1=np.concatenate([q1, p1]),
                tt_h=(1.6, 1.1, 0.8, 0.55, 0.4, 0.2))


MASSES = np.array([3.0, 4.0, 5.0])


def three_body(q, p):
    """The planar three-body problem, G = 1: q, p of shape (6,) = three (x, y) pairs."""
    x, v = q.reshape(3, 2), p.reshape(3, 2)
    kinetic = jnp.sum(jnp.sum(v * v, axis=1) / (2 * MASSES))
    potential = 0.0
    for i, j in ((0, 1), (0, 2), (1, 2)):
        d = x[i] - x[j]
        potential = potential - MASSES[i] * MASSES[j] / jnp.sqrt(d @ d)
    return kinetic + potential


def pythagorean_problem(T=5.0):
    """Burrau's problem: masses 3, 4, 5 at rest at (1, 3), (-2, -1), (1, -1). Its reference is
    cG(8)+Gauss 8 with the TimeTransform at two small steps (their difference and the
    distance to SciPy DOP853 at rtol = atol = 1e-14 are recorded). Its close encounters
    amplify a change of 1e-14 in q0 to ~1e-10 at T (recorded too), so in float64 no solver's
    final state is known better than that: the reference's ``resolution`` is ten times the
    largest of the three, and targets below it are not compared."""
    q0, p0 = jnp.asarray([1.0, 3.0, -2.0, -1.0, 1.0, -1.0]), jnp.zeros(6)
    run = jax.jit(lambda q0, h: gj.integrate(three_body, q0, p0, method=gauss(8), h=h, t1=T,
                                             controller=gj.TimeTransform(), max_steps=MAX_STEPS, error_estimate=False))
    ends = []
    for h, dq in ((2e-3, 0.0), (1e-3, 0.0), (1e-3, 1e-14)):
        sol = run(q0.at[0].add(dq), h)
        assert int(sol.status) == 0, gj.status_message(sol.status)
        ends.append(np.concatenate([sol.q[-1], sol.p[-1]]))
    field = jax.jit(peers.hamiltonian_field(three_body))
    dop = scipy.integrate.solve_ivp(lambda t, z: np.asarray(field(jnp.asarray(z))), (0.0, T),
                                    np.concatenate([q0, p0]), method="DOP853", rtol=1e-14, atol=1e-14)
    check = dict(tt_h_vs_h2=float(np.max(np.abs(ends[0] - ends[1]))),
                 dop853_1e14=float(np.max(np.abs(dop.y[:, -1] - ends[1]))),
                 q0_perturbed_1e14=float(np.max(np.abs(ends[2] - ends[1]))))
    check["resolution"] = 10 * max(check.values())
    show("Pythagorean reference", check)
    return dict(H=three_body, q0=q0, p0=p0, T=T, z1=ends[1], reference=check, resolution=check["resolution"],
                tt_h=(0.32, 0.16, 0.08, 0.04, 0.02))


def ours(method, kind):
    """``run(q0, p0, T, knob) -> (z1, status, steps, rejected, newton)``: knob is the tolerance
    (kind "PID": PIDController, first step 1e-3 T) or the step in tau (kind "TT": TimeTransform)."""
    tt = kind == "TT"

    def make(H):
        def run(q0, p0, T, knob):
            controller = gj.TimeTransform() if tt else gj.PIDController(knob, knob)
            h = knob if tt else 1e-3 * T
            sol = gj.integrate(H, q0, p0, method=method, h=h, t1=T, controller=controller, max_steps=MAX_STEPS,
                               error_estimate=False)
            return (jnp.concatenate([sol.q[-1], sol.p[-1]]), sol.status,
                    *(sol.stats[f"num_{k}"] for k in ("accepted_steps", "rejected_steps", "newton_iterations")))

        return run

    return make


def peer(solver):
    """diffrax ``solver`` with a PID controller (rtol = atol = the knob, the first step diffrax's)."""

    def make(H):
        def run(q0, p0, T, tol):
            controller = diffrax.PIDController(rtol=tol, atol=tol)
            z1, status, accepted, rejected = peers.diffrax_solve(H, T, jnp.concatenate([q0, p0]), solver, None,
                                                                 controller, MAX_STEPS)
            return z1, status, accepted, rejected, jnp.zeros((), jnp.int32)

        return run

    return make


def solvers(quick):
    ks = (6, 8) if quick else (4, 6, 8)
    decades = lambda a, b: tuple(10.0 ** -e for e in range(a, b + 1))  # one run per decade of tolerance
    tols = {4: decades(6, 14), 6: decades(4, 12), 8: decades(3, 11)}
    out = {f"cG({k})+Gauss {k} PID": (ours(gauss(k), "PID"), tols[k]) for k in ks}
    out["cG(6)+Gauss 7 PID"] = (ours(gj.CG(6, gj.gauss_legendre(7)), "PID"), tols[6])
    out["cG(6)+Gauss 6 TimeTransform"] = (ours(gauss(6), "TT"), "tt_h")
    peer_tols = decades(6, 15)
    out.update({name: (peer(solver), peer_tols) for name, solver in PEERS.items()})
    if quick:
        out = {name: (make, knobs if isinstance(knobs, str) else knobs[1::2]) for name, (make, knobs) in out.items()}
    return out


def sweep(problems, quick):
    """Every solver on every problem: one compilation per solver and problem family."""
    records = []
    for name, (make, knobs) in solvers(quick).items():
        family_calls = {}  # by H: both Kepler problems share one program
        for label, prob in problems.items():
            if id(prob["H"]) not in family_calls:
                args = (prob["q0"], prob["p0"], jnp.asarray(prob["T"]), jnp.asarray(1e-8))
                family_calls[id(prob["H"])] = compiled(make(prob["H"]), *args)
            compile_s, call = family_calls[id(prob["H"])]
            for knob in prob[knobs] if isinstance(knobs, str) else knobs:
                args = (prob["q0"], prob["p0"], jnp.asarray(prob["T"]), jnp.asarray(knob))
                z1, status, steps, rejected, newton = call(*args)
                rec = dict(problem=label, solver=name, knob=knob, status=int(status), steps=int(steps),
                           rejected=int(rejected), newton_iterations=int(newton), compile_s=compile_s,
                           evaluations=evaluations(name, int(steps) + int(rejected), int(newton)))
                if int(status) == 0:
                    rec["error"] = float(np.max(np.abs(np.asarray(z1) - prob["z1"])))
                    rec["run_s"] = best_time(call, *args, repeat=5, min_s=0.3, budget_s=2.0)
                records.append(rec)
                show(f"{label}, {name}", rec, "knob", "status", "steps", "rejected", "error", "run_s", "compile_s")
    return records


def evaluations(name, attempts, iterations):
    """Gradient (field) evaluations, a work count free of the machine's load: a peer's stages per
    attempt; ours one per Gauss point and iteration of the root finder plus one per attempt
    (the estimate), a lower bound: Jacobian refreshes of the Newton iterations are left out."""
    if name in PEER_STAGES:
        return PEER_STAGES[name] * attempts
    return int(name.split("Gauss ")[1].split()[0]) * iterations + attempts


def cost_at(points, target, key="run_s"):
    """The cost to reach a final error ``target`` on a curve (points in knob order): log-log
    interpolation between the two neighbours that bracket it, the cheapest such crossing; None
    where the curve never reaches the target."""
    pts = [(p["error"], p[key]) for p in points if "error" in p]
    costs = [c for e, c in pts if e <= target]  # the points that reach it, and the crossings
    for (e_a, c_a), (e_b, c_b) in zip(pts, pts[1:]):
        if min(e_a, e_b) <= target <= max(e_a, e_b) and e_a != e_b:
            w = (np.log(target) - np.log(e_a)) / (np.log(e_b) - np.log(e_a))
            costs.append(float(np.exp(np.log(c_a) + w * (np.log(c_b) - np.log(c_a)))))
    return min(costs, default=None)


def ratios(records, problems):
    """Per problem and target: each solver's interpolated run time, steps and evaluations
    (``cost_at``), the best peer, the best of ours, and their ratio."""
    table, names = [], sorted({r["solver"] for r in records})
    for label, prob in problems.items():
        for target in TARGETS:
            row = dict(problem=label, target=target)
            table.append(row)
            if target < prob.get("resolution", 0.0):
                row["below_resolution"] = True
                print(f"  {label:22s} error {target:.0e}: below the reference's resolution {prob['resolution']:.0e}")
                continue
            for key in ("run_s", "steps", "evaluations"):
                row[key] = {n: cost_at([r for r in records if r["problem"] == label and r["solver"] == n], target, key)
                            for n in names}
            side = lambda key, peer: {n: c for n, c in row[key].items() if c is not None and (n in PEERS) == peer}
            theirs, ours = side("run_s", True), side("run_s", False)
            if not (theirs and ours):
                print(f"  {label:22s} error {target:.0e}: not reached by both sides {sorted(theirs | ours)}", flush=True)
                continue
            bp, bo = min(theirs, key=theirs.get), min(ours, key=ours.get)
            row.update(best_peer=bp, best_ours=bo, ratio=ours[bo] / theirs[bp],
                       ratio_pid=min((c for n, c in ours.items() if "PID" in n), default=np.nan) / theirs[bp],
                       ratio_evaluations=min(side("evaluations", False).values())
                       / min(side("evaluations", True).values()))
            show(f"{label}, error {target:.0e}", row, "best_ours", "best_peer", "ratio", "ratio_pid", "ratio_evaluations")
    return table


def plot_work_precision(records, problems, path):
    """Run time (top) and gradient evaluations (bottom, free of the machine's load) against the
    final error, one column per problem."""
    with figure(path, ncols=len(problems), nrows=2, size=(5.5, 4), dpi=90) as axes:
        for column, label in enumerate(problems):
            for row, (key, unit) in enumerate((("run_s", "run time [s]"), ("evaluations", "gradient evaluations"))):
                ax = axes[row, column]
                for name in sorted({r["solver"] for r in records}):
                    pts = [r for r in records if r["problem"] == label and r["solver"] == name and "error" in r]
                    ax.loglog([p["error"] for p in pts], [p[key] for p in pts], "--" if name in PEERS else "-",
                              marker="o", ms=3, label=name)
                ax.set(title=label, xlabel="final error (max-norm)", ylabel=unit)
                ax.invert_xaxis()
                ax.grid(True, which="both", alpha=0.3)
        axes[0, 0].legend(fontsize=7)


def kepler_density(q0):
    """Kepler's own step density s = (r / r0)^(3/2), the orbit's dynamical time scale at radius r
    (Kepler's third law; the Sundman transformation's power), normalised to s(z0) = 1: one
    square root per evaluation, where the default s brings H's Hessian into the element
    equations."""
    r0 = float(np.linalg.norm(np.asarray(q0)))
    return lambda q, p: (jnp.sum(q * q) / r0**2) ** 0.75


def energy_run(kind, method, H, q0, p0, T, max_steps):
    """``run(knob) -> (energy error at every node, node times, steps, status, Newton iterations)``
    for the TimeTransform with its default s or with Kepler's own (knob: h in tau), the
    PIDController (knob: tol) or uniform steps (knob: h; fixed steps, every state saved: the
    run a user makes to watch the energy)."""

    def energies(sol, q, p, t):
        return (jax.vmap(H)(q, p) - H(q0, p0), t, sol.stats["num_accepted_steps"], sol.status,
                sol.stats["num_newton_iterations"])

    def run(knob):
        if kind == "uniform":
            def uniform(q0, p0):
                sol = gj.integrate(H, q0, p0, method=method, h=knob, n_steps=int(np.ceil(T / knob)), error_estimate=False)
                return energies(sol, sol.q, sol.p, sol.t)
            return uniform
        if kind.startswith("TimeTransform"):
            kw = dict(h=knob, controller=gj.TimeTransform(kepler_density(q0) if kind.endswith("r^1.5") else None))
        else:
            kw = dict(h=1e-2, controller=gj.PIDController(knob, knob))
        sol = gj.integrate(H, q0, p0, method=method, t1=T, max_steps=max_steps, dense=True, error_estimate=False, **kw)
        return energies(sol, *sol.dense.view(sol.dense.z), sol.dense.t)

    return run


# part c's knobs per eccentricity: h in tau, tolerances, uniform h. At e = 0.99 the pericentre's
# time scale r^(3/2) is 30x shorter than at e = 0.9: uniform steps of the same accuracy would
# take 30x as many (10^8 for 1000 orbits), so they stop at 2.5e-4 (25 million steps)
LONG_KNOBS = {
    0.9: {"TimeTransform": (0.8, 0.4, 0.2), "TimeTransform s = r^1.5": (0.8, 0.4, 0.2),
          "PID": (1e-6, 1e-8, 1e-10), "uniform": (2e-2, 1e-2, 5e-3, 2.5e-3)},
    0.99: {"TimeTransform": (1.6, 0.8, 0.4), "TimeTransform s = r^1.5": (1.6, 0.8, 0.4),
           "PID": (1e-6, 1e-8, 1e-10), "uniform": (1e-3, 5e-4, 2.5e-4)},
}
# attempts per orbit the PID runs may take (the largest measured at 1e-10, with a margin)
PID_PER_ORBIT = {0.9: 600, 0.99: 1500}


def long_runs(orbits, quick, e=0.9):
    prob = kepler_problem(e, orbits)
    H, q0, p0, T = prob["H"], prob["q0"], prob["p0"], prob["T"]
    method = gauss(4)
    knobs = LONG_KNOBS[e]
    if quick:
        knobs = {k: v[::2] for k, v in knobs.items()}
    # TimeTransform: the tau period is r0^(3/2) times 4 K(2e / (1 + e)) / sqrt(1 + e) for
    # s = (r / r0)^(3/2) (21.7 at e = 0.9, 32 at e = 0.99); 60 / h per orbit leaves room for the default s
    per_orbit = {"TimeTransform": 60 / min(knobs["TimeTransform"]), "PID": PID_PER_ORBIT[e],
                 "uniform": 2 * np.pi / min(knobs["uniform"])}
    per_orbit["TimeTransform s = r^1.5"] = per_orbit["TimeTransform"]
    records, curves = [], {}
    for kind, values in knobs.items():
        max_steps = int(per_orbit[kind] * orbits * 1.1) + 64
        run = energy_run(kind, method, H, q0, p0, T, max_steps)
        if kind != "uniform":  # one program for every knob
            compile_s, call = compiled(run, jnp.asarray(values[0]))
        for knob in values:
            if kind == "uniform":  # the number of steps is static
                compile_s, fixed = compiled(run(knob), q0, p0)
                call = lambda _: fixed(q0, p0)
            dH, t, steps, status, newton = call(jnp.asarray(knob))
            run_s = best_time(call, jnp.asarray(knob), repeat=1, min_s=0.0)  # the second call: the first allocates
            ok = np.isfinite(np.asarray(t))
            dH, t = np.abs(np.asarray(dH))[ok], np.asarray(t)[ok]
            rec = dict(kind=kind, knob=knob, status=int(status), steps=int(steps), newton_iterations=int(newton),
                       compile_s=compile_s, run_s=run_s, us_per_step=1e6 * run_s / int(steps),
                       **energy_quarters(t, dH, T))
            records.append(rec)
            orbit = np.minimum((t / (2 * np.pi)).astype(int), orbits - 1)
            per_orbit_max = np.zeros(orbits)
            np.maximum.at(per_orbit_max, orbit, dH)
            # the file keeps about 1000 points per curve, each the largest over a block of orbits
            # (the figure has them all)
            block = max(1, orbits // 1000)
            rec["orbits_per_point"] = block
            rec["max_energy_error_per_orbit"] = [float(np.max(per_orbit_max[i:i + block]))
                                                 for i in range(0, orbits, block)]
            curves[(kind, knob)] = per_orbit_max
            show(kind, rec)
    summary = []
    for rec in records:
        if not rec["kind"].startswith("TimeTransform"):
            continue
        uni = [dict(error=r["max_energy_error"], run_s=r["run_s"], steps=r["steps"]) for r in records
               if r["kind"] == "uniform"]
        cost = cost_at(uni, rec["max_energy_error"])
        steps = cost_at(uni, rec["max_energy_error"], "steps")
        summary.append(dict(kind=rec["kind"], h=rec["knob"], max_energy_error=rec["max_energy_error"], run_s=rec["run_s"],
                            steps=rec["steps"], uniform_run_s=cost, uniform_steps=steps,
                            ratio=None if cost is None else rec["run_s"] / cost,
                            ratio_steps=None if steps is None else rec["steps"] / steps))
        show(f"{rec['kind']} h = {rec['knob']} against uniform steps", summary[-1])
    return dict(orbits=orbits, e=e, method="cG(4)+Gauss 4", runs=records, tt_vs_uniform=summary), curves


def plot_energy(curves, path, e):
    styles = {"TimeTransform": "-", "TimeTransform s = r^1.5": "-.", "PID": "--", "uniform": ":"}
    with figure(path, ncols=1, size=(8, 4.5)) as (ax,):
        for (kind, knob), per_orbit in curves.items():
            ax.semilogy(np.arange(1, per_orbit.size + 1), np.maximum(per_orbit, 1e-17), styles[kind], lw=1.0,
                        label=f"{kind} {knob:g}")
        ax.set(xlabel="orbit", ylabel="max |H - H0| over the orbit's nodes", title=f"Kepler e = {e}, cG(4)+Gauss 4")
        ax.legend(fontsize=7, ncol=2)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="thinner sweeps, 100 orbits in part c (a smoke pass)")
    parser.add_argument("--only", nargs="+", choices=("a", "b", "c"), default=("a", "b", "c"))
    parser.add_argument("--orbits", type=int, default=None, help="orbits of part c (default 1000, --quick 100)")
    parser.add_argument("--e", type=float, default=0.9, choices=sorted(LONG_KNOBS),
                        help="eccentricity of part c (default 0.9)")
    parser.add_argument("--name", default=None)
    opts = parser.parse_args()
    suffix = ("_quick" if opts.quick else "") + ("" if len(opts.only) == 3 else "_" + "".join(opts.only))
    name = opts.name or "adaptive" + suffix
    results, start = dict(parts=list(opts.only)), time.perf_counter()
    problems = {}
    if "a" in opts.only:
        problems.update({f"Kepler e={e}": kepler_problem(e) for e in (0.9, 0.99)})
    if "b" in opts.only:
        print("b: reference", flush=True)
        problems["Pythagorean 3-body"] = pythagorean_problem()
        results["pythagorean_reference"] = problems["Pythagorean 3-body"]["reference"]
    if problems:
        print("a/b: work-precision", flush=True)
        records = sweep(problems, opts.quick)
        results["work_precision"] = records
        results["ratios"] = ratios(records, problems)
        plot_work_precision(records, problems, RESULTS / f"{name}_work_precision.png")
    if "c" in opts.only:
        orbits = opts.orbits or (100 if opts.quick else 1000)
        print(f"c: Kepler e = {opts.e}, {orbits} orbits", flush=True)
        results["long"], curves = long_runs(orbits, opts.quick, opts.e)
        plot_energy(curves, RESULTS / f"{name}_energy.png", opts.e)
    results["total_s"] = time.perf_counter() - start
    write(name, results)


if __name__ == "__main__":
    main()
