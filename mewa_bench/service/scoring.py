"""Scores on the server: every board entry is recomputed from its per-episode returns, never copied.

A results upload goes through the leaderboard's own checks (`leaderboard.validate.check_run` and
`verified_scores`: each episode's score from its normalised return, then the protocol's scores from
the units, compared with the stored aggregates, which must agree), after each normalised return is
checked against its episode's return; an agent evaluated by a worker
goes through `verified_scores` too, on its public or hidden suite. The stored scores are
`Scores.to_dict()`, the very dict `mewa-bench evaluate` writes, so they are byte for byte the same.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.design.suites import Suite
from mewa_bench.files import json_text
from mewa_bench.leaderboard.board import entry_row
from mewa_bench.game.normalise import normalised_return, return_bounds
from mewa_bench.leaderboard.validate import (TOLERANCE, Entry, InvalidResults, SuiteCache, check_run, finished_date,
                                             verified_scores)
from mewa_bench.protocol.results import ResultsError, validate_structure


@dataclass(frozen=True)
class Scored:
    """What a board entry stores."""

    mean: float
    privileged: bool
    row: str  # JSON of the leaderboard row
    scores: str  # canonical JSON of the recomputed scores


def score_upload(results: dict[str, Any], seeds: tuple[int, ...], submission_id: int) -> Scored:
    """Re-check and re-score an uploaded results file on its public suite; InvalidResults says what is wrong."""
    try:
        validate_structure(results, "results file")
        suite, _, units = check_run(results, SuiteCache(), seeds)
        check_normalised_returns(units, suite)
        return _scored(results, suite, units, submission_id)
    except ResultsError as e:
        raise InvalidResults(str(e)) from None
    except (AttributeError, KeyError, IndexError, TypeError, ValueError) as e:
        raise InvalidResults(f"malformed results ({type(e).__name__}: {e})") from None


def check_normalised_returns(units: list[dict[str, Any]], suite: Suite) -> None:
    """Each episode's normalised return is its return normalised by its task's bounds (SPEC section 2)."""
    for unit in units:
        task = suite.tasks[suite.pairs[unit["pair"]].task_index]
        r_min, r_max = return_bounds(task)
        returns = np.asarray(unit["returns"], dtype=np.float64)
        stored = np.asarray(unit["normalised_returns"], dtype=np.float64)
        off = np.flatnonzero(~(np.abs((returns - r_min) / (r_max - r_min) - stored) <= TOLERANCE))
        if len(off):
            k = int(off[0])
            raise InvalidResults(f"unit (pair {unit['pair']}, seed {unit['seed']}) episode {k}: normalised return "
                                 f"{float(stored[k])!r} is not that of its return {float(returns[k])!r} on the pair's task "
                                 f"({normalised_return(task, float(returns[k]))!r}): the file was edited after the run")


def score_evaluation(results: dict[str, Any], suite: Suite, submission_id: int) -> Scored:
    """Score a worker's own evaluation (complete, on `suite`, public or hidden)."""
    from mewa_bench.protocol.results import unit_key

    units = sorted(results["units"], key=unit_key)
    return _scored(results, suite, units, submission_id)


def _scored(results: dict[str, Any], suite: Suite, units: list[dict[str, Any]], submission_id: int) -> Scored:
    """Verified scores and the leaderboard row of a run."""
    scores = verified_scores(units, suite, results["scores"])
    agent = results["agent"]
    entry = Entry(suite=suite.name, agent=str(agent["name"]), path=Path(str(submission_id)) / "results.json",
                  privileged=agent.get("privileged") is True, scores=scores, seeds=tuple(results["seeds"]),
                  date=finished_date(results), package_version=str(results["package_version"]),
                  agent_sha256=str(agent.get("sha256") or ""))
    row = entry_row(entry, None, "submissions")
    return Scored(mean=scores.mean.mean, privileged=entry.privileged,
                  row=json.dumps(dataclasses.asdict(row), allow_nan=False), scores=json_text(scores.to_dict()))
