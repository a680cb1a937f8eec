"""Fail where the slow tier covers a line or branch of galerkin_jax that the default tier does not.

    python .ci/check_coverage.py DEFAULT SLOW

DEFAULT and SLOW: coverage data files of ``python -m pytest --cov`` and of ``python -m pytest
--tier=slow --cov`` (branch coverage: arcs, pairs of lines). The default tier's promise is the
whole suite's coverage in minutes (``tests/slow.txt``, ``.ci/tiers.py``); this is its check.
"""

import sys

from coverage import CoverageData


def arcs(path):
    data = CoverageData(path)
    data.read()
    return {(file, arc) for file in data.measured_files() for arc in data.arcs(file) or ()}


def main(default, slow):
    covered = arcs(default)
    missing = arcs(slow) - covered
    for file, (start, end) in sorted(missing):
        print(f"{file}: line {abs(start)} -> {'exit' if end < 0 else end}, covered by the slow tier alone")
    if missing:
        print(f"{len(missing)} arcs of galerkin_jax are covered by the slow tier alone: move a test that covers "
              "them out of tests/slow.txt, or make the list anew (.ci/tiers.py)")
        return 1
    print(f"the default tier covers every arc the slow tier covers ({len(covered)} arcs)")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
