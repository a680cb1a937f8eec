"""[GBS, Table 5.1], cell by cell: the library's measured table (``reproduce.table51``)
against the paper's cells, written out here.

C: relative change at round-off (< 1e-12) throughout; D: strictly monotone decrease; NC:
neither. The paper's NC ("nonconservation") is asserted as "no run conserves"; C* as "C with
the modified midpoint rule, not with the plain midpoint rule". Each Hooke cell is measured
at h = 1 (Figs. 4.1, 4.4) and h = 0.1 (Figs. 4.2, 4.5), 200 steps; each quartic cell
(V = c (r^2 - 1)^2 / 2) at h = 0.01, 2000 steps (Figs. 4.6, 4.7).

Measured for the boxes the paper leaves empty (arbitrary potential, symmetric N_q > 1, H):
- cG(1): C with Gauss 2, Gauss 3 and Lobatto 3 (relative change ~1e-14): DH is cubic, these
  rules integrate it exactly and Theorem 3.1 applies; NC with the trapezoid rule (1e-1).
- dG(1): NC with every multi-point rule (|dH/H| ~ 0.75, not monotone).
Also measured: dG(1)'s |L| with N_q > 1 on the quartic scene (paper: NC) decays monotonically (D).
"""

import pytest

from galerkin_jax import reproduce

# [GBS, Table 5.1] as printed; None: the box is empty.
COLUMNS = ("Hooke: exact", "Hooke: N_q = 1", "Hooke: 1 < N_q", "arbitrary V: N_q = 1", "arbitrary V: 1 < N_q")
PAPER = {
    ("cG(1)", "H"): ("C", "C", "C", "C*", None),  # Props. 4.1, 4.2 (Cor. 4.1), 4.6
    ("cG(1)", "L"): ("C", "C", "C", "C", "NC"),  # Cors. 4.3, 4.4, 4.7, 4.10
    ("dG(1)", "H"): ("D", "C", "D", "C*", None),  # Props. 4.3, 4.4 (Cor. 4.2), Cor. 4.9
    ("dG(1)", "L"): ("D", "C", "D", "C", "NC"),  # Cors. 4.5, 4.6, 4.8, 4.11
}
CELLS = [(m, q, column, paper) for (m, q), row in PAPER.items() for column, paper in zip(COLUMNS, row)]
FILLED = [cell for cell in CELLS if cell[3] is not None]


@pytest.fixture(scope="module")
def table(reproduced):
    return reproduced["table51"]  # measured once per test run (``conftest.reproduced``)


@pytest.mark.parametrize("method, quantity, column, paper", FILLED, ids=[f"{m}-{q}-{c}" for m, q, c, _ in FILLED])
def test_every_filled_cell_is_the_papers(table, method, quantity, column, paper):
    measured = table.cell(method, quantity, column).measured
    assert measured, "a cell without runs"
    if paper in ("C", "D"):
        assert set(measured.values()) == {paper}, measured
    elif paper == "NC":
        assert "C" not in measured.values(), measured
    else:  # C*: conserved only with the modified midpoint rule (Prop. 4.6, Notation 4.2)
        assert measured == {"modified midpoint": "C", "midpoint": "NC"}


def test_the_empty_cells_as_measured(table):
    """What the paper leaves open, pinned down so that a change is noticed (module docstring)."""
    cg = table.cell("cG(1)", "H", "arbitrary V: 1 < N_q").measured
    assert cg == {"gauss2": "C", "gauss3": "C", "lobatto3": "C", "trapezoid": "NC"}  # exact quadrature of a cubic DH
    assert set(table.cell("dG(1)", "H", "arbitrary V: 1 < N_q").measured.values()) == {"NC"}
    assert set(table.cell("dG(1)", "L", "arbitrary V: 1 < N_q").measured.values()) == {"D"}  # paper: NC


def test_the_library_copy_of_the_paper_and_the_rendering(table):
    """The table knows which boxes the paper fills, and the markdown marks the empty ones."""
    assert tuple(reproduce.COLUMNS) == COLUMNS
    assert reproduce.PAPER_TABLE51 == PAPER
    assert [(c.method, c.quantity, c.column, c.paper) for c in table.cells] == CELLS
    markdown = table.markdown()
    for method, quantity in PAPER:
        assert f"| {method} {quantity} |" in markdown
    assert markdown.count("*empty in the paper*") == 2
    assert "**paper" not in markdown  # no disagreement flagged
    assert table.cell("dG(1)", "L", "arbitrary V: 1 < N_q").render() == "NC (measured D)"
    assert table.cell("cG(1)", "H", "arbitrary V: N_q = 1").render() == "C*"
    assert "(empty): C (gauss2, gauss3, lobatto3), NC (trapezoid)" in table.text()
