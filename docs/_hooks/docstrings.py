"""MkDocs hook: fail the build when a public name has no docstring or no entry in docs/api.md, or
the versions disagree.

The API reference is generated from the docstrings (mkdocstrings), so a name in
``galerkin_jax.__all__`` without one would be listed with nothing to say; docs/api.md groups
the names by hand, so a new name needs its line there. The package is read
statically (griffe, which mkdocstrings-python already uses): nothing is imported, so the
check needs neither JAX nor a compiled program. ``galerkin_jax.__version__`` is a constant
that must equal the version in ``pyproject.toml``, which the changelog names.
"""

import ast
import pathlib
import re
import tomllib

import griffe
from mkdocs.exceptions import PluginError

ROOT = pathlib.Path(__file__).resolve().parents[2]


def undocumented(package="galerkin_jax", root=ROOT):
    """The names in ``package.__all__`` whose object has no docstring of its own."""
    module = griffe.load(package, search_paths=[str(root)], resolve_aliases=True)
    if module.exports is None:
        raise PluginError(f"{package} defines no __all__: the API reference lists __all__.")
    missing = []
    for name in sorted(str(n) for n in module.exports):
        member = module.get_member(name)
        target = member.final_target if member.is_alias else member
        if not (target.docstring and target.docstring.value.strip()):
            missing.append(name)
    return missing


def unlisted(package="galerkin_jax", root=ROOT):
    """The names in ``package.__all__`` that docs/api.md, grouped by hand, does not list
    (``::: package.NAME``)."""
    module = griffe.load(package, search_paths=[str(root)])
    page = (root / "docs" / "api.md").read_text()
    listed = set(re.findall(rf"^::: {re.escape(package)}\.(\w+)\s*$", page, flags=re.MULTILINE))
    return sorted(str(n) for n in module.exports or () if str(n) not in listed)


def versions(root=ROOT):
    """(the version in pyproject.toml, ``galerkin_jax.__version__`` as written)."""
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]["version"]
    module = griffe.load("galerkin_jax", search_paths=[str(root)])
    attribute = module.members.get("__version__")
    return project, (ast.literal_eval(attribute.value) if attribute is not None else None)


def on_pre_build(config):
    missing = undocumented()
    if missing:
        raise PluginError("public names without a docstring (galerkin_jax.__all__): "
                          + ", ".join(missing))
    missing = unlisted()
    if missing:
        raise PluginError("public names that docs/api.md does not list: " + ", ".join(missing))
    project, package = versions()
    if project != package:
        raise PluginError(f"pyproject.toml says version {project!r}, "
                          f"galerkin_jax.__version__ is {package!r}: make them equal.")
