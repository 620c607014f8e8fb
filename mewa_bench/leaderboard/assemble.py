"""A suite's board put together: its checkpoint rows ranked, its reference lines, its algorithms and its verdicts."""

from __future__ import annotations

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.algorithms import compare_entries, rows_of
from mewa_bench.leaderboard.board import _KIND_ORDER, Board, competition_ranks, entry_row, reference_rows, run_name
from mewa_bench.leaderboard.judging import judge_board, with_gap_won
from mewa_bench.leaderboard.validate import Entry


def make_board(suite: Suite, entries: list[Entry], root_label: str) -> Board:
    """Sort and rank the entries and merge in the reference lines, all by mean score; group them by algorithm;
    the verdicts over everything the board shows."""
    ordered = sorted(entries, key=lambda e: (-e.scores.mean.mean, e.agent, str(e.path)))
    ranks = competition_ranks([e.scores.mean.mean for e in ordered if not e.privileged])
    ranked = iter(ranks)
    best_fixed = float(suite.summary["score"]["best_fixed"])
    rows = [with_gap_won(entry_row(e, None if e.privileged else next(ranked), root_label), best_fixed)
            for e in ordered]
    runs = {run_name(e): row for e, row in zip(ordered, rows)}
    rows += reference_rows(suite)
    rows.sort(key=lambda r: (-r.mean, _KIND_ORDER[r.kind], r.name, r.file))
    if not ordered:
        return Board(suite, (), tuple(rows))
    comparison = compare_entries(suite, ordered)
    privileged = {e.algorithm or e.agent for e in ordered if e.privileged}
    algorithms = rows_of(best_fixed, comparison, privileged, runs=runs, pairs=len(suite.pairs))
    judged = judge_board(rows, algorithms, runs, pairs=len(suite.pairs))
    return Board(suite, tuple(ordered), judged.rows, comparison, judged.algorithms, judged.family)
