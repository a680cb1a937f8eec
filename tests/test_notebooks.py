"""Every notebook in notebooks/ runs, at the quick size, and prints the number it is about.

The notebooks run in a fresh kernel with ``GALERKIN_JAX_QUICK=1`` (fewer steps, degrees and
Adam iterations; see each notebook's first cell), from the notebooks folder. Each check
reads one printed number of a notebook's last cells and compares it with what was measured
at the quick size. The committed notebooks carry the outputs of the full size.
"""

import pathlib
import re

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = pathlib.Path(__file__).parents[1] / "notebooks"
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


CHECKS = {
    "01_quickstart.ipynb": check_quickstart,
    "02_gbs_galerkin_methods.ipynb": check_gbs,
    "03_tang_variational_integrators.ipynb": check_tang,
    "04_speed_and_accuracy.ipynb": check_speed,
    "05_tuning.ipynb": check_tuning,
}


def printed(notebook):
    """All text a notebook's code cells wrote to stdout, in order."""
    return "".join(o.get("text", "") for cell in notebook.cells if cell.cell_type == "code"
                   for o in cell.get("outputs", []) if o.get("output_type") == "stream")


def test_every_notebook_has_a_check():
    assert sorted(p.name for p in NOTEBOOKS.glob("*.ipynb")) == sorted(CHECKS)


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


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CHECKS))
def test_notebook_runs_at_quick_size(name, monkeypatch):
    monkeypatch.setenv("GALERKIN_JAX_QUICK", "1")  # the kernel inherits the environment
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()  # raises CellExecutionError, with the cell and its traceback, on any error
    CHECKS[name](printed(notebook))
