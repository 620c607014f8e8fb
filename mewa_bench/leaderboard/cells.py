"""A board's cells as CSV: `algorithm,run,pair,score`, one line per (run, pair), the input of rliable's estimators.

A cell is the run's mean control-variate-adjusted score on the pair (over its seeds and the 10 episodes):
exactly what the algorithms table's statistics are computed from (`protocol.aggregate`). With the cells
of an algorithm as a [runs, pairs] matrix, `rliable.metrics.aggregate_mean` and `aggregate_iqm` give the
table's mean score and IQM.
"""

from __future__ import annotations

import csv
import io

from mewa_bench.leaderboard.board import Board, run_name

HEADER = ("algorithm", "run", "pair", "score")


def cell_rows(board: Board) -> list[tuple[str, str, int, float]]:
    """(algorithm, run folder, pair, score) in the algorithms table's order, then by run and pair."""
    by_run = {run_name(e): e for e in board.entries}
    out = []
    for algorithm in board.algorithms:
        for name in algorithm.run_names:
            entry = by_run[name]
            cells = entry.scores.pair_curves.mean(axis=-1)
            out += [(algorithm.algorithm, entry.path.parent.name, pair, float(score))
                    for pair, score in zip(entry.scores.pairs, cells)]
    return out


def csv_text(board: Board) -> str:
    """The cells CSV, full-precision scores."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(HEADER)
    for algorithm, run, pair, score in cell_rows(board):
        writer.writerow([algorithm, run, pair, repr(score)])
    return out.getvalue()
