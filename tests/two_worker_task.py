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


def judge(checkpoint: Path, seeds: int, vector_agent: Callable) -> tuple[np.ndarray, np.ndarray, float]:
    """Per seed the adaptability (s_10 - s_1) and the mean score over the 10 episodes (both means over the two workers,
    on the max-expected scale) of `vector_agent(checkpoint, num_lanes)` under the protocol's loop, every (worker, seed)
    on a lane of its own, and the best fixed t-optimal policy's mean score."""
    from mewa_bench.design.exact import expected_returns
    from mewa_bench.design.policies import toptimal_family

    task = load_suite("narrow-v1").tasks[0]
    values = expected_returns(task, toptimal_family(task.N), TWO_WORKERS)  # [P, W]
    best = values.max(axis=0)
    returns = play_lanes(vector_agent(checkpoint, len(TWO_WORKERS) * seeds), task, TWO_WORKERS, seeds)
    scores = (returns / best[:, None, None]).mean(axis=0)  # [seed, episode]
    return scores[:, -1] - scores[:, 0], scores.mean(axis=1), float((values / best).mean(axis=1).max())


def play_lanes(agent, task, workers: np.ndarray, seeds: int) -> np.ndarray:
    """Normalised returns [worker, seed, episode] of a vector agent, unit (worker i, seed s) on lane i * seeds + s with
    the protocol's calls and the luck keys of `test_rl2.play_pairs` (lanes are independent: the same returns as the
    one-lane agent played unit by unit)."""
    from mewa_bench.envs import MewaEnv
    from mewa_bench.protocol.agent import Transitions

    units = [(i, s) for i in range(len(workers)) for s in range(seeds)]
    lanes = np.arange(len(units))
    envs = [MewaEnv(task=task) for _ in units]
    out = np.zeros((len(workers), seeds, 10))
    agent.reset_task(lanes, np.array([s for _, s in units], dtype=np.int64))
    for k in range(10):
        obs = np.stack([env.reset(options={"task": task, "worker": tuple(workers[i]), "luck_key": (i * 1000 + s) * 10 + k})[0]
                        for env, (i, s) in zip(envs, units)])
        playing = lanes
        while len(playing):
            actions = np.asarray(agent.act(playing, obs[playing]), dtype=np.int64)
            steps = [envs[lane].step(int(a)) for lane, a in zip(playing, actions)]
            following = np.stack([step[0] for step in steps])
            terminated = np.array([step[2] for step in steps])
            truncated = np.array([step[3] for step in steps])
            agent.observe(playing, Transitions(obs[playing], actions, np.array([step[1] for step in steps], dtype=np.float64),
                                               following, terminated, truncated))
            obs[playing] = following
            done = terminated | truncated
            for lane, step in zip(playing[done], (st for st, d in zip(steps, done) if d)):
                out[units[lane][0], units[lane][1], k] = step[4]["normalised_return"]
            if done.any():
                agent.end_episode(playing[done])
            playing = playing[~done]
    return out


def assert_adapts_and_beats_the_best_fixed_policy(adaptability: np.ndarray, score: np.ndarray, best_fixed: float) -> None:
    """Both 95% intervals over seeds above 0: s_10 - s_1, and the mean score minus the best fixed policy's."""
    half = 1.96 * adaptability.std(ddof=1) / np.sqrt(len(adaptability))
    assert adaptability.mean() - half > 0, (adaptability.mean(), half)
    gain = score - best_fixed
    assert gain.mean() - 1.96 * gain.std(ddof=1) / np.sqrt(len(gain)) > 0, gain.mean()
