"""Leaderboards from the database: one per public suite, one per hidden suite, ranked by mean score.

Rows are the leaderboard's own (`leaderboard.board.Row`, stored when the entry was scored), ranked
the way `mewa-bench leaderboard` ranks them (privileged agents unranked, equal means share a rank),
each with its `source`: server-evaluated (the server ran the agent file in its sandbox),
self-reported (a results file the submitter ran: re-scored from its episodes, but played where the
server could not see; unranked unless the server's `rank_uploads` is set) or reference,
with the suite's exact reference lines and each agent's adaptation curve s_1..s_10 with its CIs.
Above the rows of a public board, the algorithms table (`grouped_runs`): the runs a submitter
sent under one algorithm name, with statistics over training runs as the static boards have them;
the board's figure draws the same algorithms (`board_algorithms`, `service.web.curves`). Verdicts and gap won
are the static boards' (`leaderboard.judging`): one family over every row the board shows.
A hidden board shows scores only: never the hidden suite, its pairs, its size or the runs' units.
Its reference lines (the fixed policies' and the optimum's means over the whole suite) are shown:
one number each, which the agents' rows are read against, and from which no pair can be learned.
"""

from __future__ import annotations

import dataclasses
import json
import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

import numpy as np

from mewa_bench.design.suites import ALL_SUITES, Suite, load_suite
from mewa_bench.leaderboard.algorithms import AlgorithmRow
from mewa_bench.leaderboard.board import AGENT, PRIVILEGED, REFERENCE, Row, competition_ranks, reference_rows
from mewa_bench.leaderboard.judging import family_caption, judge_board, with_gap_won
from mewa_bench.protocol.verdicts import PROCEDURE
from mewa_bench.protocol.aggregate import AlgorithmComparison
from mewa_bench.protocol.config import EPISODES_PER_PAIR
from mewa_bench.service.models import REFERENCE_SOURCE, SELF_REPORTED
from mewa_bench.service.settings import HIDDEN_SUFFIX, Settings

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

KIND_ORDER = {AGENT: 0, PRIVILEGED: 1, REFERENCE: 2}


def hidden_boards(settings: Settings) -> tuple[str, ...]:
    """The hidden boards of this server (none when hidden evaluation is off)."""
    if not settings.hidden:
        return ()
    from mewa_bench.service.hidden import HIDDEN_SUITES

    return tuple(HIDDEN_SUITES)


def board_names(settings: Settings) -> list[tuple[str, bool]]:
    """(board, hidden) for every board, public first."""
    return [(name, False) for name in ALL_SUITES] + [(name, True) for name in hidden_boards(settings)]


def hidden_twin(board: str) -> str:
    """narrow-v2-hidden -> narrow-v2."""
    return board.removesuffix(HIDDEN_SUFFIX)


@lru_cache(maxsize=None)
def _public_suite(name: str) -> Suite:
    """A shipped suite, loaded once."""
    return load_suite(name)


@lru_cache(maxsize=None)
def gap_note(name: str) -> str | None:
    """A public board's note on what gap won means on a suite with a small non-adaptive gap, once."""
    from mewa_bench.leaderboard.algorithm_tables import gap_note as note_of

    return note_of(_public_suite(name))


def _hidden_suite(settings: Settings, board: str) -> Suite | None:
    """A hidden board's suite if it was generated already (the API never generates one)."""
    path = settings.data_dir / "hidden" / f"{board}.json"
    return _load_cached(path, path.stat().st_mtime_ns) if path.exists() else None


@lru_cache(maxsize=16)
def _load_cached(path: Path, mtime: int) -> Suite:
    """A hidden suite file, loaded again only when it changes."""
    return load_suite(path)


def board(session: Session, settings: Settings, name: str) -> dict[str, Any] | None:
    """A board as JSON (None: no such board)."""
    from sqlalchemy import select

    from mewa_bench.service.models import BoardEntry, Submission

    boards = dict(board_names(settings))
    if name not in boards:
        return None
    hidden = boards[name]
    suite = _hidden_suite(settings, name) if hidden else _public_suite(name)
    found = session.execute(select(BoardEntry, Submission.token_id).join(Submission,
                                                                         Submission.id == BoardEntry.submission_id)
                            .where(BoardEntry.board == name)
                            .order_by(BoardEntry.mean.desc(), BoardEntry.agent_name, BoardEntry.id)).all()
    entries = [e for e, _ in found]
    submitters = {e.id: token_id for e, token_id in found}
    def ranked(e: BoardEntry) -> bool:
        """Privileged runs never rank; self-reported ones only where the server says so."""
        return not e.privileged and (e.source != SELF_REPORTED or settings.rank_uploads)

    ranks = iter(competition_ranks([e.mean for e in entries if ranked(e)]))
    checkpoints: dict[str, Row] = {}  # run name (as the algorithms table's runs are named) -> row
    extras: dict[int, dict[str, Any]] = {}
    for e in entries:
        row = Row(**json.loads(e.row))
        row = dataclasses.replace(row, rank=next(ranks) if ranked(e) else None,
                                  file=f"/api/submissions/{e.submission_id}")
        if suite is not None:
            row = with_gap_won(row, float(suite.summary["score"]["best_fixed"]))
        checkpoints[run_label(e)] = row
        scores = json.loads(e.scores)
        extras[id(row)] = {"source": e.source, "submission_id": e.submission_id,
                           "curve": [p["mean"] for p in scores["curve"]], "curve_low": [p["low"] for p in scores["curve"]],
                           "curve_high": [p["high"] for p in scores["curve"]]}
    # What only a public board shows. A hidden board has no algorithms table (its fractions of (run, pair) cells would
    # tell the hidden suite's number of pairs) and no suite name or hash. (Its figure draws the algorithms all the
    # same: curves and run-level bands are means over pairs, no fractions.)
    public = None if hidden else suite
    grouped = None if public is None else grouped_runs(public, entries, submitters, settings.rank_uploads)
    algorithm_rows = () if grouped is None else grouped.rows
    family = None
    shown = list(checkpoints.values())
    if suite is not None:
        judged = judge_board(shown, algorithm_rows, checkpoints, pairs=len(suite.pairs))
        shown, algorithm_rows, family = list(judged.rows), judged.algorithms, judged.family
    rows: list[dict[str, Any]] = [{**dataclasses.asdict(row), **extras[id(before)]}
                                  for row, before in zip(shown, checkpoints.values())]
    references = reference_rows(suite) if suite is not None else []
    for r in references:
        rows.append({**dataclasses.asdict(r), "source": REFERENCE_SOURCE, "submission_id": None, "curve": [r.mean] * EPISODES_PER_PAIR,
                     "curve_low": None, "curve_high": None})  # fixed policies: a flat curve
    rows.sort(key=lambda r: (-r["mean"], KIND_ORDER[r["kind"]], r["name"]))
    algorithms = [] if grouped is None else grouped.table(algorithm_rows)
    several = sum(not a.within_run and a.mean.low is not None for a in algorithm_rows)
    return {"board": name, "hidden": hidden, "public_twin": hidden_twin(name) if hidden else None,
            "suite": None if public is None else {"name": public.name, "sha256": public.sha256},
            "seeds": len(settings.seeds_for(name)), "entries": len(entries), "uploads_ranked": settings.rank_uploads,
            "algorithms": algorithms, "gap_note": None if public is None else gap_note(name),
            "verdicts": None if family is None else {
                "procedure": PROCEDURE, "family_wise_error": family.alpha, "tests": family.size,
                "caption": family_caption(family, len(shown), several)},
            "rows": rows}


def run_label(entry: Any) -> str:
    """A board entry's run name in the board's algorithms table (unique: the entry's id)."""
    return f"{entry.agent_name} #{entry.id}"


@dataclass(frozen=True)
class BoardAlgorithms:
    """A board's runs grouped by (submitter, algorithm name): the statistics over runs (`comparison`, best mean
    first, what the board's figure draws), the table's rows in the same order, and each algorithm's source."""

    comparison: AlgorithmComparison
    rows: tuple[AlgorithmRow, ...]
    sources: dict[str, str]

    def table(self, rows: Iterable[AlgorithmRow] | None = None) -> list[dict[str, Any]]:
        """The algorithms table as JSON rows (`rows`: these rows, judged, instead of the grouping's)."""
        return [{**dataclasses.asdict(row), "source": self.sources[row.algorithm]}
                for row in (self.rows if rows is None else rows)]


_GROUPED: dict[tuple, BoardAlgorithms | None] = {}  # board entries never change once written: groups by their ids
_GROUPED_KEPT = 32
_GROUPED_LOCK = threading.Lock()  # the pages' and the figures' request threads share the cache
_NOT_CACHED = object()  # None is a cached value: a board without runs


def _grouped_key(suite: Suite, ids: Iterable[int], rank_uploads: bool) -> tuple:
    """The cache key of a board's groups: its suite, its entries (written once, never changed) and the ranking rule."""
    return suite.sha256, tuple(sorted(ids)), rank_uploads


def _cached(key: tuple) -> Any:
    """A board's cached groups (None: it has no run), or _NOT_CACHED."""
    with _GROUPED_LOCK:
        return _GROUPED.get(key, _NOT_CACHED)


def grouped_runs(suite: Suite, entries: list[Any], submitters: dict[int, int],
                 rank_uploads: bool) -> BoardAlgorithms | None:
    """A board's runs grouped by (submitter, algorithm name), with statistics over the runs (None: no run).

    `entries` are board entries (or rows with their `id`, `agent_name`, `algorithm`, `source`, `privileged` and
    `pair_curves`), `submitters` maps an entry's id to its submitter's token. A submitter's runs under one
    algorithm name share an algorithm (another submitter's runs under the same name never join it: the algorithm is
    then named with its submitter's number); a self-reported run never joins a server-evaluated one. A run without
    per-pair curves (stored before the service kept them) is left out. Cached by the entries' ids."""
    key = _grouped_key(suite, (e.id for e in entries), rank_uploads)
    cached = _cached(key)
    if cached is not _NOT_CACHED:
        return cached
    grouped = _group(suite, entries, submitters, rank_uploads)
    with _GROUPED_LOCK:
        while len(_GROUPED) >= _GROUPED_KEPT:
            _GROUPED.pop(next(iter(_GROUPED)))
        _GROUPED[key] = grouped
    return grouped


def board_algorithms(session: Session, settings: Settings, name: str, suite: Suite) -> BoardAlgorithms | None:
    """`grouped_runs` of a board, read from the database: its entries' ids first (the cache's key; the board's
    page has usually grouped them just before), then, only if they are not cached, the columns the grouping reads
    (the stored rows, small, for one-run algorithms' within-run intervals; never the stored scores)."""
    from sqlalchemy import select

    from mewa_bench.service.models import BoardEntry, Submission

    ids = session.scalars(select(BoardEntry.id).where(BoardEntry.board == name)).all()
    cached = _cached(_grouped_key(suite, ids, settings.rank_uploads))
    if cached is not _NOT_CACHED:
        return cached
    found = session.execute(select(BoardEntry.id, BoardEntry.agent_name, BoardEntry.algorithm, BoardEntry.source,
                                   BoardEntry.privileged, BoardEntry.pair_curves, BoardEntry.row, Submission.token_id)
                            .join(Submission, Submission.id == BoardEntry.submission_id)
                            .where(BoardEntry.board == name)).all()
    return grouped_runs(suite, found, {e.id: e.token_id for e in found}, settings.rank_uploads)


def _group(suite: Suite, entries: list[Any], submitters: dict[int, int],
           rank_uploads: bool) -> BoardAlgorithms | None:
    """grouped_runs, computed."""
    from mewa_bench.leaderboard.algorithms import rows_of
    from mewa_bench.protocol.aggregate import Run, aggregate
    from mewa_bench.protocol.scoring import reference_line_cells

    kept = [e for e in entries if e.pair_curves is not None]
    owners: dict[str, set[int]] = {}
    for e in kept:
        owners.setdefault(e.algorithm or e.agent_name, set()).add(submitters[e.id])
    runs, privileged, unranked, sources = [], set(), set(), {}
    for e in kept:
        name = e.algorithm or e.agent_name
        if len(owners[name]) > 1:
            name = f"{name} [submitter {submitters[e.id]}]"
        if e.source == SELF_REPORTED:
            name = f"{name} (self-reported)"
            if not rank_uploads:
                unranked.add(name)
        if e.privileged:
            privileged.add(name)
        sources[name] = e.source
        runs.append(Run(name=run_label(e), algorithm=name, curves=np.array(json.loads(e.pair_curves))))
    if not runs:
        return None
    comparison = aggregate(runs, reference_line_cells(suite), pairwise=False)
    best_fixed = float(suite.summary["score"]["best_fixed"])
    checkpoints = {run_label(e): with_gap_won(Row(**json.loads(e.row)), best_fixed) for e in kept}
    return BoardAlgorithms(comparison, rows_of(best_fixed, comparison, privileged, frozenset(unranked), checkpoints,
                                               len(suite.pairs)), sources)


def boards_index(session: Session, settings: Settings) -> list[dict[str, Any]]:
    """Every board with its number of entries and its best mean score."""
    from sqlalchemy import func, select

    from mewa_bench.service.models import BoardEntry

    counts = {b: (n, best) for b, n, best in session.execute(
        select(BoardEntry.board, func.count(), func.max(BoardEntry.mean)).group_by(BoardEntry.board))}
    return [{"board": name, "hidden": hidden, "entries": counts.get(name, (0, None))[0],
             "best_mean": counts.get(name, (0, None))[1], "url": f"/api/leaderboards/{name}",
             "html": f"/leaderboards/{name}"} for name, hidden in board_names(settings)]
