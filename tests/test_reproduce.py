"""``galerkin_jax.reproduce``: the files it writes, the table it returns, the [Tang] numbers."""

import numpy as np
import pytest

from galerkin_jax import reproduce

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURES = ["fig4_1", "fig4_2", "fig4_3", "fig4_4", "fig4_5", "fig4_6", "fig4_7",
           "tang_equivalence", "tang_order", "tang_symplecticity"]


@pytest.fixture(scope="module")
def result(reproduced):
    return reproduced  # once per test run, shared with test_table51.py (``conftest.reproduced``)


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
    """Cell by cell in test_table51.py; here: every box the paper fills agrees, none is left out."""
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
