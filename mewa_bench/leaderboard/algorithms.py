"""A suite's algorithms table: the board's entries grouped by algorithm (run.json), statistics over training runs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.board import Row, competition_ranks, run_name
from mewa_bench.leaderboard.judging import checkpoint_estimates
from mewa_bench.leaderboard.validate import Entry
from mewa_bench.protocol.aggregate import AlgorithmComparison, Run, aggregate
from mewa_bench.protocol.scoring import Estimate, gap_won, reference_line_cells


@dataclass(frozen=True)
class AlgorithmRow:
    """One line of the algorithms table; verdicts None until the board is judged (or when there is no interval)."""

    rank: int | None  # None: privileged or unranked
    algorithm: str
    privileged: bool
    runs: int
    gap_won: Estimate  # (mean - best fixed) / (1 - best fixed)
    iqm: Estimate
    mean: Estimate
    s_first: float
    s_last: float
    adaptability: Estimate
    adapts: bool | None
    beats_best_fixed: bool | None
    note: str
    within_run: bool = False  # one run: the intervals and verdicts are its checkpoint's (conditional on it)
    adapting_runs: int | None = None  # runs whose checkpoint is judged to adapt (several runs only)
    run_names: tuple[str, ...] = ()


def entry_runs(entries: Sequence[Entry]) -> list[Run]:
    """Each entry as a training run of its algorithm, named by its results file."""
    return [Run(name=run_name(e), algorithm=e.algorithm or e.agent, curves=e.scores.pair_curves) for e in entries]


def compare_entries(suite: Suite, entries: Sequence[Entry]) -> AlgorithmComparison:
    """Algorithm-level statistics of a suite's entries, against the suite's exact reference lines."""
    return aggregate(entry_runs(entries), reference_line_cells(suite))


WITHIN_RUN_NOTE = "1 run: within-run intervals, conditional on this checkpoint"


def rows_of(best_fixed: float, comparison: AlgorithmComparison, privileged: set[str], unranked: frozenset[str] =
            frozenset(), runs: Mapping[str, Row] | None = None, pairs: int = 0) -> tuple[AlgorithmRow, ...]:
    """The table's rows, best mean first; `privileged` and `unranked` algorithms get no rank; equal means share one.
    A one-run algorithm whose checkpoint row is in `runs` (run name -> row; `pairs`: the suite's) takes that row's
    within-run intervals."""
    ranked = [s for s in comparison.algorithms if s.algorithm not in privileged | unranked]
    ranks = dict(zip((s.algorithm for s in ranked), competition_ranks([s.mean.mean for s in ranked])))
    rows = []
    for s in comparison.algorithms:
        mean, adaptability, won, note, within = s.mean, s.adaptability, gap_won(s.mean, best_fixed), s.note, False
        checkpoint = (runs or {}).get(s.runs[0]) if len(s.runs) == 1 else None
        if checkpoint is not None and checkpoint.mean_low is not None:
            estimates = checkpoint_estimates(checkpoint, pairs)
            mean, adaptability, won = estimates["mean"], estimates["adaptability"], estimates["gap_won"]
            note, within = WITHIN_RUN_NOTE, True
        rows.append(AlgorithmRow(rank=ranks.get(s.algorithm), algorithm=s.algorithm,
                                 privileged=s.algorithm in privileged, runs=len(s.runs), gap_won=won, iqm=s.iqm,
                                 mean=mean, s_first=s.curve[0].mean, s_last=s.curve[-1].mean,
                                 adaptability=adaptability, adapts=None, beats_best_fixed=None, note=note,
                                 within_run=within, run_names=s.runs))
    return tuple(rows)
