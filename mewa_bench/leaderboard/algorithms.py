"""A suite's algorithms table: the board's entries grouped by algorithm (run.json), statistics over training runs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.validate import Entry
from mewa_bench.protocol.aggregate import AlgorithmComparison, Run, aggregate
from mewa_bench.protocol.scoring import Estimate, reference_line_cells


@dataclass(frozen=True)
class AlgorithmRow:
    """One line of the algorithms table."""

    rank: int | None  # None: privileged (not ranked)
    algorithm: str
    privileged: bool
    runs: int
    iqm: Estimate
    mean: Estimate
    s_first: float
    s_last: float
    adaptability: Estimate
    over_best_fixed: Estimate  # probability of improvement over the best fixed policy
    adapts: bool
    beats_best_fixed: bool
    note: str


def entry_runs(entries: Sequence[Entry]) -> list[Run]:
    """Each entry as a training run of its algorithm."""
    return [Run(name=e.agent, algorithm=e.algorithm or e.agent, curves=e.scores.pair_curves) for e in entries]


def compare_entries(suite: Suite, entries: Sequence[Entry]) -> AlgorithmComparison:
    """Algorithm-level statistics of a suite's entries, against the suite's exact reference lines."""
    return aggregate(entry_runs(entries), reference_line_cells(suite))


def algorithm_rows(suite: Suite, entries: Sequence[Entry],
                   comparison: AlgorithmComparison) -> tuple[AlgorithmRow, ...]:
    """The table's rows, best mean first; privileged algorithms unranked; equal means share a rank."""
    return rows_of(suite, comparison, privileged={e.algorithm or e.agent for e in entries if e.privileged})


def rows_of(suite: Suite, comparison: AlgorithmComparison, privileged: set[str],
            unranked: frozenset[str] = frozenset()) -> tuple[AlgorithmRow, ...]:
    """The table's rows, best mean first; `privileged` and `unranked` algorithms get no rank; equal means share one."""
    from mewa_bench.leaderboard.board import competition_ranks

    best_fixed = float(suite.summary["score"]["best_fixed"])
    ranked = [s for s in comparison.algorithms if s.algorithm not in privileged | unranked]
    ranks = dict(zip((s.algorithm for s in ranked), competition_ranks([s.mean.mean for s in ranked])))
    rows = []
    for s in comparison.algorithms:
        verdicts = s.verdicts(best_fixed)
        rows.append(AlgorithmRow(rank=ranks.get(s.algorithm), algorithm=s.algorithm,
                                 privileged=s.algorithm in privileged, runs=len(s.runs), iqm=s.iqm, mean=s.mean,
                                 s_first=s.curve[0].mean, s_last=s.curve[-1].mean, adaptability=s.adaptability,
                                 over_best_fixed=s.over_lines["best_fixed"], adapts=verdicts["adapts"],
                                 beats_best_fixed=verdicts["beats_best_fixed"], note=s.note))
    return tuple(rows)
