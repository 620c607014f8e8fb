"""The two-worker task the offline baselines' learning tests share: narrow-v1's canonical task with two opposite
workers (greedy building is perfect for (0,1,1,1) and fails for (1,1,1,0), parallel building the reverse), the
posterior-sampling learners' histories on it, and the judge of a checkpoint under the protocol's loop."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from mewa_bench.design.suites import load_suite

TWO_WORKERS = np.array([[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]])


def learner_histories(histories: int, episodes: int, seed: int):
    """Posterior-sampling learners (the learning-histories tier's behaviour) on the two workers in turn, `episodes`
    episodes each, as `SequenceFrames` (optimal_action: 3 on every frame, a label these tests never learn)."""
    from mewa_bench.datasets.learning_histories import play_histories
    from mewa_bench.datasets.meta_episodes import frames_in_sequences
    from mewa_bench.game.table import transition_table

    task = load_suite("narrow-v1").tasks[0]
    rng = np.random.default_rng(seed)
    workers = TWO_WORKERS[np.arange(histories) % 2]
    keys = rng.integers(0, 1 << 62, size=(histories, episodes), dtype=np.uint64)
    played, _ = play_histories(task, workers, keys, rng)
    return frames_in_sequences(np.arange(len(played.t)), transition_table(task).obs[played.state], played.action,
                               played.reward, np.full(len(played.t), 3), played.episode // episodes,
                               played.episode % episodes)


def judge(checkpoint: Path, seeds: int, agent: Callable) -> tuple[np.ndarray, np.ndarray, float]:
    """Per seed the adaptability (s_10 - s_1) and the mean score over the 10 episodes (both means over the two workers,
    on the max-expected scale) of `agent(checkpoint, seed)` (a one-lane agent) under the protocol's loop, and the best
    fixed t-optimal policy's mean score."""
    from test_rl2 import play_pairs

    from mewa_bench.design.exact import expected_returns
    from mewa_bench.design.policies import toptimal_family

    task = load_suite("narrow-v1").tasks[0]
    values = expected_returns(task, toptimal_family(task.N), TWO_WORKERS)  # [P, W]
    best = values.max(axis=0)
    returns = play_pairs(checkpoint, task, [tuple(w) for w in TWO_WORKERS], seeds=seeds, agent=agent)
    scores = (returns / best[:, None, None]).mean(axis=0)  # [seed, episode]
    return scores[:, -1] - scores[:, 0], scores.mean(axis=1), float((values / best).mean(axis=1).max())


def assert_adapts_and_beats_the_best_fixed_policy(adaptability: np.ndarray, score: np.ndarray, best_fixed: float) -> None:
    """Both 95% intervals over seeds above 0: s_10 - s_1, and the mean score minus the best fixed policy's."""
    half = 1.96 * adaptability.std(ddof=1) / np.sqrt(len(adaptability))
    assert adaptability.mean() - half > 0, (adaptability.mean(), half)
    gain = score - best_fixed
    assert gain.mean() - 1.96 * gain.std(ddof=1) / np.sqrt(len(gain)) > 0, gain.mean()
