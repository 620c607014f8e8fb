"""The adaptation-curve figure of a suite's leaderboard (like the paper's Fig. 4): one line per algorithm."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mewa_bench.leaderboard.board import Board, reference_rows
from mewa_bench.protocol.config import EPISODES_PER_PAIR
from mewa_bench.protocol.scoring import Estimate
from mewa_bench.reports.figures import save_png

# One (grey, dash pattern) per reference line, so that five lines stay apart in print and on screen.
_REFERENCE_STYLES = (("#000000", (0, (6, 2))), ("#555555", (0, (1, 1.5))), ("#333333", (0, (6, 2, 1, 2))),
                     ("#777777", (0, (3, 3))), ("#999999", (0, (6, 2, 1, 2, 1, 2))))


_LINE_STYLES = ("-", "--", "-.", ":")


def _palette() -> tuple[tuple[float, float, float], ...]:
    """18 distinct colours: tab10's, then tab20's lighter shades of them, without the greys (the reference lines')."""
    from matplotlib import colormaps

    tab20 = colormaps["tab20"].colors
    return tuple(c for i, c in enumerate(tab20[0::2] + tab20[1::2]) if i % 10 != 7)


def line_style(i: int) -> tuple[tuple[float, float, float], str]:
    """(colour, line style) of the i-th algorithm: the first 18 solid, a colour each; then the colours again, dashed,
    and so on: no two of the first 72 share both."""
    palette = _palette()
    return palette[i % len(palette)], _LINE_STYLES[(i // len(palette)) % len(_LINE_STYLES)]


def curves_figure(board: Board):
    """s_1..s_K per algorithm with its 95% CI band over training runs, the suite's reference lines dashed."""
    # Figure + Agg canvas directly: no pyplot, so the caller's global backend and state are untouched.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    lines = _lines(board)
    for i, (label, curve) in enumerate(lines):
        x = np.arange(1, len(curve) + 1)
        color, style = line_style(i)
        ax.plot(x, [e.mean for e in curve], marker="o", ms=3, color=color, ls=style, label=label)
        if curve[0].low is not None:
            ax.fill_between(x, [e.low for e in curve], [e.high for e in curve], color=color, alpha=0.15, lw=0)
    k = len(lines[0][1]) if lines else EPISODES_PER_PAIR
    for row, (grey, dashes) in zip(reference_rows(board.suite), _REFERENCE_STYLES):
        ax.axhline(row.mean, ls=dashes, lw=1.2, color=grey, label=f"{row.name} (exact)")
    ax.set_xticks(range(1, k + 1))
    ax.set_xlim(0.7, k + 0.3)
    ax.set_xlabel("episode k with the same hidden worker")
    ax.set_ylabel("score s_k (1 = max expected)")
    what = ("per algorithm (mean, 95% CI over training runs)" if board.comparison is not None
            else "(mean and 95% CI over pairs x seeds)")
    ax.set_title(f"{board.suite.name}: adaptation curves {what}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return fig


def _lines(board: Board) -> list[tuple[str, tuple[Estimate, ...]]]:
    """(legend label, curve) per algorithm, or per entry for a board without algorithms (CIs of checkpoints)."""
    privileged = {r.algorithm for r in board.algorithms if r.privileged} | {e.agent for e in board.entries
                                                                           if e.privileged and board.comparison is None}
    if board.comparison is not None:
        named = [(a.algorithm, f" ({len(a.runs)} run{'s' if len(a.runs) > 1 else ''})", a.curve)
                 for a in board.comparison.algorithms]
    else:
        named = [(e.agent, "", e.scores.curve) for e in board.entries]
    return [(name.replace("$", r"\$") + runs + (" (privileged)" if name in privileged else ""), curve)
            for name, runs, curve in named]  # a name is text, never mathtext


def plot_curves(board: Board, path: Path) -> None:
    """The board's curve figure, written atomically as PNG."""
    save_png(curves_figure(board), path)
