"""Where an env's (task, worker) pairs come from: a fixed pair, or meta-train sampling.

Shared by the scalar and the batched env, so both sample pairs the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from mewa_bench.game.distributions import sample_meta_train_workers
from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.task import Task, Worker

SCALAR_PAIR_BATCH = 64  # pairs a scalar env (or a lane seeded on its own) samples per call of the sampler


def as_task(value: Task | dict[str, Any]) -> Task:
    """Accept a Task or its JSON dict."""
    if isinstance(value, Task):
        return value
    if isinstance(value, dict):
        return Task.from_dict(value)
    raise ValueError(f"expected a Task or a task dict, got {type(value).__name__}")


def default_tasks() -> tuple[Task, ...]:
    """The canonical narrow task of the shipped `narrow-v1` suite."""
    from mewa_bench.design.suites import load_suite  # the suite file is the one source of the task

    return tuple(load_suite("narrow-v1").tasks)


@dataclass
class PairSource:
    """Tasks to play and, if `worker` is None, meta-train workers sampled at every reset.

    Workers come from each task's own meta-train distribution: the v2 mixture for a task of a v2
    suite (it carries a `worker_distribution`), else the paper's box sampler (SPEC section 3).
    """

    tasks: tuple[Task, ...]
    worker: Worker | None = None
    include_centre: bool = False
    worker_set: tuple[Worker, ...] = ()  # if given: each pair's worker drawn uniformly from these

    @classmethod
    def build(cls, task: Task | dict | None, worker: Sequence[float] | Worker | None,
              tasks: Sequence[Task | dict] | None, include_centre: bool = False,
              workers: Sequence[Sequence[float]] | None = None) -> "PairSource":
        """Validate the env's construction arguments and build the source."""
        if workers is not None:
            if worker is not None or task is None:
                raise ValueError("`workers` (a set to draw from) needs one `task` and no fixed `worker`")
            worker_set = tuple(Worker.of(w) for w in workers)
            if not worker_set:
                raise ValueError("`workers` is empty")
            source = cls((as_task(task),), None, include_centre, worker_set)
            for w in worker_set:
                w.check_fits(source.tasks[0])
            return source
        if task is not None and tasks is not None:
            raise ValueError("give either `task` or `tasks`, not both")
        if tasks is not None:
            chosen = tuple(as_task(t) for t in tasks)
            if not chosen:
                raise ValueError("`tasks` is empty")
        elif task is not None:
            chosen = (as_task(task),)
        else:
            if worker is not None:
                raise ValueError("a `worker` needs a `task`")
            chosen = default_tasks()
        w = Worker.of(worker) if worker is not None else None
        if w is not None and len(chosen) > 1:
            raise ValueError("a fixed `worker` needs a single `task`")
        source = cls(chosen, w, include_centre)
        source.check()
        return source

    def check(self) -> None:
        """Raise ValueError if a worker cannot be had for every task."""
        for t in self.tasks:
            if self.worker is not None:
                self.worker.check_fits(t)
            elif t.average_worker is None or t.sigma is None:
                raise ValueError(f"task {t.name or list(t.order)} has no worker distribution "
                                 "(average_worker, sigma): pass an explicit `worker`")

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """n pairs: task indices int [n] and workers float64 [n, 4] (unused components 0)."""
        if len(self.tasks) == 1:
            task_idx = np.zeros(n, dtype=np.int64)
        else:
            task_idx = rng.integers(0, len(self.tasks), size=n)
        workers = np.zeros((n, NUM_COLORS))
        if self.worker_set:
            chosen = np.array([w.w for w in self.worker_set])[rng.integers(0, len(self.worker_set), size=n)]
            workers[:, : chosen.shape[1]] = chosen
            return task_idx, workers
        if self.worker is not None:
            workers[:, : len(self.worker.w)] = self.worker.w
            return task_idx, workers
        for i, task in enumerate(self.tasks):
            rows = np.flatnonzero(task_idx == i)
            if len(rows):
                workers[rows, : task.N] = sample_meta_train_workers(task, rng, len(rows), self.include_centre)
        return task_idx, workers
