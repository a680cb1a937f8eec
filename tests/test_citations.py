"""Every script, test, file and anchor that the documentation names exists.

The README, CONTRIBUTING.md, benchmarks/README.md, the pages of docs/ and the docstrings of the
package, the benchmarks and the tests name files (`benchmarks/bench_peers.py`,
`tests/test_sweep.py`, `results/peers.md`), tests (`tests/test_sweep.py::test_name`, or a bare
`test_name`), benchmark commands (`python -m benchmarks peers --only fput`) and sections of
pages (`docs/solver.md#newton`, or docs/solver.md, "Newton"). A removed script or a renamed
test must not stay cited: each citation is checked here, a test name by parsing the test files
for its ``def``. (Links between the pages of docs/ are checked by the strict site build as
well.) This file's own examples are not read.
"""

import ast
import pathlib
import re
import unicodedata

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

PATH = re.compile(r"(?<![\w/.:@-])((?:benchmarks|tests|notebooks|galerkin_jax|docs|notes|\.ci|results)"
                  r"/[\w./-]*\w\.(?:py|md|ipynb|json|png|txt|toml|yml))(?:::(test_\w+))?")
BARE_FILE = re.compile(r"(?<![\w/.:-])((?:bench|test)_\w+\.py)(?:::(test_\w+))?")
BARE_TEST = re.compile(r"`(test_\w+)`")
COMMAND = re.compile(r"python -m benchmarks ([a-z_]+)((?: +(?:--[\w-]+|[a-z_0-9.]+))*)")
SECTION = re.compile(r"((?:docs|notes)/[\w-]+\.md),? \"([^\"]+)\"")
LINK = re.compile(r"\]\((?!https?:|mailto:)([^)\s#]*)(?:#([^)\s]+))?\)")
PLACEHOLDER = re.compile(r"NAME|COMMIT|WHAT|<")


def sources(root):
    """(where, text) for each document that cites: Markdown files and the package's docstrings."""
    found = []
    for name in ["README.md", "CONTRIBUTING.md", "benchmarks/README.md", *sorted(
            str(p.relative_to(root)) for p in (root / "docs").glob("*.md"))]:
        if (root / name).exists():
            found.append((name, (root / name).read_text()))
    for path in sorted([*(root / "galerkin_jax").glob("*.py"), *(root / "benchmarks").glob("*.py"),
                        *(root / "tests").glob("*.py")]):
        if path.name == "test_citations.py":
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                doc = ast.get_docstring(node)
                if doc:
                    found.append((f"{path.relative_to(root)}:{getattr(node, 'lineno', 1)}", doc))
    return found


def defined_tests(root):
    """Every ``def test_...`` of tests/, by file."""
    names = {}
    for path in (root / "tests").glob("test_*.py"):
        tree = ast.parse(path.read_text())
        names[path.name] = {node.name for node in ast.walk(tree)
                            if isinstance(node, ast.FunctionDef) and node.name.startswith("test_")}
    return names


def slug(heading):
    """A heading's anchor as mkdocs (Python-Markdown's toc) writes it."""
    text = re.sub(r"`|\*\*|\[|\]\([^)]*\)", "", heading)
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def headings(path):
    """The titles of a Markdown file's headings, without their code marks."""
    return [m[1].replace("`", "") for m in re.finditer(r"^#{1,6} +(.*?) *#*$", path.read_text(), re.MULTILINE)]


def anchors(path):
    return {slug(title) for title in headings(path)}


def _path(root, cited, where):
    """The file a cited path names: docs/ pages say results/ for benchmarks/results/."""
    if cited.startswith("results/"):
        return root / "benchmarks" / cited
    if where.startswith("docs/") and not (root / cited).exists():
        return root / "docs" / cited
    return root / cited


def broken_citations(root):
    """Each citation in ``root``'s documents that names nothing, as ``(where, citation)``."""
    names = defined_tests(root)
    every_test = set().union(*names.values()) if names else set()
    broken = []
    for where, text in sources(root):
        for match in PATH.finditer(text):
            cited, test = match[1], match[2]
            if PLACEHOLDER.search(cited):
                continue
            if not _path(root, cited, where).exists():
                broken.append((where, cited))
            elif test and test not in names.get(pathlib.Path(cited).name, set()):
                broken.append((where, f"{cited}::{test}"))
        for match in BARE_FILE.finditer(text):
            cited, test = match[1], match[2]
            if PLACEHOLDER.search(cited):
                continue
            folder = "benchmarks" if cited.startswith("bench_") else "tests"
            if not (root / folder / cited).exists():
                broken.append((where, cited))
            elif test and test not in names.get(cited, set()):
                broken.append((where, f"{cited}::{test}"))
        for match in BARE_TEST.finditer(text):
            if match[1] not in every_test and not (root / "tests" / f"{match[1]}.py").exists():
                broken.append((where, match[1]))
        for match in COMMAND.finditer(text):
            script = root / "benchmarks" / f"bench_{match[1]}.py"
            if not script.exists():
                broken.append((where, match[0]))
                continue
            source = script.read_text()
            for word in match[2].split():  # an option or a part's name: a string in the script
                if f'"{word}"' not in source and not re.fullmatch(r"[\d.e-]+", word):
                    broken.append((where, f"{match[0]}: {word}"))
        for match in SECTION.finditer(text):  # a page and a section's title: docs/accuracy.md, "Dense output"
            target = root / match[1]
            titles = headings(target) if target.exists() else []
            if not any(title.startswith(" ".join(match[2].split())) for title in titles):
                broken.append((where, match[0]))
        if where.endswith(".md") and not where.startswith("docs/"):
            for match in LINK.finditer(text):
                target = (root / pathlib.Path(where).parent / match[1]) if match[1] else root / where
                if not target.exists():
                    broken.append((where, match[0]))
                elif match[2] and target.suffix == ".md" and match[2] not in anchors(target):
                    broken.append((where, match[0]))
    return broken


def test_every_citation_resolves():
    assert broken_citations(ROOT) == []


def test_a_removed_script_or_test_stays_cited_no_more(tmp_path):
    """The check itself: each kind of citation is found, and reported once its target is gone."""
    (tmp_path / "benchmarks" / "results").mkdir(parents=True)
    (tmp_path / "tests").mkdir()
    (tmp_path / "docs").mkdir()
    (tmp_path / "galerkin_jax").mkdir()
    (tmp_path / "benchmarks" / "bench_peers.py").write_text('PARTS = ["kepler", "--only"]\n')
    (tmp_path / "benchmarks" / "results" / "peers.md").write_text("| table |\n")
    (tmp_path / "tests" / "test_sweep.py").write_text("def test_a_sweep():\n    pass\n")
    (tmp_path / "docs" / "guide.md").write_text("# Guide\n\n## Newton's method\n")
    (tmp_path / "galerkin_jax" / "_x.py").write_text('"""See `bench_peers.py`."""\n')
    (tmp_path / "README.md").write_text(
        "`python -m benchmarks peers --only kepler` (`results/peers.md`), "
        "`tests/test_sweep.py::test_a_sweep`, `test_a_sweep`, "
        "[Newton](docs/guide.md#newtons-method) (docs/guide.md, \"Newton's method\"), "
        "`git show abc:benchmarks/bench_gone.py`, "
        "`benchmarks/bench_NAME.py`.\n")
    assert broken_citations(tmp_path) == []

    (tmp_path / "benchmarks" / "bench_peers.py").unlink()
    (tmp_path / "tests" / "test_sweep.py").write_text("def test_renamed():\n    pass\n")
    (tmp_path / "docs" / "guide.md").write_text("# Guide\n\n## Newton\n")
    assert sorted(broken_citations(tmp_path)) == sorted([
        ("README.md", "python -m benchmarks peers --only kepler"),
        ("README.md", "tests/test_sweep.py::test_a_sweep"),
        ("README.md", "test_a_sweep"),
        ("README.md", "](docs/guide.md#newtons-method)"),
        ("README.md", 'docs/guide.md, "Newton\'s method"'),
        ("galerkin_jax/_x.py:1", "bench_peers.py"),
    ])


@pytest.mark.parametrize(("heading", "anchor"), [
    ("The error estimate", "the-error-estimate"),
    ("Per step, against `ModifiedMidpoint`", "per-step-against-modifiedmidpoint"),
    ("Poincaré against Hairer–Söderlind", "poincare-against-hairersoderlind"),
    ("Time span and (c) adaptive steps", "time-span-and-c-adaptive-steps"),
])
def test_anchors_are_written_as_the_site_writes_them(heading, anchor):
    assert slug(heading) == anchor
