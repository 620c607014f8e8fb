"""The generator-wide task-inferring learner: it keeps exactly the tasks that the plain task-inferring learner keeps
when that one is told every renaming of the structures, with the same worker posterior, and it does not know a
task's sub-goal order before playing."""

from __future__ import annotations

import numpy as np
import pytest

import mewa_bench.datasets.inferring_histories as inferring_histories
from mewa_bench.datasets.generated_tasks import task_structures
from mewa_bench.datasets.generator_histories import RENAMINGS, GeneratorInferringLearner
from mewa_bench.datasets.inferring_histories import TaskInferringLearner
from mewa_bench.datasets.pool_models import every_model
from mewa_bench.design.suites import load_suite
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.game.relabel import relabelled_task
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition


def game_key(task: Task) -> tuple:
    """What tells tasks apart in play."""
    return task.colors, task.order, task.K, task.M, task.worker_blocks


@pytest.fixture(scope="module")
def structures() -> tuple[Task, ...]:
    """A few of wide-v2's structures with N = 3 and N = 4 (K = 3, so M = 3)."""
    some = task_structures(load_suite("wide-v2"), ks=(3,))
    return tuple(t for t in some if t.N == 3) + tuple(t for t in some if t.N == 4)[:2]


def log_marginals(learner: TaskInferringLearner) -> dict[tuple, float]:
    """The plain learner's posterior probability of each candidate task (its joint summed over the grid)."""
    out = {}
    for c in learner.candidates:
        m = every_model(learner.tasks[c])
        joint = (learner.mistakes[c] @ m.log_w.T + (learner.trials[c] - learner.mistakes[c]) @ m.log_not_w.T
                 - np.log(len(m.grid)))
        out[game_key(learner.tasks[c])] = float(np.logaddexp.reduce(joint))
    return out


def normalised(log_weights: dict[tuple, float]) -> dict[tuple, float]:
    top = max(log_weights.values())
    total = sum(np.exp(v - top) for v in log_weights.values())
    return {k: float(np.exp(v - top) / total) for k, v in log_weights.items()}


def test_it_keeps_what_the_plain_learner_told_every_renaming_keeps(structures, monkeypatch) -> None:
    renamed = [relabelled_task(t, p) for p in RENAMINGS for t in structures]
    structure_of = {game_key(relabelled_task(t, p)): t for p in RENAMINGS for t in structures}
    # a renamed task's model is its structure's (the rules do not care which colour is which)
    monkeypatch.setattr(inferring_histories, "learner_model", lambda task: every_model(structure_of[game_key(task)]))
    generator, plain = GeneratorInferringLearner(structures), TaskInferringLearner(renamed)
    rng = np.random.default_rng(3)
    for pair in range(4):
        task = renamed[int(rng.integers(len(renamed)))]
        worker = np.sort(rng.uniform(0.0, 0.6, task.N))[::-1]
        env = MewaEnv(task=task, worker=list(worker))
        generator.reset_task(pair)
        plain.reset_task(pair)
        for _ in range(3):
            obs, _ = env.reset(options={"task": task, "worker": list(worker), "luck_key": int(rng.integers(1 << 40))})
            done = False
            while not done:
                action = generator.act(obs)
                plain.act(obs)  # the plain learner samples for itself; both see the generator learner's play
                nxt, reward, terminated, truncated, _ = env.step(action)
                step = Transition(obs, action, float(reward), nxt, bool(terminated), bool(truncated))
                generator.observe(step)
                plain.observe(step)
                kept = sorted(game_key(t) for t in generator.candidates())
                assert kept == sorted(game_key(plain.tasks[c]) for c in plain.candidates)
                assert game_key(task) in kept
                obs, done = nxt, terminated or truncated
            generator.end_episode()
            plain.end_episode()
            expected = normalised(log_marginals(plain))
            got = normalised(dict(zip(map(game_key, generator.candidates()), generator.candidate_log_weights())))
            assert got.keys() == expected.keys()
            assert all(got[k] == pytest.approx(expected[k], rel=1e-9, abs=1e-12) for k in got)


def test_before_playing_it_hands_each_colour_first_equally_often(structures) -> None:
    task = relabelled_task(next(t for t in structures if t.N == 4), (2, 0, 3, 1))
    learner = GeneratorInferringLearner(structures)
    env = MewaEnv(task=task, worker=[0.1] * 4)
    obs, _ = env.reset(options={"task": task, "worker": [0.1] * 4, "luck_key": 1})
    first = []
    for seed in range(800):
        learner.reset_task(seed)
        first.append(learner.act(obs))
    counts = np.bincount(first, minlength=4) / len(first)
    assert np.all(np.abs(counts - 0.25) < 0.06), counts  # 4 standard errors; told the structures, it always hands order[0]


def test_a_task_the_generator_cannot_draw_is_a_clear_error(structures) -> None:
    narrow = load_suite("narrow-v2").tasks[0]
    learner = GeneratorInferringLearner(structures)
    env = MewaEnv(task=narrow, worker=[0.1] * narrow.N)
    obs, _ = env.reset(options={"task": narrow, "worker": [0.1] * narrow.N, "luck_key": 1})
    with pytest.raises(ValueError, match="no renaming of the learner's task structures explains an episode's first"):
        learner.act(obs)
