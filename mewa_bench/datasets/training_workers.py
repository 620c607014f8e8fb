"""Workers of training data: drawn from a suite's meta-train distribution, never a curated (test) worker.

A worker is refused if it equals (to 1e-9) a curated worker of any shipped suite, or if it lies where
the suite's meta-test workers may lie: for a v1 task in the task's meta-test region, for a v2 task
closer than its `grid_clearance` to the 0.05 grid every meta-test worker sits on (hidden suites
included). The meta-train samplers never draw such workers; the check makes it a guarantee.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from mewa_bench.datasets.training_keys import TrainingDataError
from mewa_bench.game.distributions import clear_of_grid, in_test_region, meta_train_spec, sample_meta_train_workers
from mewa_bench.game.task import Task

CURATED_TOLERANCE = 1e-9


class CuratedWorker(NamedTuple):
    """Where a curated worker comes from."""

    suite: str
    pair: int
    worker: tuple[float, ...]


@lru_cache(maxsize=1)
def curated_workers() -> tuple[CuratedWorker, ...]:
    """Every curated (test) worker of every shipped suite."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite

    out = []
    for name in ALL_SUITES:
        for pair in load_suite(name).pairs:
            out.append(CuratedWorker(name, pair.index, tuple(pair.worker.w)))
    return tuple(out)


def sample_training_pairs(tasks: tuple[Task, ...], rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n (task index, meta-train worker) pairs: a task uniformly, then a worker from its meta-train sampler.

    Returns task indices int64 [n] and workers float64 [n, 4] (unused components 0)."""
    task_idx = rng.integers(0, len(tasks), size=n) if len(tasks) > 1 else np.zeros(n, dtype=np.int64)
    workers = np.zeros((n, 4))
    for i, task in enumerate(tasks):
        rows = np.flatnonzero(task_idx == i)
        if len(rows):
            workers[rows, : task.N] = sample_meta_train_workers(task, rng, len(rows))
    return task_idx.astype(np.int64), workers


def check_training_workers(task: Task, workers: np.ndarray, where: str) -> float:
    """Raise TrainingDataError if a worker is curated or could be a meta-test worker; returns the smallest
    L-inf distance to a curated worker of the same size (inf if there is none)."""
    arr = np.asarray(workers, dtype=np.float64)[:, : task.N]
    curated = [c for c in curated_workers() if len(c.worker) == task.N]
    nearest = np.inf
    if curated and len(arr):
        points = np.array([c.worker for c in curated])
        dist = np.abs(arr[:, None, :] - points[None, :, :]).max(axis=2)  # [W, C]
        row, col = np.unravel_index(int(np.argmin(dist)), dist.shape)
        nearest = float(dist[row, col])
        if nearest <= CURATED_TOLERANCE:
            c = curated[col]
            raise TrainingDataError(f"{where}: worker {arr[row].tolist()} (row {row}) is the curated test worker of "
                                    f"{c.suite} pair {c.pair}; training data must never use a test worker")
    spec = meta_train_spec(task)
    if spec is None:
        bad = np.flatnonzero(np.atleast_1d(in_test_region(task, arr)))
        reason = "lies in the task's meta-test region"
    else:
        bad = np.flatnonzero(~clear_of_grid(arr, float(spec["grid_clearance"]), float(spec["grid_step"])))
        reason = f"lies within {spec['grid_clearance']} of the {spec['grid_step']} grid of meta-test workers"
    if bad.size:
        raise TrainingDataError(f"{where}: worker {arr[bad[0]].tolist()} (row {int(bad[0])}) {reason}; "
                                "training workers come from the meta-train distribution only")
    return nearest
