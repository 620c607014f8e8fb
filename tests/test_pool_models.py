"""A pool of more look-alike tasks than the learner's model cache holds plays the same histories as the
task-inferring learner, with each task's model computed once."""

from __future__ import annotations

import itertools

import numpy as np

from mewa_bench.datasets import learning_histories
from mewa_bench.datasets.inferring_histories import play_inferring_histories
from mewa_bench.datasets.pool_models import every_model, play_pool_histories
from mewa_bench.design.generate import designed
from mewa_bench.game.task import Task


def test_a_pool_larger_than_the_cache_plays_the_learners_histories_computing_each_model_once() -> None:
    # 18 tasks with the same first observation: every sample of the learner weighs all 18 models
    pool = tuple(designed(Task(colors=(0, 1, 2), order=o, K=3, M=3, rewards=(-1.0, -0.5, -0.2),
                               worker_blocks=(b, 8 - b, 0), name=f"t{i}"), True)[0]
                 for i, (o, b) in enumerate(itertools.product(itertools.permutations(range(3)), (1, 3, 5))))
    workers = np.array([[0.6, 0.3, 0.1, 0.0], [0.2, 0.1, 0.05, 0.0]])
    keys, seeds, tasks = np.arange(6).reshape(2, 3) * 7919 + 11, np.array([1, 2]), np.array([0, 7])
    every_model.cache_clear()
    kept = play_pool_histories(pool, tasks, workers, keys, seeds)
    assert every_model.cache_info().misses == len(pool)
    learning_histories.learner_model.cache_clear()
    bounded = play_inferring_histories(pool, tasks, workers, keys, seeds)
    assert learning_histories.learner_model.cache_info().misses > len(pool)  # what the kept models save
    for name, value in vars(bounded).items():
        assert np.array_equal(np.asarray(getattr(kept, name)), np.asarray(value)), name
    assert len(bounded.returns) == 6
