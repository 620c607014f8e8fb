"""Training curves of learned agents: episode-1 and episode-10 normalised returns against env steps."""

from __future__ import annotations

import csv
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
    """Trailing moving average over up to `window` points (the first points average what there is)."""
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v - (values[i - window] if i >= window else 0.0)
        out.append(total / min(i + 1, window))
    return out


def plot_training_curves(runs: Mapping[str, Path], png: Path, title: str, window: int = 20) -> Path:
    """One PNG: per run, the meta-train episode-1 (dashed) and episode-10 (solid) normalised returns,
    smoothed over `window` updates; the gap between them is what the agent learns within a pair."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.0), dpi=100)
    for i, (label, path) in enumerate(sorted(runs.items())):
        m = read_metrics(path)
        steps = [s / 1e6 for s in m["env_steps"]]
        colour = f"C{i}"
        ax.plot(steps, smoothed(m[LAST], window), color=colour, label=f"{label}: episode 10")
        ax.plot(steps, smoothed(m[FIRST], window), color=colour, linestyle="--", label=f"{label}: episode 1")
    ax.set_xlabel("env steps (millions)")
    ax.set_ylabel("normalised return (meta-train workers)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    save_png(fig, png)
    plt.close(fig)
    return png
