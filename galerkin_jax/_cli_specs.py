"""What the command line tool runs: method specs such as ``cg2:gauss3`` and scenes.

A method spec is ``KIND[DEGREE][:RULE[POINTS]]``: ``cg3:gauss3`` is cG(3) with the 3-point
Gauss-Legendre rule, ``dg1:lobatto3`` dG(1) with 3 Gauss-Lobatto points, ``mm`` the modified
midpoint rule. A scene is a built-in name from ``scenes.SCENES`` or a Python file.
"""

import dataclasses
import os
import re
import runpy
from typing import Any, Callable, Optional

import numpy as np

import galerkin_jax as gj

from . import scenes


class CliError(Exception):
    """A message for the user; ``code`` is the exit status."""

    def __init__(self, message, code=1):
        super().__init__(message)
        self.code = code


@dataclasses.dataclass(frozen=True)
class Kind:
    """A family of methods: its class, its description in words with the paper's equations."""

    name: str
    words: str
    least_degree: Optional[int]  # None: no degree and no rule
    make: Callable  # (k, rule) -> method, or () -> method


KINDS = {
    "cg": Kind("cG", "continuous Galerkin, degree {k} [GBS, eq. (16)]", 1, gj.CG),
    "dg": Kind("dG", "discontinuous Galerkin, degree {k} [GBS, eq. (19)]", 0, gj.DG),
    "vi": Kind("GalerkinVI", "Galerkin variational integrator, Q of degree {k} [Tang, eqs. (2.21), (2.34)-(2.35)]",
               1, gj.GalerkinVI),
    "lvi": Kind("LagrangianVI", "Lagrangian variational integrator, degree {k} [Tang, eqs. (2.16)-(2.17)]", 1,
                gj.LagrangianVI),
    "mm": Kind("ModifiedMidpoint", "energy-momentum modified midpoint rule [GBS, eqs. (90)-(91)]", None,
               gj.ModifiedMidpoint),
    "dgrad": Kind("DiscreteGradient", "Gonzalez's midpoint discrete gradient (conserves H)", None,
                  gj.DiscreteGradient),
}
KIND_ALIASES = {"galerkinvi": "vi", "lagrangianvi": "lvi", "modifiedmidpoint": "mm", "discretegradient": "dgrad"}


@dataclasses.dataclass(frozen=True)
class Rule:
    """A family of quadrature rules on [0, 1]."""

    words: str
    least: int  # fewest points
    fixed: Optional[int]  # the number of points of a rule of one size, else None
    make: Callable  # n -> QuadratureRule


RULES = {
    "gauss": Rule("Gauss-Legendre", 1, None, gj.gauss_legendre),
    "lobatto": Rule("Gauss-Lobatto", 2, None, gj.gauss_lobatto),
    "radau": Rule("right Gauss-Radau", 1, None, gj.gauss_radau),
    "midpoint": Rule("midpoint", 1, 1, lambda n: gj.midpoint()),
    "trapezoid": Rule("trapezoid", 2, 2, lambda n: gj.trapezoid()),
}
RULE_ALIASES = {"gauss-legendre": "gauss", "legendre": "gauss", "gl": "gauss", "gauss-lobatto": "lobatto",
                "gauss-radau": "radau", "mid": "midpoint", "trap": "trapezoid"}

DEFAULT_DEGREE = 3


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A method as the user names it; ``None`` fields take their defaults in ``complete``."""

    kind: str
    degree: Optional[int] = None
    rule: Optional[str] = None
    points: Optional[int] = None


def kind_key(text):
    """The key of ``KINDS`` that ``text`` names (case-insensitive, long names accepted)."""
    key = text.strip().lower().replace("_", "")
    key = KIND_ALIASES.get(key, key)
    if key not in KINDS:
        names = ", ".join(f"{k} ({v.name})" for k, v in KINDS.items())
        raise CliError(f"unknown method {text!r}; choose one of {names}.")
    return key


def rule_key(text):
    """The key of ``RULES`` that ``text`` names (case-insensitive)."""
    key = text.strip().lower().replace("_", "-")
    key = RULE_ALIASES.get(key, key)
    if key not in RULES:
        raise CliError(f"unknown rule {text!r}; choose one of {', '.join(RULES)}.")
    return key


def parse_spec(text):
    """``"cg2:gauss3"`` -> ``MethodSpec("cg", 2, "gauss", 3)``; parts left out stay None."""
    match = re.fullmatch(r"\s*([a-z_]+?)(\d*)(?::([a-z_-]+?)(\d*))?\s*", text.lower())
    if match is None:
        raise CliError(f"cannot read the method {text!r}; write KIND[DEGREE][:RULE[POINTS]], e.g. cg2:gauss3 or mm.")
    kind, degree, rule, points = match.groups()
    return MethodSpec(kind_key(kind), int(degree) if degree else None,
                      rule_key(rule) if rule else None, int(points) if points else None)


def parse_specs(text):
    """A comma-separated list of specs, each completed with its defaults."""
    specs = [complete(parse_spec(part)) for part in text.split(",") if part.strip()]
    if not specs:
        raise CliError("--methods: give at least one method, e.g. cg2:gauss3,mm.")
    return specs


def complete(spec):
    """Fill the defaults: degree 3, the Gauss-Legendre rule with k points for cG and the
    VIs (Gauss collocation, symplectic) and k + 1 otherwise; fixed rules keep their size."""
    kind = KINDS[spec.kind]
    if kind.least_degree is None:
        if spec.degree is not None or spec.rule is not None or spec.points is not None:
            raise CliError(f"{kind.name} takes no degree and no quadrature rule.")
        return spec
    k = DEFAULT_DEGREE if spec.degree is None else spec.degree
    if k < kind.least_degree:
        raise CliError(f"{kind.name} needs a degree >= {kind.least_degree}, got {k}.")
    key = spec.rule or "gauss"
    rule = RULES[key]
    collocation = spec.kind in ("cg", "vi", "lvi") and key == "gauss"
    points = next(n for n in (spec.points, rule.fixed, k if collocation else k + 1) if n is not None)
    if points < rule.least or (rule.fixed is not None and points != rule.fixed):
        expected = f"exactly {rule.fixed}" if rule.fixed else f"at least {rule.least}"
        raise CliError(f"the {rule.words} rule has {expected} point(s), got {points}.")
    return MethodSpec(spec.kind, k, key, points)


def build(spec):
    """The method object of a completed spec."""
    kind = KINDS[spec.kind]
    if kind.least_degree is None:
        return kind.make()
    return kind.make(spec.degree, RULES[spec.rule].make(spec.points))


def label(spec):
    """Short name, e.g. ``cG(3)``."""
    name = KINDS[spec.kind].name
    return name if spec.degree is None else f"{name}({spec.degree})"


def rule_words(spec):
    """E.g. ``3-point Gauss-Legendre rule``."""
    rule = RULES[spec.rule]
    return f"{rule.words} rule" if rule.fixed else f"{spec.points}-point {rule.words} rule"


def describe(spec):
    """The method in words, e.g. ``cG(3): continuous Galerkin, degree 3 [GBS, eq. (16)], 3-point
    Gauss-Legendre rule``."""
    words = KINDS[spec.kind].words.format(k=spec.degree)
    return f"{label(spec)}: {words}" + (f", {rule_words(spec)}" if spec.rule else "")


def short(spec):
    """One table cell, e.g. ``cG(2) Gauss-Lobatto 3``."""
    if spec.rule is None:
        return label(spec)
    rule = RULES[spec.rule]
    return f"{label(spec)} {rule.words}" + ("" if rule.fixed else f" {spec.points}")


def tag(spec):
    """For file names, e.g. ``cG3-gauss3``."""
    if spec.rule is None:
        return KINDS[spec.kind].name
    points = "" if RULES[spec.rule].fixed else spec.points
    return f"{label(spec).replace('(', '').replace(')', '')}-{spec.rule}{points}"


@dataclasses.dataclass(frozen=True)
class Problem(scenes.Scene):
    """A scene as the command line tool runs it: ``scenes.Scene`` plus what a file may add.

    Attributes:
        args: passed to ``H(q, p, args)`` when not None.
        L: ``L(q, qdot)`` (or ``L(q, qdot, args)``) for LagrangianVI, else None.
    """

    args: Any = None
    L: Optional[Callable] = None


DEFAULT_FILE_H, DEFAULT_FILE_STEPS = 0.1, 1000


def load_scene(text):
    """The built-in scene called ``text`` or the scene defined in the Python file ``text``."""
    if text in scenes.SCENES:
        scene = scenes.get(text)
        return Problem(**{f.name: getattr(scene, f.name) for f in dataclasses.fields(scene)})
    if text.endswith(".py") or os.path.isfile(text):
        return _load_file(text)
    raise CliError(f"unknown scene {text!r}. The built-in scenes are {', '.join(scenes.SCENES)}; "
                   "or give the path of a Python file that defines H(q, p), q0 and p0.")


def _load_file(path):
    if not os.path.isfile(path):
        raise CliError(f"scene file {path!r} does not exist.")
    try:
        namespace = runpy.run_path(path, run_name="galerkin_jax_scene")
    except BaseException as error:  # the user's code: report it, whatever it raised
        raise CliError(f"scene file {path!r} raised {type(error).__name__}: {error}") from None
    missing = [name for name in ("H", "q0", "p0") if name not in namespace]
    if missing:
        raise CliError(f"scene file {path!r} must define H(q, p), q0 and p0; it does not define "
                       f"{', '.join(missing)}.")
    for name in ("H", "L", "exact"):
        if (name == "H" or namespace.get(name) is not None) and not callable(namespace[name]):
            raise CliError(f"scene file {path!r}: {name} must be a function.")
    invariants = namespace.get("invariants") or {}
    if not isinstance(invariants, dict) or not all(callable(f) for f in invariants.values()):
        raise CliError(f"scene file {path!r}: invariants must be a dict name -> I(q, p).")
    q0, p0 = (_vector(namespace[name], name, path) for name in ("q0", "p0"))
    try:
        h, n_steps = float(namespace.get("h", DEFAULT_FILE_H)), int(namespace.get("n_steps", DEFAULT_FILE_STEPS))
    except (TypeError, ValueError) as error:
        raise CliError(f"scene file {path!r}: h must be a number and n_steps an integer ({error}).") from None
    stem = os.path.splitext(os.path.basename(path))[0]
    return Problem(
        name=stem, description=str(namespace.get("description", f"user scene {path}")), H=namespace["H"],
        q0=q0, p0=p0, h=h, n_steps=n_steps, invariants=dict(invariants),
        exact=namespace.get("exact"), args=namespace.get("args"), L=namespace.get("L"),
    )


def _vector(value, name, path):
    """A scene file's q0 or p0: an array of numbers of any shape (``(d,)``, or ``(N, 2)``,
    ``(N, 3)`` for N bodies; H then receives states of that shape)."""
    try:
        x = np.atleast_1d(np.asarray(value, dtype=float))
    except (TypeError, ValueError) as error:
        raise CliError(f"scene file {path!r}: {name} must be an array of numbers ({error}).") from None
    if x.size == 0:
        raise CliError(f"scene file {path!r}: {name} must have at least one element, got shape {x.shape}.")
    return x
