"""The adaptation-curve figure of a board, drawn by the static leaderboard's `plot_curves`.

The board's entries come from the database (their scores as the workers stored them, the very
dict `mewa-bench evaluate` writes), best first; at most PLOTTED of them are drawn so that the
legend stays readable. Entries are written once and never change, so a figure is cached under
the board's entry count and newest entry id.
"""

from __future__ import annotations

import json
import tempfile
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mewa_bench.design.suites import Suite, load_suite
from mewa_bench.leaderboard.board import Board
from mewa_bench.leaderboard.validate import Entry
from mewa_bench.protocol.scoring import Comparison, Estimate, Scores
from mewa_bench.service.settings import Settings

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

PLOTTED = 10  # agents drawn, best mean first
CACHED_FIGURES = 32


@dataclass(frozen=True)
class BoardVersion:
    """What a board's figure depends on: which entries it has (they never change once written)."""

    database: str  # which server's board (several apps may share a process)
    board: str
    entries: int
    newest: int | None
    suite_sha256: str


def _estimate(d: dict[str, Any]) -> Estimate:
    return Estimate(d["mean"], d["low"], d["high"])


def scores_from_dict(d: dict[str, Any]) -> Scores:
    """`Scores` back from its `to_dict()` form (the stored scores of a board entry)."""
    comparisons = {k: Comparison(_estimate(c["difference"]), None if c.get("probability_of_improvement") is None
                                 else _estimate(c["probability_of_improvement"]))
                   for k, c in d["comparisons"].items()}
    return Scores(curve=tuple(_estimate(p) for p in d["curve"]), mean=_estimate(d["mean"]), iqm=_estimate(d["iqm"]),
                  adaptability=_estimate(d["adaptability"]), skill=_estimate(d["skill"]), raw=d["raw"],
                  comparisons=comparisons, units=d["units"], control_variates=d["control_variates"])


def plain_label(name: str) -> str:
    """A submitted name as literal text in a matplotlib legend ("$...$" would otherwise be parsed as math)."""
    return name.replace("$", r"\$")


def board_suite(settings: Settings, board: str, hidden: bool) -> Suite | None:
    """The suite a board is played on; a hidden board's only once the server has generated it."""
    if not hidden:
        return load_suite(board)
    path = settings.data_dir / "hidden" / f"{board}.json"
    return load_suite(path) if path.exists() else None


def board_version(session: Session, settings: Settings, board: str, suite: Suite) -> BoardVersion:
    """The cache key of a board's figure."""
    from sqlalchemy import func, select

    from mewa_bench.service.models import BoardEntry

    count, newest = session.execute(select(func.count(), func.max(BoardEntry.id))
                                    .where(BoardEntry.board == board)).one()
    return BoardVersion(settings.database_url, board, count, newest, suite.sha256)


def board_entries(session: Session, board: str, limit: int) -> list[Entry]:
    """The board's best `limit` entries as leaderboard entries, ordered as the board ranks them."""
    from sqlalchemy import select

    from mewa_bench.service.models import BoardEntry, Job

    rows = session.execute(select(BoardEntry, Job.seeds).join(Job, Job.id == BoardEntry.job_id)
                           .where(BoardEntry.board == board)
                           .order_by(BoardEntry.mean.desc(), BoardEntry.agent_name, BoardEntry.id).limit(limit)).all()
    entries = []
    for e, seeds in rows:
        row = json.loads(e.row)
        entries.append(Entry(suite=board, agent=plain_label(e.agent_name),
                             path=Path(str(e.submission_id)) / "results.json", privileged=e.privileged,
                             scores=scores_from_dict(json.loads(e.scores)), seeds=tuple(json.loads(seeds)),
                             date=row.get("date", ""), package_version=row.get("package_version", ""),
                             agent_sha256=e.agent_sha256))
    return entries


def render_png(suite: Suite, entries: list[Entry]) -> bytes:
    """The figure `mewa-bench leaderboard` draws, for these entries, as PNG bytes."""
    from mewa_bench.leaderboard.plot import plot_curves

    with tempfile.TemporaryDirectory(prefix="mewa-curves-") as tmp:
        path = Path(tmp) / "curves.png"
        plot_curves(Board(suite, tuple(entries), ()), path)
        return path.read_bytes()


class FigureCache:
    """The latest figures by board version (a small LRU shared by the server's request threads)."""

    def __init__(self, size: int = CACHED_FIGURES) -> None:
        self.size, self._figures, self._lock = size, OrderedDict(), threading.Lock()

    def get(self, key: BoardVersion) -> bytes | None:
        with self._lock:
            if key in self._figures:
                self._figures.move_to_end(key)
            return self._figures.get(key)

    def put(self, key: BoardVersion, png: bytes) -> None:
        with self._lock:
            self._figures[key] = png
            self._figures.move_to_end(key)
            while len(self._figures) > self.size:
                self._figures.popitem(last=False)


FIGURES = FigureCache()


def board_figure(session: Session, key: BoardVersion, suite: Suite) -> bytes:
    """The PNG of a board at version `key` (drawn once per version)."""
    png = FIGURES.get(key)
    if png is None:
        png = render_png(suite, board_entries(session, key.board, PLOTTED))
        FIGURES.put(key, png)
    return png
