"""Every fenced ``python`` block of README.md and docs/*.md runs, as a reader would run it.

Each block is one test, named by its page and line (``README.md:34``). The blocks of a page
run in page order in one namespace, so a block may use the names of an earlier one; a test
selected alone runs the blocks before it first. Fences of other languages (shell commands,
output) and indented code are not run.

Two HTML comments, invisible on the rendered page, steer a page:

* ``<!-- docs-test: skip REASON -->`` on the line before a block skips it; the reason is
  required (a slow block, one that needs a device or the network).
* ``<!-- docs-test: after PAGE -->`` anywhere on a page starts its namespace from PAGE's names
  after all of PAGE's blocks ran, where the text says the examples use another page's names.

The blocks run with JAX's default rank promotion, as a reader's session has it (conftest.py
raises on it for the library's own tests).

A small collector rather than a plugin: pytest-markdown-docs and pytest-codeblocks run each
block on its own unless every later fence is marked as a continuation, and they, like Sybil,
collect only files that pytest walks, which ``testpaths`` limits to tests/.
"""

import dataclasses
import linecache
import pathlib
import re
import textwrap
from typing import Optional

import jax
import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

FENCE = re.compile(r"^(?P<indent> {0,3})(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`]*)$")
SKIP = re.compile(r"^\s*<!--\s*docs-test:\s*skip\b\s*(?P<reason>.*?)\s*-->\s*$")
AFTER = re.compile(r"^\s*<!--\s*docs-test:\s*after\s+(?P<page>\S+)\s*-->\s*$", re.MULTILINE)


@dataclasses.dataclass(frozen=True)
class Block:
    page: str  # relative to the repository root
    line: int  # of the opening fence, counted from 1
    source: str
    skip: Optional[str]  # the reason, or None

    @property
    def id(self):
        return f"{self.page}:{self.line}"


def blocks(path):
    """The ``python`` blocks of the Markdown file ``path``, in page order."""
    lines = path.read_text().splitlines()
    found, i = [], 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        fence, indent = opening["fence"], len(opening["indent"])
        end = i + 1
        while end < len(lines) and not re.fullmatch(rf" {{0,3}}{fence[0]}{{{len(fence)},}}\s*", lines[end]):
            end += 1
        language = opening["info"].split()[0] if opening["info"].split() else ""
        if language == "python":
            body = [line[indent:] if line[:indent].isspace() else line for line in lines[i + 1 : end]]
            before = next((line for line in reversed(lines[:i]) if line.strip()), "")
            skip = SKIP.match(before)
            if skip is not None and not skip["reason"]:
                raise ValueError(f"{path}:{i + 1}: a docs-test skip needs its reason beside it")
            # the code on its own lines of the file, so that a traceback names the page's line
            source = "\n" * (i + 1) + textwrap.dedent("\n".join(body))
            page = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
            found.append(Block(str(page), i + 1, source,
                               None if skip is None else skip["reason"]))
        i = end + 1
    return found


def after(path):
    """The page whose names this page's examples use, or None."""
    match = AFTER.search(path.read_text())
    return None if match is None else path.parent / match["page"]


BLOCKS = {path: blocks(path) for path in PAGES}


def _show_python_lines(path):
    """Tracebacks quote a page's line from its Python blocks alone (in place, the rest blank):
    pytest parses the quoted file as Python to find the statement around a line."""
    lines = [""] * len(path.read_text().splitlines())
    for block in BLOCKS[path]:
        for number, line in enumerate(block.source.split("\n")):
            lines[number] = line if line else lines[number]
    linecache.cache[str(path)] = (None, None, [line + "\n" for line in lines], str(path))


for _path in PAGES:
    _show_python_lines(_path)


class PageRun:
    """A page's namespace and the outcome of each of its blocks that ran."""

    def __init__(self, path):
        self.path = path
        self.outcomes = {}  # block index -> ("pass" | "skip" | "fail", reason or exception)
        self.failed = None  # the id of the first block that failed
        first = after(path)
        if first is None:
            self.namespace = {"__name__": "__main__"}
        else:
            assert first.resolve() in BLOCKS, f"{path.name}: docs-test: after {first.name}, not a page"
            prelude = run(first.resolve(), len(BLOCKS[first.resolve()]) - 1)
            self.namespace = dict(prelude.namespace)
            self.failed = prelude.failed

    def run(self, upto):
        for index, block in enumerate(BLOCKS[self.path][: upto + 1]):
            if index in self.outcomes:
                continue
            if self.failed is not None:
                self.outcomes[index] = ("skip", f"{self.failed}, which runs before it, failed")
            elif block.skip is not None:
                self.outcomes[index] = ("skip", block.skip)
            else:
                try:
                    with jax.numpy_rank_promotion("allow"):
                        exec(compile(block.source, str(self.path), "exec"), self.namespace)
                    failed_runs(self.namespace)
                    self.outcomes[index] = ("pass", None)
                except Exception as error:  # noqa: BLE001 - reported by the block's own test
                    self.outcomes[index] = ("fail", error)
                    self.failed = block.id
        return self


def failed_runs(namespace):
    """Raise where a ``Solution`` or ``SweepResult`` of the namespace has a status other than
    SUCCESS: an example whose run fails would teach from NaNs."""
    import galerkin_jax as gj

    for name, value in namespace.items():
        if isinstance(value, (gj.Solution, gj.SweepResult)):
            status = np.asarray(value.status)
            assert np.all(status == gj.Status.SUCCESS), f"{name}.status is {status}, not SUCCESS"


RUNS = {}


def run(path, upto):
    """Run the blocks of ``path`` up to index ``upto`` (those not yet run) in its namespace."""
    if path not in RUNS:
        RUNS[path] = PageRun(path)
    return RUNS[path].run(upto)


CASES = [(path, index) for path in PAGES for index in range(len(BLOCKS[path]))]


@pytest.mark.parametrize(("path", "index"), CASES, ids=[BLOCKS[p][i].id for p, i in CASES])
def test_block_runs(path, index):
    kind, detail = run(path, index).outcomes[index]
    if kind == "skip":
        pytest.skip(detail)
    if kind == "fail":
        raise detail


def test_the_collector_finds_the_blocks_a_reader_sees(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(textwrap.dedent("""\
        Text.

        ```python
        x = 1
        ```

        ```
        not python
        ```

        <!-- docs-test: skip needs a GPU -->

        ```python
        y = x + 1
        ```

        - a list item:

          ```python
          z = 3
          ```

        ````markdown
        ```python
        inside = "a fence of another language"
        ```
        ````
        """))
    found = blocks(page)
    assert [(b.line, b.skip) for b in found] == [(3, None), (13, "needs a GPU"), (19, None)]
    assert [b.source.strip() for b in found] == ["x = 1", "y = x + 1", "z = 3"]
    assert found[1].source.count("\n") == 13  # the code stands on its own line of the page
    assert sum(len(found) for found in BLOCKS.values()) >= 10
    page.write_text("<!-- docs-test: skip -->\n```python\nx = 1\n```\n")
    with pytest.raises(ValueError, match="needs its reason"):
        blocks(page)


def test_a_page_after_another_starts_from_its_names():
    sweeps = ROOT / "docs" / "sweeps.md"
    assert after(sweeps) == ROOT / "docs" / "getting-started.md"
    names = run(sweeps, 0).namespace
    assert {"H", "q0", "p0", "method", "result"} <= set(names)
    assert "result" not in run(after(sweeps), 0).namespace  # the earlier page keeps its own names


def test_the_api_reference_lists_public_names_only():
    """docs/api.md lists names by their public path, ``galerkin_jax.NAME`` with NAME in
    ``__all__`` (Events and DenseOutput, which a Solution carries, were listed by their private
    modules); the package exports them as the objects a run returns."""
    import galerkin_jax as gj
    from galerkin_jax import _controllers, _output

    page = (ROOT / "docs" / "api.md").read_text()
    assert re.findall(r"galerkin_jax\._\w+", page) == []
    listed = re.findall(r"^::: galerkin_jax\.(\w+)\s*$", page, flags=re.MULTILINE)
    assert sorted(set(listed) - set(gj.__all__)) == []
    assert gj.Events is _controllers.Events and gj.DenseOutput is _output.DenseOutput
    assert {"Events", "DenseOutput"} <= set(gj.__all__)


def test_the_status_docstring_lists_every_code():
    """``Status``'s docstring, which the API reference renders, gives every code with its number
    (``NAME: N, meaning``), in order."""
    import galerkin_jax as gj

    section = gj.Status.__doc__.split("Attributes:")[1]
    entries = re.findall(r"^ {8}(\w+): (\d+), \S", section, flags=re.MULTILINE)
    assert [(name, int(value)) for name, value in entries] == [(s.name, s.value) for s in gj.Status]


def _anchor_check():
    """.ci/check_anchors.py, the check of the built site's links to anchors (run by .ci/run)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("check_anchors", ROOT / ".ci" / "check_anchors.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_anchor_check_finds_a_link_to_a_missing_heading(tmp_path):
    """The site check reports a link whose fragment names no element of its page, on the page
    itself or another (a notebook's table of contents linked ``#did-the-solves-converge`` where
    the heading's id was ``status-did-the-solves-converge``), and passes links out of the site."""
    check = _anchor_check()
    (tmp_path / "nb").mkdir()
    (tmp_path / "nb" / "index.html").write_text(
        '<h2 id="status-did-the-solves-converge">status</h2><h2 id="one-run">One run</h2>'
        '<a href="#did-the-solves-converge">toc</a><a href="#one-run">toc</a>'
        '<a href="../#top">home</a><a href="../#gone">home</a><a href="https://example.org/#x">out</a>')
    (tmp_path / "index.html").write_text('<a name="top"></a><a href="nb/#one-run">nb</a><a href="nb/">nb</a>')
    assert check.broken_anchors(tmp_path) == [("nb/index.html", "#did-the-solves-converge"),
                                               ("nb/index.html", "../#gone")]
    assert check.main(["check_anchors.py", str(tmp_path)]) == 1
    (tmp_path / "nb" / "index.html").write_text('<h2 id="a%20b">x</h2><a href="#a%2520b">x</a>')
    assert check.broken_anchors(tmp_path) == [("index.html", "nb/#one-run")]


def test_notebook_headings_hold_no_code():
    """mkdocs-jupyter's table of contents drops the code of a heading from its link's slug,
    while the heading's id keeps it (``## `status`: ...``: a link to ``#did-...``, the id
    ``status-did-...``), so a notebook's headings are plain text. The built site's links are
    checked by .ci/check_anchors.py; this catches the cause without a build."""
    import json

    coded = []
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        for cell in json.loads(path.read_text())["cells"]:
            if cell["cell_type"] == "markdown":
                coded += [f"{path.name}: {line}" for line in "".join(cell["source"]).splitlines()
                          if re.match(r"#{1,6} .*`", line)]
    assert coded == []
