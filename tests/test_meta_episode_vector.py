"""The batched meta-episode env against the scalar env fed the same pairs, luck keys and actions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from mewa_bench.envs import MetaEpisodeVectorEnv, MewaEnv
from mewa_bench.game.task import Task

EPISODES = 3


def expected_extension(action: int | None, reward: float, new_episode: bool) -> np.ndarray:
    """The six floats after the 18 env floats, written out from the documented layout."""
    out = np.zeros(6, dtype=np.float32)
    if action is not None:
        out[action] = 1.0
    out[4], out[5] = reward, float(new_episode)
    return out


def test_meta_episodes_match_the_scalar_env_step_by_step(canonical_task: Task) -> None:
    n = 6
    vec = MetaEpisodeVectorEnv(num_envs=n, episodes=EPISODES, task=canonical_task)  # meta-train workers
    obs, info = vec.reset(seed=3)
    assert obs.shape == (n, 24) and vec.observation_space.contains(obs)
    scalars = [MewaEnv(task=canonical_task) for _ in range(n)]

    def start_scalar(i: int) -> np.ndarray:
        """Reset scalar env i on sub-env i's current pair and luck key."""
        options = {"task": canonical_task, "worker": tuple(vec.workers[i]), "luck_key": int(vec.luck_keys[i])}
        return scalars[i].reset(options=options)[0]

    expected_obs = [start_scalar(i) for i in range(n)]
    for i in range(n):
        np.testing.assert_array_equal(obs[i, :18], expected_obs[i])
        np.testing.assert_array_equal(obs[i, 18:], expected_extension(None, 0.0, False))
    rng = np.random.default_rng(0)
    inner = np.zeros(n, dtype=int)
    trials_ended = np.zeros(n, dtype=int)
    pending_reset = np.zeros(n, dtype=bool)
    workers = vec.workers
    for _ in range(2500):
        actions = rng.integers(0, 4, size=n)
        obs, reward, terminated, truncated, info = vec.step(actions)
        for i in range(n):
            if pending_reset[i]:  # NEXT_STEP autoreset: a new meta-episode on a new pair, action ignored
                assert reward[i] == 0.0 and not (terminated[i] or truncated[i])
                assert not np.array_equal(vec.workers[i], workers[i])
                workers[i] = vec.workers[i]
                np.testing.assert_array_equal(obs[i, :18], start_scalar(i))
                np.testing.assert_array_equal(obs[i, 18:], expected_extension(None, 0.0, False))
                pending_reset[i], inner[i] = False, 0
                continue
            s_obs, s_reward, s_term, s_trunc, s_info = scalars[i].step(int(actions[i]))
            assert reward[i] == pytest.approx(s_reward, abs=0.0) and info["episode_in_trial"][i] == inner[i]
            ended = s_term or s_trunc
            assert bool(info["inner_done"][i]) == ended
            if not ended:
                np.testing.assert_array_equal(obs[i, :18], s_obs)
                np.testing.assert_array_equal(obs[i, 18:], expected_extension(int(actions[i]), s_reward, False))
                continue
            assert info["normalised_return"][i] == pytest.approx(s_info["normalised_return"], abs=1e-12)
            np.testing.assert_array_equal(vec.workers[i], workers[i])  # the pair is kept for the whole trial
            if inner[i] + 1 < EPISODES:  # the next inner episode starts at once, flagged
                inner[i] += 1
                assert not (terminated[i] or truncated[i])
                np.testing.assert_array_equal(obs[i, :18], start_scalar(i))
                np.testing.assert_array_equal(obs[i, 18:], expected_extension(int(actions[i]), s_reward, True))
            else:  # the meta-episode ends as its last inner episode did; no new-episode flag
                assert (terminated[i], truncated[i]) == (s_term, s_trunc)
                np.testing.assert_array_equal(obs[i, :18], s_obs)
                np.testing.assert_array_equal(obs[i, 18:], expected_extension(int(actions[i]), s_reward, False))
                pending_reset[i], trials_ended[i] = True, trials_ended[i] + 1
    assert trials_ended.min() >= 2  # every sub-env went through whole meta-episodes and autoresets


def test_make_vec_and_determinism(canonical_task: Task) -> None:
    def run(seed: int) -> list[np.ndarray]:
        env = gym.make_vec("mewa/MEWA-Meta-v0", num_envs=16, vectorization_mode="vector_entry_point", episodes=2)
        out = [env.reset(seed=seed)[0]]
        rng = np.random.default_rng(1)
        for _ in range(300):
            out.append(env.step(rng.integers(0, 4, size=16))[0])
        return out

    first, again, other = run(7), run(7), run(8)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert not all(np.array_equal(a, b) for a, b in zip(first, other))
    scalar = gym.make("mewa/MEWA-Meta-v0", episodes=2)
    assert scalar.observation_space == MetaEpisodeVectorEnv(num_envs=1).single_observation_space


def test_bad_episode_count_is_rejected() -> None:
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        MetaEpisodeVectorEnv(num_envs=2, episodes=0)
