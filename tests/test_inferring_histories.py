"""The task-inferring learner: told neither task nor worker, it samples both from an exact joint posterior."""

from __future__ import annotations

import numpy as np

from mewa_bench.agents.task_inference import starts_like
from mewa_bench.datasets.expert_rollout import play_agent
from mewa_bench.datasets.inferring_histories import TaskInferringLearner, play_inferring_histories
from mewa_bench.datasets.learning_histories import learner_model
from mewa_bench.datasets.training_workers import sample_training_pairs
from mewa_bench.design.policies import toptimal_family
from mewa_bench.design.suites import load_suite
from mewa_bench.game.normalise import normalised_return
from mewa_bench.game.rules import initial_state, observation
from mewa_bench.game.table import transition_table

WIDE = load_suite("wide-v2")
LOOK_ALIKE = (0, 4)  # wide-v2 tasks with the same first observation


def meta_train_workers(task: int, n: int, seed: int) -> np.ndarray:
    """n meta-train workers of a wide-v2 task."""
    idx, workers = sample_training_pairs(WIDE.tasks, np.random.default_rng(seed), 40 * n)
    return workers[np.flatnonzero(idx == task)[:n]]


def test_look_alike_tasks_get_the_same_actions_until_what_is_seen_differs():
    a, b = (WIDE.tasks[i] for i in LOOK_ALIKE)
    assert np.array_equal(observation(a, initial_state(a)), observation(b, initial_state(b)))
    workers = meta_train_workers(0, 12, 1)
    keys = np.random.default_rng(2).integers(0, 2**62, (len(workers), 1)).astype(np.uint64)
    seeds = np.arange(len(workers))
    played = [play_inferring_histories(WIDE.tasks, np.full(len(workers), i), workers, keys, seeds) for i in LOOK_ALIKE]
    shared_steps = []
    for m in range(len(workers)):
        runs = [(p, transition_table(WIDE.tasks[i]), np.flatnonzero(p.episode == m)) for p, i in zip(played, LOOK_ALIKE)]
        (pa, ta, fa), (pb, tb, fb) = runs
        seen_same = 0  # steps whose whole history (observations, actions, rewards) is the same in both tasks
        while (seen_same < min(len(fa), len(fb))
               and np.array_equal(ta.obs[pa.state[fa[seen_same]]], tb.obs[pb.state[fb[seen_same]]])):
            assert pa.action[fa[seen_same]] == pb.action[fb[seen_same]], (m, seen_same)
            if pa.reward[fa[seen_same]] != pb.reward[fb[seen_same]]:
                break
            seen_same += 1
        assert seen_same < min(len(fa), len(fb))  # the tasks do come apart in every episode
        shared_steps.append(seen_same)
    assert np.mean(shared_steps) > 3  # and the learner acts on what it sees for several steps first


def test_the_learner_finds_its_task_in_one_episode_and_improves():
    task = 0
    workers = meta_train_workers(task, 24, 3)
    keys = np.random.default_rng(4).integers(0, 2**62, (len(workers), 10)).astype(np.uint64)
    learner = TaskInferringLearner(WIDE.tasks)
    found = 0
    for m, worker in enumerate(workers):  # one episode each, then ask which tasks it still considers
        play_agent(learner, WIDE.tasks, np.array([task]), worker[None], keys[m : m + 1, :1], np.array([m]))
        assert task in learner.candidates
        found += learner.candidates == [task]
    assert found >= 0.9 * len(workers)
    played = play_inferring_histories(WIDE.tasks, np.full(len(workers), task), workers, keys, np.arange(len(workers)))
    score = normalised_return(WIDE.tasks[task], played.returns).reshape(len(workers), 10)
    assert score[:, 5:].mean() > score[:, 0].mean() + 0.03


def test_a_choice_is_a_draw_from_the_exact_joint_posterior():
    learner = TaskInferringLearner(WIDE.tasks)
    learner.candidates = [5, 6, 8]  # three look-alike N = 4 tasks
    rng = np.random.default_rng(7)
    for c in learner.candidates:
        learner.trials[c] = rng.integers(0, 6, 4).astype(float)
        learner.mistakes[c] = np.minimum(rng.integers(0, 3, 4), learner.trials[c]).astype(float)
    assert all(starts_like(WIDE.tasks[c], observation(WIDE.tasks[5], initial_state(WIDE.tasks[5])))
               for c in learner.candidates)
    exact: dict[tuple[int, str], float] = {}
    for c in learner.candidates:  # independent: the product of Bernoulli likelihoods at each grid worker
        model = learner_model(WIDE.tasks[c])
        like = np.prod(model.grid ** learner.mistakes[c] * (1 - model.grid) ** (learner.trials[c] - learner.mistakes[c]),
                       axis=1) / len(model.grid)
        for g, p in enumerate(like):
            key = (c, toptimal_family(4)[model.best_policy[g]].name)
            exact[key] = exact.get(key, 0.0) + p
    total = sum(exact.values())
    draws = 4_000
    counts: dict[tuple[int, str], int] = {}
    learner.rng = np.random.default_rng(8)
    for _ in range(draws):
        learner.choose()
        key = (learner.acting_for, learner.policy.name)
        counts[key] = counts.get(key, 0) + 1
    assert set(counts) <= set(exact)
    for key, p in exact.items():
        p /= total
        assert abs(counts.get(key, 0) / draws - p) < 4 * np.sqrt(p * (1 - p) / draws) + 1e-3, key
