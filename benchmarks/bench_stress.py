"""Hard first elements: the solver's iterations against plain Newton's.

    python -m benchmarks stress

For every case of the stress set (``tests/test_stress.py``: large h omega, large momenta,
near-collisions, a non-separable H, every method family; one element from the constant guess)
this records plain Newton's iterations (a fresh dense Jacobian every iteration, full steps,
written in the test independently of the library), the solver's at the default options and
with the watchdog off (``SolverOptions(watch=0)``: halving from the first full step that
raises the residual, the watchdog's alternative), the ratio to plain Newton, the status, and the
distance between the two roots in units of eps times the state's size, and the element
tangent that derivatives solve, matrix-free (Richardson's iteration, then GMRES) at plain
Newton's root against LU's, in units of eps cond(dR/dZ) (``test_stress.tangent_error``). Writes
results/stress.json.
"""

import argparse
import pathlib
import sys

from _common import show, write  # first: one BLAS thread

import numpy as np  # noqa: E402

import galerkin_jax as gj  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent.parent / "tests"))
import test_stress  # noqa: E402


def row(name):
    H, q, p, method, h, keywords = test_stress.CASES[name]
    plain, ours, difference, status = test_stress.compare(name)
    _, no_watch, no_watch_status = test_stress.solver_element(
        method, H, q, p, h, dict(keywords, solver=gj.SolverOptions(watch=0)))
    return {"plain_newton_iterations": plain, "iterations": ours, "ratio": ours / plain, "status": status,
            "root_difference_eps": difference, "iterations_without_watchdog": no_watch,
            "status_without_watchdog": no_watch_status, "tangent_error_cond_eps": test_stress.tangent_error(name)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", nargs="+", choices=list(test_stress.CASES), default=list(test_stress.CASES),
                        metavar="CASE", help="run only these cases (names as in tests/test_stress.py)")
    parser.add_argument("--name", default="stress")
    options = parser.parse_args()
    rows = {}
    for name in options.only:
        rows[name] = row(name)
        show(name, rows[name])
    ratios = np.array([r["ratio"] for r in rows.values()])
    summary = {"cases": len(rows), "max_ratio": float(ratios.max()), "mean_ratio": float(ratios.mean()),
               "failures": sum(r["status"] != 0 for r in rows.values()),
               "failures_without_watchdog": sum(r["status_without_watchdog"] != 0 for r in rows.values()),
               "default_cap": gj.SolverOptions().max_iterations,
               "max_tangent_error_cond_eps": float(max(r["tangent_error_cond_eps"] for r in rows.values()))}
    show("summary", summary)
    write(options.name, {"summary": summary, "rows": rows})


if __name__ == "__main__":
    main()
