"""The ``galerkin-jax`` command line tool: ``run``, ``sweep`` and ``reproduce``.

``main(argv)`` returns the exit status: 0 success, 1 an error in the input (unknown scene,
a scene file that raises, lacks H, q0 or p0, or holds values the library rejects, such as a
non-finite q0 or h <= 0: checked before anything is written), 2 a bad option (a method spec
that names no method included), 3 an implicit solve that failed in ``run`` or in any
configuration of ``sweep`` (``gj.status_message`` says why). An error is one line on stderr,
``galerkin-jax: error: ...``; argparse's own messages for a bad option come with the usage.
"""

import argparse
import dataclasses
import functools
import os
import sys
import time
import warnings

import jax
import numpy as np

import galerkin_jax as gj

from . import _cli_output as output
from . import _cli_specs as specs
from . import _cli_summary as summary
from . import _cli_sweep as sweeps
from ._cache import CACHE_VARIABLE, compile_cache_folder, use_compilation_cache  # noqa: F401 (names of the command)
from ._cli_specs import EXIT_BAD_OPTION, CliError

EXIT_FAILED_SOLVE = 3
DENSE_LIMIT = 2 * 10**7  # numbers kept for dense output
DEFAULT_SCENE = "kepler"
DEFAULT_OUT, DEFAULT_REPRODUCE_OUT = "galerkin-jax-output", "galerkin-jax-reproduce"
DEFAULT_SWEEP_METHODS = "cg2:gauss2,cg2:lobatto3,cg2:gauss4,dg1:gauss2,dgrad"
SCENES_AND_METHODS = """\
SCENE is one of oscillator, quartic, kepler, pendulum, fput, or the path of a Python file
that defines H(q, p), q0 and p0 (optionally h, n_steps, args -- then H(q, p, args) --,
invariants = {name: I(q, p)}, description, exact(t) -> (q, p), center (a fixed central
body's position), and L(q, qdot) for LagrangianVI). q0 and p0 may have the shape (N, 2) or
(N, 3) of N bodies; H then receives them in that shape, and `run` draws the bodies' paths.

A method is KIND[DEGREE][:RULE[POINTS]]: KIND is cg, dg, vi (GalerkinVI), lvi
(LagrangianVI), mm (ModifiedMidpoint) or dgrad (DiscreteGradient); RULE is gauss
(Gauss-Legendre), lobatto, radau, midpoint or trapezoid. Examples: cg3:gauss3, dg1:lobatto3, mm;
verlet is vi1:trapezoid (Stormer-Verlet). SCHEME@METHOD composes a symmetric method
(SCHEME: yoshida4, suzuki4, mclachlan4, yoshida6, kahan_li6, mclachlan6, kahan_li8_s15
(or kahan_li8), kahan_li8_s17, mclachlan8), e.g. kahan_li6@verlet, yoshida4@cg1:gauss1; split:SCHEME is a
splitting for separable H (leapfrog, blanes_moan4, blanes_moan6, blanes_moan_rkn4,
blanes_moan_rkn6), e.g. split:blanes_moan_rkn6; tao is Tao's explicit map for any H (e.g.
yoshida4@tao: order 4). See docs/which-method.md.

exit status: 0 success, 1 bad input, 2 bad option, 3 an implicit solve failed.
"""
EXAMPLES = """\
examples:
  galerkin-jax run                                  Kepler, cG(3) with 3 Gauss points
  galerkin-jax run quartic --method mm --steps 2000
  galerkin-jax run my_scene.py --method dG --degree 1 --rule lobatto --points 3 --format csv
  galerkin-jax run fput --method kahan_li6@verlet    explicit: FPUT's H is separable
  galerkin-jax sweep kepler --methods cg2:gauss2,cg2:gauss4,mm --step-sizes 0.1,0.05,0.02
  galerkin-jax reproduce --quick
"""


ADAPTIVE_MAX_STEPS = 100_000  # steps of --tol / --time-transform: a run that needs more says so (status 4)
SAVED_STATES = 2001  # states a run to --t-end saves, evenly in time, from the element polynomials


def console(argv=None):
    """The ``galerkin-jax`` script (and ``python -m galerkin_jax``): ``main`` with JAX's
    persistent compilation cache in ``compile_cache_folder()`` (``gj.use_compilation_cache``),
    so that a command run again with the same shapes and methods loads its XLA programs instead
    of compiling them. The script sets this global option; ``main`` does not, and the library
    only where a user calls ``use_compilation_cache``."""
    use_compilation_cache()
    return main(argv)


def main(argv=None):
    """Run the command line tool on ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    parser = build_parser()
    try:
        options = parser.parse_args(argv)
    except SystemExit as exit:  # --help, or argparse's message for a bad option
        return exit.code
    previous = jax.config.read("jax_enable_x64")
    jax.config.update("jax_enable_x64", not getattr(options, "float32", False))
    _use_agg()
    try:
        with warnings.catch_warnings():
            # --float32 asked for it: the library's Float32Warning would only repeat that
            warnings.filterwarnings("ignore", message="galerkin_jax is computing in float32")
            return options.command(options)
    except CliError as error:
        print(f"galerkin-jax: error: {error}", file=sys.stderr)
        return error.code
    finally:
        jax.config.update("jax_enable_x64", previous)  # for callers in the same process (tests)


def _floats(text):
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None
    if not values or not all(np.isfinite(v) and v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive numbers, got {text!r}")
    return values


def _pair(text):
    parts = [output.parse_coordinate(part) for part in text.split(",")]
    if len(parts) != 2 or None in parts:
        raise argparse.ArgumentTypeError(f"expected two coordinates such as q0,q1 or q2,p2, got {text!r}")
    return tuple(parts)


def _positive(kind):
    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {kind.__name__}, got {text!r}") from None
        if not value > 0 or not np.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
        return value

    return parse


def build_parser():
    """The argument parser: one subcommand per ``*_command`` function."""
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog="galerkin-jax", formatter_class=raw, epilog=SCENES_AND_METHODS + "\n" + EXAMPLES,
        description="Galerkin finite elements in time for Hamiltonian systems (galerkin_jax). "
                    "Start with 'galerkin-jax run': a Kepler orbit, its energy error and a summary.")
    commands = parser.add_subparsers(title="commands", metavar="{run,sweep,reproduce}", required=True)
    scene = argparse.ArgumentParser(add_help=False)
    scene.add_argument("scene", nargs="?", metavar="SCENE",
                       help=f"built-in scene or scene file (default {DEFAULT_SCENE})")
    scene.add_argument("--steps", type=_positive(int), metavar="N",
                       help="number of time elements (default: the scene's)")
    scene.add_argument("--float32", action="store_true", help="compute in float32 (default float64)")
    scene.add_argument("--progress", action=argparse.BooleanOptionalAction, default=sys.stderr.isatty(),
                       help="a progress bar while the elements run (default: on when stderr is a terminal)")
    scene.add_argument("--krylov", action="store_true",
                       help="Newton-Krylov for systems of more than 256 unknowns (stiff large scenes, h omega >~ 1)")
    common = dict(parents=[scene], formatter_class=raw, epilog=SCENES_AND_METHODS)
    out = dict(metavar="FOLDER", default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")

    run = commands.add_parser("run", help="integrate one scene; write its trajectory, plots and a summary",
                              description="Integrate one scene with one method.", **common)
    run.add_argument("--method", "-m", metavar="METHOD", default="cg",
                     help="cG, dG, GalerkinVI, ModifiedMidpoint, DiscreteGradient, Tao (LagrangianVI with a scene "
                          "file defining L), or a spec such as cg3:gauss3 (default cG)")
    run.add_argument("--degree", "-k", type=int, metavar="K", help=f"degree k (default {specs.DEFAULT_DEGREE})")
    run.add_argument("--rule", "-r", metavar="RULE",
                     help="quadrature rule: gauss (Gauss-Legendre, default), lobatto, radau, midpoint, trapezoid")
    run.add_argument("--points", "-n", type=int, metavar="N",
                     help="points of the rule (default: k Gauss points for cG and the VIs, otherwise k + 1)")
    run.add_argument("--step-size", type=_positive(float), metavar="H", help="step size h (default: the scene's)")
    run.add_argument("--t-end", type=_positive(float), metavar="T",
                     help="integrate to t = T (the last step shortened to land on it) instead of --steps")
    run.add_argument("--tol", type=_positive(float), metavar="TOL",
                     help="choose the steps by error-per-step control, rtol = atol = TOL (needs an end time)")
    run.add_argument("--time-transform", action="store_true",
                     help="variable steps that keep the method's structure (the Poincare transformation; "
                          "--step-size is then the first step)")
    run.add_argument("--max-steps", type=_positive(int), metavar="N", default=ADAPTIVE_MAX_STEPS,
                     help=f"cap on the steps of --tol or --time-transform (default {ADAPTIVE_MAX_STEPS})")
    run.add_argument("--save-every", type=_positive(int), metavar="N", default=1,
                     help="save every N-th state (default 1)")
    run.add_argument("--out", **out)
    run.add_argument("--format", choices=("npz", "csv"), default="npz", help="trajectory file format (default npz)")
    run.add_argument("--plot", type=_pair, metavar="X,Y",
                     help="the coordinates of the second plot, e.g. q0,q1 or q2,p2 (0-based, as the CSV columns; "
                          "default: the bodies' paths for states of shape (N, 2) or (N, 3) and d = 2, 3, else q_i "
                          "against p_i for the coordinate that varies most)")
    run.set_defaults(command=run_command)

    sweep = commands.add_parser("sweep", help="methods x step sizes in one batched call; a table and plots",
                                description="Run every method at every step size (and initial state) for the "
                                            "same number of steps, batched.", **common)
    sweep.add_argument("--methods", metavar="SPECS", default=DEFAULT_SWEEP_METHODS,
                       help=f"comma-separated method specs (default {DEFAULT_SWEEP_METHODS})")
    sweep.add_argument("--step-sizes", type=_floats, metavar="H,H,...",
                       help="comma-separated step sizes (default: the scene's h times 2, 1, 1/2, 1/4)")
    sweep.add_argument("--q0-scale", type=_floats, metavar="S,S,...", default=[1.0],
                       help="initial states (s q0, p0), comma-separated s (default 1)")
    sweep.add_argument("--t-end", type=_positive(float), metavar="T",
                       help="every configuration integrates to t = T instead of --steps")
    sweep.add_argument("--out", **out)
    sweep.set_defaults(command=sweep_command)

    reproduce = commands.add_parser("reproduce", help="regenerate Table 5.1 and the papers' figures",
                                    description="Regenerate Table 5.1 of [GBS] and the papers' figures.")
    reproduce.add_argument("--out", metavar="FOLDER", default=DEFAULT_REPRODUCE_OUT,
                           help=f"output folder (default {DEFAULT_REPRODUCE_OUT})")
    reproduce.add_argument("--quick", action="store_true", help="shorter runs for the figures (Table 5.1 in full)")
    reproduce.set_defaults(command=reproduce_command)
    return parser


def timed(fn, *args):
    """Compile ``fn`` for ``args`` and run it; returns ``(result, compile_s, run_s)``.

    Values passed as ``args`` (step sizes, states) are arguments of the compiled program, not
    constants in it, so that the compilation cache serves a run that changes only them.
    Input the library rejects, and errors raised by the user's H while it is traced,
    become a ``CliError``.
    """
    start = time.perf_counter()
    try:
        compiled = jax.jit(fn).lower(*args).compile()
    except Exception as error:  # the library's ValueError/TypeError or the user's H
        raise CliError(f"{type(error).__name__}: {error}") from None
    compiled_at = time.perf_counter()
    result = jax.block_until_ready(compiled(*args))
    return result, compiled_at - start, time.perf_counter() - compiled_at


def _bind(f, args):
    return f if args is None else (lambda q, p: f(q, p, args))


def _use_agg():
    import matplotlib

    matplotlib.use("Agg")  # files only, no display


def _dtype():
    return np.float64 if jax.config.read("jax_enable_x64") else np.float32


def _method_spec(options):
    """The spec of ``--method``, with ``--degree``, ``--rule`` and ``--points`` taking precedence."""
    try:
        spec = specs.parse_spec(options.method)
        if spec.kind in ("comp", "split"):
            if (options.degree, options.rule, options.points) != (None, None, None):
                raise CliError(f"{specs.label(spec)} takes no --degree, --rule or --points (a composition's are "
                               "written in its spec, e.g. kahan_li6@cg1:gauss1).", EXIT_BAD_OPTION)
            return spec
        pick = lambda option, default: default if option is None else option
        rule = None if options.rule is None else specs.rule_key(options.rule)
        return specs.complete(specs.MethodSpec(spec.kind, pick(options.degree, spec.degree), pick(rule, spec.rule),
                                               pick(options.points, spec.points)))
    except CliError as error:
        raise CliError(f"--method: {error}", error.code) from None


def _check_plot(pair, d):
    for part, index in pair or ():
        if index >= d:
            raise CliError(f"--plot: {part}{index} does not exist; the scene has q0 .. q{d - 1} and p0 .. p{d - 1}.",
                           EXIT_BAD_OPTION)


def run_command(options):
    """``galerkin-jax run``: integrate, write the trajectory and the plots, print the summary.
    Every input is checked before the integration, and nothing is written before it ran."""
    spec = _method_spec(options)
    problem = specs.load_scene(options.scene or DEFAULT_SCENE)
    if spec.kind == "lvi" and problem.L is None:
        raise CliError("LagrangianVI integrates L(q, qdot): give a scene file that defines L.")
    h = options.step_size or problem.h
    span = _span(options, problem, h)
    n_steps = options.steps or problem.n_steps
    if span is None and n_steps % options.save_every:
        raise CliError(f"--steps ({n_steps}) must be a multiple of --save-every ({options.save_every}).",
                       EXIT_BAD_OPTION)
    _check_plot(options.plot, problem.d)
    method = specs.build(spec)
    q0, p0 = problem.q0.astype(_dtype()), problem.p0.astype(_dtype())
    if span is None:
        timing = dict(n_steps=n_steps, save_every=options.save_every, dense=_dense(spec, n_steps, problem.d))
    elif _dense(spec, options.max_steps, problem.d):  # the steps themselves: states at the nodes
        timing = dict(t1=span["t1"], controller=span["controller"], max_steps=options.max_steps, dense=True)
    else:  # too many steps to keep: states between the nodes, from the element polynomials
        timing = dict(t1=span["t1"], controller=span["controller"], max_steps=options.max_steps,
                      save_at=np.linspace(0.0, span["t1"], SAVED_STATES).astype(_dtype()))
    integrate = functools.partial(
        gj.integrate, problem.L if spec.kind == "lvi" else problem.H, q0, p0, method=method, args=problem.args,
        progress=options.progress, krylov=options.krylov, **timing)
    solution, compile_s, run_s = timed(lambda h: integrate(h=h), np.asarray(h, _dtype()))
    if span is not None:
        n_steps = int(solution.stats["num_accepted_steps"])
        solution = _nodes(solution, n_steps)
    energy, invariants = _observe(problem, solution)
    files = _write_run(problem, spec, solution, energy, invariants, h, n_steps, options, span)
    n_unknowns = summary.unknowns(method, q0, p0)
    rule = dict(controller=None, tol=None) if span is None else dict(controller=span["name"], tol=span["tol"])
    text = summary.run_summary(problem, spec, solution, energy, invariants, h, n_steps, (compile_s, run_s), files,
                               n_unknowns, options.krylov, **rule)
    print(text if span is None else summary.with_step_rule(text, solution, span["rule"], span["name"]))
    status = int(solution.status)
    if status:
        raise CliError(summary.failure_message(status, n_unknowns, options.krylov, h, max_steps=options.max_steps,
                                               **rule), code=EXIT_FAILED_SOLVE)
    return 0


def _nodes(solution, n_steps):
    """A run with dense output as the states at its steps' ends (the nodes), where its
    element polynomials are less accurate than the nodes (superconvergence)."""
    dense = solution.dense
    if dense is None:
        return solution
    q, p = dense.view(dense.z[: n_steps + 1])
    return dataclasses.replace(solution, t=dense.t[: n_steps + 1], q=q, p=p)


def _span(options, problem, h):
    """``None`` for a run of ``--steps``, else its end time, controller and how to say it:
    ``--t-end`` (or the scene's ``t1``) with fixed steps, ``--tol`` (or the scene's ``tol``) or
    ``--time-transform`` for variable ones. ``name`` ("pid", "time-transform" or None for fixed
    steps) goes into the file names and tells the summary how the steps were chosen."""
    t1 = options.t_end or problem.t1
    tol = options.tol or (None if options.time_transform else problem.tol)
    if options.tol and options.time_transform:
        raise CliError("--tol and --time-transform choose the steps in two different ways: give one.", EXIT_BAD_OPTION)
    if options.steps and options.t_end:
        raise CliError("--steps and --t-end both set the run's length: give one.", EXIT_BAD_OPTION)
    if t1 is None and options.steps is None and (tol or options.time_transform):
        t1 = h * problem.n_steps
    if t1 is None or (options.steps and not (tol or options.time_transform)):
        return None
    if tol:
        return dict(t1=t1, controller=gj.PIDController(rtol=tol, atol=tol), rule=f"error per step, tol = {tol:g}",
                    name="pid", tol=tol)
    if options.time_transform:
        return dict(t1=t1, controller=gj.TimeTransform(), rule="time transformation (default s), h in tau",
                    name="time-transform", tol=None)
    return dict(t1=t1, controller=None, rule="fixed steps, the last shortened to land on t1", name=None, tol=None)


def _dense(spec, n_steps, d):
    """Keep the element polynomials for the plots (drawn between the saved states) unless they
    would take more than ~160 MB: n_steps x (k + 1) x 2d numbers."""
    return n_steps * ((spec.degree or 1) + 1) * 2 * d <= DENSE_LIMIT


def _observe(problem, solution):
    """H and the invariants at every saved state: ``(energy, {name: values})``."""
    functions = [("H", _bind(problem.H, problem.args))] + list(problem.invariants.items())
    values = []
    for name, f in functions:
        try:
            values.append(np.asarray(jax.vmap(f)(solution.q, solution.p)))
        except Exception as error:  # the user's function
            raise CliError(f"{name}(q, p) raised {type(error).__name__}: {error}") from None
    return values[0], dict(zip(problem.invariants, values[1:]))


def run_stem(problem, spec, span):
    """The files' common name, e.g. ``kepler_cG3-gauss3``; a run whose steps a controller
    chose adds it (``_pid``, ``_time-transform``), so that it does not overwrite the
    fixed-step run's files."""
    name = None if span is None else span["name"]
    return f"{problem.name}_{specs.tag(spec)}" + ("" if name is None else f"_{name}")


def plot_title(problem, spec, h, span, solution):
    """E.g. ``kepler, cG(3) Gauss-Legendre 3, h = 0.05``; under a controller, on a second line,
    how it chose the steps and their range in t where the saved states are the steps' ends
    (the time transformation's h is its step in the fictive time tau)."""
    name = None if span is None else span["name"]
    steps = summary.step_range(solution) if name is not None else None
    if name == "pid":
        words = f"tol = {span['tol']:g}" + ("" if steps is None else f", h from {steps[0]:.3g} to {steps[1]:.3g}")
    elif name == "time-transform":
        words = f"h = {h:g} in tau" + ("" if steps is None else f", steps in t from {steps[0]:.3g} to {steps[1]:.3g}")
    else:
        return f"{problem.name}, {specs.short(spec)}, h = {h:g}"
    return f"{problem.name}, {specs.short(spec)}\n{words}"  # two lines: the plots are 5 and 7 inches wide


def _write_run(problem, spec, solution, energy, invariants, h, n_steps, options, span=None):
    """The trajectory (NPZ or CSV) and the two plots of a run; returns their paths."""
    os.makedirs(options.out, exist_ok=True)
    stem = os.path.join(options.out, run_stem(problem, spec, span))
    status = int(solution.status)
    columns = dict(t=solution.t, q=solution.q, p=solution.p, energy=energy,
                   **{f"invariant_{name}": value for name, value in invariants.items()})
    meta = dict(scene=problem.description, method=specs.describe(spec), h=h, n_steps=n_steps,
                save_every=options.save_every, status=status, status_message=gj.status_message(status),
                state_shape=np.asarray(problem.shape or problem.q0.shape),
                step_rule=f"fixed steps of h = {h:g}" if span is None else span["rule"])
    path = f"{stem}.{options.format}"
    files = [output.write_trajectory(path, {k: np.asarray(v) for k, v in columns.items()}, meta)]
    title = plot_title(problem, spec, h, span, solution)
    view = output.choose_view(problem.shape or problem.q0.shape, solution.q, options.plot)
    return files + output.plot_run(stem, solution, problem.H, problem.args, problem.invariants, title, view,
                                   problem.center)


def sweep_command(options):
    """``galerkin-jax sweep``: methods x step sizes (x initial states) batched, one ``gj.sweep``
    per kind and degree; writes a markdown and a CSV table and two plots, prints the table.
    Exits 3 when any configuration failed (its row shows NaN diagnostics)."""
    try:
        method_specs = specs.parse_specs(options.methods)
    except CliError as error:
        raise CliError(f"--methods: {error}", error.code) from None
    problem = specs.load_scene(options.scene or DEFAULT_SCENE)
    hs = options.step_sizes or [problem.h * f for f in (2.0, 1.0, 0.5, 0.25)]
    if options.steps and options.t_end:
        raise CliError("--steps and --t-end both set the runs' length: give one.", EXIT_BAD_OPTION)
    n_steps = options.steps or problem.n_steps
    states = [((s * problem.q0).astype(_dtype()), problem.p0.astype(_dtype())) for s in options.q0_scale]
    rows, times, n_unknowns = [], np.zeros(2), {}
    groups = sweeps.groups(method_specs)
    for group in groups:
        result, *seconds = timed(*sweeps.sweep_call(problem, group, hs, states, options.q0_scale, n_steps, _dtype(),
                                                    options.progress, options.krylov, options.t_end))
        times += seconds
        rows += sweeps.rows(group, hs, options.q0_scale, result, n_steps)
        n_unknowns.update({spec: summary.unknowns(specs.build(spec), *states[0]) for spec in group})
    rows.sort(key=lambda row: method_specs.index(row["spec"]))
    header = [c for c in rows[0] if c != "spec" and (c != "q0 scale" or len(states) > 1)]
    table = [[row[c] for c in header] for row in rows]
    notes = sweeps.notes(problem, rows, n_steps)
    os.makedirs(options.out, exist_ok=True)
    stem = os.path.join(options.out, f"{problem.name}_sweep")
    files = output.write_table(stem, header, table, notes, sweeps.FORMATS)
    energy, final = sweeps.per_method(rows, method_specs, hs)
    files += output.plot_sweep(stem, energy, final if problem.exact else None, [specs.short(s) for s in method_specs],
                               hs, f"{problem.name}, {n_steps} steps", floor=1e3 * np.finfo(_dtype()).eps)
    print(f"{problem.name}: {problem.description}\n{len(table)} configurations of {n_steps} steps each, in "
          f"{len(groups)} batched sweep(s), one per method kind and degree\n")
    print(output.markdown(header, table, sweeps.FORMATS) + "\n\n" + notes)
    print(f"time     compile {times[0]:.2f} s, run {times[1]:.3f} s")
    print("files    " + "\n         ".join(f"{p} ({output.size_text(p)})" for p in files))
    print(f"Look at {files[2]}: the energy error of each method (rows) at each step size (columns).")
    failed = sweeps.failures(rows, n_unknowns, options.krylov)
    if failed:
        raise CliError(failed, code=EXIT_FAILED_SOLVE)
    return 0


def reproduce_command(options):
    """``galerkin-jax reproduce``: Table 5.1 and the papers' figures, via ``galerkin_jax.reproduce``."""
    from . import reproduce

    result = reproduce.reproduce(options.out, quick=options.quick)
    print(f"Table 5.1 of [GBS]: is H (and |L|) conserved (C), decreasing (D) or neither (NC)?\n\n{result['table51'].text()}")
    paths = sorted(result["files"].values())
    print("files    " + "\n         ".join(f"{p} ({output.size_text(p)})" for p in paths))
    return 0
