"""What the command line tool says about a run: the summary of ``galerkin-jax run``, its
verdict on the energy error (read from the run's numbers), and the message of a failed solve.
"""

import re

import jax
import numpy as np

import galerkin_jax as gj

from . import _cli_output as output
from . import _cli_specs as specs
from ._solver_options import SolverOptions

DENSE_LIMIT = SolverOptions().dense_limit  # unknowns per element above which Newton needs --krylov

ROUND_OFF = 1e3  # in eps: a relative energy change below it is round-off, over thousands of steps
LARGE = 1e-2  # a relative energy error above it: the steps do not resolve the motion
DRIFT = 2.0  # the last quarter's largest energy error over the first quarter's above which it drifts
# (a bounded oscillation gives about 1, growth like t gives 4)
MIN_SAVES_FOR_TREND = 9  # saved states (two in each quarter) needed to compare the quarters
TOO_LARGE = 0.1  # local error estimate over the initial state's size above which a step means little

# What each method does to the energy, and which verdicts of ``energy_verdict`` agree with it
HINTS = {
    "cg": ("cG(k) conserves H to round-off when its rule integrates the DH terms exactly (polynomial H, enough "
           "points) [GBS, Thm. 3.1]; otherwise expect a small error, bounded or slowly drifting",
           {"round-off", "bounded", "drift"}),
    "cg_gauss": ("cG(k) with k Gauss points is Gauss collocation, a symplectic method: "
                 "the energy error oscillates and does not drift", {"round-off", "bounded"}),
    "dg": ("dG(k) is dissipative [GBS, Prop. 3.1]: the energy error grows as the scheme damps", {"drift"}),
    "vi": ("a variational integrator is symplectic: the energy error oscillates and does not drift",
           {"round-off", "bounded"}),
    "mm": ("energy and angular momentum are conserved to round-off for H = |p|^2/2m + V(|q|) (central forces)",
           {"round-off"}),
    "dgrad": ("the energy is conserved to round-off", {"round-off"}),
}
HINTS["lvi"] = HINTS["vi"]
HINTS["tao"] = ("Tao's map reads the mean of two copies of phase space: not symplectic, symmetric to high order; "
               "expect a small energy error that drifts slowly (its compositions: far more slowly)",
               {"round-off", "bounded", "drift"})
HINTS["split"] = ("a splitting method is symplectic: the energy error oscillates and does not drift",
                  {"round-off", "bounded"})
# the symplectic methods, as their hints name them: what a step rule does to that structure
SYMPLECTIC = {"cg_gauss": "cG(k) with k Gauss points is Gauss collocation, a symplectic method",
              "vi": "a variational integrator is symplectic", "lvi": "a variational integrator is symplectic"}
UNDER_CONTROL = {
    "pid": (" with fixed steps; steps chosen from the state by error-per-step control break that structure, so "
            "the energy error can drift over long runs (--time-transform varies the steps and keeps it)",
            {"round-off", "bounded", "drift"}),
    "time-transform": (", and the time transformation keeps it symplectic (a constant step in the fictive time tau "
                       "on the extended phase space): the energy error oscillates and does not drift",
                       {"round-off", "bounded"}),
}
TIME_TRANSFORMED_DGRAD = ("the time transformation hands the method K = s (H + p_t), which it conserves as far as its "
                          "line integral of DK is exact; the energy error is K / s", {"round-off", "bounded"})


def _hint(spec, controller=None):
    """``(words, verdicts that agree)`` for the method of ``spec`` under ``controller`` (None:
    fixed steps, "pid" or "time-transform"). A composition's is its method's: a composition of
    symplectic (energy-conserving) steps is symplectic (energy-conserving)."""
    if spec.kind == "comp":
        return _hint(spec.inner, controller)
    gauss = spec.kind == "cg" and spec.rule == "gauss" and spec.points == spec.degree
    key = "cg_gauss" if gauss else spec.kind
    if controller in UNDER_CONTROL and key in SYMPLECTIC:
        tail, agrees = UNDER_CONTROL[controller]
        return SYMPLECTIC[key] + tail, agrees
    if controller == "time-transform" and key == "dgrad":
        return TIME_TRANSFORMED_DGRAD
    return HINTS[key]


def energy_verdict(change, eps):
    """What the energy error of a run did: ``(verdict, words)``, ``words`` completing "the
    energy error ...".

    The verdict is "round-off" (every change below ``ROUND_OFF`` eps), "drift" (the largest
    error in the last quarter of the saved states exceeds ``DRIFT`` times that in the first
    quarter), "bounded" (it does not), or "short" (too few saved states to compare).

    Args:
        change: the relative (or, where H(0) = 0, absolute) energy change at each saved state,
            shape ``(m,)``, finite, ``change[0] = 0``.
        eps: the machine epsilon of the run's dtype.
    """
    change = np.asarray(change, dtype=float)
    largest = float(np.max(change))
    if largest <= ROUND_OFF * eps:
        return "round-off", f"stays at round-off (largest change {largest:.1e})"
    if len(change) < MIN_SAVES_FOR_TREND:
        return "short", f"reaches {largest:.1e} (too few saved states to tell a drift)"
    quarter = (len(change) - 1) // 4
    first, last = float(np.max(change[1 : quarter + 1])), float(np.max(change[-quarter:]))
    if last > DRIFT * max(first, ROUND_OFF * eps):
        return "drift", f"grows from {first:.1e} in the first quarter of the run to {last:.1e} in the last: it drifts"
    return "bounded", f"is {first:.1e} at most in the first quarter of the run and {last:.1e} in the last: no drift"


def remedy(controller, h, tol):
    """What to change where the steps are too coarse: a smaller --step-size (the step in tau
    under the time transformation) or, under error-per-step control, a smaller --tol."""
    if controller == "pid":
        return f"the tolerance is too loose for this scene: try a smaller --tol than {tol:g}"
    where = " (the step in the fictive time tau)" if controller == "time-transform" else ""
    return f"the steps are too large for this scene: try a smaller --step-size than {h:g}{where}"


def closing_line(png, spec, change, eps, relative, h, controller=None, tol=None):
    """The summary's last line: what the energy error did, whether the method promised it
    (under the run's step rule: ``controller`` None, "pid" or "time-transform"), and, where
    the error is large, that the steps are too coarse."""
    verdict, words = energy_verdict(change, eps)
    largest = float(np.max(change))
    if largest >= LARGE:
        size = f"{100 * largest:.3g} % of |H(0)|" if relative else f"{largest:.2e}"
        fix = remedy(controller, h, tol)
        return f"Look at {png}: the energy error is large, up to {size}, and {words}. {fix[0].upper()}{fix[1:]}."
    hint, agrees = _hint(spec, controller)
    if verdict in agrees:
        return f"Look at {png}: the energy error {words}. As expected: {hint}."
    return f"Look at {png}: the energy error {words}. Not what the method usually does: {hint}."


def unknowns(method, q0, p0):
    """The unknowns of one element of ``method`` for states like ``q0``, ``p0``."""
    guess = jax.eval_shape(method.initial_guess, q0, p0)
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(guess))


# the command's own words for statuses whose library message names Python arguments
COMMAND_WORDS = {
    gj.Status.MAX_STEPS: "The run reached --max-steps (accepted and rejected steps together) before its end time.",
    gj.Status.TIME_TRANSFORM: (
        "The time transformation's step density s(q, p) was not positive and finite at a state of the run: the "
        "command's s, the default (|F(z0)| / |F(z)|)^(3/4) with F Hamilton's field (at most 3 where F vanishes), "
        "fails where F overflows, at a collision."
    ),
}


def failure_words(status, n_unknowns, krylov):
    """``gj.status_message(status)`` in the command's terms (``COMMAND_WORDS``), less its advice
    on Newton-Krylov where that cannot help (at most ``DENSE_LIMIT`` unknowns per element, or
    --krylov given)."""
    message = COMMAND_WORDS.get(int(status)) or gj.status_message(status)
    sentences = re.split(r"(?<=\.)\s+", message)
    applies = n_unknowns > DENSE_LIMIT and not krylov
    return " ".join(s.replace("krylov=True", "--krylov") for s in sentences if applies or "krylov" not in s.lower())


def what_to_try(status, n_unknowns, krylov, h, controller=None, tol=None, max_steps=None):
    """The last sentence of a failed run's message: which option to change, for the run's
    step rule (``controller`` None, "pid" or "time-transform")."""
    more = " or --krylov" if n_unknowns > DENSE_LIMIT and not krylov else ""
    status = int(status)
    if status == gj.Status.TIME_TRANSFORM:
        return "Try --tol or fixed steps (--t-end alone): the command's time transformation has only the default s."
    if status == gj.Status.MAX_STEPS:
        other = f"a looser --tol than {tol:g}" if controller == "pid" else f"a larger --step-size than {h:g}"
        return f"Try a larger --max-steps than {max_steps} or {other}."
    if controller == "pid":
        if status == gj.Status.DTMIN:
            return f"Try a looser --tol than {tol:g}, or fixed steps."
        return f"Try a smaller --tol than {tol:g}{more}."
    where = " (the step in tau)" if controller == "time-transform" else ""
    return f"Try a smaller --step-size than {h:g}{where}{more}."


def failure_message(status, n_unknowns, krylov, h, controller=None, tol=None, max_steps=None):
    """One line for a failed run: the status, its message, and what to try."""
    name = gj.Status(status).name
    return (f"the solve failed (status {status}, {name}): {failure_words(status, n_unknowns, krylov)} "
            f"{what_to_try(status, n_unknowns, krylov, h, controller, tol, max_steps)}")


def state_words(problem):
    """E.g. ``d = 2 degrees of freedom`` or ``3 bodies in 2-D, d = 6 degrees of freedom``."""
    shape = tuple(problem.shape) or problem.q0.shape
    if len(shape) == 2:
        return f"{shape[0]} bodies in {shape[1]}-D, d = {problem.d} degrees of freedom"
    return f"d = {problem.d} degrees of freedom"


def run_summary(problem, spec, solution, energy, invariants, h, n_steps, times, files, n_unknowns, krylov,
                controller=None, tol=None):
    """The summary of a run, for a reader who has not read the papers; returns the text.
    ``n_unknowns`` (per element) and ``krylov`` (given) decide whether a failure's message
    mentions --krylov (``failure_words``); ``controller`` (None: fixed steps, "pid" with its
    ``tol``, or "time-transform") how the closing line judges the energy error."""
    t, status = np.asarray(solution.t), int(solution.status)
    lines = [
        ("scene", f"{problem.name}: {problem.description} ({state_words(problem)})"),
        ("method", specs.describe(spec)),
        ("steps", f"{n_steps} steps of h = {h:g}, t = 0 .. {t[-1]:g}; {len(t)} states saved"),
        ("status", f"{status} ({gj.Status(status).name}): {failure_words(status, n_unknowns, krylov)}"),
    ]
    failed = ~np.isfinite(energy)
    end = int(np.argmax(failed)) if failed.any() else len(t)
    if end < len(t):
        lines.append(("", f"the run failed between t = {t[end - 1]:g} and t = {t[end]:g}; the later states are NaN"))
    relative = energy[0] != 0
    measure = "max |H(t) - H(0)| / |H(0)|" if relative else "max |H(t) - H(0)|"
    change = output.relative_change(energy[:end], energy[0])
    lines.append(("energy", f"{measure} = {np.max(change):.2e}   (H(0) = {energy[0]:.6g})"))
    lines += [(name, f"max relative change {np.max(output.relative_change(v[:end], v[0])):.2e}   "
                     "(conserved by the exact flow)") for name, v in invariants.items()]
    if status == 0:
        lines += accuracy_lines(problem, solution, n_steps)
    total, largest = int(solution.stats["num_newton_iterations"]), int(solution.stats["max_newton_iterations"])
    lines.append(("Newton", f"{total} iterations, {total / max(n_steps, 1):.2f} per step, at most {largest} in one step"))
    compile_s, run_s = times
    lines.append(("time", f"compile {compile_s:.2f} s, run {run_s:.3f} s ({1e6 * run_s / max(n_steps, 1):.1f} us per "
                          f"step), {np.dtype(energy.dtype).name} on {jax.devices()[0].platform}"))
    lines += [("files" if i == 0 else "", f"{path} ({output.size_text(path)})") for i, path in enumerate(files)]
    text = "\n".join(f"{key:<9}{value}" for key, value in lines)
    if status:
        return text
    energy_png = next(f for f in files if f.endswith("_energy.png"))
    eps = float(np.finfo(energy.dtype).eps)
    return text + "\n" + closing_line(energy_png, spec, change, eps, relative, h, controller, tol)


def accuracy_lines(problem, solution, n_steps):
    """The global error (against the exact solution, where the scene has one) and the local
    error estimate, told apart: one step's error, against the error accumulated at the end."""
    lines, t_end = [], float(solution.t[-1])
    if problem.exact is not None:
        q, p = problem.exact(t_end)
        error = max(np.max(np.abs(np.asarray(solution.q[-1]) - q)), np.max(np.abs(np.asarray(solution.p[-1]) - p)))
        lines.append(("global", f"error at t = {t_end:g} against the exact solution: {error:.2e} (max-norm over q, p), "
                                f"accumulated over the {n_steps} steps"))
    else:
        lines.append(("global", f"error at t = {t_end:g}: unknown (the scene has no exact solution); it accumulates "
                                f"over the {n_steps} steps: compare with a run at h / 2 to measure it"))
    estimate = float(solution.error_estimate)
    size = float(np.max(np.abs(np.concatenate([problem.q0, problem.p0]))))
    size = size if size > 0 else 1.0
    verdict = "; the steps are too large to mean much" if estimate >= TOO_LARGE * size else ""
    lines.append(("local", f"estimated error of one step, the largest of the run: {estimate:.2e} (max-norm; "
                           f"{estimate / size:.1e} of the initial state's largest |q_i|, |p_i|{verdict})"))
    return lines


def step_range(solution):
    """``(smallest, largest)`` step in t of a run whose saved states are its steps' ends (one
    state more than steps), else None (states between the steps: the steps are not known)."""
    t = np.asarray(solution.t)
    if len(t) != int(solution.stats["num_accepted_steps"]) + 1 or len(t) < 2:
        return None
    steps = np.diff(t)
    return float(np.min(steps)), float(np.max(steps))


def with_step_rule(text, solution, rule, controller=None):
    """The summary of a run to an end time, with a line on how its steps were chosen: the
    accepted and rejected steps and the smallest and largest h (under the time transformation
    h in tau, and the steps in t where the saved states are the steps' ends)."""
    stats = solution.stats
    line = (f"{'control':<9}{rule}: {int(stats['num_accepted_steps'])} steps, {int(stats['num_rejected_steps'])} rejected, "
            f"h from {float(stats['min_step']):.3g} to {float(stats['max_step']):.3g}")
    span = step_range(solution)
    if controller == "time-transform" and span is not None:
        line += f"; steps in t from {span[0]:.3g} to {span[1]:.3g}"
    lines = text.split("\n")
    at = next((i for i, l in enumerate(lines) if l.startswith("steps")), 0)
    t = np.asarray(solution.t)
    saved = f"{len(t)} states saved" + ("" if len(t) == int(stats["num_accepted_steps"]) + 1 else
                                        " (between the steps, from the element polynomials)")
    steps = f"{'steps':<9}{int(stats['num_accepted_steps'])} steps, t = {t[0]:g} .. {t[-1]:g}; {saved}"
    return "\n".join(lines[:at] + [steps, line] + lines[at + 1:])
