"""Power analysis of the evaluation protocol: per-unit SDs and the seeds each CI target needs.

Reads complete results files (default: the shipped submissions), recomputes their scores with the
protocol's estimators, and prints, per agent and suite, the 95% CI half-widths reached and the
seeds needed for adaptability <= 0.01 and mean score <= 0.005 (half-width ~ 1/sqrt(seeds)).

    .venv/bin/python benchmarks/power_analysis.py [RESULTS.json ...]
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from mewa_bench.design.suites import load_suite
from mewa_bench.protocol.results import read_results
from mewa_bench.protocol.scoring import score_units

TARGETS = {"adaptability": 0.01, "mean": 0.005}


def half_width(estimate: dict) -> float:
    """Half the CI width (inf when the CI is unknown)."""
    return math.inf if estimate["low"] is None else (estimate["high"] - estimate["low"]) / 2


def main(paths: list[Path]) -> None:
    print(f"{'agent':<22} {'suite':<10} {'seeds':>5}  {'hw mean':>8} {'hw adapt':>8} {'raw hw adapt':>12}"
          f"  {'seeds for mean':>14} {'seeds for adapt':>15}")
    for path in paths:
        results = read_results(path)
        if results.get("protocol_version") != 2 or not results.get("complete"):
            continue
        suite = load_suite(results["suite"]["name"])
        scores = score_units(suite, results["units"], suite.summary["score"]["random_task_specific"]).to_dict()
        seeds = len(results["seeds"])
        hw = {k: half_width(scores[k]) for k in TARGETS}
        need = {k: math.ceil(seeds * (hw[k] / t) ** 2) for k, t in TARGETS.items()}
        print(f"{results['agent']['name']:<22} {suite.name:<10} {seeds:>5}  {hw['mean']:>8.4f} {hw['adaptability']:>8.4f} "
              f"{half_width(scores['raw']['adaptability']):>12.4f}  {need['mean']:>14} {need['adaptability']:>15}")


if __name__ == "__main__":
    given = [Path(p) for p in sys.argv[1:]]
    main(given or sorted(Path(__file__).resolve().parents[1].glob("submissions/*/results-*.json")))
