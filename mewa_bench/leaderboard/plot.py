"""The adaptation-curve figure of a suite's leaderboard (like the paper's Fig. 4): one line per algorithm."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mewa_bench.leaderboard.board import Board, reference_rows
from mewa_bench.protocol.config import EPISODES_PER_PAIR
from mewa_bench.reports.figures import save_png

# One (grey, dash pattern) per reference line, so that five lines stay apart in print and on screen.
_REFERENCE_STYLES = (("#000000", (0, (6, 2))), ("#555555", (0, (1, 1.5))), ("#333333", (0, (6, 2, 1, 2))),
                     ("#777777", (0, (3, 3))), ("#999999", (0, (6, 2, 1, 2, 1, 2))))


_LINE_STYLES = ("-", "--", "-.", ":")


def line_style(i: int) -> tuple[int, str]:
    """(tab10 colour index, line style) of the i-th algorithm: no two of the first 40 share both."""
    return i % 10, _LINE_STYLES[(i // 10) % len(_LINE_STYLES)]


def curves_figure(board: Board):
    """s_1..s_K per algorithm with its 95% CI band over training runs, the suite's reference lines dashed."""
    # Figure + Agg canvas directly: no pyplot, so the caller's global backend and state are untouched.
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    colors = colormaps["tab10"].colors
    algorithms = board.comparison.algorithms if board.comparison is not None else ()
    privileged = {r.algorithm for r in board.algorithms if r.privileged}
    for i, algo in enumerate(algorithms):
        x = np.arange(1, len(algo.curve) + 1)
        color, style = line_style(i)
        name = algo.algorithm.replace("$", r"\$")  # a name is text, never mathtext
        label = f"{name} ({len(algo.runs)} run{'s' if len(algo.runs) > 1 else ''})"
        label += " (privileged)" if algo.algorithm in privileged else ""
        ax.plot(x, [e.mean for e in algo.curve], marker="o", ms=3, color=colors[color], ls=style, label=label)
        if algo.curve[0].low is not None:
            ax.fill_between(x, [e.low for e in algo.curve], [e.high for e in algo.curve], color=colors[color],
                            alpha=0.15, lw=0)
    k = len(algorithms[0].curve) if algorithms else EPISODES_PER_PAIR
    for row, (grey, dashes) in zip(reference_rows(board.suite), _REFERENCE_STYLES):
        ax.axhline(row.mean, ls=dashes, lw=1.2, color=grey, label=f"{row.name} (exact)")
    ax.set_xticks(range(1, k + 1))
    ax.set_xlim(0.7, k + 0.3)
    ax.set_xlabel("episode k with the same hidden worker")
    ax.set_ylabel("score s_k (1 = max expected)")
    ax.set_title(f"{board.suite.name}: adaptation curves per algorithm (mean, 95% CI over training runs)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return fig


def plot_curves(board: Board, path: Path) -> None:
    """The board's curve figure, written atomically as PNG."""
    save_png(curves_figure(board), path)
