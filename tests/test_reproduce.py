"""``galerkin_jax.reproduce``: the files it writes, the table it returns, the [Tang] numbers.

[GBS, Table 5.1], cell by cell (the tests after ``PAPER``): the library's measured table
(``reproduce.table51``) against the paper's cells, written out here.

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

import numpy as np
import pytest

from galerkin_jax import reproduce

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURES = ["fig4_1", "fig4_2", "fig4_3", "fig4_4", "fig4_5", "fig4_6", "fig4_7",
           "tang_equivalence", "tang_order", "tang_symplecticity"]


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    """``reproduce.reproduce(folder, quick=True)``, once for the module: every test of the
    table and of the figures reads it (one module, so one pytest-xdist worker computes it)."""
    return reproduce.reproduce(tmp_path_factory.mktemp("reproduce"), quick=True)


def test_writes_every_figure_and_the_table(result):
    files = result["files"]
    assert sorted(files) == sorted(FIGURES + ["table51"])
    for name in FIGURES:
        with open(files[name], "rb") as f:
            data = f.read()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000, name  # a drawn figure, not an empty canvas
    with open(files["table51"]) as f:
        markdown = f.read()
    for row in ("cG(1) H", "cG(1) L", "dG(1) H", "dG(1) L"):
        assert f"| {row} |" in markdown
    assert markdown.count("*empty in the paper*") == 2


def test_the_returned_table_agrees_with_every_filled_cell_of_the_paper(result):
    """Cell by cell below; here: every box the paper fills agrees, none is left out."""
    table = result["table51"]
    filled = [cell for cell in table.cells if cell.paper is not None]
    assert len(table.cells) == 20 and len(filled) == 18
    assert all(reproduce.agrees(cell.paper, cell.measured) for cell in filled), table.text()


def test_tang_numbers(result):
    numbers = result["numbers"]
    # Kepler e = 0.5, reproduce.ORDER_STEPS; quick: s = 1, 2. Measured slopes 2.000, 3.999
    # (and 5.999, 7.983 for s = 3, 4 in the full run): in the asymptotic range, so 0.1 is ample
    assert list(numbers["tang_order"]) == ["GalerkinVI(1)", "GalerkinVI(2)"]
    for s in (1, 2):
        assert numbers["tang_order"][f"GalerkinVI({s})"] == pytest.approx(2 * s, abs=0.1)
    defects = numbers["tang_symplecticity"]  # largest over h = 0.01 .. 0.32
    assert sorted(defects) == ["GalerkinVI(2), Gauss 3", "GalerkinVI(2), Lobatto 3", "dG(1), Gauss 2"]
    # round-off (Corollary 2.1): measured 1.3e-15 and 5.8e-16
    assert max(defects["GalerkinVI(2), Gauss 3"], defects["GalerkinVI(2), Lobatto 3"]) < 1e-13
    assert defects["dG(1), Gauss 2"] > 0.1  # not symplectic: measured 0.29 at h = 0.32
    # quick: s = 2, 100 steps; the same scheme, so round-off (measured 6e-16; 1e-14 after 1000 steps)
    assert list(numbers["tang_equivalence"]) == ["s = 2"]
    assert numbers["tang_equivalence"]["s = 2"] < 1e-13


def test_classify():
    assert reproduce.classify([1.0, 1.0 + 1e-14, 1.0 - 1e-14]) == "C"
    assert reproduce.classify([1.0, 0.9, 0.8]) == "D"
    assert reproduce.classify([1.0, 0.9, 0.9]) == "NC"  # not strictly decreasing
    assert reproduce.classify([1.0, 1.0 + 1e-11]) == "NC"  # above the 1e-12 tolerance
    assert reproduce.classify(np.array([2.0, 2.0])) == "C"
    with pytest.raises(ValueError, match="values"):
        reproduce.classify([1.0])
    with pytest.raises(ValueError, match="values"):
        reproduce.classify([[1.0, 1.0]])


def test_summarize_and_agrees():
    assert reproduce.summarize({"modified midpoint": "C", "midpoint": "NC"}) == "C*"
    assert reproduce.summarize({"a": "C", "b": "NC", "c": "C"}) == "C (a, c), NC (b)"
    assert reproduce.agrees("NC", {"a": "D", "b": "NC"})
    assert not reproduce.agrees("NC", {"a": "D", "b": "C"})
    assert not reproduce.agrees("C", {"a": "C", "b": "D"})


def test_bad_arguments(tmp_path):
    not_a_folder = tmp_path / "file.txt"
    not_a_folder.write_text("")
    with pytest.raises(ValueError, match="folder"):
        reproduce.reproduce(not_a_folder, quick=True)
    with pytest.raises(TypeError, match="quick"):
        reproduce.reproduce(tmp_path, quick="yes")
    with pytest.raises(TypeError, match="folder"):
        reproduce.reproduce(3.5, quick=True)


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
def table(result):
    return result["table51"]


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
