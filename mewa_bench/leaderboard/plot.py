"""The figures of a suite's leaderboard: adaptation curves as small multiples, and gap won as a forest plot.

Curves: one panel per algorithm (its mean s_1..s_10 over runs x pairs with its 95% band over training
runs) against the suite's exact reference lines, the same in every panel; the best fixed policy drawn
last, in bold black, so that no other line hides it (on narrow-v2 the random task-specific line lies
on it). Each panel's title gives the algorithm's runs and gap won. Gap won: one line per algorithm,
its point and 95% interval, with 0 (the best fixed policy) and 100% (max expected) marked.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

from mewa_bench.leaderboard.board import Board, reference_rows
from mewa_bench.protocol.config import EPISODES_PER_PAIR
from mewa_bench.reports.figures import save_png

# (grey, dash pattern) per reference line but the best fixed policy's (bold black, drawn on top)
_REFERENCE_STYLES = {"known-worker optimum": ("#777777", (0, (1, 1.5))), "max expected": ("#555555", (0, (6, 2))),
                     "random task-specific": ("#999999", (0, (3, 3))), "random": ("#aaaaaa", (0, (6, 2, 1, 2)))}
BEST_FIXED = "best fixed policy"
COLUMNS = 4
TITLE_WIDTH = 40  # characters of a panel title's line: four panels side by side never overlap
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


def _text(name: str) -> str:
    """A name as matplotlib text, never mathtext."""
    return name.replace("$", r"\$")


def panel_titles(board: Board) -> list[str]:
    """Each algorithm panel's title: name, runs (privileged), gap won with its interval."""
    from mewa_bench.leaderboard.algorithm_tables import gap_cell

    titles = []
    for algo, row in zip(board.comparison.algorithms, board.algorithms):
        runs = f"{len(algo.runs)} run{'s' if len(algo.runs) > 1 else ''}"
        within = " within run" if row.within_run else ""
        name = f"{_text(algo.algorithm)} ({runs}){' (privileged)' if row.privileged else ''}"
        # a long name wraps within its panel instead of running into the next panel's title
        titles.append("\n".join(textwrap.wrap(name, TITLE_WIDTH, break_on_hyphens=False))
                      + f"\ngap won {gap_cell(row.gap_won)}{within}")
    return titles


def _draw_references(ax, board: Board, labelled: bool) -> None:
    """The suite's exact reference lines, the best fixed policy's bold black on top."""
    for row in reference_rows(board.suite):
        if row.name == BEST_FIXED:
            ax.axhline(row.mean, color="black", lw=2.2, zorder=5, label=f"{row.name} (exact)" if labelled else None)
        else:
            grey, dashes = _REFERENCE_STYLES[row.name]
            ax.axhline(row.mean, color=grey, ls=dashes, lw=1.1, zorder=1,
                       label=f"{row.name} (exact)" if labelled else None)


def curves_figure(board: Board):
    """Small multiples: a panel per algorithm with its curve and band, the reference lines in each."""
    # Figure + Agg canvas directly: no pyplot, so the caller's global backend and state are untouched.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    algorithms = board.comparison.algorithms if board.comparison is not None else ()
    n = max(len(algorithms), 1)
    cols = min(COLUMNS, n)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(3.4 * max(cols, 2) + 0.4, 2.9 * rows + 1.0), dpi=100)  # one panel: still readable
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False).reshape(-1)
    k = len(algorithms[0].curve) if algorithms else EPISODES_PER_PAIR
    x = np.arange(1, k + 1)
    titles = panel_titles(board) if algorithms else [f"{board.suite.name}: no runs yet"]
    for i, ax in enumerate(axes):
        if i >= n:
            ax.set_visible(False)
            continue
        _draw_references(ax, board, labelled=i == 0)
        if algorithms:
            algo = algorithms[i]
            color, style = line_style(i)
            ax.plot(x, [e.mean for e in algo.curve], marker="o", ms=3, color=color, ls=style, lw=1.8, zorder=6)
            if algo.curve[0].low is not None:
                ax.fill_between(x, [e.low for e in algo.curve], [e.high for e in algo.curve], color=color, alpha=0.25,
                                lw=0, zorder=4)
        ax.set_title(titles[i], fontsize=8.5)
        ax.grid(alpha=0.3)
        ax.set_xticks(range(1, k + 1, 1 if k <= 10 else 2))
        ax.set_xlim(0.7, k + 0.3)
    for ax in axes[(rows - 1) * cols:]:
        ax.set_xlabel("episode k (same hidden worker)", fontsize=8)
    for ax in axes[::cols]:
        ax.set_ylabel("score s_k", fontsize=8)
    handles, labels = axes[0].get_legend_handles_labels()
    what = "mean; band: 95% CI over training runs, none for one run" if algorithms else "exact reference lines"
    fig.suptitle(f"{board.suite.name}: adaptation curves per algorithm ({what})", fontsize=11)
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.0))
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    return fig


def gap_won_figure(board: Board):
    """Forest plot: each algorithm's gap won with its 95% interval, best first; 0 and 100% marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = board.algorithms
    fig = Figure(figsize=(8, 1.2 + 0.42 * max(len(rows), 1)), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for y, row in enumerate(rows):
        e = row.gap_won
        color = line_style(y)[0]
        if e.low is not None:
            ax.plot([100 * e.low, 100 * e.high], [y, y], color=color, lw=2.2, solid_capstyle="butt")
        ax.plot([100 * e.mean], [y], marker="o" if not row.within_run else "D", ms=6, color=color,
                mfc=color if not row.within_run else "white")
    labels = [f"{_text(r.algorithm)} ({r.runs} run{'s' if r.runs > 1 else ''}{', within run' if r.within_run else ''})"
              for r in rows]
    ax.set_yticks(range(len(rows)), labels, fontsize=8)
    ax.set_ylim(len(rows) - 0.5, -0.5) if rows else ax.set_ylim(-0.5, 0.5)
    # labels on either side of their line, so that they never overlap however wide the axis is
    for value, label, side in ((0.0, "0 = best fixed policy", "right"), (100.0, "100% = max expected", "left")):
        ax.axvline(value, color="black", lw=1.2 if value == 0 else 0.8, ls="-" if value == 0 else (0, (4, 2)))
        ax.annotate(label, (value, 1.0), xycoords=("data", "axes fraction"), xytext=(-3 if side == "right" else 3, 2),
                    textcoords="offset points", fontsize=8, va="bottom", ha=side)
    ax.set_xlabel("gap won, % of (1 - best fixed): what only adaptation can win (95% CI)")
    ax.grid(axis="x", alpha=0.3)
    ax.set_title(f"{board.suite.name}: gap won per algorithm (non-adaptive gap "
                 f"{float(board.suite.summary['non_adaptive_gap']):.4f})", fontsize=10, pad=16)
    fig.tight_layout()
    return fig


def plot_curves(board: Board, path: Path) -> None:
    """The board's curves figure, written atomically as PNG."""
    save_png(curves_figure(board), path)


def plot_gap_won(board: Board, path: Path) -> None:
    """The board's gap-won forest plot, written atomically as PNG."""
    save_png(gap_won_figure(board), path)
