"""The Gymnasium env: reference traces, seeding, mistake statistics, API conformance."""

from __future__ import annotations


import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import mewa_bench  # noqa: F401 - registers mewa/MEWA-v0
from mewa_bench.envs import MetaEpisode, MewaEnv
from mewa_bench.game import Task
from mewa_bench.game.distributions import in_test_region, is_non_increasing, sample_train_workers


def replay_env(env: gym.Env, trace: dict) -> None:
    task = Task.from_dict(trace["task"])
    obs, info = env.reset(seed=0, options={"task": task, "worker": trace["worker"]})
    assert info["progress"] == 0
    for i, step in enumerate(trace["steps"]):
        obs, reward, terminated, truncated, info = env.step(step["action"])
        where = f"{trace['kind']} worker {trace['worker']} step {i}"
        np.testing.assert_array_equal(obs, np.float32(step["obs"]), err_msg=where)
        assert reward == step["reward"], where
        assert (terminated or truncated) == step["done"], where
        assert info["progress"] == step["progress"], where
    assert terminated or truncated


def test_gym_make_replays_every_reference_trace(traces: list[dict], canonical_task: Task) -> None:
    env = gym.make("mewa/MEWA-v0", task=canonical_task)
    for trace in traces:
        replay_env(env, trace)


def test_check_env(canonical_task: Task) -> None:
    check_env(MewaEnv(task=canonical_task), skip_render_check=True)
    check_env(MewaEnv(task=canonical_task, worker=(0.5, 0.4, 0.3, 0.2)), skip_render_check=True)


def play(env: gym.Env, seed: int, n_episodes: int = 5) -> list[tuple]:
    """Seeded rollouts with a seeded action sequence; the full trajectory as a list."""
    rng = np.random.default_rng(123)
    out = []
    env.reset(seed=seed)
    for _ in range(n_episodes):
        done = False
        out.append(("worker", env.unwrapped.worker.w))
        while not done:
            obs, r, term, trunc, info = env.step(int(rng.integers(0, 4)))
            out.append((obs.tobytes(), r, term, trunc, info["events"]))
            done = term or trunc
        env.reset()
    return out


def test_same_seed_same_trajectory_different_seed_different(canonical_task: Task) -> None:
    a = play(MewaEnv(task=canonical_task, events=True), seed=7)
    b = play(MewaEnv(task=canonical_task, events=True), seed=7)
    c = play(MewaEnv(task=canonical_task, events=True), seed=8)
    assert a == b
    assert a != c
    fixed = dict(task=canonical_task, worker=(0.5, 0.5, 0.5, 0.5), events=True)
    assert play(MewaEnv(**fixed), seed=1) == play(MewaEnv(**fixed), seed=1)
    assert play(MewaEnv(**fixed), seed=1) != play(MewaEnv(**fixed), seed=2)


def test_mistake_frequencies_match_the_worker(canonical_task: Task) -> None:
    """Per mistake type x, the fraction of second blocks that got a mistake is w_x (binomial z-test)."""
    w = (0.7, 0.45, 0.3, 0.15)
    env = MewaEnv(task=canonical_task, worker=w, events=True)
    env.reset(seed=2024)
    rng = np.random.default_rng(5)
    trials, hits = np.zeros(4), np.zeros(4)
    for _ in range(60_000):
        s = env._s
        a = int(rng.integers(0, 4))
        x = env._fast.mistake_type[s][a]
        _, _, term, trunc, info = env.step(a)
        if x >= 0:
            trials[x] += 1
            hits[x] += any(e.kind == "mistake" for e in info["events"])
        if term or trunc:
            env.reset()
    assert (trials > 500).all(), trials
    freq = hits / trials
    z = (freq - np.array(w)) / np.sqrt(np.array(w) * (1 - np.array(w)) / trials)
    assert (np.abs(z) < 4.0).all(), (freq, z)


def test_invalid_actions(canonical_task: Task) -> None:
    env = MewaEnv(task=canonical_task, worker=(0, 0, 0, 0))
    env.reset(seed=0)
    for bad in (4, -1, 1.5, "red"):
        with pytest.raises((ValueError, TypeError)):
            env.step(bad)


def test_unused_colour_costs_a_step(small_task: Task) -> None:
    env = MewaEnv(task=small_task, worker=(0, 0, 0))
    obs0, _ = env.reset(seed=0)
    obs, reward, term, trunc, _ = env.step(1)  # blue is not in this task
    np.testing.assert_array_equal(obs, obs0)
    assert reward == small_task.rewards[0] and not term and not trunc


def test_truncation_after_T_steps(small_task: Task) -> None:
    env = MewaEnv(task=small_task, worker=(0, 0, 0))
    env.reset(seed=0)
    for t in range(small_task.T):
        _, _, term, trunc, info = env.step(1)
        assert not term
        assert trunc == (t == small_task.T - 1)
    assert info["normalised_return"] == 0.0
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_bad_construction_arguments(canonical_task: Task, small_task: Task) -> None:
    with pytest.raises(ValueError, match="N = 4"):
        MewaEnv(task=canonical_task, worker=(0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match="worker distribution"):
        MewaEnv(task=Task.from_dict({k: v for k, v in canonical_task.to_dict().items()
                                     if k not in ("average_worker", "sigma")}))
    with pytest.raises(ValueError, match="not both"):
        MewaEnv(task=canonical_task, tasks=[small_task])
    with pytest.raises(ValueError, match="unknown reset option"):
        MewaEnv(task=canonical_task).reset(options={"wroker": (0, 0, 0, 0)})


def test_sampled_workers_are_meta_train(canonical_task: Task, small_task: Task) -> None:
    env = MewaEnv(tasks=[canonical_task, small_task])
    env.reset(seed=3)
    seen = set()
    for _ in range(200):
        w = np.array(env.worker.w)
        assert is_non_increasing(w) and not in_test_region(env.task, w)
        seen.add(env.task.name)
        env.reset()
    assert seen == {"canonical", "n3"}


def test_train_and_test_regions_never_overlap(canonical_task: Task) -> None:
    rng = np.random.default_rng(0)
    for centre in (False, True):
        w = sample_train_workers(canonical_task, rng, 20_000, include_centre=centre)
        assert not in_test_region(canonical_task, w).any()
        assert is_non_increasing(w).all()
        avg, sig = np.array(canonical_task.average_worker), np.array(canonical_task.sigma)
        assert (np.abs(w - avg) < 2 * sig + 1e-12).all()
    # A worker exactly 2 sigma away is a test worker, never a train one.
    edge = np.array(canonical_task.average_worker) + np.array([2 * canonical_task.sigma[0], 0, 0, 0])
    assert in_test_region(canonical_task, edge)


def test_info_reports_events_and_normalised_return(canonical_task: Task) -> None:
    env = MewaEnv(task=canonical_task, worker=(0, 0, 0, 0), events=True)
    env.reset(seed=0)
    kinds = []
    for c in canonical_task.order:
        for _ in range(canonical_task.M):
            _, _, term, _, info = env.step(c)
            kinds += [e.kind for e in info["events"]]
    assert term and info["normalised_return"] == pytest.approx(1.0)
    assert kinds.count("structure_completed") == 4 and kinds.count("subgoal_reached") == 4


def test_meta_episode_wrapper(canonical_task: Task) -> None:
    env = MetaEpisode(MewaEnv(task=canonical_task), episodes=3)
    obs, info = env.reset(seed=11)
    assert obs.shape == (24,) and env.observation_space.contains(obs)
    worker = env.unwrapped.worker.w
    inner_ends, steps, rng = 0, 0, np.random.default_rng(0)
    done = False
    while not done:
        a = int(rng.integers(0, 4))
        obs, r, term, trunc, info = env.step(a)
        steps += 1
        assert env.unwrapped.worker.w == worker  # the pair is kept across inner episodes
        assert obs[18 + a] == 1.0 and obs[22] == np.float32(r)
        if info["inner_done"]:
            inner_ends += 1
            assert obs[23] == (1.0 if inner_ends < 3 else 0.0)  # no new episode after the last one
            if inner_ends < 3:  # next inner episode starts from the initial state
                np.testing.assert_array_equal(obs[:18], env.unwrapped._fast.obs[0])
        else:
            assert obs[23] == 0.0
        done = term or trunc
    assert inner_ends == 3 and info["episode_in_trial"] == 2
    env.reset()
    assert env.unwrapped.worker.w != worker  # a new meta-episode draws a new pair
    check_env(MetaEpisode(MewaEnv(task=canonical_task), episodes=2), skip_render_check=True)
