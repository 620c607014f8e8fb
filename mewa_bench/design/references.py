"""The reference lines of a set of curated pairs (suite summary, or the pairs of a partial run).

Means of the exact baselines, best fixed policy and known-worker optimum, on the normalised-return
scale and on the score scale (ratio to each pair's max-expected baseline), plus skill and the
non-adaptive gap. Numbers are rounded to the suites' 12 decimals so that files are byte-stable.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mewa_bench.game.normalise import episode_score, skill_of

DECIMALS = 12  # every float a suite or results file stores is rounded to this many decimals


def round_floats(x: Any) -> Any:
    """Round floats (also inside lists / arrays) to 12 decimals; arrays become lists."""
    if isinstance(x, np.ndarray):
        return [round_floats(v) for v in x.tolist()]
    if isinstance(x, (list, tuple)):
        return [round_floats(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return round(float(x), DECIMALS) + 0.0  # + 0.0 turns -0.0 into 0.0
    return x


def summarise(pairs: list[dict[str, Any]]) -> dict[str, Any]:
    """Reference means over pair records (as stored in a suite's `pairs`)."""
    cols = {
        "random": [p["baselines"]["random"] for p in pairs],
        "random_task_specific": [p["baselines"]["random_task_specific"] for p in pairs],
        "max_expected": [p["baselines"]["max_expected"] for p in pairs],
        "best_fixed": [p["best_fixed"] for p in pairs],
        "known_worker_optimum": [p["known_worker_optimum"] for p in pairs],
    }
    best = np.array(cols["max_expected"])
    normalised = {k: round_floats(float(np.mean(v))) for k, v in cols.items()}
    score = {k: round_floats(float(np.mean(episode_score(np.array(v), best)))) for k, v in cols.items()}
    s_rts = score["random_task_specific"]
    return {
        "pairs": len(pairs), "normalised": normalised, "score": score,
        "non_adaptive_gap": round_floats(1.0 - score["best_fixed"]),
        "skill": {k: round_floats(skill_of(s, s_rts)) for k, s in score.items()},
    }
