"""Griffe extension for the API reference (docs/api.md): what a static reading misses.

* The constructors of ``@pytree_dataclass`` classes. Griffe builds the ``__init__`` of a class
  decorated with ``dataclasses.dataclass`` from its annotated fields, so the reference shows
  its signature and the defaults of its parameters; ``galerkin_jax.pytree_dataclass`` applies
  that decorator at run time, which a static reader does not see: without this PIDController,
  Event, Solution and the methods had no signature, and every parameter of theirs was listed
  as required. Fields come from the class body (``name: type``, ``name: type = default`` or
  ``= dataclasses.field(...)``), after those of its dataclass bases; a base
  ``degree_and_rule("k", ...)`` (``_method``) gives the fields ``(k: int, quadrature:
  QuadratureRule)``.
* Sections of a Google-style docstring. Griffe reads ``Returns:`` or ``Raises:`` as a section
  only after a blank line; the docstrings here start them on the line after the ``Args:``
  block, so a blank line is put before each section title.

Nothing is imported.
"""

import ast
import re

import griffe

DECORATOR = "galerkin_jax._pytree.pytree_dataclass"
DEGREE_AND_RULE = "galerkin_jax._method.degree_and_rule"
SECTION = re.compile(r"(Args|Arguments|Parameters|Returns|Raises|Attributes|Yields|Warns|Examples?|Notes?)\s*:\s*")


def _spaced_sections(text):
    """``text`` with a blank line before each section title (at the docstring's margin)."""
    lines = text.split("\n")
    spaced = lines[:1]
    for line in lines[1:]:
        if SECTION.fullmatch(line) and spaced[-1].strip():
            spaced.append("")
        spaced.append(line)
    return "\n".join(spaced)


def _decorators(cls):
    return {d.value.canonical_path if isinstance(d.value, griffe.Expr) else str(d.value) for d in cls.decorators}


def _is_dataclass(cls):
    return bool(_decorators(cls) & {DECORATOR, "dataclasses.dataclass"})


def _field_default(cls, value):
    """The default of a field whose class-body value is ``value`` (None: required); a module
    constant (``LINE_POINTS``) is shown by its value."""
    if isinstance(value, griffe.ExprCall) and value.canonical_path == "dataclasses.field":
        named = {a.name: a.value for a in value.arguments if isinstance(a, griffe.ExprKeyword)}
        value = named.get("default")
    if isinstance(value, griffe.ExprName):
        try:
            constant = cls.modules_collection.get_member(value.canonical_path)
        except (KeyError, ValueError):
            return value
        if constant.is_attribute and isinstance(constant.value, str):
            return constant.value
    return value


def _own_fields(cls):
    fields = []
    for member in cls.members.values():
        # a field has an annotation (not ClassVar, which griffe labels a class attribute only)
        if member.is_alias or not member.is_attribute or member.annotation is None \
                or "instance-attribute" not in member.labels:
            continue
        fields.append(griffe.Parameter(member.name, annotation=member.annotation,
                                       kind=griffe.ParameterKind.positional_or_keyword,
                                       default=_field_default(cls, member.value), docstring=member.docstring))
    return fields


def _fields(cls):
    fields = []
    for base in cls.bases:
        if isinstance(base, griffe.ExprCall) and base.canonical_path == DEGREE_AND_RULE:
            degree = ast.literal_eval(str(base.arguments[0]))
            fields += [griffe.Parameter(degree, annotation="int"),
                       griffe.Parameter("quadrature", annotation="QuadratureRule")]
            continue
        try:
            resolved = cls.modules_collection.get_member(base if isinstance(base, str) else base.canonical_path)
        except (AttributeError, KeyError, ValueError):
            continue
        if resolved.is_class and _is_dataclass(resolved):
            fields += _fields(resolved)
    if _is_dataclass(cls):
        fields += _own_fields(cls)
    return list({f.name: f for f in fields}.values())  # a redefined field keeps its place


def _walk(obj, seen):
    if obj.path in seen:
        return
    seen.add(obj.path)
    if obj.docstring is not None:
        obj.docstring.value = _spaced_sections(obj.docstring.value)
    for member in obj.members.values():
        if member.is_alias:
            continue
        if member.is_class and DECORATOR in _decorators(member) and "__init__" not in member.members:
            self_ = griffe.Parameter("self", kind=griffe.ParameterKind.positional_or_keyword)
            member.set_member("__init__", griffe.Function(
                "__init__", lineno=0, endlineno=0, parent=member,
                parameters=griffe.Parameters(self_, *_fields(member)), returns="None"))
            member.labels.add("dataclass")
        _walk(member, seen)


class ApiReference(griffe.Extension):
    """The constructors of ``@pytree_dataclass`` classes; a blank line before each section."""

    def on_package(self, *, pkg, **kwargs):
        _walk(pkg, set())
