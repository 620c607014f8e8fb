"""`mewa-bench compare`: runs given as folders, results files or globs, grouped by algorithm, compared as algorithms.

Every run must be a complete protocol run on the one suite, with the same seeds as the others, and
listed once; anything else is refused with a message naming the file. A run's algorithm is, in order:
the NAME of an `--algorithm NAME=GLOB` whose pattern names it, its folder's run.json, its folder's name
(a submission folder, with agent.py), or else the agent name inside the results file; how each run was
grouped is part of the result (`Compared.groupings`), never silent. Algorithms are listed in the order
given (the --algorithm ones first, then the others by first appearance). Verdicts ("adapts", "beats
best fixed", "X better") are decided together over everything the comparison shows (`judging`).
"""

from __future__ import annotations

import glob
import hashlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.algorithms import AlgorithmRow, entry_runs, rows_of
from mewa_bench.leaderboard.board import Row, entry_row, run_name
from mewa_bench.leaderboard.judging import Judged, judge_board, with_gap_won
from mewa_bench.leaderboard.validate import Entry, InvalidResults, SuiteCache, check_run, finished_date, verified_scores
from mewa_bench.protocol.aggregate import AlgorithmComparison, aggregate
from mewa_bench.protocol.config import default_seeds
from mewa_bench.protocol.results import ResultsError, read_results
from mewa_bench.protocol.run_info import RunInfoError, read_run_info
from mewa_bench.protocol.scoring import Estimate, reference_line_cells
from mewa_bench.protocol.verdicts import COMPARISONS, Hypothesis

BY_OPTION, BY_RUN_JSON, BY_FOLDER, BY_AGENT = ("--algorithm", "run.json", "folder name",
                                               "agent name in the results file")


class CompareError(ValueError):
    """A run that cannot be compared; the message names the file."""


@dataclass(frozen=True)
class Grouping:
    """How one run was assigned to its algorithm."""

    path: Path
    algorithm: str
    by: str  # BY_OPTION (with its pattern), BY_RUN_JSON, BY_FOLDER or BY_AGENT


@dataclass(frozen=True)
class Compared:
    """The suite, the runs (entries) and how each was grouped, the algorithm-level comparison (algorithms in the
    order given), and the verdicts over everything shown: checkpoint rows, algorithm rows and P(X > Y) both ways."""

    suite: Suite
    entries: tuple[Entry, ...]
    comparison: AlgorithmComparison
    groupings: tuple[Grouping, ...] = ()
    judged: Judged | None = None

    @property
    def algorithms(self) -> tuple[AlgorithmRow, ...]:
        """The judged algorithm rows, in the comparison's order."""
        return self.judged.algorithms if self.judged is not None else ()

    @property
    def rows(self) -> tuple[Row, ...]:
        """The judged checkpoint rows, in the entries' order."""
        return self.judged.rows if self.judged is not None else ()

    def better(self, x: str, y: str) -> bool | None:
        """Whether "X better than Y" (P(X > Y) > 1/2) is a yes of the family (None: no interval)."""
        return None if self.judged is None else self.judged.family.decision(better_key(x, y))


def expand(items: Sequence[str], suite: str | None) -> list[Path]:
    """Results files named by folders (their results-*.json), files or glob patterns, in the order given."""
    paths: list[Path] = []
    for item in items:
        matches = sorted(glob.glob(item)) if any(c in item for c in "*?[") else [item]
        if not matches:
            raise CompareError(f"{item}: no file or folder matches")
        for match in map(Path, matches):
            if match.is_dir():
                found = sorted(match.glob(f"results-{suite}.json" if suite else "results-*.json"))
                if not found:
                    raise CompareError(f"{match}: no results{'-' + suite if suite else '-*'}.json in this folder")
                if len(found) > 1:
                    raise CompareError(f"{match}: results for several suites ({', '.join(p.name for p in found)}): "
                                       f"pass --suite")
                paths += found
            elif match.is_file():
                paths.append(match)
            else:
                raise CompareError(f"{match}: no such file or folder")
    return paths


def parse_algorithm(option: str) -> tuple[str, str]:
    """`NAME=GLOB` as (name, glob)."""
    name, sep, pattern = option.partition("=")
    if not sep or not name.strip() or not pattern.strip():
        raise CompareError(f"--algorithm {option!r}: expected NAME=GLOB, e.g. --algorithm 'mine=runs/mine-*'")
    return name.strip(), pattern.strip()


def read_run(path: Path, suite: str | None) -> dict[str, Any]:
    """A results file that can be compared: complete, not partial, on `suite` (when given)."""
    try:
        results = read_results(path)
    except ResultsError as e:
        raise CompareError(str(e)) from None
    if results.get("pairs") is not None or results.get("complete") is not True:
        raise CompareError(f"{path}: an unranked partial run (--pairs, or not finished): only complete runs are "
                           f"compared")
    name = results["suite"]["name"]
    if suite is not None and name != suite:
        raise CompareError(f"{path}: a run on {name}, not {suite}: runs of different suites are never compared")
    return results


def _seeds_text(seeds: tuple[int, ...]) -> str:
    """`256 seeds (0..255)` or the list."""
    if seeds == tuple(range(len(seeds))):
        return f"{len(seeds)} seed{'s' if len(seeds) != 1 else ''} (0..{len(seeds) - 1})"
    return f"{len(seeds)} seeds {list(seeds)}"


def common_seeds(runs: Sequence[tuple[Path, dict[str, Any]]]) -> tuple[int, ...]:
    """The seeds every run must have: the suite's default ones if any run used them, else the most common set
    (ties: the first given); CompareError naming the first run that differs, whatever the order given."""
    seed_sets = [tuple(r["seeds"]) if isinstance(r["seeds"], list) else () for _, r in runs]
    default = default_seeds(runs[0][1]["suite"]["name"])
    counts = Counter(seed_sets)
    expected = default if default in counts else max(counts, key=lambda s: (counts[s], -seed_sets.index(s)))
    counted = expected == tuple(range(len(expected)))  # `--seeds N` means 0..N-1
    option = str(len(expected)) if counted else ",".join(map(str, expected))
    for (path, _), seeds in zip(runs, seed_sets):
        if seeds != expected:
            fix = ("re-evaluate it with the protocol's default seeds (omit --seeds)" if expected == default
                   else f"re-evaluate it with --seeds {option}")
            raise CompareError(f"{path}: evaluated with {_seeds_text(seeds)}, the other runs with "
                               f"{_seeds_text(expected)}; runs are compared on the same seeds: {fix}")
    return expected


def load_run(path: Path, results: dict[str, Any], suites: SuiteCache, seeds: tuple[int, ...],
             algorithm: str | None) -> tuple[Entry, Grouping]:
    """One run checked for comparison, and how it was grouped (`algorithm`: named by --algorithm)."""
    name = results["suite"]["name"]
    try:
        checked_suite, run_seeds, units = check_run(results, suites, seeds)
        scores = verified_scores(units, checked_suite, results["scores"])
        agent = results["agent"]
        folder_named = (path.parent / "agent.py").is_file()
        has_run_json = (path.parent / "run.json").is_file()
        info = read_run_info(path.parent, path.parent.name if folder_named else str(agent["name"]))
    except (InvalidResults, RunInfoError) as e:
        raise CompareError(f"{path}: {e}") from None
    if algorithm is not None:
        grouping = Grouping(path, algorithm, BY_OPTION)
    else:
        grouping = Grouping(path, info.algorithm, BY_RUN_JSON if has_run_json else BY_FOLDER if folder_named
                            else BY_AGENT)
    entry = Entry(suite=name, agent=str(agent["name"]), path=path, privileged=agent.get("privileged") is True,
                  scores=scores, seeds=run_seeds, date=finished_date(results),
                  package_version=str(results["package_version"]), agent_sha256=str(agent.get("sha256") or ""),
                  algorithm=grouping.algorithm)
    return entry, grouping


def better_key(x: str, y: str) -> tuple[str, str, str]:
    """The key of the test "X better than Y"."""
    return ("better", x, y)


def pairwise_tests(comparison: AlgorithmComparison) -> list[Hypothesis]:
    """"X better than Y" for every ordered pair: P(X > Y) > 1/2 (P(Y > X) = 1 - P(X > Y): one estimate, two sides)."""
    return [Hypothesis(better_key(x, y), p, 0.5, COMPARISONS) for (x, y), p in comparison.improvement.items()]


def compare(items: Sequence[str], suite: str | None = None, algorithms: Sequence[str] = (),
            progress: Callable[[int, int, Path], None] | None = None) -> Compared:
    """Load, check and compare the runs (`items`, and `algorithms` as NAME=GLOB); CompareError naming the file on
    the first run that cannot be compared. `progress(done, total, path)` is called as each run is scored."""
    named = [parse_algorithm(option) for option in algorithms]
    listed: list[tuple[Path, str | None]] = [(p, name) for name, pattern in named for p in expand([pattern], suite)]
    listed += [(p, None) for p in expand(items, suite)]
    if not listed:
        raise CompareError("no runs given")
    seen: dict[str, Path] = {}
    read: list[tuple[Path, dict[str, Any]]] = []
    for path, _ in listed:
        key = str(path.resolve())
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        for earlier in (seen.get(key), seen.get(digest)):
            if earlier is not None:
                raise CompareError(f"{path}: listed twice (the same run as {earlier}): each run counts once")
        seen[key] = seen[digest] = path
        read.append((path, read_run(path, suite or (read[0][1]["suite"]["name"] if read else None))))
    seeds = common_seeds(read)
    suites = SuiteCache()
    entries, groupings = [], []
    for i, ((path, results), (_, algorithm)) in enumerate(zip(read, listed)):
        entry, grouping = load_run(path, results, suites, seeds, algorithm)
        entries.append(entry)
        groupings.append(grouping)
        if progress is not None:
            progress(i + 1, len(read), path)
    the_suite = suites.get(entries[0].suite)
    comparison = aggregate(entry_runs(entries), reference_line_cells(the_suite))
    order = list(dict.fromkeys(g.algorithm for g in groupings))
    comparison = AlgorithmComparison(tuple(sorted(comparison.algorithms, key=lambda a: order.index(a.algorithm))),
                                     comparison.improvement, comparison.samples, comparison.seed)
    best_fixed = float(the_suite.summary["score"]["best_fixed"])
    runs = {run_name(e): with_gap_won(entry_row(e, None, e.path.parent.name), best_fixed) for e in entries}
    rows = rows_of(best_fixed, comparison, {e.algorithm for e in entries if e.privileged}, runs=runs,
                   pairs=len(the_suite.pairs))
    judged = judge_board(list(runs.values()), rows, runs, len(the_suite.pairs), pairwise_tests(comparison))
    return Compared(the_suite, tuple(entries), comparison, tuple(groupings), judged)


def verdict(name_x: str, name_y: str, p: Estimate, compared: Compared | None = None) -> str:
    """The algorithm-level verdict of P(X > Y), decided in the comparison's family (alone when none is given)."""
    if p.low is None:
        return "no interval (an algorithm has a single run)"
    if compared is not None:
        x_better, y_better = compared.better(name_x, name_y), compared.better(name_y, name_x)
    else:
        x_better, y_better = p.low > 0.5, p.high < 0.5
    if x_better:
        return f"{name_x} better"
    if y_better:
        return f"{name_y} better"
    return "no significant difference"


def compared_board(compared: Compared):
    """The comparison as a leaderboard `Board` (what the board figures are drawn from)."""
    from mewa_bench.leaderboard.board import Board

    return Board(compared.suite, compared.entries, compared.rows, compared.comparison, compared.algorithms,
                 None if compared.judged is None else compared.judged.family)


def compare_figure(compared: Compared, path: Path) -> tuple[Path, Path]:
    """The boards' figures of the comparison: curves a panel per algorithm at `path`, gap won beside it
    (`<stem>-gap-won.png`); PNGs written atomically."""
    from mewa_bench.leaderboard.plot import plot_curves, plot_gap_won

    board = compared_board(compared)
    forest = path.with_name(f"{path.stem}-gap-won.png")
    plot_curves(board, path)
    plot_gap_won(board, forest)
    return path, forest


def summary(compared: Compared) -> dict[str, Any]:
    """A JSON-ready record of the comparison (grouping, algorithms with gap won and verdicts, P(X > Y), bootstrap)."""
    rows = {r.algorithm: r for r in compared.algorithms}
    return {"suite": compared.suite.name, "runs": [{"file": str(g.path), "algorithm": g.algorithm, "grouped_by": g.by}
                                                  for g in compared.groupings],
            "algorithms": [{**a.to_dict(), "gap_won": rows[a.algorithm].gap_won.to_dict(),
                            "adapts": rows[a.algorithm].adapts, "beats_best_fixed": rows[a.algorithm].beats_best_fixed,
                            "adapting_runs": rows[a.algorithm].adapting_runs, "within_run": rows[a.algorithm].within_run}
                           for a in compared.comparison.algorithms],
            "improvement": [{"x": x, "y": y, **p.to_dict(), "x_better": compared.better(x, y)}
                            for (x, y), p in compared.comparison.improvement.items()],
            "verdicts": None if compared.judged is None else {"tests": compared.judged.family.size,
                                                              "family_wise_error": compared.judged.family.alpha},
            "bootstrap": compared.comparison.bootstrap()}
