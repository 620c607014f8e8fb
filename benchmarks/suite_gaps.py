"""Non-adaptive gap of every shipped suite against its target (narrow-v2 >= 0.06, wide-v2 >= 0.04).

The gap is 1 - the best fixed t-optimal policy's mean score (ratio to each pair's max-expected
baseline): what only adaptation can win. It is read from the suite files (exact values) and
recomputed from their pairs; per family for the v2 suites. Exits 1 if a target is missed.

    .venv/bin/python benchmarks/suite_gaps.py
"""

from __future__ import annotations

import sys

import numpy as np

from mewa_bench.design.generate import GAP_TARGETS
from mewa_bench.design.suites import ALL_SUITES, Suite, load_suite


def recomputed_gap(suite: Suite) -> float:
    """1 - mean over pairs of best_fixed / max_expected, from the pair records."""
    return float(1.0 - np.mean([p.data["best_fixed"] / p.max_expected for p in suite.pairs]))


def family_counts(suite: Suite) -> str:
    """How many curated pairs each worker family has (v2 suites)."""
    families = [p.data.get("family") for p in suite.pairs]
    if families[0] is None:
        return "paper only"
    return ", ".join(f"{name} {families.count(name)}" for name in sorted(set(families)))


def main() -> int:
    """Print one line per suite; return 1 if a target is missed."""
    missed = 0
    print(f"{'suite':<10} {'pairs':>5} {'gap':>8} {'target':>8}  verdict  families")
    for name in ALL_SUITES:
        suite = load_suite(name)
        gap = suite.summary["non_adaptive_gap"]
        assert abs(gap - recomputed_gap(suite)) < 1e-9, f"{name}: summary gap disagrees with its pairs"
        target = GAP_TARGETS.get(name)
        verdict = "-" if target is None else ("met" if gap >= target else "MISSED")
        missed += verdict == "MISSED"
        shown = "-" if target is None else f"{target:.2f}"
        print(f"{name:<10} {len(suite.pairs):>5} {gap:>8.4f} {shown:>8}  {verdict:<7}  {family_counts(suite)}")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
