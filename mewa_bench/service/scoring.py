"""Scores on the server: every board entry is recomputed from its per-episode returns, never copied.

A results upload goes through the leaderboard's own checks (`leaderboard.validate.check_run` and
`verified_scores`: the protocol's env seeds, each normalised return from its return, each episode's
score from its normalised return, then the protocol's scores from the units, compared with the
stored aggregates, which must agree); an agent evaluated by a worker
goes through `verified_scores` too, on its public or hidden suite. The stored scores are
`Scores.to_dict()`, the very dict `mewa-bench evaluate` writes, so they are byte for byte the same.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mewa_bench.design.suites import Suite
from mewa_bench.files import json_text
from mewa_bench.leaderboard.board import entry_row
from mewa_bench.leaderboard.validate import (Entry, InvalidResults, SuiteCache, check_run, finished_date,
                                             verified_scores)
from mewa_bench.protocol.results import ResultsError, validate_structure


@dataclass(frozen=True)
class Scored:
    """What a board entry stores."""

    mean: float
    privileged: bool
    row: str  # JSON of the leaderboard row
    scores: str  # canonical JSON of the recomputed scores
    run_digest: str  # the run's episodes (`uploads.results_digest`): one board row per run
    pair_curves: str  # JSON [pairs][episodes]: the run's (run, pair) cells for the algorithms table


def score_upload(results: dict[str, Any], seeds: tuple[int, ...], submission_id: int) -> Scored:
    """Re-check and re-score an uploaded results file on its public suite; InvalidResults says what is wrong."""
    try:
        results = validate_structure(results, "results file")  # schema 3: its unit columns decoded
        suite, _, units = check_run(results, SuiteCache(), seeds)
        return _scored(results, suite, units, submission_id)
    except ResultsError as e:
        raise InvalidResults(str(e)) from None
    except (AttributeError, KeyError, IndexError, TypeError, ValueError) as e:
        raise InvalidResults(f"malformed results ({type(e).__name__}: {e})") from None


def score_evaluation(results: dict[str, Any], suite: Suite, submission_id: int) -> Scored:
    """Score a worker's own evaluation (complete, on `suite`, public or hidden)."""
    from mewa_bench.protocol.results import unit_key

    units = sorted(results["units"], key=unit_key)
    return _scored(results, suite, units, submission_id)


def _scored(results: dict[str, Any], suite: Suite, units: list[dict[str, Any]], submission_id: int) -> Scored:
    """Verified scores and the leaderboard row of a run."""
    from mewa_bench.service.uploads import results_digest

    scores = verified_scores(units, suite, results["scores"])
    agent = results["agent"]
    entry = Entry(suite=suite.name, agent=str(agent["name"]), path=Path(str(submission_id)) / "results.json",
                  privileged=agent.get("privileged") is True, scores=scores, seeds=tuple(results["seeds"]),
                  date=finished_date(results), package_version=str(results["package_version"]),
                  agent_sha256=str(agent.get("sha256") or ""))
    row = entry_row(entry, None, "submissions")
    return Scored(mean=scores.mean.mean, privileged=entry.privileged,
                  row=json.dumps(dataclasses.asdict(row), allow_nan=False), scores=json_text(scores.to_dict()),
                  run_digest=results_digest(results, units), pair_curves=json_text(scores.pair_curves.tolist()))
