"""The adaptation-curve figure of a board, drawn by the static leaderboard's `curves_figure`: one panel per algorithm.

The algorithms are the board's algorithms table's (`boards.board_algorithms`: a submitter's runs
under one algorithm name, from their stored per-pair curves), each drawn with its 95% CI band over
training runs, as the static boards draw theirs; at most PLOTTED of them, best mean first, so that
the legend stays readable. A hidden board's figure draws its algorithms too, though its page has no
algorithms table: that table's cells include fractions of (run, pair) cells, which would tell the
hidden suite's number of pairs; the figure's curves and bands are means over pairs and over resampled
runs, which do not. Entries are written once and never change, so a figure is cached under the
board's entry count and newest entry id.
"""

from __future__ import annotations

import dataclasses
import tempfile
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from mewa_bench.design.suites import Suite, load_suite
from mewa_bench.leaderboard.board import Board
from mewa_bench.service import boards
from mewa_bench.service.settings import Settings

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from sqlalchemy.orm import Session

PLOTTED = 10  # algorithms drawn, best mean first
CACHED_FIGURES = 32


@dataclass(frozen=True)
class BoardVersion:
    """What a board's figure depends on: which entries it has (they never change once written)."""

    database: str  # which server's board (several apps may share a process)
    board: str
    entries: int
    newest: int | None
    suite_sha256: str


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


def figure_board(suite: Suite, grouped: boards.BoardAlgorithms | None, plotted: int = PLOTTED) -> Board:
    """The leaderboard `Board` the static boards' figure is drawn from: the `plotted` best algorithms of the
    board's algorithms table (none: only the suite's reference lines)."""
    if grouped is None:
        return Board(suite, (), (), None)  # no entry with per-pair curves: nothing to draw but the reference lines
    shown = grouped.comparison.algorithms[:plotted]
    return Board(suite, (), (), dataclasses.replace(grouped.comparison, algorithms=shown), grouped.rows[:plotted])


def board_curves(session: Session, settings: Settings, board: str, suite: Suite) -> Figure:
    """The figure of a board, as a matplotlib Figure (`curves_figure` of the static boards)."""
    from mewa_bench.leaderboard.plot import curves_figure

    return curves_figure(figure_board(suite, boards.board_algorithms(session, settings, board, suite)))


def render_png(figure: Figure) -> bytes:
    """A figure as the PNG bytes `mewa-bench leaderboard` would write."""
    from mewa_bench.reports.figures import save_png

    with tempfile.TemporaryDirectory(prefix="mewa-curves-") as tmp:
        path = Path(tmp) / "curves.png"
        save_png(figure, path)
        return path.read_bytes()


def drawn_from(grouped: boards.BoardAlgorithms | None) -> tuple[int, int]:
    """(algorithms, runs) a board's figure is drawn from (before the PLOTTED best are kept)."""
    if grouped is None:
        return 0, 0
    return len(grouped.comparison.algorithms), sum(len(a.runs) for a in grouped.comparison.algorithms)


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


def board_figure(session: Session, settings: Settings, key: BoardVersion, suite: Suite) -> bytes:
    """The PNG of a board at version `key` (drawn once per version)."""
    png = FIGURES.get(key)
    if png is None:
        png = render_png(board_curves(session, settings, key.board, suite))
        FIGURES.put(key, png)
    return png
