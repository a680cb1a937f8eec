"""The suite's two tiers: the slow tier's list names tests that exist, and CI's coverage check
fails where the slow tier covers what the default tier does not."""

import functools
import importlib.util
import pathlib
import subprocess
import sys

from conftest import SLOW

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _ci(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / ".ci" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def collected(*args):
    """The node ids ``python -m pytest ARGS`` would run (each set of ARGS collected once)."""
    return _collected(args)


@functools.cache
def _collected(args):
    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-n", "0", *args], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout.splitlines()
    return tuple(line for line in out if "::" in line)


def test_every_test_of_the_slow_tier_exists():
    """A renamed or removed test left in tests/slow.txt would move its successor into the
    default tier unseen: every listed node id is one the suite collects."""
    assert len(SLOW) > 300
    assert sorted(SLOW - set(collected("--tier=all"))) == []


def test_the_claims_stay_in_the_default_tier():
    """``.ci/tiers.py`` keeps the tests of its ``CLAIMS`` in the default tier: none is listed in
    tests/slow.txt, and each entry names tests the suite collects (a renamed claim would leave
    its entry naming nothing), among them every test of tests/test_claims.py."""
    tiers = _ci("tiers")
    everything = collected("--tier=all")
    assert sorted(n for n in SLOW if tiers.is_claim(n)) == []
    assert all(any(n.startswith(prefix) for n in everything) for prefix in tiers.CLAIMS)
    claims = {n for n in everything if tiers.is_claim(n)}
    assert {n for n in everything if n.startswith("tests/test_claims.py::")} < claims
    assert len(claims) >= 21  # 20 in test_claims.py, 1 in test_midpoint.py


def test_a_test_named_on_the_command_line_runs_whatever_its_tier():
    """A file runs its default tier's tests; a slow test named by its id runs (not deselected)."""
    name = "tests/test_derivatives.py::test_every_output_of_a_run_against_central_differences[pid]"
    assert name in SLOW
    ids = collected("tests/test_tangent.py", name)
    assert SLOW & set(ids) == {name} and len(ids) > 1


def _data(path, arcs_by_context):
    """A coverage data file at ``path`` holding, per context (a test, or "" outside any), arcs of
    one module of galerkin_jax."""
    from coverage import CoverageData

    data = CoverageData(str(path))
    for context, arcs in arcs_by_context.items():
        data.set_context(context)
        data.add_arcs({"/src/galerkin_jax/_solve.py": arcs})
    data.write()
    return str(path)


def test_the_coverage_check_names_an_arc_only_the_slow_tier_covers(tmp_path, capsys):
    check = _ci("check_coverage").main
    default = _data(tmp_path / "default", {"": [(-1, 3), (3, 4), (4, -1)]})
    assert check(default, _data(tmp_path / "same", {"": [(-1, 3), (3, 4)]})) == 0
    assert check(default, _data(tmp_path / "more", {"": [(-1, 3), (3, 7)]})) == 1
    assert capsys.readouterr().out.splitlines()[-2:] == [
        "/src/galerkin_jax/_solve.py: line 3 -> 7, covered by the slow tier alone",
        "1 arcs of galerkin_jax are covered by the slow tier alone: move a test that covers them out of "
        "tests/slow.txt, or make the list anew (.ci/tiers.py)"]


def test_the_tiers_are_a_cover_of_every_arc_and_keep_no_test_another_covers(tmp_path):
    """``.ci/tiers.py`` reads each test's arcs from a coverage file with per-test contexts, and its
    set cover keeps the cheap pair that covers a, b and c (Y and Z, 3 s), not the one test of 10 s
    nor the 0.1 s test whose arc Z covers too (the greedy pass takes it first; the swap drops it),
    unless they are kept (``CLAIMS``)."""
    tiers = _ci("tiers")
    path = _data(tmp_path / "per-test", {"": [(1, 2)], "tests/t.py::x|run": [(3, 4), (4, 5), (5, 6)],
                                         "tests/t.py::y|run": [(3, 4)], "tests/t.py::z|run": [(4, 5), (5, 6)],
                                         "tests/t.py::w|run": [(5, 6)]})
    cover, base = tiers.arcs_by_test(path)
    assert base == {("/src/galerkin_jax/_solve.py", 1, 2)} and sorted(cover) == [f"tests/t.py::{n}" for n in "wxyz"]
    cost = {f"tests/t.py::{n}": c for n, c in zip("xyzw", (10.0, 1.0, 2.0, 0.1))}
    assert tiers.default_tier(cover, base, cost) == {"tests/t.py::y", "tests/t.py::z"}
    # kept tests (the claims) stay where the cover would drop them: w, whose arc z covers too,
    # beside y and z; x (10 s, covered by y and z for 3 s), which then needs no other test
    assert tiers.default_tier(cover, base, cost, {"tests/t.py::w"}) == {"tests/t.py::w", "tests/t.py::y",
                                                                      "tests/t.py::z"}
    assert tiers.default_tier(cover, base, cost, {"tests/t.py::x"}) == {"tests/t.py::x"}
