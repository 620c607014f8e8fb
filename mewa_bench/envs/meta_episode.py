"""Meta-episodes for in-context learners (RL^2, VariBAD): k episodes on one pair as one episode."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mewa_bench.game.palette import NUM_COLORS, OBS_SIZE

META_OBS_SIZE = OBS_SIZE + NUM_COLORS + 2


class MetaEpisode(gym.Wrapper):
    """Play `episodes` consecutive episodes of the same (task, worker) pair as one long episode.

    The observation is extended to float32[24]: the env's 18 floats, then the previous action
    (one-hot, 4), the previous reward and a done flag (1.0 on the first step of every inner episode
    after the first), which is what RL^2 / VariBAD-style agents condition on. Each `reset()` draws a
    new pair from the wrapped `MewaEnv`; the inner episodes replay it with `keep_pair`. The meta-episode
    ends with the last inner episode (terminated or truncated as that one was).
    `info["episode_in_trial"]` counts inner episodes from 0; `info["inner_done"]` marks their ends.
    """

    def __init__(self, env: gym.Env, episodes: int = 10) -> None:
        super().__init__(env)
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        self.episodes = episodes
        low = np.concatenate([np.zeros(OBS_SIZE), np.zeros(NUM_COLORS), [-np.inf], [0.0]]).astype(np.float32)
        high = np.concatenate([np.full(OBS_SIZE, 255.0), np.ones(NUM_COLORS), [0.0], [1.0]]).astype(np.float32)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self._episode = 0

    def _extend(self, obs: np.ndarray, action: int | None, reward: float, done: bool) -> np.ndarray:
        out = np.zeros(META_OBS_SIZE, dtype=np.float32)
        out[:OBS_SIZE] = obs
        if action is not None:
            out[OBS_SIZE + action] = 1.0
        out[-2] = reward
        out[-1] = float(done)
        return out

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start a meta-episode on a new pair (or on the pair fixed by `options`)."""
        obs, info = self.env.reset(seed=seed, options=options)
        self._episode = 0
        return self._extend(obs, None, 0.0, False), {**info, "episode_in_trial": 0}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Step the inner episode; start the next inner episode on the same pair when it ends."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        info = {**info, "episode_in_trial": self._episode, "inner_done": terminated or truncated}
        if not (terminated or truncated):
            return self._extend(obs, int(action), float(reward), False), reward, False, False, info
        self._episode += 1
        if self._episode == self.episodes:
            return self._extend(obs, int(action), float(reward), True), reward, terminated, truncated, info
        obs, _ = self.env.reset(options={"keep_pair": True})
        return self._extend(obs, int(action), float(reward), True), reward, False, False, info
