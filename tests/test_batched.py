"""The batched vector env: reference traces, agreement with the scalar env, autoreset."""

from __future__ import annotations

from collections import defaultdict

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import mewa_bench  # noqa: F401 - registers mewa/MEWA-v0
from mewa_bench.envs import MewaEnv, MewaVectorEnv
from mewa_bench.game import Task


def test_make_vec_replays_every_reference_trace(traces: list[dict], canonical_task: Task) -> None:
    by_worker: dict[tuple, list[dict]] = defaultdict(list)
    for trace in traces:
        by_worker[tuple(trace["worker"])].append(trace)
    for worker, group in by_worker.items():
        env = gym.make_vec("mewa/MEWA-v0", num_envs=len(group), vectorization_mode="vector_entry_point",
                           task=Task.from_dict(group[0]["task"]), worker=worker)
        assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
        env.reset(seed=0)
        length = max(len(t["steps"]) for t in group)
        for i in range(length):
            live = [k for k, t in enumerate(group) if i < len(t["steps"])]
            actions = np.array([t["steps"][i]["action"] if i < len(t["steps"]) else 0 for t in group])
            obs, reward, term, trunc, info = env.step(actions)
            for k in live:
                step, where = group[k]["steps"][i], f"{group[k]['kind']} worker {worker} step {i}"
                np.testing.assert_array_equal(obs[k], np.float32(step["obs"]), err_msg=where)
                assert reward[k] == step["reward"], where
                assert bool(term[k] or trunc[k]) == step["done"], where
                assert info["progress"][k] == step["progress"], where


def episode_stats(returns: list[float], lengths: list[int]) -> tuple[float, float, float]:
    r = np.array(returns)
    return r.mean(), r.std(ddof=1) / np.sqrt(len(r)), float(np.mean(lengths))


def test_batched_and_scalar_agree_in_distribution(canonical_task: Task) -> None:
    """Random actions on one worker: mean normalised return of both envs within 4 standard errors."""
    worker = (0.55, 0.4, 0.3, 0.1)
    n = 4000
    venv = MewaVectorEnv(num_envs=n, task=canonical_task, worker=worker)
    venv.reset(seed=1)
    rng = np.random.default_rng(2)
    finished: list[float] = []
    done_once = np.zeros(n, dtype=bool)
    while not done_once.all():
        _, _, term, trunc, info = venv.step(rng.integers(0, 4, size=n))
        ended = (term | trunc) & ~done_once
        finished += info["normalised_return"][ended].tolist() if ended.any() else []
        done_once |= term | trunc
    env = MewaEnv(task=canonical_task, worker=worker)
    env.reset(seed=3)
    scalar: list[float] = []
    while len(scalar) < n:
        _, _, term, trunc, info = env.step(int(rng.integers(0, 4)))
        if term or trunc:
            scalar.append(info["normalised_return"])
            env.reset()
    a, b = np.array(finished), np.array(scalar)
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    assert abs(a.mean() - b.mean()) < 4 * se, (a.mean(), b.mean(), se)


def test_next_step_autoreset(small_task: Task) -> None:
    env = MewaVectorEnv(num_envs=2, task=small_task, worker=(0, 0, 0))
    first, _ = env.reset(seed=0)
    # sub-env 0 plays the perfect episode; sub-env 1 wastes steps on an unused colour.
    plan = [c for c in small_task.order for _ in range(small_task.M)]
    for i, c in enumerate(plan):
        obs, reward, term, trunc, info = env.step(np.array([c, 1]))
    assert term[0] and not term[1]
    assert info["_normalised_return"][0] and info["normalised_return"][0] == pytest.approx(1.0)
    obs, reward, term, trunc, _ = env.step(np.array([2, 1]))  # ignored for sub-env 0: it resets
    np.testing.assert_array_equal(obs[0], first[0])
    assert reward[0] == 0.0 and not term[0] and reward[1] == small_task.rewards[0]


def test_sampling_tasks_and_workers_is_seeded(canonical_task: Task, small_task: Task) -> None:
    def run(seed: int) -> bytes:
        env = MewaVectorEnv(num_envs=64, tasks=[canonical_task, small_task])
        env.reset(seed=seed)
        rng, out = np.random.default_rng(0), []
        for _ in range(150):
            obs, r, *_ = env.step(rng.integers(0, 4, size=64))
            out.append(obs.tobytes() + r.tobytes() + env.workers.tobytes())
        return b"".join(out)

    assert run(5) == run(5)
    assert run(5) != run(6)
    env = MewaVectorEnv(num_envs=256, tasks=[canonical_task, small_task])
    env.reset(seed=0)
    assert set(env.task_indices.tolist()) == {0, 1}
    assert (env.workers[env.task_indices == 1, 3] == 0).all()  # N = 3: unused component stays 0


def test_invalid_batched_actions(canonical_task: Task) -> None:
    env = MewaVectorEnv(num_envs=3, task=canonical_task, worker=(0, 0, 0, 0))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="sub-env"):
        env.step(np.array([0, 4, 1]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.array([0, 1]))
