"""Training curves of learned agents: episode-1 and episode-10 normalised returns against env steps."""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from pathlib import Path

from mewa_bench.reports.figures import save_png

FIRST, LAST = "episode_1_normalised_return", "episode_10_normalised_return"


def read_metrics(path: Path) -> dict[str, list[float]]:
    """The columns of a training metrics CSV (`mewa_bench.agents.rl2.METRICS`) as floats."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path}: no training metrics rows")
    missing = {"env_steps", FIRST, LAST} - set(rows[0])
    if missing:
        raise ValueError(f"{path}: missing column(s) {sorted(missing)}")
    return {name: [float(r[name]) for r in rows] for name in rows[0]}


def smoothed(values: list[float], window: int) -> list[float]:
    """Trailing mean over up to `window` points, ignoring NaN (an update in which no such episode ended)."""
    out = []
    for i in range(len(values)):
        recent = [v for v in values[max(0, i - window + 1): i + 1] if not math.isnan(v)]
        out.append(sum(recent) / len(recent) if recent else math.nan)
    return out


def plot_training_curves(runs: Mapping[str, Path], png: Path, title: str, window: int = 20) -> Path:
    """One PNG: per run, the meta-train episode-1 (dashed) and episode-10 (solid) normalised returns
    (top) and their difference, what the agent gains within a pair (bottom), smoothed over `window` updates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.0, 5.5), dpi=100, sharex=True,
                                      gridspec_kw={"height_ratios": [2, 1]})
    for i, (label, path) in enumerate(sorted(runs.items())):
        m = read_metrics(path)
        steps = [s / 1e6 for s in m["env_steps"]]
        first, last = smoothed(m[FIRST], window), smoothed(m[LAST], window)
        colour = f"C{i}"
        top.plot(steps, last, color=colour, label=f"{label}: episode 10")
        top.plot(steps, first, color=colour, linestyle="--", alpha=0.7, label=f"{label}: episode 1")
        bottom.plot(steps, [b - a for a, b in zip(first, last)], color=colour, label=label)
    top.set_ylabel("normalised return\n(meta-train workers)")
    top.set_title(title)
    top.legend(fontsize=7, loc="lower right")
    bottom.axhline(0.0, color="grey", linewidth=0.8)
    bottom.set_ylabel("episode 10 - episode 1")
    bottom.set_xlabel("env steps (millions)")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    save_png(fig, png)
    plt.close(fig)
    return png
