"""``galerkin-jax sweep``: the batched calls and the rows of its table."""

import itertools
import math

import numpy as np

import galerkin_jax as gj

from . import _cli_specs as specs
from . import _cli_summary as summary
from ._cli_specs import CliError


FORMATS = {"h": "g", "q0 scale": "g", "Newton per step": ".2f"}


def groups(method_specs):
    """The specs grouped by kind and degree, in order of first appearance: ``gj.grid`` stacks
    methods of one kind and degree (rules of any size) into one batch."""
    grouped = {}
    for spec in method_specs:  # compositions and splittings: one per scheme (a static field)
        grouped.setdefault(spec if spec.kind in ("comp", "split") else (spec.kind, spec.degree), []).append(spec)
    return list(grouped.values())


def sweep_call(problem, group, hs, states, scales, n_steps, dtype, progress=False, krylov=False, t1=None):
    """One ``gj.sweep`` over ``group`` x ``hs`` x ``states``: ``(fn, configs, reference)``,
    ``fn(configs, reference)`` the sweep (the values are its arguments, not constants in it).

    The reference for the final error is the scene's exact solution at ``n_steps h`` (or at
    ``t1``, which every configuration reaches when given) for the unscaled initial state (NaN
    for the others). With LagrangianVI the sweep integrates L,
    so the energy is tracked as the invariant "H" and reported as the energy error.
    """
    fn, invariants = problem.H, dict(problem.invariants)
    if group[0].kind == "lvi":
        if problem.L is None:
            raise CliError("LagrangianVI integrates L(q, qdot): give a scene file that defines L.")
        H, args = problem.H, problem.args
        fn, invariants = problem.L, {"H": H if args is None else (lambda q, p: H(q, p, args)), **invariants}
    configs = gj.grid(method=[specs.build(s) for s in group], h=hs, state=states,
                      args=None if problem.args is None else [problem.args])
    reference = None
    if problem.exact is not None:
        nan = np.full(problem.q0.shape, np.nan)
        exact = [problem.exact(n_steps * h if t1 is None else t1) if scale == 1.0 else (nan, nan)
                 for _, h, scale in itertools.product(group, hs, scales)]
        reference = tuple(np.stack([np.asarray(x[i], dtype=float) for x in exact]).astype(dtype) for i in (0, 1))
    length = dict(n_steps=n_steps) if t1 is None else dict(t1=t1, max_steps=math.ceil(t1 / min(hs)) + 1)
    call = lambda configs, reference: gj.sweep(fn, configs, invariants=invariants, reference=reference,
                                               progress=progress, krylov=krylov, **length)
    return call, configs, reference


def rows(group, hs, scales, result, n_steps):
    """One dict per configuration, in ``gj.grid`` order (method, h, state): the spec, then the
    table's columns; NaN for the diagnostics of a failed configuration."""
    status = np.asarray(result.status)
    failed = status != 0
    invariants = {name: np.asarray(v, dtype=float) for name, v in result.invariant_errors.items()}
    energy = invariants.pop("H") if group[0].kind == "lvi" else np.asarray(result.energy_error, dtype=float)
    final = None if result.final_error is None else np.where(failed, np.nan, np.asarray(result.final_error, float))
    estimate = np.where(failed, np.nan, np.asarray(result.error_estimate, dtype=float))
    table = []
    for i, (spec, h, scale) in enumerate(itertools.product(group, hs, scales)):
        row = {"spec": spec, "method": specs.short(spec), "h": h, "q0 scale": scale, "status": int(status[i]),
               "energy error": float(energy[i])}
        row.update({f"{name} error": float(value[i]) for name, value in invariants.items()})
        if final is not None:
            row["final error"] = float(final[i])
        row["error estimate"] = float(estimate[i])
        steps = n_steps if result.num_accepted_steps is None else max(1, int(result.num_accepted_steps[i]))
        row["Newton per step"] = round(int(result.num_newton_iterations[i]) / steps, 2)
        row["max Newton"] = int(result.max_newton_iterations[i])
        table.append(row)
    return table


def _largest(values):
    finite = [v for v in values if not np.isnan(v)]
    return max(finite) if finite else np.nan


def per_method(table, method_specs, hs):
    """The energy error (largest over the initial states) and the final error (unscaled
    state), each shape ``(len(method_specs), len(hs))``."""
    energy = np.full((len(method_specs), len(hs)), np.nan)
    final = np.full_like(energy, np.nan)
    for i, spec in enumerate(method_specs):
        for j, h in enumerate(hs):
            mine = [row for row in table if row["spec"] == spec and row["h"] == h]
            energy[i, j] = _largest([row["energy error"] for row in mine])
            final[i, j] = _largest([row.get("final error", np.nan) for row in mine if row["q0 scale"] == 1.0])
    return energy, final


def notes(problem, table, n_steps):
    """The footnotes of the sweep table: what the columns mean, and the failures."""
    lines = [f"energy error: max over the {n_steps} steps of |H(t) - H(0)| / |H(0)|; the invariants' errors likewise.",
             f"Every configuration runs {n_steps} steps, so a larger h runs to a later time t = {n_steps} h."]
    if problem.exact is not None:
        lines.append("final error: max-norm error of (q, p) at t = n_steps h against the exact solution "
                     "(unscaled initial state only).")
    lines.append("error estimate: the largest estimated local error of one step (max-norm over q, p); the final "
                 f"error accumulates such errors over the {n_steps} steps.")
    lines.append("Newton per step: mean iterations per step; max Newton: the most in one step.")
    for status in sorted({row["status"] for row in table} - {0}):
        count = sum(row["status"] == status for row in table)
        lines.append(f"status {status}: {count} configuration(s) failed: {gj.status_message(status)}")
    return "\n".join(lines)


def failures(table, n_unknowns, krylov):
    """One line on the failed configurations (for the exit status 3), or None if none failed.

    Args:
        n_unknowns: spec -> unknowns per element, for the message's advice on --krylov.
    """
    failed = [row for row in table if row["status"] != 0]
    if not failed:
        return None
    parts = []
    for status in sorted({row["status"] for row in failed}):
        mine = [row for row in failed if row["status"] == status]
        largest = max(n_unknowns[row["spec"]] for row in mine)
        where = ", ".join(f"{row['method']} at h = {row['h']:g}" for row in mine[:3]) + (", ..." if len(mine) > 3 else "")
        parts.append(f"status {status} ({gj.Status(status).name}) in {len(mine)} ({where}): "
                     f"{summary.failure_words(status, largest, krylov)}")
    more = " or --krylov" if any(n > summary.DENSE_LIMIT for n in n_unknowns.values()) and not krylov else ""
    return (f"{len(failed)} of {len(table)} configurations failed, their diagnostics shown as '-': {'; '.join(parts)} "
            f"Try smaller --step-sizes{more}.")
