"""Short random-action rollouts of the default env (the smoke test behind `mewa-bench rollout`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterator

import gymnasium as gym
import numpy as np

from mewa_bench.envs.mewa_env import render_text


@dataclass(frozen=True)
class EpisodeSummary:
    """One finished episode."""

    index: int
    worker: tuple[float, ...]
    steps: int
    episode_return: float
    normalised_return: float


def random_rollouts(episodes: int, seed: int, render: Callable[[str], None] | None = None,
                    **env_kwargs) -> Iterator[EpisodeSummary]:
    """Play `episodes` episodes of `mewa/MEWA-v0` with uniformly random actions, seeded."""
    env = gym.make("mewa/MEWA-v0", **env_kwargs)
    rng = np.random.default_rng(seed)
    for index in range(episodes):
        obs, _ = env.reset(seed=seed if index == 0 else None)
        worker = env.unwrapped.worker.w
        steps, done, info = 0, False, {}
        while not done:
            obs, _, terminated, truncated, info = env.step(int(rng.integers(0, 4)))
            steps += 1
            done = terminated or truncated
            if render is not None:
                render(render_text(env.unwrapped.task, obs, steps))
        yield EpisodeSummary(index, worker, steps, info["episode_return"], info["normalised_return"])
    env.close()
