"""The task-inferring learner's task models kept for every task it meets, so that a pool of many tasks plays as fast
as a suite of ten.

`inferring_histories.TaskInferringLearner` asks `learning_histories.learner_model` for the model of every candidate
task each time it samples a (task, worker) pair. That function's cache holds 16 tasks, enough for a suite's ten; in
a pool of 200 generated tasks (`generated_tasks`) a first observation leaves 27 candidates on average and up to
53, so every sample would recompute them (about a second each) and a 3 M-frame build would take weeks. Both files
are fixed by the sha256 that every learning-histories and task-inferring build records, so this module plays the
same learner with the same models (the same function, its results kept without bound) instead of changing them.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache

import numpy as np

from mewa_bench.datasets import inferring_histories, learning_histories
from mewa_bench.datasets.chain_rollout import Played
from mewa_bench.game.task import Task

__all__ = ["every_model", "play_pool_histories"]

every_model = cache(learning_histories.learner_model.__wrapped__)  # the learner's model of a task, kept


@contextmanager
def _models_kept() -> Iterator[None]:
    """While inside, the task-inferring learner takes its models from `every_model`."""
    bounded = inferring_histories.learner_model
    inferring_histories.learner_model = every_model
    try:
        yield
    finally:
        inferring_histories.learner_model = bounded


def play_pool_histories(tasks: tuple[Task, ...], task_idx: np.ndarray, workers: np.ndarray, keys: np.ndarray,
                        seeds: np.ndarray) -> Played:
    """`inferring_histories.play_inferring_histories`, each task's model computed once per process."""
    with _models_kept():
        return inferring_histories.play_inferring_histories(tasks, task_idx, workers, keys, seeds)
