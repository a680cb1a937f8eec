"""The benchmarks' one entry point, ``python -m benchmarks`` (benchmarks/__main__.py), the record
each result file carries (``_common.machine``), each guard's entry point, and one guard run for
real at a tiny size."""

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ROOT = pathlib.Path(__file__).parent.parent
GUARDS = {"adaptive", "compile", "gradients", "learning", "moderate", "newton", "peers", "stress"}


def _peers_installed():
    """The guards import the peers (``pip install -e ".[bench]"``); CI's test extra leaves them out."""
    for name in ("diffrax", "optimistix", "scipy"):
        pytest.importorskip(name)


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
    environment = dict(os.environ)
    try:
        import _common
    finally:
        sys.path.pop(0)
        os.environ.clear()  # _common pins BLAS to one thread for the benchmarks' processes, not for the suite's
        os.environ.update(environment)
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
    _peers_installed()
    env = dict(os.environ, BENCHMARKS_RESULTS=str(tmp_path), PYTHONPATH=str(ROOT))
    done = _run("peers", "--quick", "--only", "explicit", "--name", "smoke", env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads((tmp_path / "smoke.json").read_text())
    assert result["machine"]["command"] == "python -m benchmarks peers --quick --only explicit --name smoke"
    assert result["versions"]["diffrax"] and result["quick"]
    for scene in ("LJ13", "FPUT N = 64"):
        row = result["explicit"][scene]
        assert row["n_steps"] == 1000 and row["max_difference"] < 1e-11
        assert row["galerkin_jax_us_per_step"] > 0 and row["leapfrog_us_per_step"] > 0
    table = (tmp_path / "smoke.md").read_text()
    assert table.startswith("`python ") and "| FPUT N = 64, 1,000 Stormer-Verlet steps: µs per step |" in table


def test_the_hand_written_peers_have_their_orders():
    """``_peers``' integrators on the harmonic oscillator to T = 1 (exact: a rotation), 8 and 16
    steps: the error ratio is 2^order. Measured 63.99 for 3-stage Gauss (order 6), 15.84 for the
    triple jump of the midpoint rule and 16.03 for that of velocity Verlet (order 4); asserted
    within 5 %."""
    _peers_installed()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import _peers as peers
    finally:
        sys.path.pop(0)
    H = lambda q, p: 0.5 * (q @ q) + 0.5 * (p @ p)
    z0, exact = jnp.array([1.0, 0.0]), np.array([np.cos(1.0), -np.sin(1.0)])

    def midpoint_jump(n):
        step, zero = peers.gauss_step(H, 1.0 / n, 1, peers.TRIPLE_JUMP), jnp.zeros((), jnp.int32)
        carry = (z0, jnp.zeros((3, 1, 2)), zero, zero)
        return lambda z0: jax.lax.fori_loop(0, n, lambda _, c: step(c), carry)[::2]

    for make, order in ((lambda n: peers.gauss_rk(H, 1.0, n), 6), (midpoint_jump, 4),
                        (lambda n: peers.leapfrog(H, 1.0, n, peers.TRIPLE_JUMP), 4)):
        coarse, fine = (np.max(np.abs(np.asarray(jax.jit(make(n))(z0)[0]) - exact)) for n in (8, 16))
        assert abs(coarse / fine / 2**order - 1) < 0.05, (order, coarse / fine)
