"""What the command line tool runs: method specs such as ``cg2:gauss3`` and scenes.

A method spec is ``KIND[DEGREE][:RULE[POINTS]]``: ``cg3:gauss3`` is cG(3) with the 3-point
Gauss-Legendre rule, ``dg1:lobatto3`` dG(1) with 3 Gauss-Lobatto points, ``mm`` the modified
midpoint rule, ``verlet`` Stormer-Verlet (``vi1:trapezoid``); ``SCHEME@SPEC`` the composition
``SCHEME`` of the method ``SPEC`` (``kahan_li6@verlet``), ``split:SCHEME`` a splitting for
separable H (``split:blanes_moan_rkn6``). A scene is a built-in name from ``scenes.SCENES`` or
a Python file.
"""

import dataclasses
import difflib
import os
import re
import runpy
from typing import Any, Callable, Optional

import numpy as np

import galerkin_jax as gj

from . import _checks, scenes
from ._composition import ALIASES, SCHEMES as COMPOSITIONS
from ._splitting import SCHEMES as SPLITTINGS

EXIT_BAD_INPUT, EXIT_BAD_OPTION = 1, 2


class CliError(Exception):
    """A message for the user; ``code`` is the exit status (1 bad input, 2 bad option, 3 a
    failed solve)."""

    def __init__(self, message, code=EXIT_BAD_INPUT):
        super().__init__(message)
        self.code = code


def _suggest(text, choices):
    close = difflib.get_close_matches(text, choices, n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


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
    "tao": Kind("Tao", "Tao's extended phase space map, explicit for any H [Tao 2016]", None, gj.Tao),
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

    kind: str  # a key of KINDS, or "comp" (a composition) or "split" (a splitting)
    degree: Optional[int] = None
    rule: Optional[str] = None
    points: Optional[int] = None
    scheme: Optional[str] = None  # of a composition or a splitting
    inner: Optional["MethodSpec"] = None  # the method a composition composes


def _scheme(text, schemes, what, aliases=None):
    key = text.strip().lower()
    key = (aliases or {}).get(key, key)
    if key not in schemes:
        raise CliError(f"unknown {what} scheme {text!r}{_suggest(key, list(schemes))}; choose one of "
                       f"{', '.join(schemes)}.", EXIT_BAD_OPTION)
    return key


def kind_key(text):
    """The key of ``KINDS`` that ``text`` names (case-insensitive, long names accepted)."""
    key = text.strip().lower().replace("_", "")
    key = KIND_ALIASES.get(key, key)
    if key not in KINDS:
        names = ", ".join(f"{k} ({v.name})" for k, v in KINDS.items())
        raise CliError(f"unknown method {text!r}{_suggest(key, list(KINDS))}; choose one of {names}.", EXIT_BAD_OPTION)
    return key


def rule_key(text):
    """The key of ``RULES`` that ``text`` names (case-insensitive)."""
    key = text.strip().lower().replace("_", "-")
    key = RULE_ALIASES.get(key, key)
    if key not in RULES:
        raise CliError(f"unknown rule {text!r}{_suggest(key, list(RULES))}; choose one of {', '.join(RULES)}.",
                       EXIT_BAD_OPTION)
    return key


def parse_spec(text):
    """``"cg2:gauss3"`` -> ``MethodSpec("cg", 2, "gauss", 3)``; parts left out stay None.
    ``"SCHEME@SPEC"``: the composition (its SPEC completed); ``"split[:SCHEME]"``: a splitting
    (default blanes_moan4); ``"verlet"``: ``vi1:trapezoid``."""
    if "@" in text:
        scheme, inner = text.split("@", 1)
        return MethodSpec("comp", scheme=_scheme(scheme, COMPOSITIONS, "composition", ALIASES), inner=complete(parse_spec(inner)))
    split = re.fullmatch(r"\s*split(?:ting)?(?::([a-z0-9_]+))?\s*", text.lower())
    if split:
        return MethodSpec("split", scheme=_scheme(split.group(1) or "blanes_moan4", SPLITTINGS, "splitting"))
    if text.strip().lower() == "verlet":
        text = "vi1:trapezoid"
    match = re.fullmatch(r"\s*([a-z_]+?)(\d*)(?::([a-z_-]+?)(\d*))?\s*", text.lower())
    if match is None:
        raise CliError(f"cannot read the method {text!r}; write KIND[DEGREE][:RULE[POINTS]], e.g. cg2:gauss3 or mm.",
                       EXIT_BAD_OPTION)
    kind, degree, rule, points = match.groups()
    return MethodSpec(kind_key(kind), int(degree) if degree else None,
                      rule_key(rule) if rule else None, int(points) if points else None)


def parse_specs(text):
    """A comma-separated list of specs, each completed with its defaults."""
    specs = [complete(parse_spec(part)) for part in text.split(",") if part.strip()]
    if not specs:
        raise CliError("--methods: give at least one method, e.g. cg2:gauss3,mm.", EXIT_BAD_OPTION)
    return specs


def complete(spec):
    """Fill the defaults: degree 3, the Gauss-Legendre rule with k points for cG and the
    VIs (Gauss collocation, symplectic) and k + 1 otherwise; fixed rules keep their size.
    A spec that names no method raises ``CliError`` with exit status 2 (a bad option)."""
    if spec.kind in ("comp", "split"):
        return spec
    kind = KINDS[spec.kind]
    if kind.least_degree is None:
        if spec.degree is not None or spec.rule is not None or spec.points is not None:
            raise CliError(f"{kind.name} takes no degree and no quadrature rule.", EXIT_BAD_OPTION)
        return spec
    k = DEFAULT_DEGREE if spec.degree is None else spec.degree
    if k < kind.least_degree:
        raise CliError(f"{kind.name} needs a degree >= {kind.least_degree}, got {k}.", EXIT_BAD_OPTION)
    key = spec.rule or "gauss"
    rule = RULES[key]
    collocation = spec.kind in ("cg", "vi", "lvi") and key == "gauss"
    points = next(n for n in (spec.points, rule.fixed, k if collocation else k + 1) if n is not None)
    if points < rule.least or (rule.fixed is not None and points != rule.fixed):
        expected = f"exactly {rule.fixed}" if rule.fixed else f"at least {rule.least}"
        raise CliError(f"the {rule.words} rule has {expected} point(s), got {points}.", EXIT_BAD_OPTION)
    return MethodSpec(spec.kind, k, key, points)


def build(spec):
    """The method object of a completed spec."""
    if spec.kind == "comp":
        return gj.Composition(build(spec.inner), spec.scheme)
    if spec.kind == "split":
        return gj.Splitting(spec.scheme)
    kind = KINDS[spec.kind]
    if kind.least_degree is None:
        return kind.make()
    return kind.make(spec.degree, RULES[spec.rule].make(spec.points))


def label(spec):
    """Short name, e.g. ``cG(3)``."""
    if spec.kind == "comp":
        return f"{spec.scheme}({short(spec.inner)})"
    if spec.kind == "split":
        return f"Splitting {spec.scheme}"
    name = KINDS[spec.kind].name
    return name if spec.degree is None else f"{name}({spec.degree})"


def rule_words(spec):
    """E.g. ``3-point Gauss-Legendre rule``."""
    rule = RULES[spec.rule]
    return f"{rule.words} rule" if rule.fixed else f"{spec.points}-point {rule.words} rule"


def describe(spec):
    """The method in words, e.g. ``cG(3): continuous Galerkin, degree 3 [GBS, eq. (16)], 3-point
    Gauss-Legendre rule``."""
    if spec.kind == "comp":
        order = COMPOSITIONS[spec.scheme][0]
        return (f"{label(spec)}: the symmetric composition {spec.scheme} (order {order} on a symmetric method of "
                f"order 2) of {describe(spec.inner)}")
    if spec.kind == "split":
        order, _, _, nystrom = SPLITTINGS[spec.scheme]
        return (f"{label(spec)}: splitting for separable H = T(p) + V(q), order {order}"
                + (" where T is quadratic in p" if nystrom else "") + " [Blanes & Moan 2002]")
    words = KINDS[spec.kind].words.format(k=spec.degree)
    return f"{label(spec)}: {words}" + (f", {rule_words(spec)}" if spec.rule else "")


def short(spec):
    """One table cell, e.g. ``cG(2) Gauss-Lobatto 3``."""
    if spec.kind in ("comp", "split"):
        return label(spec)
    if spec.rule is None:
        return label(spec)
    rule = RULES[spec.rule]
    return f"{label(spec)} {rule.words}" + ("" if rule.fixed else f" {spec.points}")


def tag(spec):
    """For file names, e.g. ``cG3-gauss3``."""
    if spec.kind == "comp":
        return f"{spec.scheme}-{tag(spec.inner)}"
    if spec.kind == "split":
        return f"split-{spec.scheme}"
    if spec.rule is None:
        return KINDS[spec.kind].name
    points = "" if RULES[spec.rule].fixed else spec.points
    return f"{label(spec).replace('(', '').replace(')', '')}-{spec.rule}{points}"


@dataclasses.dataclass(frozen=True)
class Problem(scenes.Scene):
    """A scene as the command line tool runs it: ``scenes.Scene`` plus what a file may add.

    The library sees flat states of shape ``(d,)``; a scene file's ``q0`` of another shape,
    e.g. ``(N, 3)`` for N bodies, is flattened here, and its functions receive the states in
    that shape (``_flat_functions``).

    Attributes:
        args: passed to ``H(q, p, args)`` when not None.
        L: ``L(q, qdot)`` (or ``L(q, qdot, args)``) for LagrangianVI, else None.
        shape: the shape of the scene's ``q0``, e.g. ``(N, 3)``; ``(d,)`` for a flat state.
        t1: the end time a file may set (``--t-end`` overrides it), else None.
        tol: the tolerance a file may set for error-per-step control (``--tol``), else None.
    """

    args: Any = None
    L: Optional[Callable] = None
    shape: tuple = ()
    t1: Optional[float] = None
    tol: Optional[float] = None

    @property
    def d(self):
        return self.q0.shape[0]


DEFAULT_FILE_H, DEFAULT_FILE_STEPS = 0.1, 1000


def load_scene(text):
    """The built-in scene called ``text`` or the scene defined in the Python file ``text``."""
    if text in scenes.SCENES:
        scene = scenes.get(text)
        return Problem(**{f.name: getattr(scene, f.name) for f in dataclasses.fields(scene)}, shape=scene.q0.shape)
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
    q0, p0 = (_array(namespace[name], name, path) for name in ("q0", "p0"))
    if q0.shape != p0.shape:
        raise CliError(f"scene file {path!r}: q0 and p0 must have the same shape, got {q0.shape} and {p0.shape}.")
    h, n_steps = _step_size(namespace.get("h", DEFAULT_FILE_H), path), _count(namespace.get("n_steps",
                                                                                              DEFAULT_FILE_STEPS), path)
    center = namespace.get("center")
    if center is not None:
        center = _array(center, "center", path)
        if center.shape != q0.shape[-1:]:
            raise CliError(f"scene file {path!r}: center must be a point of shape {q0.shape[-1:]}, got {center.shape}.")
    t1, tol = (_optional_positive(namespace.get(name), name, path) for name in ("t1", "tol"))
    H, L, invariants = _flat_functions(q0.shape, namespace["H"], namespace.get("L"), invariants)
    stem = os.path.splitext(os.path.basename(path))[0]
    return Problem(
        name=stem, description=str(namespace.get("description", f"user scene {path}")), H=H, q0=q0.ravel(),
        p0=p0.ravel(), h=h, n_steps=n_steps, invariants=invariants, exact=_flat_exact(namespace.get("exact"), q0.shape),
        args=namespace.get("args"), L=L, shape=q0.shape, center=None if center is None else tuple(center),
        t1=t1, tol=tol,
    )


def _array(value, name, path):
    try:
        x = np.atleast_1d(np.asarray(value, dtype=float))
    except (TypeError, ValueError) as error:
        raise CliError(f"scene file {path!r}: {name} must be an array of numbers ({error}).") from None
    if name in ("q0", "p0"):  # the library's check of the initial state: shape and finiteness
        try:
            _checks.check_state(x.ravel(), x.ravel())
        except ValueError as error:
            raise CliError(f"scene file {path!r}: {str(error).replace('q0', name, 1)}") from None
    elif not np.all(np.isfinite(x)):
        raise CliError(f"scene file {path!r}: {name} must be finite, got {x}.")
    return x


def _step_size(value, path):
    """The scene's ``h``, through the library's check (finite, > 0)."""
    try:
        _checks.check_step_size(float(value))
    except (TypeError, ValueError) as error:
        raise CliError(f"scene file {path!r}: {error}" if "h must" in str(error)
                       else f"scene file {path!r}: h must be a number, got {value!r}.") from None
    return float(value)


def _optional_positive(value, name, path):
    """A scene's optional ``t1`` or ``tol``: None, or a finite number > 0."""
    if value is None:
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise CliError(f"scene file {path!r}: {name} must be a number, got {value!r}.") from None
    if not np.isfinite(number) or number <= 0:
        raise CliError(f"scene file {path!r}: {name} must be finite and > 0, got {number}.")
    return number


def _count(value, path):
    """The scene's ``n_steps``: an integer >= 1."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise CliError(f"scene file {path!r}: n_steps must be an integer >= 1, got {value!r}.")
    return int(value)


def _flat_functions(shape, H, L, invariants):
    """``(H, L, invariants)``, the user's functions of states of ``shape``, as functions of
    flat states ``(d,)``; L None stays None."""
    if len(shape) == 1:
        return H, L, dict(invariants)
    wrap = lambda f: None if f is None else (lambda q, p, *args: f(q.reshape(shape), p.reshape(shape), *args))
    return wrap(H), wrap(L), {name: wrap(f) for name, f in invariants.items()}


def _flat_exact(exact, shape):
    """``exact(t)`` with its states flattened to ``(..., d)``."""
    if exact is None or len(shape) == 1:
        return exact

    def flat(t):
        q, p = exact(t)
        return tuple(np.reshape(x, np.shape(x)[: np.ndim(x) - len(shape)] + (-1,)) for x in (q, p))

    return flat
