"""Choose the test suite's two tiers from one measured run of the whole suite.

The default tier (``python -m pytest -q``) must cover every line and branch of ``galerkin_jax``
that the whole suite covers; the slow tier (``--tier=slow``) holds the rest. Given coverage
data recorded per test (``--cov-context=test``) and each test's duration, this finds a cheap
set of tests whose arcs (branch coverage's ``(from, to)`` line pairs) are those of the whole
suite: every test that alone covers an arc, then greedily the test of least seconds per arc
still uncovered, then each chosen test replaced where cheaper ones cover what it alone covers
(a weighted set cover). Every test under ``--cheap`` seconds stays in the default tier too: it
costs nothing and keeps its check where a developer runs first. The rest, one node id a line,
is written to ``tests/slow.txt``, which ``tests/conftest.py`` reads.

The claims stay in the default tier whatever their coverage: the tests whose node ids begin
with an entry of ``CLAIMS`` (tests/test_claims.py, the docs' claims in fast form: the orders of
convergence, Theorem 3.1 and the dissipation of dG(k) of [GBS], the equivalences,
symplecticity, the explicit paths; test_midpoint.py's discrete gradient over 10^4 steps, whose
run a test of the default tier shares). They enter the set cover as chosen (what they cover
needs no other test) and are never written to slow.txt; tests/test_tiers.py checks that none
is listed there and that each entry names a test.

Made anew after tests are added or moved (about half an hour on the two-core machine):

    python -m pytest -q --tier=all --cov --cov-context=test --cov-report= --durations=0 | tee durations.txt
    python .ci/tiers.py .coverage durations.txt > tests/slow.txt

``.ci/check_coverage.py`` checks the result in CI: a default tier that stops covering an arc
the slow tier covers fails it.
"""

import argparse
import collections
import re
import sqlite3

# Node-id prefixes of the tests kept in the default tier whatever their coverage (the docstring).
CLAIMS = (
    "tests/test_claims.py::",
    "tests/test_midpoint.py::test_discrete_gradient_conserves_energy_over_1e4_steps",
)
DURATION = re.compile(r"^\s*([\d.]+)s (?:setup|call|teardown)\s+(\S.*?)\s*$")


def arcs_by_test(path):
    """``{node id: {(file, from, to)}}`` from a coverage data file with per-test contexts, and
    the arcs covered outside any test (importing the modules: both tiers cover them)."""
    db = sqlite3.connect(path)
    contexts = dict(db.execute("select id, context from context"))
    files = dict(db.execute("select id, path from file"))
    cover = collections.defaultdict(set)
    for file, context, start, end in db.execute("select file_id, context_id, fromno, tono from arc"):
        cover[contexts[context].split("|")[0]].add((files[file], start, end))
    return cover, cover.pop("", set())


def durations(path):
    """Each test's seconds (setup, call and teardown added) from pytest's ``--durations=0`` lines."""
    seconds = collections.Counter()
    with open(path) as lines:
        for match in filter(None, map(DURATION.match, lines)):
            seconds[match[2]] += float(match[1])
    return seconds


def cheapest_cover(arcs, pool, cover, cost):
    """Greedy weighted set cover of ``arcs`` from the tests in ``pool``, or None."""
    chosen, left = [], set(arcs)
    while left:
        candidates = [n for n in pool if cover[n] & left]
        if not candidates:
            return None
        best = min(candidates, key=lambda n: cost[n] / len(cover[n] & left))
        chosen.append(best)
        left -= cover[best]
    return chosen


def is_claim(node):
    """Whether a node id names a test that ``CLAIMS`` keeps in the default tier."""
    return node.startswith(CLAIMS)


def default_tier(cover, base, cost, kept=frozenset()):
    """A set of tests that covers every arc of ``cover`` beyond ``base``, of few seconds, with
    the tests ``kept`` (chosen beforehand, never swapped out)."""
    owners = collections.defaultdict(list)
    for node, arcs in cover.items():
        for arc in arcs - base:
            owners[arc].append(node)
    chosen = {nodes[0] for nodes in owners.values() if len(nodes) == 1} | set(kept)
    covered = set().union(base, *(cover[n] for n in chosen))
    chosen |= set(cheapest_cover(set(owners) - covered, [n for n in cover if n not in chosen], cover, cost))
    improved = True
    while improved:  # swap a test for cheaper ones that cover what it alone covers
        improved = False
        for node in sorted(chosen - set(kept), key=lambda n: -cost[n]):
            alone = cover[node] - set().union(base, *(cover[n] for n in chosen if n != node))
            others = cheapest_cover(alone, [n for n in cover if n not in chosen], cover, cost)
            if others is not None and sum(cost[n] for n in others) < cost[node]:
                chosen = (chosen - {node}) | set(others)
                improved = True
                break
    return chosen


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("coverage", help="coverage data file recorded with --cov-context=test")
    parser.add_argument("durations", help="pytest's output with --durations=0")
    parser.add_argument("--cheap", type=float, default=1.0, help="seconds under which a test stays (default 1)")
    options = parser.parse_args()
    cover, base = arcs_by_test(options.coverage)
    seconds = durations(options.durations)
    cost = {n: seconds[n] for n in set(cover) | set(seconds)}  # 0 s for a test pytest did not time
    claims = {n for n in cost if is_claim(n)}
    fast = default_tier(cover, base, cost, claims) | claims | {n for n in cost if cost[n] < options.cheap}
    slow = sorted(set(cost) - fast)
    total = sum(cost.values())
    print(f"# The slow tier (python -m pytest --tier=slow): {len(slow)} tests, {sum(cost[n] for n in slow):.0f} of the whole")
    print(f"# suite's {total:.0f} test-seconds; none covers a line or branch of galerkin_jax that the default")
    print("# tier does not. Written by .ci/tiers.py, whose docstring says how to make it anew.")
    print("\n".join(slow))


if __name__ == "__main__":
    main()
