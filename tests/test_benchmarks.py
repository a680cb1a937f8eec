"""The benchmarks' one entry point, ``python -m benchmarks`` (benchmarks/__main__.py), and the
record each result file carries (``_common.machine``)."""

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).parent.parent


def _run(*argv):
    return subprocess.run([sys.executable, "-m", "benchmarks", *argv], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)


def test_the_entry_point_lists_every_benchmark_and_refuses_an_unknown_name():
    listed = _run()
    assert listed.returncode == 0
    names = {line.split()[0] for line in listed.stdout.splitlines()[2:] if line.strip()}
    assert names == {p.stem[len("bench_"):] for p in (ROOT / "benchmarks").glob("bench_*.py")}
    unknown = _run("no_such_benchmark")
    assert unknown.returncode == 2
    assert "no benchmark named 'no_such_benchmark'" in unknown.stderr


def test_a_result_records_the_command_the_commit_and_the_date():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import _common
    finally:
        sys.path.pop(0)
    record = _common.machine()
    assert set(record) >= {"command", "commit", "date", "processor", "jax", "load_average"}
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    if head:  # a git checkout (CI's fresh clone is one)
        assert record["commit"].rstrip("+") == head
    assert record["date"].endswith("UTC") and record["date"][:2] == "20"
