"""The adaptation-curve figure of a suite's leaderboard (like the paper's Fig. 4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mewa_bench.leaderboard.board import Board, reference_rows
from mewa_bench.protocol.config import EPISODES_PER_PAIR
from mewa_bench.reports.figures import save_png

# One (grey, dash pattern) per reference line, so that five lines stay apart in print and on screen.
_REFERENCE_STYLES = (("#000000", (0, (6, 2))), ("#555555", (0, (1, 1.5))), ("#333333", (0, (6, 2, 1, 2))),
                     ("#777777", (0, (3, 3))), ("#999999", (0, (6, 2, 1, 2, 1, 2))))


def plot_curves(board: Board, path: Path) -> None:
    """s_1..s_K per agent with its 95% CI band, the suite's reference lines dashed; written atomically."""
    # Figure + Agg canvas directly: no pyplot, so the caller's global backend and state are untouched.
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    colors = colormaps["tab10"].colors
    for i, entry in enumerate(board.entries):
        curve = entry.scores.curve
        x = np.arange(1, len(curve) + 1)
        color = colors[i % len(colors)]
        name = entry.agent.replace("$", r"\$")  # an agent's name is text, never mathtext
        label = f"{name} (privileged)" if entry.privileged else name
        ax.plot(x, [e.mean for e in curve], marker="o", ms=3, color=color, ls=":" if entry.privileged else "-",
                label=label)
        ax.fill_between(x, [e.low for e in curve], [e.high for e in curve], color=color, alpha=0.2, lw=0)
    k = len(board.entries[0].scores.curve) if board.entries else EPISODES_PER_PAIR
    for row, (grey, dashes) in zip(reference_rows(board.suite), _REFERENCE_STYLES):
        ax.axhline(row.mean, ls=dashes, lw=1.2, color=grey, label=f"{row.name} (exact)")
    ax.set_xticks(range(1, k + 1))
    ax.set_xlim(0.7, k + 0.3)
    ax.set_xlabel("episode k with the same hidden worker")
    ax.set_ylabel("score s_k (1 = max expected)")
    ax.set_title(f"{board.suite.name}: adaptation curves (mean and 95% CI over pairs x seeds)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    save_png(fig, path)
