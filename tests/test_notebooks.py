"""Every notebook in notebooks/ runs, prints the numbers it is about, and its committed
outputs are what the code prints now.

The notebooks run in a fresh kernel from the notebooks folder. With ``GALERKIN_JAX_QUICK=1``
(fewer steps, degrees and Adam iterations; see each notebook's first cell) each check reads
one printed number of a notebook's last cells and compares it with what was measured at the
quick size. The committed notebooks carry the outputs of the full size.

Stale outputs: ``KEY_FIGURES`` lists, per notebook, the statuses and the figures its text
teaches from. The quick run must print the committed value of every figure that does not
depend on the size (``quick=True``). At the committed size every key figure is compared with
the committed output: a change of the code that changes what a notebook says fails CI until
the notebook is re-executed (and its text read again).

Executing the notebooks takes minutes (a kernel and its compilations per notebook), so the
suite reads their committed outputs only; ``GALERKIN_JAX_NOTEBOOKS=quick`` executes them at the
quick size, ``=committed`` at the committed size, ``=quick,committed`` both (a line of
``.ci/run``).
"""

import dataclasses
import math
import os
import pathlib
import re
from typing import Optional

import pytest

from conftest import user_xla_flags

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = pathlib.Path(__file__).parents[1] / "notebooks"
EXECUTE = set(os.environ.get("GALERKIN_JAX_NOTEBOOKS", "").split(","))
MAX_BYTES = 300_000  # committed with outputs: PNGs at dpi 80, so a notebook stays small


def number(pattern, text):
    """The float captured by ``pattern`` (one group) in ``text``."""
    match = re.search(pattern, text)
    assert match, f"the notebook did not print {pattern!r}"
    return float(match.group(1))


def check_quickstart(text):
    # measured 7.09 over h = 0.2 .. 0.025 (2k + 1 = 7 for cG(3)); the pre-asymptotic h = 0.2
    # lifts it a little. 0.3 separates order 7 from 6 (the nodal order) and 8.
    assert number(r"error_estimate falls like h\^([\d.]+)", text) == pytest.approx(7, abs=0.3)
    # measured 0.963 .. 1.000: the estimate follows the true local error to a few percent
    assert number(r"estimate / true local error: ([\d.]+)", text) > 0.9
    assert number(r"estimate / true local error: [\d.]+ \.\. ([\d.]+)", text) < 1.1


def check_gbs(text):
    assert number(r"Table 5.1: (\d+) of \d+ filled boxes disagree", text) == 0
    # measured 6.7e-16 (round-off of A = dz1/dz0, entries <= 2.2); the printed sign of eq. (57)
    # moves the diagonal by 2 beta1 beta2 Omega^2 / (1 + beta2^2 Omega^2) >= 5e-3 at Omega = 0.1
    assert number(r"from the corrected form ([\d.e+-]+)", text) < 1e-13
    assert number(r"from the printed form ([\d.e+-]+)", text) > 1e-3
    # measured 5.6e-16: H_n+1 / H_n = rho^2 of eq. (69) is exact up to round-off per step
    assert number(r"equal eq. \(69\) to ([\d.e+-]+)", text) < 1e-12


def check_tang(text):
    # measured 2.00 and 4.00 (quick: s = 1, 2), as tests/test_variational.py: 0.1 tells 2s from 2s +- 1
    line = text.split("orders of GalerkinVI(s):")[1].splitlines()[0]
    orders = {int(s): float(order) for s, order in re.findall(r"GalerkinVI\((\d)\) ([\d.]+)", line)}
    assert orders and all(order == pytest.approx(2 * s, abs=0.1) for s, order in orders.items()), orders
    # measured 5.6e-17: the corrected kernel of eq. (2.35) is GalerkinVI; the printed one misses by 3e-2
    assert number(r"reproduces GalerkinVI's step to ([\d.e+-]+)", text) < 1e-13
    assert number(r"the printed one misses by ([\d.e+-]+)", text) > 1e-3


def check_speed(text):
    # measured 3.95 from n = 200, 400 steps per Kepler period (e = 0.6): nodal order 2k = 4
    assert number(r"cG\(2\), Gauss 2 +order ([\d.]+)", text) == pytest.approx(4, abs=0.2)


def check_tuning(text):
    # measured 27.0 after the 10 quick Adam steps (29 after 60): the first steps do most of it
    assert number(r"Kepler: loss reduced by ([\d.]+)x", text) > 10
    # through a time-transformed run (save times read between the nodes at the nodes' accuracy):
    # measured 3800 after 30 steps, 231 after the quick 5
    assert number(r"time-transformed Kepler: loss reduced by ([\d.]+)x", text) > 100


def check_adaptive(text):
    # measured 1.03: the time transformation's energy error does not drift over 20 orbits, PID
    # control's does (3.04); the events lie on the section q1 = 0 to round-off (2.4e-16)
    assert number(r"TimeTransform +max\|dH\| .* ratio +([\d.]+)", text) < 1.2
    assert number(r"PID +max\|dH\| .* ratio +([\d.]+)", text) > 1.5
    assert number(r"max \|q1\| at the events: ([\d.e+-]+)", text) < 1e-12


def check_learning(text):
    # measured (committed; quick) 3.5e-9; 4.9e-9: the learned energy under cG(2) + Gauss 2 is a
    # bounded O(h^4) oscillation (halving h divides it by 16), the same in the last quarter of the
    # rollout as in the first (1.0; 1.04); dG(1)'s drifts linearly (last / first quarter 3.85 of
    # the 4 a straight line gives) and is 7e4 .. 1.2e5 times larger
    cg, dg = (rf"{name}, Gauss 2: final loss ([\d.e+-]+); max \|H_theta - H_theta\(0\)\| ([\d.e+-]+), "
              rf"last / first quarter ([\d.]+)" for name in (r"cG\(2\)", r"dG\(1\)"))
    assert float(re.search(cg, text).group(2)) < 1e-7
    assert float(re.search(cg, text).group(3)) < 1.2
    assert float(re.search(dg, text).group(3)) > 3
    assert number(r"learned energy drift dG\(1\) / cG\(2\): ([\d.e+-]+)", text) > 1e4
    # measured 1.9e-4 after 1500 Adam steps, 1.6e-3 after the quick 150, from 0.48 .. 0.30
    assert float(re.search(cg, text).group(1)) < 3e-3


CHECKS = {
    "01_quickstart.ipynb": check_quickstart,
    "02_gbs_galerkin_methods.ipynb": check_gbs,
    "03_tang_variational_integrators.ipynb": check_tang,
    "04_speed_and_accuracy.ipynb": check_speed,
    "05_tuning.ipynb": check_tuning,
    "06_adaptive.ipynb": check_adaptive,
    "07_learning_hamiltonian.ipynb": check_learning,
}


@dataclasses.dataclass(frozen=True)
class Figure:
    """A status or number a notebook prints and its text relies on.

    Attributes:
        pattern: a regular expression (multi-line) with one group: a word, an integer or a float
            (``nan`` included).
        rel: numbers: the relative tolerance between two runs (other machines, XLA versions).
        below: a round-off figure: both values below it (its digits are noise); None: compare.
        quick: the quick run prints the same value (the figure does not depend on the size).
    """

    pattern: str
    rel: float = 0.0
    below: Optional[float] = None
    quick: bool = False


FLOAT = r"([-+]?(?:\d+\.?\d*(?:e[-+]?\d+)?|nan))"
KEY_FIGURES = {
    "01_quickstart.ipynb": [
        Figure(r"^status (\d+) \w+ - ", quick=True),
        Figure(r"^h = 0\.3: status (\d+)", quick=True),
        Figure(r"^h = 1\.0: status (\d+)", quick=True),  # the element with no root the text teaches from
        # the run's largest estimate: taken where the embedded estimate peaks, so it depends on the run's length
        Figure(rf"^h = 0\.3: .*error_estimate {FLOAT},", rel=0.05),
        Figure(rf"^h = 1\.0: .*error_estimate {FLOAT},", rel=0.05, quick=True),
        Figure(rf"^h = 0\.3: .*max \|q - q_exact\| = {FLOAT}", rel=0.1),
        Figure(rf"error_estimate falls like h\^{FLOAT}", rel=0.01, quick=True),
        Figure(rf"estimate / true local error: {FLOAT}", rel=0.01),
        Figure(rf"pilot: est\(0.1\) = {FLOAT}", rel=0.02, quick=True),
        Figure(r"that run: status (\d+)", quick=True),
        Figure(rf"max \|q - q_exact\|: nodes {FLOAT}", rel=0.05, quick=True),
        Figure(rf"chord at mid-element {FLOAT}", rel=0.05, quick=True),
        Figure(rf"angular momentum change with Gauss 3: {FLOAT}", below=1e-13, quick=True),
        Figure(r"^status +(\d+) \(\w+\): "),  # the command line's summary
        Figure(rf"^energy +max \|H\(t\) - H\(0\)\| / \|H\(0\)\| = {FLOAT}", rel=0.05),
        Figure(rf"^global +error at t = 10 against the exact solution: {FLOAT}", rel=0.05),
    ],
    "02_gbs_galerkin_methods.ipynb": [
        Figure(r"^(\d+) runs:", quick=True),
        Figure(r"boxes that disagree with the paper: (\d+)", quick=True),
        Figure(r"Table 5.1: (\d+) of \d+ filled boxes disagree", quick=True),
        Figure(rf"from the printed form {FLOAT}", rel=0.01, quick=True),
        Figure(rf"from the corrected form {FLOAT}", below=1e-13, quick=True),
        Figure(rf"equal eq. \(69\) to {FLOAT}", below=1e-12, quick=True),
        Figure(rf"1 - rho\^2 = {FLOAT} by eq\. \(65\)", rel=0.01, quick=True),
    ],
    "03_tang_variational_integrators.ipynb": [
        Figure(rf"^s = 2: one step \|L - G\| slope {FLOAT}", rel=0.01, quick=True),
        Figure(rf"^s = 3: one step \|L - G\| slope {FLOAT}", rel=0.01),
        Figure(rf"orders of GalerkinVI\(s\):.*GalerkinVI\(2\) {FLOAT}", rel=0.01, quick=True),
        Figure(rf"orders of GalerkinVI\(s\):.*GalerkinVI\(4\) {FLOAT}", rel=0.01),
        Figure(rf"symplecticity defect:.*GalerkinVI\(2\), Gauss 3 {FLOAT}", below=1e-13),
        Figure(rf"symplecticity defect:.*dG\(1\), Gauss 2 {FLOAT}", rel=0.05),
        Figure(rf"variable mass, global slopes: s = 2: {FLOAT}", rel=0.01, quick=True),
        Figure(rf"variable mass, global slopes:.*s = 3: {FLOAT}", rel=0.01),
        Figure(rf"reproduces GalerkinVI's step to {FLOAT}", below=1e-13, quick=True),
        Figure(rf"the printed one misses by {FLOAT}", rel=0.05, quick=True),
    ],
    "04_speed_and_accuracy.ipynb": [  # the benchmark's figures, read from its result file, and the live orders
        Figure(rf"cheapest galerkin_jax run / cheapest peer run: {FLOAT}x", rel=0.01, quick=True),
        Figure(rf"cheapest peer run: [\d.]+x \.\. {FLOAT}x", rel=0.01, quick=True),
        Figure(rf"^kepler +1e-12 .* {FLOAT}$", rel=0.01, quick=True),
        Figure(rf"^quartic +1e-6 .* {FLOAT}$", rel=0.01, quick=True),
        Figure(rf"energy error of cG\(3\) {FLOAT}", rel=0.01, quick=True),
        Figure(rf"cost per step of cG\(3\)\+Gauss 3: {FLOAT}x diffrax Tsit5", rel=0.01, quick=True),
        Figure(rf"cost per step of cG\(3\)\+Gauss 3: .* {FLOAT}x a hand-written Gauss RK", rel=0.01, quick=True),
        Figure(rf"cost per step of cG\(3\)\+Gauss 3: .* {FLOAT}x diffrax Dopri8", rel=0.01, quick=True),
        Figure(rf"^cG\(2\), Gauss 2 +order {FLOAT}", rel=0.02),
        Figure(rf"^cG\(4\), Gauss 4 +order {FLOAT}", rel=0.02),
    ],
    "05_tuning.ipynb": [
        Figure(rf"Kepler: loss reduced by {FLOAT}x", rel=0.05),
        Figure(rf"dG\(1\) rho: loss reduced by {FLOAT}x", rel=0.05),
        Figure(rf"rho at Omega = 0.1, 100: \[{FLOAT} ", rel=0.01),
        Figure(rf"rho at Omega = 0.1, 100: \[[\d.]+ {FLOAT}\]", rel=0.05),
        Figure(rf"time-transformed Kepler: loss reduced by {FLOAT}x", rel=0.05),
    ],
    "06_adaptive.ipynb": [  # one size: the quick run is the committed one
        Figure(r"^PID +status (\d+)", quick=True),
        Figure(r"^TimeTransform +status (\d+)", quick=True),
        Figure(r"^steps: PID (\d+)", rel=0.02, quick=True),
        Figure(r"^steps: .*TimeTransform (\d+)", rel=0.02, quick=True),
        Figure(rf"^last / first quarter: PID {FLOAT}", rel=0.1, quick=True),
        Figure(rf"^last / first quarter: .*TimeTransform {FLOAT}", rel=0.05, quick=True),
        Figure(rf"max \|q1\| at the events: {FLOAT}", below=1e-12, quick=True),
    ],
    "07_learning_hamiltonian.ipynb": [
        Figure(r"^cG\(2\), Gauss 2: status (\d+)", quick=True),
        Figure(r"^dG\(1\), Gauss 2: status (\d+)", quick=True),
        Figure(rf"^cG\(2\), Gauss 2: final loss {FLOAT}", rel=0.1),
        Figure(rf"^dG\(1\), Gauss 2: final loss {FLOAT}", rel=0.1),
        Figure(rf"^cG\(2\), Gauss 2: final loss .* max \|H_theta - H_theta\(0\)\| {FLOAT}", rel=0.1),
        Figure(rf"^dG\(1\), Gauss 2: final loss .* max \|H_theta - H_theta\(0\)\| {FLOAT}", rel=0.1),
        Figure(rf"^dG\(1\), Gauss 2: final loss .* last / first quarter {FLOAT}", rel=0.05),
    ],
}


def figure_value(figure, text):
    """The value of ``figure`` in a notebook's printed ``text`` (a float, or the word)."""
    match = re.search(figure.pattern, text, flags=re.MULTILINE)
    assert match, f"the notebook did not print {figure.pattern!r}"
    value = next(g for g in match.groups() if g is not None)
    try:
        return float(value)
    except ValueError:
        return value


def agree(figure, committed, fresh):
    if isinstance(committed, str) or isinstance(fresh, str):
        return committed == fresh
    if math.isnan(committed) or math.isnan(fresh):
        return math.isnan(committed) and math.isnan(fresh)
    if figure.below is not None:
        return committed < figure.below and fresh < figure.below
    return abs(committed - fresh) <= figure.rel * max(abs(committed), abs(fresh))


def stale_figures(name, committed_text, fresh_text, quick):
    """The key figures of notebook ``name`` on which the committed outputs and a fresh run
    disagree: lines ``pattern: committed -> fresh``."""
    figures = [f for f in KEY_FIGURES[name] if f.quick or not quick]
    pairs = [(f, figure_value(f, committed_text), figure_value(f, fresh_text)) for f in figures]
    return [f"{f.pattern}: committed {a!r}, now {b!r}" for f, a, b in pairs if not agree(f, a, b)]


def printed(notebook):
    """All text a notebook's code cells wrote to stdout, in order."""
    return "".join(o.get("text", "") for cell in notebook.cells if cell.cell_type == "code"
                   for o in cell.get("outputs", []) if o.get("output_type") == "stream")


def executed(name, monkeypatch, quick):
    """The committed and the fresh printed text of notebook ``name``, run in a fresh kernel from
    the notebooks folder at the quick or the committed size (a cell may take 300 s or 900 s).
    Raises CellExecutionError, with the cell and its traceback, on any error. The kernel is killed
    at the end, not asked to stop: a graceful shutdown can wait on the kernel with no time limit."""
    if quick:
        monkeypatch.setenv("GALERKIN_JAX_QUICK", "1")  # the kernel inherits the environment
    else:
        monkeypatch.delenv("GALERKIN_JAX_QUICK", raising=False)
    monkeypatch.setenv("XLA_FLAGS", user_xla_flags())  # compiled as a user's: conftest.COMPILE_FLAGS
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    committed = printed(notebook)
    nbclient.NotebookClient(notebook, timeout=300 if quick else 900, kernel_name="python3",
                            shutdown_kernel="immediate", resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()
    return committed, printed(notebook)


def assert_not_stale(name, committed, fresh, quick):
    stale = stale_figures(name, committed, fresh, quick)
    assert not stale, f"{name}: the committed outputs are stale; re-execute the notebook:\n" + "\n".join(stale)


def test_every_notebook_has_a_check():
    assert sorted(p.name for p in NOTEBOOKS.glob("*.ipynb")) == sorted(CHECKS) == sorted(KEY_FIGURES)


@pytest.mark.parametrize("name", sorted(KEY_FIGURES))
def test_committed_outputs_print_every_key_figure(name):
    text = printed(nbformat.read(NOTEBOOKS / name, as_version=4))
    assert all(figure_value(f, text) is not None for f in KEY_FIGURES[name])


def test_a_stale_status_or_number_is_caught():
    """The committed output of 01 once showed h = 1.0 converging with an estimate of 4.7e3."""
    committed = "h = 1.0: status 0 (SUCCESS), error_estimate 4.7e+03, max |q - q_exact| = 7.7e+03\n"
    now = "h = 1.0: status 1 (NEWTON_MAX_ITERATIONS), error_estimate nan, max |q - q_exact| = nan\n"
    status, estimate = KEY_FIGURES["01_quickstart.ipynb"][2:5:2]
    assert figure_value(status, committed) == 0.0 and not agree(status, 0.0, figure_value(status, now))
    assert not agree(estimate, figure_value(estimate, committed), figure_value(estimate, now))
    assert agree(estimate, 1.3e-3, 1.33e-3) and not agree(estimate, 1.3e-3, 1.4e-3)  # rel = 0.05
    round_off = Figure("x", below=1e-13)
    assert agree(round_off, 4.4e-16, 6.7e-16) and not agree(round_off, 4.4e-16, 2e-13)


@pytest.mark.parametrize("name", sorted(CHECKS))
def test_committed_notebook_is_executed_and_small(name):
    path = NOTEBOOKS / name
    notebook = nbformat.read(path, as_version=4)
    assert path.stat().st_size < MAX_BYTES
    assert notebook.cells[0].cell_type == "markdown" and notebook.cells[0].source.startswith("# ")
    first_code = next(cell for cell in notebook.cells if cell.cell_type == "code").source
    assert 'jax.config.update("jax_enable_x64", True)' in first_code and "GALERKIN_JAX_QUICK" in first_code
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert all(cell.execution_count is not None for cell in code), "commit the notebook executed"
    assert not any(o.get("output_type") == "error" for cell in code for o in cell.get("outputs", []))


@pytest.mark.skipif("quick" not in EXECUTE,
                    reason="executes every notebook at the quick size: set GALERKIN_JAX_NOTEBOOKS=quick (.ci/run does)")
@pytest.mark.parametrize("name", sorted(CHECKS))
def test_notebook_runs_at_quick_size(name, monkeypatch):
    committed, fresh = executed(name, monkeypatch, quick=True)
    CHECKS[name](fresh)
    assert_not_stale(name, committed, fresh, quick=True)


@pytest.mark.skipif("committed" not in EXECUTE,
                    reason="executes every notebook at its committed size (minutes): set GALERKIN_JAX_NOTEBOOKS=committed")
@pytest.mark.parametrize("name", sorted(KEY_FIGURES))
def test_committed_outputs_are_what_the_code_prints(name, monkeypatch):
    assert_not_stale(name, *executed(name, monkeypatch, quick=False), quick=False)
