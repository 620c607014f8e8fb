"""Worker distributions of a task (SPEC section 3): meta-train sampling and the meta-test region.

A task's worker distribution is centred on its `average_worker` with widths `sigma`. Meta-train
workers lie strictly inside the 2-sigma box around the average; meta-test workers lie outside it
(at least one component at >= 2 sigma). Both sides use `in_test_region`, rounded to 12 decimals,
so that the two sets can never overlap.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from mewa_bench.game.task import Task

ROUND = 12  # decimals for region comparisons (keeps grid points like 0.05 k exact)
_MAX_TRIES = 10_000


def _distribution(task: Task) -> tuple[np.ndarray, np.ndarray]:
    if task.average_worker is None or task.sigma is None:
        raise ValueError(f"task {task.name or task.order!r} has no worker distribution (average_worker, sigma)")
    return np.asarray(task.average_worker, dtype=np.float64), np.asarray(task.sigma, dtype=np.float64)


def in_test_region(task: Task, w: Sequence[float] | np.ndarray) -> np.ndarray | bool:
    """True where a worker (or each row of an [n, N] array) has a component with |w_x - avg_x| >= 2 sigma_x."""
    avg, sigma = _distribution(task)
    arr = np.asarray(w, dtype=np.float64)
    dev = np.round(np.abs(arr - avg), ROUND) >= np.round(2.0 * sigma, ROUND)
    out = dev.any(axis=-1)
    return bool(out) if out.ndim == 0 else out


def is_non_increasing(w: np.ndarray) -> np.ndarray | bool:
    """True where w_0 >= w_1 >= ... (for a worker or each row of an array)."""
    arr = np.asarray(w, dtype=np.float64)
    out = (np.diff(arr, axis=-1) <= 0).all(axis=-1)
    return bool(out) if out.ndim == 0 else out


def sample_train_workers(task: Task, rng: np.random.Generator, n: int, include_centre: bool = False) -> np.ndarray:
    """n meta-train workers, float64 [n, N].

    Each component is drawn uniformly from (avg - 2 sigma, avg - 0.5 sigma) or
    (avg + 0.5 sigma, avg + 2 sigma), picked with equal probability (with `include_centre`, the centre
    band (avg - 0.5 sigma, avg + 0.5 sigma) is a third equally likely choice), then clipped to [0, 1].
    Draws that are not non-increasing, or that clipping pushed onto the test region, are redrawn.
    """
    avg, sigma = _distribution(task)
    bands = np.array([[-2.0, -0.5], [0.5, 2.0]] + ([[-0.5, 0.5]] if include_centre else []))
    out = np.empty((n, task.N))
    filled = 0
    for _ in range(_MAX_TRIES):
        if filled == n:
            return out
        m = max(2 * (n - filled), 16)
        pick = rng.integers(0, len(bands), size=(m, task.N))
        u = rng.random((m, task.N))
        lo, hi = bands[pick, 0], bands[pick, 1]
        w = np.clip(avg + sigma * (lo + (hi - lo) * u), 0.0, 1.0)
        ok = is_non_increasing(w) & ~in_test_region(task, w)
        good = w[ok][: n - filled]
        out[filled : filled + len(good)] = good
        filled += len(good)
    raise ValueError(f"could not sample non-increasing meta-train workers for task {task.name!r} "
                     f"(average {task.average_worker}, sigma {task.sigma})")


def sample_train_worker(task: Task, rng: np.random.Generator, include_centre: bool = False) -> tuple[float, ...]:
    """One meta-train worker (see `sample_train_workers`)."""
    return tuple(float(v) for v in sample_train_workers(task, rng, 1, include_centre)[0])


def worker_grid(n: int, step: float = 0.05) -> np.ndarray:
    """All non-increasing workers on the `step` grid over [0, 1]^n, lexicographically sorted, [m, n]."""
    k = int(round(1.0 / step))
    axes = np.meshgrid(*([np.arange(k + 1)] * n), indexing="ij")
    pts = np.stack([a.ravel() for a in axes], axis=1)
    pts = pts[(np.diff(pts, axis=1) <= 0).all(axis=1)]
    return np.round(pts * step, ROUND)


def meta_test_candidates(task: Task, step: float = 0.05) -> np.ndarray:
    """Non-increasing grid workers in the task's meta-test region (SPEC section 4), lexicographic order."""
    grid = worker_grid(task.N, step)
    return grid[in_test_region(task, grid)]
