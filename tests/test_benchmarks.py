"""The benchmarks' one entry point, ``python -m benchmarks`` (benchmarks/__main__.py), the record
each result file carries (``_common.machine``), each guard's entry point, and one guard run for
real at a tiny size."""

import json
import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).parent.parent
GUARDS = {"adaptive", "compile", "gradients", "moderate", "peers", "stress"}


def _run(*argv, env=None, timeout=120):
    return subprocess.run([sys.executable, "-m", "benchmarks", *argv], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_the_entry_point_lists_every_benchmark_and_refuses_an_unknown_name():
    listed = _run()
    assert listed.returncode == 0
    names = {line.split()[0] for line in listed.stdout.splitlines()[2:] if line.strip()}
    assert names == {p.stem[len("bench_"):] for p in (ROOT / "benchmarks").glob("bench_*.py")} == GUARDS
    unknown = _run("no_such_benchmark")
    assert unknown.returncode == 2
    assert "no benchmark named 'no_such_benchmark'" in unknown.stderr


def test_every_guard_imports_and_parses_its_options_from_the_entry_point():
    """``main([NAME, "--help"])`` for each guard in one process: its imports (the harness, the
    peers, the library) and its argument parser run; argparse exits 0 after the usage."""
    code = ("import contextlib, io, sys\nfrom benchmarks.__main__ import main\nfor name in sys.argv[1:]:\n"
            "    out = io.StringIO()\n    try:\n        with contextlib.redirect_stdout(out):\n"
            "            main([name, '--help'])\n    except SystemExit as e:\n"
            "        print(name, e.code, out.getvalue().split()[1])\n")
    done = subprocess.run([sys.executable, "-c", code, *sorted(GUARDS)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [line.split() for line in done.stdout.splitlines()]
    assert rows == [[name, "0", f"bench_{name}.py"] for name in sorted(GUARDS)]


def test_a_result_records_the_command_the_commit_and_the_date():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import _common
    finally:
        sys.path.pop(0)
    record = _common.machine()
    assert set(record) >= {"command", "commit", "date", "processor", "jax", "versions", "load_average"}
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    if head:  # a git checkout (CI's fresh clone is one)
        assert record["commit"].rstrip("+") == head
    assert record["date"].endswith("UTC") and record["date"][:2] == "20"


def test_a_guard_runs_and_writes_its_record_and_table(tmp_path):
    """``peers --quick --only explicit`` (1000 steps): explicit Stormer-Verlet through
    ``gj.integrate`` and the hand-written leapfrog are the same map, so their end states agree
    to round-off (measured 1.6e-13 and 2.8e-13 on FPUT N = 64 and LJ13); the JSON carries the
    record, the markdown the command."""
    env = dict(os.environ, BENCHMARKS_RESULTS=str(tmp_path), PYTHONPATH=str(ROOT))
    done = _run("peers", "--quick", "--only", "explicit", "--name", "smoke", env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads((tmp_path / "smoke.json").read_text())
    assert result["machine"]["command"].endswith("--quick --only explicit --name smoke")
    assert result["versions"]["diffrax"] and result["quick"]
    for scene in ("LJ13", "FPUT N = 64"):
        row = result["explicit"][scene]
        assert row["n_steps"] == 1000 and row["max_difference"] < 1e-11
        assert row["galerkin_jax_us_per_step"] > 0 and row["leapfrog_us_per_step"] > 0
    table = (tmp_path / "smoke.md").read_text()
    assert table.startswith("`python ") and "| FPUT N = 64, 1,000 Stormer-Verlet steps: µs per step |" in table
