"""Untuned moderate systems: galerkin_jax against diffrax and the integrators
a user of each field would write, at a largest relative energy error of 1e-6, 1e-8 and 1e-10.

    python -m benchmarks moderate [--quick] [--only LJ13 LJ55 Morse13 Morse55 Plummer32 Chain10 Chain2 Learned2]

The systems (``_moderate.py``, where each is described with its start and seed): Lennard-Jones
and Morse (rho = 6) clusters of 13 and 55 atoms from their relaxed Mackay icosahedra with
Maxwell-Boltzmann velocities at T* = 0.3; a softened Plummer sphere of 32 bodies in virial
equilibrium; a planar 10-link pendulum and the double pendulum (non-separable); a learned
network H on two degrees of freedom (non-separable).

The accuracy of a run is max |H(z_j) - H(z_0)| / |H(z_0)| over the states z_j at t = j T / 10,
j = 1..10, the same for every solver: every run is cut into ten segments whose ends its steps
land on (fixed steps: a tenth of them each; controlled runs: a run to T / 10 per segment, the
next one's first step the mean step of the last, the first's 1e-3 T / 10).

The solvers (``solver_list``): galerkin_jax cG(k) + Gauss k at fixed steps, with a
PIDController and iterating to 1e-10 instead of round-off; its explicit elements on the
separable systems (``EXPLICIT``); diffrax Tsit5 and Dopri8, fixed steps and PID; velocity Verlet
and its triple jump (separable systems), the implicit midpoint rule and its triple jump (the
chain), in plain JAX (``_peers``). No TimeTransform: the softened Plummer sphere has no close
encounters to follow (with its default s a first try compiled in 58 s; notes/performance-studies.md).

For each solver and accuracy the cheapest run that meets it (``cheapest``): the knob on a grid
of ratio 2^(1/4) (steps) or 10^(1/4) (tolerances), searched by predictions from the error's
measured slope, one compilation per solver and system (the knob traced; fixed steps through a
stand-in, ``cg_fixed(search=True)``); a run predicted to take more than ``--cap`` seconds is recorded
as not reached. Each cheapest run is then compiled ahead of time (``Solver.final``) and timed
as the best of several calls, twice, minutes apart; compile time apart.

Writes results/moderate.json (every run) and results/moderate.md (the tables, also printed);
``--quick`` (short spans, small systems, a few solvers) and ``--only`` add a suffix to these
names unless ``--name`` is given.
"""

import argparse
import dataclasses
import functools
import math
import time
from typing import Callable, NamedTuple

from _common import best_time, compiled, machine, markdown_table, show, write  # first: one BLAS thread

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import _moderate as systems  # noqa: E402
import _peers as peers  # noqa: E402
import galerkin_jax as gj  # noqa: E402

SAVES = 10  # the energy is measured at t = j T / SAVES, j = 0..SAVES
LEVELS = (1e-6, 1e-8, 1e-10)
MAX_STEPS = 200_000  # a controlled segment's attempts


def system_list(quick):
    """The systems of a full run (name -> factory), or of ``--quick``: smaller, shorter."""
    lj, morse, plummer, chain = ((systems.lennard_jones, "LJ"), (systems.morse, "Morse"), (systems.plummer, "Plummer"),
                                 (systems.pendulum_chain, "Chain"))
    chosen = ([(lj, 13, 5.0), (morse, 13, 5.0), (plummer, 16, 2.0), (chain, 5, 5.0)] if quick else [
        (lj, 13, 50.0), (lj, 55, 10.0), (morse, 13, 50.0), (morse, 55, 10.0), (plummer, 32, 10.0), (chain, 10, 20.0),
        (chain, 2, 20.0)])
    found = {f"{name}{n}": functools.partial(f, n, T=T) for (f, name), n, T in chosen}
    found["Learned2"] = functools.partial(systems.learned, dim=2, T=5.0 if quick else 20.0)  # the network H
    return found


class Out(NamedTuple):
    """What every run returns (``run(system, q0, p0, knob)``): the states at the SAVES + 1 save
    times (shape (SAVES + 1, d) each), status (0: success), accepted and rejected steps, field
    evaluations (of DH, or of dV/dq for the explicit ones, at one state) and iterations
    (galerkin_jax's ``num_newton_iterations``; the midpoint rules' fixed-point updates; else 0)."""

    q: jax.Array
    p: jax.Array
    status: jax.Array
    steps: jax.Array
    rejected: jax.Array
    evaluations: jax.Array
    iterations: jax.Array


def segments(step_segment, q0, p0, carry0):
    """Run ``step_segment((q, p, carry)) -> (q, p, carry, counts)`` SAVES times in a
    ``lax.scan``; ``counts`` = (status, steps, rejected, evaluations, iterations), summed (status: max)."""

    def body(c, _):
        (q, p, carry), totals = c
        q, p, carry, counts = step_segment(q, p, carry)
        totals = tuple(jnp.maximum(a, b) if i == 0 else a + b for i, (a, b) in enumerate(zip(totals, counts)))
        return ((q, p, carry), totals), (q, p)

    zero = jnp.zeros((), jnp.int32)
    ((_, _, _), totals), (qs, ps) = jax.lax.scan(body, ((q0, p0, carry0), (zero,) * 5), None, length=SAVES)
    return Out(jnp.concatenate([q0[None], qs]), jnp.concatenate([p0[None], ps]), *totals)


def counts(status=0, steps=0, rejected=0, evaluations=0, iterations=0):
    return tuple(jnp.asarray(x).astype(jnp.int32) for x in (status, steps, rejected, evaluations, iterations))


def evaluations(k, iterations, attempts):
    """galerkin_jax's field evaluations, counted from its iterations: k (one per Gauss point) per
    residual, one residual per iteration and one per attempt (the start's). On a separable H with
    more than 8 degrees of freedom a residual is the Gauss-Seidel sweep's two halves, dH/dp and
    dH/dq, which read T and V apart: one evaluation's work together."""
    return k * (iterations + attempts)


def fixed(method, count, solver=None):
    """galerkin_jax's ``method`` at ``n = SAVES * m`` fixed steps, every m-th state saved
    (``integrate(..., n_steps=n, save_every=m)``: m static, a compilation each); field
    evaluations ``count(system, iterations, steps)``. A ``Solver.final``."""

    def run(system, q0, p0, m):
        sol = gj.integrate(system.H, q0, p0, method=method, h=system.T / (SAVES * m), n_steps=SAVES * m, save_every=m,
                           error_estimate=False, solver=solver)
        it, steps = sol.stats["num_newton_iterations"], sol.stats["num_accepted_steps"]
        return Out(sol.q, sol.p, *counts(sol.status, steps, 0, count(system, it, steps), it))

    return run


def cg_fixed(k, tolerance=0.0, search=False):
    """cG(k) + Gauss k at fixed steps, iterating to ``SolverOptions.tolerance`` (0: round-off).
    With ``search`` the search's stand-in, compiled once: h traced, through ``integrate(...,
    t1=T, save_at=...)`` (a while loop over elements of the constant h, the saved states from
    the element polynomials, which end there; its errors equal the static runs' to six digits,
    LJ13, cG(4), seven step counts checked)."""
    method, solver = gj.CG(k, gj.gauss_legendre(k)), gj.SolverOptions(tolerance=tolerance)
    count = lambda system, it, steps: evaluations(k, it, steps)
    if not search:
        return fixed(method, count, solver)

    def run(system, q0, p0, m):
        sol = gj.integrate(system.H, q0, p0, method=method, h=system.T / (SAVES * m), t1=system.T,
                           save_at=jnp.linspace(0.0, system.T, SAVES + 1), max_steps=SAVES * MAX_STEPS,
                           error_estimate=False, solver=solver)
        it, steps = sol.stats["num_newton_iterations"], sol.stats["num_accepted_steps"]
        return Out(sol.q, sol.p, *counts(sol.status, steps, 0, count(system, it, steps), it))

    return run


def cg_pid(k):
    """cG(k) + Gauss k with a PIDController, knob rtol = atol, one run to T / SAVES per segment
    (the next one's first step the last one's mean). Evaluations as ``evaluations`` per attempt,
    plus the controller's embedded estimate, one per attempt."""
    method = gj.CG(k, gj.gauss_legendre(k))

    def run(system, q0, p0, tol):
        span = system.T / SAVES

        def step_segment(q, p, h):
            sol = gj.integrate(system.H, q, p, method=method, h=h, t1=span, controller=gj.PIDController(tol, tol),
                               max_steps=MAX_STEPS, error_estimate=False)
            steps, rejected, it = (sol.stats[f"num_{x}"] for x in ("accepted_steps", "rejected_steps", "newton_iterations"))
            count = evaluations(k, it, steps + rejected) + steps + rejected
            return sol.q[-1], sol.p[-1], span / jnp.maximum(steps, 1), counts(sol.status, steps, rejected, count, it)

        return segments(step_segment, q0, p0, jnp.asarray(1e-3 * span, q0.dtype))

    return run


def explicit(method, forces, search=False):
    """An explicit element of galerkin_jax (``gj.structure`` finds every separable system
    separable), a composition of Stormer-Verlet or a ``Splitting``, at fixed steps (``fixed``),
    ``forces`` gradients of V a step; or Tao's map on any H (``TAO``), ``forces`` gradients of H. With ``search`` the search's stand-in, compiled once (m
    traced): ``gj.step`` in a ``fori_loop``, the same elements (each start's force computed
    again, which the scan hands on: not timed, see ``choose_finals``)."""
    if not search:
        return fixed(method, lambda system, it, steps: forces * steps)

    def run(system, q0, p0, m):
        def step_segment(q, p, c):
            h = system.T / SAVES / m
            q, p = jax.lax.fori_loop(0, m, lambda _, s: gj.step(system.H, *s, method=method, h=h), (q, p))
            return q, p, c, counts(jnp.where(jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(p)), 0, 1), m, 0, forces * m)

        return segments(step_segment, q0, p0, jnp.zeros((), q0.dtype))

    return run


# galerkin_jax's explicit candidates on separable H: (label, method, order, forces a step, start)
VERLET = gj.GalerkinVI(1, gj.trapezoid())
EXPLICIT = [
    ("GalerkinVI(1, trapezoid) (Verlet)", VERLET, 2, 1, 0.125),
    ("Composition mclachlan4 of Verlet", gj.Composition(VERLET, "mclachlan4"), 4, 5, 0.5),
    ("Splitting blanes_moan_rkn4", gj.Splitting("blanes_moan_rkn4"), 4, 6, 0.5),
    ("Composition mclachlan6 of Verlet", gj.Composition(VERLET, "mclachlan6"), 6, 9, 1.0),
    ("Splitting blanes_moan_rkn6", gj.Splitting("blanes_moan_rkn6"), 6, 11, 1.0),
    ("Composition kahan_li8 of Verlet", gj.Composition(VERLET, "kahan_li8"), 8, 15, 1.5),
]
# galerkin_jax's explicit candidates on a non-separable H, Tao's map (``gj.Tao``) and its
# compositions on the extended space: (label, method, order, gradients of H a step, start)
TAO = [
    ("Tao", gj.Tao(), 2, 4, 0.125),
    ("Composition yoshida4 of Tao", gj.Composition(gj.Tao(), "yoshida4"), 4, 10, 0.5),
    ("Composition kahan_li6 of Tao", gj.Composition(gj.Tao(), "kahan_li6"), 6, 28, 1.0),
    ("Composition kahan_li8 of Tao", gj.Composition(gj.Tao(), "kahan_li8"), 8, 46, 1.5),
]
DIFFRAX_STAGES = {"Tsit5": 6, "Dopri8": 12}  # new field evaluations per attempt (first same as last)


def diffrax_run(name, controlled):
    """diffrax ``name`` (Tsit5 or Dopri8) on z = (q, p) (``_peers.diffrax_solve``): knob m steps
    of T / (SAVES m) per segment (ConstantStepSize) or rtol = atol (PIDController)."""
    solver = getattr(diffrax, name)()

    def run(system, q0, p0, knob):
        span, d = system.T / SAVES, system.q0.size
        controller = diffrax.PIDController(rtol=knob, atol=knob) if controlled else diffrax.ConstantStepSize()

        def step_segment(q, p, dt0):
            z, status, accepted, rejected = peers.diffrax_solve(system.H, span, jnp.concatenate([q, p]), solver, dt0,
                                                                controller, MAX_STEPS)
            dt = span / jnp.maximum(accepted, 1) if controlled else dt0
            return z[:d], z[d:], dt, counts(status, accepted, rejected, DIFFRAX_STAGES[name] * (accepted + rejected) + 1)

        return segments(step_segment, q0, p0, jnp.asarray(1e-3 * span if controlled else span / knob, q0.dtype))

    return run


def verlet(weights=(1.0,)):
    """Velocity Verlet (``_peers.verlet_step``: one gradient of V per substep), composed with
    ``weights`` (Yoshida's triple jump: order 4); knob m steps of T / (SAVES m) per segment."""

    def run(system, q0, p0, m):
        step = peers.verlet_step(system.H, system.T / SAVES / m, weights)

        def step_segment(q, p, f):
            q, p, f = jax.lax.fori_loop(0, m, lambda _, c: step(c), (q, p, f))
            return q, p, f, counts(0, m, 0, len(weights) * m)

        return segments(step_segment, q0, p0, jax.grad(system.H)(q0, p0))

    return run


def midpoint(weights=(1.0,)):
    """The implicit midpoint rule (``_peers.gauss_step`` of one stage: fixed-point iteration to
    round-off, each update one field evaluation; status 1 if a step took its cap), composed with
    ``weights`` (the triple jump: order 4); knob m steps of T / (SAVES m) per segment."""

    def run(system, q0, p0, m):
        step, d, zero = peers.gauss_step(system.H, system.T / SAVES / m, 1, weights), q0.size, jnp.zeros((), jnp.int32)

        def step_segment(q, p, Zs):
            z, Zs, status, it = jax.lax.fori_loop(0, m, lambda _, c: step(c), (jnp.concatenate([q, p]), Zs, zero, zero))
            return z[:d], z[d:], Zs, counts(status, m, 0, it, it)

        return segments(step_segment, q0, p0, jnp.zeros((len(weights), 1, 2 * d), q0.dtype))

    return run


@dataclasses.dataclass(frozen=True)
class Solver:
    """A solver of the comparison.

    Attributes:
        name: its label.
        ours: galerkin_jax (True) or a peer.
        kind: "steps" (knob: steps m per segment, index i -> round(2^(i/4))) or "tol" (rtol =
            atol, i -> 10^(-i/4)); the cost grows with i.
        order: the error's expected exponent in the knob (steps: error ~ m^-order; tol: ~ tol^order),
            for the first predictions; later ones use the measured slope.
        make: ``run(system, q0, p0, knob) -> Out``, compiled once per system (the knob traced).
        start: where the search starts: a multiple c of the system's scale step h0 (steps: m =
            T / (SAVES c h0)) or the tolerance.
        applies: which systems it runs on.
        final: ``run(system, q0, p0, knob)`` with the knob static, where the timed run differs
            from ``make``'s (galerkin_jax's fixed steps: n_steps is static); each cheapest knob
            is compiled and checked again with it.
    """

    name: str
    ours: bool
    kind: str
    order: float
    make: Callable
    start: float
    applies: Callable = lambda system: True
    final: Callable = None


def separable(system):
    return system.V is not None


def solver_list(quick):
    """The solvers; ``start`` is a multiple of the system's scale step h0 (fixed steps) or a
    tolerance. ``--quick`` keeps cG(4) fixed, cG(6) PID and every peer."""
    cg = [Solver(f"cG({k})+Gauss {k}", True, "steps", 2 * k, cg_fixed(k, search=True), start, final=cg_fixed(k))
          for k, start in ((3, 1.0), (4, 1.0), (6, 1.5))]
    pid = [Solver(f"cG({k})+Gauss {k} PID", True, "tol", 1.0, cg_pid(k), 1e-4) for k in (4, 6)]
    # iterating to 1e-10 of the unknowns instead of their round-off (``SolverOptions.tolerance``)
    loose = [Solver(f"cG({k})+Gauss {k} tolerance 1e-10", True, "steps", 2 * k, cg_fixed(k, 1e-10, search=True), 1.0,
                    final=cg_fixed(k, 1e-10)) for k in (3, 4)]
    named_peers = [
        Solver("diffrax Tsit5", False, "steps", 5, diffrax_run("Tsit5", False), 0.5),
        Solver("diffrax Dopri8", False, "steps", 8, diffrax_run("Dopri8", False), 1.0),
        Solver("diffrax Tsit5 PID", False, "tol", 1.0, diffrax_run("Tsit5", True), 1e-6),
        Solver("diffrax Dopri8 PID", False, "tol", 1.0, diffrax_run("Dopri8", True), 1e-6),
        Solver("velocity Verlet", False, "steps", 2, verlet(), 0.125, applies=separable),
        Solver("Verlet triple jump (order 4)", False, "steps", 4, verlet(peers.TRIPLE_JUMP), 0.5, applies=separable),
        Solver("implicit midpoint", False, "steps", 2, midpoint(), 0.125, applies=lambda system: not separable(system)),
        Solver("midpoint triple jump (order 4)", False, "steps", 4, midpoint(peers.TRIPLE_JUMP), 0.5,
               applies=lambda system: not separable(system)),
    ]
    elements = [Solver(label, True, "steps", order, explicit(method, forces, search=True), start, applies=separable,
                       final=explicit(method, forces)) for label, method, order, forces, start in EXPLICIT]
    general = lambda system: not separable(system)
    tao = [Solver(label, True, "steps", order, explicit(method, forces, search=True), start, applies=general,
                  final=explicit(method, forces)) for label, method, order, forces, start in TAO]
    if quick:
        return [cg[1], pid[1]] + elements + tao + named_peers
    return cg + pid + loose + elements + tao + named_peers


SCALE_STEP = 0.05  # h0 of ``Solver.start``: a step that resolves every system's motion
LOOSEST_TOL = 8  # the grid index of the loosest tolerance tried: 1e-2


def knob_value(solver, i):
    return max(1, round(2 ** (i / 4))) if solver.kind == "steps" else 10 ** (-i / 4)


def start_index(solver, system):
    """``solver.start`` as a grid index for ``system``."""
    if solver.kind == "steps":
        return max(4, round(4 * math.log2(system.T / SAVES / (SCALE_STEP * solver.start))))
    return max(LOOSEST_TOL, round(-4 * math.log10(solver.start)))


class Probe:
    """One solver on one system: its runs by grid index (compiled once, the knob traced), each
    with its relative energy error; and the ``final`` runs of a solver that has them."""

    def __init__(self, solver, system, cap_s):
        self.solver, self.system, self.cap_s = solver, system, cap_s
        self.q0, self.p0 = jnp.asarray(system.q0), jnp.asarray(system.p0)
        self.H0 = float(system.H(self.q0, self.p0))
        self.energies = jax.jit(jax.vmap(system.H))
        self.records, self.finals, self.calls = {}, {}, {}
        self.shared = None  # (compile_s, call) of make(system)

    def call(self, i):
        """(compile_s, call(q0, p0) -> Out) for index i: the final run where the solver has one."""
        if i not in self.calls:
            knob = knob_value(self.solver, i)
            if self.solver.final is not None:
                self.calls[i] = compiled(functools.partial(self.solver.final, self.system, m=knob), self.q0, self.p0)
            else:
                compile_s, call = self.searching()
                self.calls[i] = (compile_s, lambda q0, p0, call=call, k=jnp.asarray(knob): call(q0, p0, k))
        return self.calls[i]

    def searching(self):
        if self.shared is None:
            start = knob_value(self.solver, start_index(self.solver, self.system))
            self.shared = compiled(functools.partial(self.solver.make, self.system), self.q0, self.p0, jnp.asarray(start))
        return self.shared

    def __call__(self, i):
        """The search's record of index i (its first call, timed once)."""
        if i not in self.records:
            compile_s, call = self.searching()
            self.records[i] = self.record(i, lambda q0, p0: call(q0, p0, jnp.asarray(knob_value(self.solver, i))),
                                          compile_s, first=len(self.records) == 0)
        return self.records[i]

    def final(self, i):
        """The record of index i's timed run (``call``): the search's, or the final run's."""
        if self.solver.final is None:
            return self(i)
        if i not in self.finals:
            compile_s, call = self.call(i)
            self.finals[i] = dict(self.record(i, call, compile_s, first=True), final=True)
        return self.finals[i]

    def record(self, i, call, compile_s, first):
        """Run index i once (timed: first_s) and record its error and counts; print them (with the
        compile time on a ``first`` run)."""
        t0 = time.perf_counter()
        out = jax.block_until_ready(call(self.q0, self.p0))
        first_s = time.perf_counter() - t0
        error = self.error(out) if int(out.status) == 0 else math.inf
        r = dict(index=i, knob=knob_value(self.solver, i), status=int(out.status),
                 error=error if math.isfinite(error) else math.inf, steps=int(out.steps), rejected=int(out.rejected),
                 evaluations=int(out.evaluations), iterations=int(out.iterations), compile_s=compile_s,
                 first_s=first_s)
        show(self.solver.name, r, *(() if first else ("knob", "error", "steps", "rejected", "status", "first_s")))
        return r

    def error(self, out):
        energies = np.asarray(self.energies(out.q, out.p))
        return float(np.max(np.abs(energies - self.H0)) / abs(self.H0))

    def predicted_s(self, i):
        """A run's time at index i from the nearest measured run, by steps (fixed) or by the
        measured time's growth with the knob (tol: 1.15x a quarter decade)."""
        done = [r for r in self.records.values() if r["status"] == 0]
        if not done:
            return 0.0
        r = min(done, key=lambda r: abs(r["index"] - i))
        if self.solver.kind == "steps":
            return r["first_s"] * knob_value(self.solver, i) / r["knob"]
        return r["first_s"] * 10 ** ((i - r["index"]) / 16)


def slope(probe, near):
    """The measured decrease of log10 error per grid index near index ``near``, from the two
    successful records closest to it; None if there are not two with distinct errors."""
    done = sorted((r for r in probe.records.values() if r["status"] == 0 and 0 < r["error"] < math.inf),
                  key=lambda r: abs(r["index"] - near))[:2]
    if len(done) < 2 or done[0]["index"] == done[1]["index"]:
        return None
    a, b = done
    s = (math.log10(a["error"]) - math.log10(b["error"])) / (b["index"] - a["index"])
    return s if s > 0.05 else None


def expected_slope(solver):
    """log10 error per grid index from the solver's order."""
    if solver.kind == "tol":
        return solver.order / 4
    return solver.order * math.log10(2) / 4


def cheapest(probe, target, start, max_runs=12, max_jump=8):
    """The smallest grid index whose run meets ``target`` (a failed run never does): from
    ``start``, each next index predicted from the error's slope (at most ``max_jump`` indices
    at once), until a run that meets it sits next to one that does not. Returns (index or
    None, note)."""
    fails, passes = -math.inf, None  # the largest index known to miss, the smallest known to meet
    i = start
    for _ in range(max_runs):
        if probe.predicted_s(i) > probe.cap_s:
            return passes, (f"knob {knob_value(probe.solver, i):.4g} predicted to take {probe.predicted_s(i):.1f} s "
                            f"(cap {probe.cap_s:g} s)")
        r = probe(i)
        if r["error"] <= target:
            passes = i if passes is None else min(passes, i)
        else:
            fails = max(fails, i)
        if passes is not None and passes - fails == 1:
            return passes, ""
        if r["status"] != 0:
            step = 2  # a failed run: finer steps, a smaller tolerance
        else:
            s = slope(probe, i) or expected_slope(probe.solver)
            step = math.ceil((math.log10(r["error"]) - math.log10(target)) / s)
            if r["error"] <= target:
                step = min(step, -1)
        lowest = max(fails + 1, LOOSEST_TOL if probe.solver.kind == "tol" else 0)
        if passes is not None and lowest >= passes:  # e.g. the loosest tolerance tried meets it
            return passes, ""
        i = max(i + max(-max_jump, min(max_jump, step)), lowest)
        if passes is not None:
            i = min(i, passes - 1)
    return passes, f"search ended after {max_runs} runs"


def run_system(system, solvers, cap_s):
    """Every solver at every level on ``system``: the cheapest run per level (found, not yet
    timed; ``time_cheapest`` times them)."""
    print(f"{system.name}: {system.description}", flush=True)
    result = dict(description=system.description, facts=system.facts, T=system.T, d=int(system.q0.size),
                  H0=float(system.H(jnp.asarray(system.q0), jnp.asarray(system.p0))), solvers={})
    probes = {}
    for solver in solvers:
        if not solver.applies(system):
            continue
        probe = probes[solver.name] = Probe(solver, system, cap_s)
        entry, start = {}, start_index(solver, system)
        for level in LEVELS:
            index, note = cheapest(probe, level, start)
            entry[f"{level:.0e}"] = dict(index=index, note=note)
            if index is not None:
                start = index
        result["solvers"][solver.name] = dict(ours=solver.ours, kind=solver.kind, levels=entry)
    choose_finals(result, probes)
    return result, probes


FINAL_MARGIN = 1.5


def choose_finals(result, probes):
    """Which of galerkin_jax's fixed-step solvers get their timed run (a compilation each) at a
    level: those whose search run there took at most FINAL_MARGIN times the fastest one's (the
    search's while loop costs 1.4-1.8x the timed scan, alike for every k). The others keep the
    search's run, marked ``search_only``, and do not enter the comparison. The explicit elements
    (``EXPLICIT``, whose stand-in is another loop) are all timed."""
    elements = {label for label, *_ in EXPLICIT}
    for level in (f"{x:.0e}" for x in LEVELS):
        entries = {name: r["levels"][level] for name, r in result["solvers"].items()
                   if probes[name].solver.final is not None and r["levels"][level]["index"] is not None
                   and name not in elements}
        if not entries:
            continue
        first = {name: probes[name](e["index"])["first_s"] for name, e in entries.items()}
        fastest = min(first.values())
        for name, entry in entries.items():
            if first[name] > FINAL_MARGIN * fastest:
                entry.update(probes[name](entry["index"]), search_only=True)


def time_cheapest(result, probes, repeat, budget_s):
    """Time each solver's cheapest run per level (the same index once) and attach it. Where
    the timed run is a ``final`` one, its own error must meet the level too, else the next
    index is taken (at most twice)."""
    for name, solver_result in result["solvers"].items():
        probe = probes[name]
        for level, entry in solver_result["levels"].items():
            if entry["index"] is None or entry.get("search_only"):
                continue
            record = probe.final(entry["index"])
            while record["error"] > float(level) and record["index"] < entry["index"] + 2:
                record = probe.final(record["index"] + 1)
            if record["error"] > float(level):
                entry.update(index=None, note=f"its final run missed: error {record['error']:.2e}")
                continue
            compile_s, call = probe.call(record["index"])
            record["run_s"] = min(record.get("run_s", math.inf),
                                  best_time(call, probe.q0, probe.p0, repeat=repeat, budget_s=budget_s))
            entry.update(record)


def summarize(result):
    """Per level: the best galerkin_jax run, the best peer, the ratios of their run times and
    field evaluations."""
    result["summary"] = {}
    for level in (f"{x:.0e}" for x in LEVELS):
        ours, peer = (min((dict(solver=name, **r["levels"][level]) for name, r in result["solvers"].items()
                           if r["ours"] == side and r["levels"][level].get("run_s") is not None),
                          key=lambda c: c["run_s"], default=None) for side in (True, False))
        both = ours is not None and peer is not None
        result["summary"][level] = dict(ours=ours, peer=peer, ratio=ours["run_s"] / peer["run_s"] if both else None,
                                        evaluations_ratio=ours["evaluations"] / peer["evaluations"] if both else None)


def describe(run, kind_of):
    if run is None:
        return "none reached it"
    knob = knob_text(kind_of[run["solver"]], run)
    rejected = f" + {run['rejected']} rejected" if run["rejected"] else ""
    return (f"{run['solver']}, {knob}: {1e3 * run['run_s']:.3g} ms ({run['steps']} steps{rejected}, "
            f"compile {run['compile_s']:.1f} s)")


def knob_text(kind, run):
    return f"n = {SAVES * run['knob']}" if kind == "steps" else f"tol {run['knob']:.1e}"


def tables(results):
    """The summary (best of each side, ratio), then per system every solver's cheapest runs."""
    return "\n\n".join([summary_table(results)] + [detail_table(n, r) for n, r in results.items()]) + "\n"


def summary_table(results):
    rows = []
    for name, result in results.items():
        kinds = {s: r["kind"] for s, r in result["solvers"].items()}
        for level, row in result["summary"].items():
            rows.append([name, level, describe(row["ours"], kinds), describe(row["peer"], kinds),
                         *("n/a" if row[k] is None else f"{row[k]:.2f}x" for k in ("ratio", "evaluations_ratio"))])
    return markdown_table(["system", "max \\|dH/H\\|", "best galerkin_jax", "best peer", "ratio (time)",
                           "ratio (field evaluations)"], rows)


def detail_table(name, result):
    rows = [[s, *(cell(r["kind"], r["levels"][f"{x:.0e}"]) for x in LEVELS)] for s, r in result["solvers"].items()]
    header = ["solver"] + [f"{x:.0e}: ms / steps (+ rejected) / field evaluations" for x in LEVELS]
    return f"{name}: {result['description']}; d = {result['d']}, H0 = {result['H0']:.6g}\n\n" + markdown_table(header, rows)


def cell(kind, e):
    """One solver's cheapest run at one level: time / steps / evaluations (knob, iterations per
    step where it iterates, time per evaluation)."""
    if e.get("search_only"):
        return (f"search run {1e3 * e['first_s']:.3g} / {e['steps']} / {e['evaluations']} ({knob_text(kind, e)}; "
                f"not timed: over {FINAL_MARGIN}x the best k's search run)")
    if e.get("run_s") is None:
        return "not reached" + (f" ({e['note']})" if e.get("note") else "")
    attempts = e["steps"] + e["rejected"]
    its = f", {e['iterations'] / attempts:.1f} it/step" if e["iterations"] else ""
    rejected = f" + {e['rejected']}" if e["rejected"] else ""
    return (f"{1e3 * e['run_s']:.3g} / {e['steps']}{rejected} / {e['evaluations']} "
            f"({knob_text(kind, e)}{its}, {1e6 * e['run_s'] / e['evaluations']:.2f} us/eval)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small systems, short spans, a few solvers (minutes)")
    parser.add_argument("--only", nargs="+", metavar="SYSTEM", help="run only these systems (names as in the table)")
    parser.add_argument("--cap", type=float, default=None, help="the longest predicted run that is run (s; "
                        "default 3, --quick 0.5)")
    parser.add_argument("--solvers", nargs="+", metavar="TEXT", help="run only the solvers whose names contain one "
                        "of these (e.g. Tao Dopri8)")
    parser.add_argument("--name", help="output name (default moderate, with _quick and the systems run when not all)")
    options = parser.parse_args()
    available = system_list(options.quick)
    chosen = options.only or list(available)
    unknown = sorted(set(chosen) - set(available))
    if unknown:
        parser.error(f"unknown systems {unknown}; choose from {list(available)}")
    cap_s = options.cap or (0.5 if options.quick else 3.0)
    suffix = ("_quick" if options.quick else "") + ("" if chosen == list(available) else "_" + "_".join(chosen))
    before, start = machine(), time.perf_counter()
    results, all_probes = {}, {}
    repeat, budget_s = (1, 0.5) if options.quick else (3, 3.0)
    for system_name in chosen:
        chosen_solvers = [solver for solver in solver_list(options.quick)
                          if not options.solvers or any(text in solver.name for text in options.solvers)]
        results[system_name], all_probes[system_name] = run_system(available[system_name](), chosen_solvers, cap_s)
        time_cheapest(results[system_name], all_probes[system_name], repeat, budget_s)
    # a second timing pass, minutes after the first: this machine's speed drifts
    for system_name in chosen:
        time_cheapest(results[system_name], all_probes[system_name], repeat, budget_s)
        summarize(results[system_name])
        for probe_name, probe in all_probes[system_name].items():
            entry = results[system_name]["solvers"][probe_name]
            entry["runs"] = sorted(probe.records.values(), key=lambda r: r["index"])
            entry["final_runs"] = sorted(probe.finals.values(), key=lambda r: r["index"])
    markdown = tables(results)
    total_s = time.perf_counter() - start
    write(options.name or "moderate" + suffix,
          {"machine_before": before, "quick": options.quick, "versions": before["versions"], "saves": SAVES,
           "levels": list(LEVELS), "cap_s": cap_s, "total_s": total_s, "systems": results}, markdown)
    print(markdown)
    print(f"total {total_s / 60:.1f} min")


if __name__ == "__main__":
    main()
