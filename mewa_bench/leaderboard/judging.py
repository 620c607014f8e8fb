"""A board's verdicts (`protocol.verdicts`) over everything it shows: its checkpoints and its algorithms.

The family of a board (or of a comparison, or of the service's board) is every one-sided test it shows:
- each checkpoint row: "adapts" (adaptability > 0) and "beats the best fixed policy" (gap won > 0, the
  paired difference with the best fixed policy), on the run's within-run interval;
- each algorithm of several runs: the same two, on its interval over training runs;
- a one-run algorithm: its checkpoint's two tests (the same tests, counted once), labelled as
  conditional on that checkpoint; a multi-run algorithm also says in how many of its runs the
  checkpoint verdict "adapts" is yes;
- whatever else the display adds (`compare`: "X better" for every two algorithms, both ways).
Holm's weighted step-down over the family, each table (checkpoint rows, algorithms of several runs,
comparisons) an equal share, keeps the chance of any false "yes" at most FAMILY_ALPHA.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Hashable, Mapping, Sequence

from mewa_bench.leaderboard.board import Row
from mewa_bench.protocol.scoring import Estimate, gap_won
from mewa_bench.protocol.verdicts import (ALGORITHMS, CHECKPOINTS, FAMILY_ALPHA, PROCEDURE, Family, Hypothesis, judge,
                                          read_back)

if TYPE_CHECKING:
    from mewa_bench.leaderboard.algorithms import AlgorithmRow

ADAPTS, BEATS = "adapts", "beats best fixed"


def with_gap_won(row: Row, best_fixed: float) -> Row:
    """A checkpoint row with its gap won: its paired difference with the best fixed policy over the gap."""
    if row.vs_best_fixed is None:
        return row
    won = gap_won(Estimate(row.vs_best_fixed, row.vs_best_fixed_low, row.vs_best_fixed_high), best_fixed,
                  difference=True)
    return dataclasses.replace(row, gap_won=won.mean, gap_won_low=won.low, gap_won_high=won.high)


def checkpoint_estimates(row: Row, pairs: int) -> dict[str, Estimate]:
    """A checkpoint row's mean, adaptability and gap won as estimates with the standard errors of their intervals
    (Student t on pairs x (seeds - 1) degrees of freedom, as the run's scores made them)."""
    df = max(pairs * ((row.seeds or 0) - 1), 1)
    return {"mean": read_back(row.mean, row.mean_low, row.mean_high, df),
            "adaptability": read_back(row.adaptability, row.adaptability_low, row.adaptability_high, df),
            "gap_won": read_back(row.gap_won, row.gap_won_low, row.gap_won_high, df)}


@dataclass(frozen=True)
class Judged:
    """A board's rows and algorithm rows with their verdicts, and the family they were decided in."""

    rows: tuple[Row, ...]
    algorithms: tuple
    family: Family


def run_key(name: str, verdict: str) -> tuple[str, str, str]:
    """The key of a checkpoint's test."""
    return ("run", name, verdict)


def algorithm_key(name: str, verdict: str) -> tuple[str, str, str]:
    """The key of a multi-run algorithm's test."""
    return ("algorithm", name, verdict)


def board_tests(runs: Mapping[str, Row], algorithms: Sequence[AlgorithmRow], pairs: int) -> list[Hypothesis]:
    """Every test of the checkpoints `runs` (run name -> row) and of the algorithms."""
    tests = []
    for name, row in runs.items():
        estimates = checkpoint_estimates(row, pairs)
        tests += [Hypothesis(run_key(name, ADAPTS), estimates["adaptability"], 0.0),
                  Hypothesis(run_key(name, BEATS), estimates["gap_won"], 0.0)]
    for a in algorithms:
        if a.within_run:  # a one-run algorithm's tests are its checkpoint's
            key, table = (lambda v: run_key(a.run_names[0], v)), CHECKPOINTS
        else:
            key, table = (lambda v: algorithm_key(a.algorithm, v)), ALGORITHMS
        tests += [Hypothesis(key(ADAPTS), a.adaptability, 0.0, table), Hypothesis(key(BEATS), a.gap_won, 0.0, table)]
    return tests


def judge_board(rows: Sequence[Row], algorithms: Sequence[AlgorithmRow], runs: Mapping[str, Row], pairs: int,
                extra: Sequence[Hypothesis] = ()) -> Judged:
    """Holm over the board's tests (and `extra` ones); the rows and algorithm rows with their verdicts. `runs` maps
    each checkpoint's run name to its row (the same objects as in `rows`)."""
    family = judge([*board_tests(runs, algorithms, pairs), *extra])
    name_of = {id(row): name for name, row in runs.items()}
    judged_rows = []
    for row in rows:
        name = name_of.get(id(row))
        if name is not None:
            row = dataclasses.replace(row, adapts=family.decision(run_key(name, ADAPTS)),
                                      beats_best_fixed=family.decision(run_key(name, BEATS)))
        judged_rows.append(row)
    judged_algorithms = []
    for a in algorithms:
        if a.within_run:
            verdicts = {v: family.decision(run_key(a.run_names[0], v)) for v in (ADAPTS, BEATS)}
            adapting = None
        else:
            verdicts = {v: family.decision(algorithm_key(a.algorithm, v)) for v in (ADAPTS, BEATS)}
            decided = [family.decision(run_key(n, ADAPTS)) for n in a.run_names if n in runs]
            adapting = sum(d is True for d in decided) if len(a.run_names) > 1 and decided else None
        judged_algorithms.append(dataclasses.replace(a, adapts=verdicts[ADAPTS], beats_best_fixed=verdicts[BEATS],
                                                     adapting_runs=adapting))
    return Judged(tuple(judged_rows), tuple(judged_algorithms), family)


def _counted(n: int, noun: str) -> str:
    """`1 checkpoint row`, `30 checkpoint rows`."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def family_caption(family: Family, checkpoints: int, algorithms: int, what: str = "board") -> str:
    """The sentence naming the verdicts' procedure, its family and the tables' shares of it."""
    sizes = family.table_sizes
    parts = [f"the {n} tests of the {table}" if i == 0 else f"the {n} of the {table}"
             for i, (table, n) in enumerate(sizes.items())]
    share = {2: "half", 3: "a third"}.get(len(sizes), f"1/{len(sizes)}")
    shares = "" if len(sizes) < 2 else f"; {', '.join(parts[:-1])} and {parts[-1]} weigh {share} of the family each"
    return (f"Verdicts (adapts: adaptability > 0; beats best fixed: gap won > 0) are one-sided tests on each row's "
            f"95% interval statistic, decided together by {PROCEDURE} procedure over all {family.size} tests this "
            f"{what} shows ({_counted(checkpoints, 'checkpoint row')} and {_counted(algorithms, 'algorithm')} of "
            f"several runs, two tests each; a one-run algorithm's are its checkpoint's){shares}: the chance that the "
            f"{what} shows any false \"yes\" is at most {family.alpha:.1%}. \"no\" means not shown at that level.")


__all__ = ["ADAPTS", "BEATS", "FAMILY_ALPHA", "Judged", "checkpoint_estimates", "family_caption", "judge_board",
           "with_gap_won"]
