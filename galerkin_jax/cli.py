"""The ``galerkin-jax`` command line tool: ``run``, ``sweep`` and ``reproduce``.

``main(argv)`` returns the exit status: 0 success, 1 an error in the input (unknown scene,
a scene file that raises or lacks H, q0 or p0, input the library rejects), 2 a bad
option, 3 an implicit solve that failed (``gj.status_message`` says why).
"""

import argparse
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
from . import _cli_sweep as sweeps
from ._cli_specs import CliError

EXIT_FAILED_SOLVE = 3
DENSE_LIMIT = 2 * 10**7  # numbers kept for dense output
DEFAULT_SCENE = "kepler"
DEFAULT_OUT, DEFAULT_REPRODUCE_OUT = "galerkin-jax-output", "galerkin-jax-reproduce"
DEFAULT_SWEEP_METHODS = "cg2:gauss2,cg2:lobatto3,cg2:gauss4,dg1:gauss2,dgrad"
HINTS = {
    "cg": "cG(k) conserves H to round-off when its rule integrates the DH terms exactly (polynomial H, enough "
          "points) [GBS, Thm. 3.1]; otherwise expect a small error, bounded or slowly drifting",
    "cg_gauss": "cG(k) with k Gauss points is Gauss collocation, a symplectic method: "
                "the energy error oscillates and does not drift",
    "dg": "dG(k) is dissipative [GBS, Prop. 3.1]: the energy error grows as the scheme damps",
    "vi": "a variational integrator is symplectic: the energy error oscillates and does not drift",
    "mm": "energy and angular momentum are conserved to round-off for H = |p|^2/2m + V(|q|) (central forces)",
    "dgrad": "the energy is conserved to round-off",
}
HINTS["lvi"] = HINTS["vi"]

SCENES_AND_METHODS = """\
SCENE is one of oscillator, quartic, kepler, pendulum, fput, or the path of a Python file
that defines H(q, p), q0 and p0 (arrays of one shape: (d,), or (N, 2), (N, 3) for N bodies;
optionally h, n_steps, args -- then H(q, p, args) --,
invariants = {name: I(q, p)}, description, exact(t) -> (q, p), and L(q, qdot) for
LagrangianVI).

A method is KIND[DEGREE][:RULE[POINTS]]: KIND is cg, dg, vi (GalerkinVI), lvi
(LagrangianVI), mm (ModifiedMidpoint) or dgrad (DiscreteGradient); RULE is gauss
(Gauss-Legendre), lobatto, radau, midpoint or trapezoid. Examples: cg3:gauss3, dg1:lobatto3, mm.

exit status: 0 success, 1 bad input, 2 bad option, 3 an implicit solve failed.
"""
EXAMPLES = """\
examples:
  galerkin-jax run                                  Kepler, cG(3) with 3 Gauss points
  galerkin-jax run quartic --method mm --steps 2000
  galerkin-jax run my_scene.py --method dG --degree 1 --rule lobatto --points 3 --format csv
  galerkin-jax sweep kepler --methods cg2:gauss2,cg2:gauss4,mm --step-sizes 0.1,0.05,0.02
  galerkin-jax reproduce --quick
"""


CACHE_VARIABLE = "GALERKIN_JAX_CACHE"


def compile_cache_folder(environ=os.environ):
    """Where the command keeps its compiled programs: ``$GALERKIN_JAX_CACHE`` (set but empty:
    nowhere), else ``$XDG_CACHE_HOME/galerkin_jax/xla`` or ``~/.cache/galerkin_jax/xla``."""
    if CACHE_VARIABLE in environ:
        return environ[CACHE_VARIABLE] or None
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "galerkin_jax", "xla")


def console(argv=None):
    """The ``galerkin-jax`` script (and ``python -m galerkin_jax``): ``main`` with JAX's
    persistent compilation cache in ``compile_cache_folder()``, so that a command run again
    with the same shapes and methods loads its XLA programs instead of compiling them. Only
    the script sets this global option; the library and ``main`` never do."""
    folder = compile_cache_folder()
    if folder:
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # ours take 0.3 to 2 s
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
                     help="cG, dG, GalerkinVI, ModifiedMidpoint, DiscreteGradient (LagrangianVI with a scene file "
                          "defining L), or a spec such as cg3:gauss3 (default cG)")
    run.add_argument("--degree", "-k", type=int, metavar="K", help=f"degree k (default {specs.DEFAULT_DEGREE})")
    run.add_argument("--rule", "-r", metavar="RULE",
                     help="quadrature rule: gauss (Gauss-Legendre, default), lobatto, radau, midpoint, trapezoid")
    run.add_argument("--points", "-n", type=int, metavar="N",
                     help="points of the rule (default: k Gauss points for cG and the VIs, otherwise k + 1)")
    run.add_argument("--step-size", type=_positive(float), metavar="H", help="step size h (default: the scene's)")
    run.add_argument("--save-every", type=_positive(int), metavar="N", default=1,
                     help="save every N-th state (default 1)")
    run.add_argument("--out", **out)
    run.add_argument("--format", choices=("npz", "csv"), default="npz", help="trajectory file format (default npz)")
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
    spec = specs.parse_spec(options.method)
    pick = lambda option, default: default if option is None else option
    rule = None if options.rule is None else specs.rule_key(options.rule)
    return specs.complete(specs.MethodSpec(spec.kind, pick(options.degree, spec.degree), pick(rule, spec.rule),
                                           pick(options.points, spec.points)))


def run_command(options):
    """``galerkin-jax run``: integrate, write the trajectory and the plots, print the summary."""
    problem = specs.load_scene(options.scene or DEFAULT_SCENE)
    spec = _method_spec(options)
    if spec.kind == "lvi" and problem.L is None:
        raise CliError("LagrangianVI integrates L(q, qdot): give a scene file that defines L.")
    h, n_steps = options.step_size or problem.h, options.steps or problem.n_steps
    if n_steps % options.save_every:
        raise CliError(f"--steps ({n_steps}) must be a multiple of --save-every ({options.save_every}).")
    integrate = functools.partial(
        gj.integrate, problem.L if spec.kind == "lvi" else problem.H, problem.q0.astype(_dtype()),
        problem.p0.astype(_dtype()), method=specs.build(spec), n_steps=n_steps, args=problem.args,
        save_every=options.save_every, dense=_dense(spec, n_steps, problem.q0.size), progress=options.progress,
        krylov=options.krylov)
    solution, compile_s, run_s = timed(lambda h: integrate(h=h), np.asarray(h, _dtype()))
    energy, invariants = _observe(problem, solution)
    files = _write_run(problem, spec, solution, energy, invariants, h, n_steps, options)
    print(run_summary(problem, spec, solution, energy, invariants, h, (compile_s, run_s), files))
    status = int(solution.status)
    if status:
        raise CliError(f"the solve failed (status {status}): {gj.status_message(status)} "
                       f"Try a smaller --step-size than {h:g}.", code=EXIT_FAILED_SOLVE)
    return 0


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


def _write_run(problem, spec, solution, energy, invariants, h, n_steps, options):
    """The trajectory (NPZ or CSV) and the two plots of a run; returns their paths."""
    os.makedirs(options.out, exist_ok=True)
    stem = os.path.join(options.out, f"{problem.name}_{specs.tag(spec)}")
    status = int(solution.status)
    columns = dict(t=solution.t, q=solution.q, p=solution.p, energy=energy,
                   **{f"invariant_{name}": value for name, value in invariants.items()})
    meta = dict(scene=problem.description, method=specs.describe(spec), h=h, n_steps=n_steps,
                save_every=options.save_every, status=status, status_message=gj.status_message(status))
    path = f"{stem}.{options.format}"
    files = [output.write_trajectory(path, {k: np.asarray(v) for k, v in columns.items()}, meta)]
    title = f"{problem.name}, {specs.short(spec)}, h = {h:g}"
    return files + output.plot_run(stem, solution, problem.H, problem.args, problem.invariants, title)


def _hint(spec):
    gauss = spec.kind == "cg" and spec.rule == "gauss" and spec.points == spec.degree
    return HINTS["cg_gauss" if gauss else spec.kind]


def run_summary(problem, spec, solution, energy, invariants, h, times, files):
    """The summary of a run, for a reader who has not read the papers; returns the text."""
    t, status = np.asarray(solution.t), int(solution.status)
    n_steps, d = round(float(t[-1]) / h), problem.q0.size
    lines = [
        ("scene", f"{problem.name}: {problem.description} (d = {d} degrees of freedom)"),
        ("method", specs.describe(spec)),
        ("steps", f"{n_steps} elements of h = {h:g}, t = 0 .. {t[-1]:g}; {len(t)} states saved"),
        ("status", f"{status} ({gj.Status(status).name}): {gj.status_message(status)}"),
    ]
    failed = ~np.isfinite(energy)
    end = int(np.argmax(failed)) if failed.any() else len(t)
    if end < len(t):
        lines.append(("", f"the run failed between t = {t[end - 1]:g} and t = {t[end]:g}; the later states are NaN"))
    measure = "max |H(t) - H(0)| / |H(0)|" if energy[0] != 0 else "max |H(t) - H(0)|"
    change = lambda values: np.max(output.relative_change(values[:end], values[0]))
    lines.append(("energy", f"{measure} = {change(energy):.2e}   (H(0) = {energy[0]:.6g})"))
    lines += [(name, f"max relative change {change(v):.2e}   (conserved by the exact flow)")
              for name, v in invariants.items()]
    if status == 0:
        lines += _accuracy_lines(problem, solution)
    total, largest = int(solution.stats["num_newton_iterations"]), int(solution.stats["max_newton_iterations"])
    lines.append(("Newton", f"{total} iterations, {total / max(n_steps, 1):.2f} per element, "
                            f"at most {largest} in one element"))
    compile_s, run_s = times
    lines.append(("time", f"compile {compile_s:.2f} s, run {run_s:.3f} s ({1e6 * run_s / max(n_steps, 1):.1f} us per "
                          f"element), {np.dtype(energy.dtype).name} on {jax.devices()[0].platform}"))
    lines += [("files" if i == 0 else "", f"{path} ({output.size_text(path)})") for i, path in enumerate(files)]
    text = "\n".join(f"{key:<9}{value}" for key, value in lines)
    energy_png = next(f for f in files if f.endswith("_energy.png"))
    return text if status else text + f"\nLook at {energy_png}: {_hint(spec)}."


def _accuracy_lines(problem, solution):
    """The error against the exact solution (where the scene has one) and the error estimate."""
    lines, t_end = [], float(solution.t[-1])
    if problem.exact is not None:
        q, p = problem.exact(t_end)
        error = max(np.max(np.abs(np.asarray(solution.q[-1]) - q)), np.max(np.abs(np.asarray(solution.p[-1]) - p)))
        lines.append(("accuracy", f"error against the exact solution at t = {t_end:g}: {error:.2e} (max-norm)"))
    estimate = float(solution.error_estimate)
    size = max(np.max(np.abs(np.asarray(solution.q))), np.max(np.abs(np.asarray(solution.p))))
    verdict = "; the steps are too large to mean much" if estimate >= 0.1 * size else ""
    lines.append(("estimate", f"largest estimated local error of one element: {estimate:.2e} (max-norm; "
                              f"{estimate / size:.1e} of the largest |q_i|, |p_i|{verdict})"))
    return lines


def sweep_command(options):
    """``galerkin-jax sweep``: methods x step sizes (x initial states) batched, one ``gj.sweep``
    per kind and degree; writes a markdown and a CSV table and two plots, prints the table."""
    problem = specs.load_scene(options.scene or DEFAULT_SCENE)
    method_specs = specs.parse_specs(options.methods)
    hs = options.step_sizes or [problem.h * f for f in (2.0, 1.0, 0.5, 0.25)]
    n_steps = options.steps or problem.n_steps
    states = [((s * problem.q0).astype(_dtype()), problem.p0.astype(_dtype())) for s in options.q0_scale]
    rows, times = [], np.zeros(2)
    groups = sweeps.groups(method_specs)
    for group in groups:
        result, *seconds = timed(*sweeps.sweep_call(problem, group, hs, states, options.q0_scale, n_steps, _dtype(),
                                                    options.progress, options.krylov))
        times += seconds
        rows += sweeps.rows(group, hs, options.q0_scale, result, n_steps)
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
    return 0


def reproduce_command(options):
    """``galerkin-jax reproduce``: Table 5.1 and the papers' figures, via ``galerkin_jax.reproduce``."""
    from . import reproduce

    result = reproduce.reproduce(options.out, quick=options.quick)
    print(f"Table 5.1 of [GBS]: is H (and |L|) conserved (C), decreasing (D) or neither (NC)?\n\n{result['table51'].text()}")
    paths = sorted(result["files"].values())
    print("files    " + "\n         ".join(f"{p} ({output.size_text(p)})" for p in paths))
    return 0
