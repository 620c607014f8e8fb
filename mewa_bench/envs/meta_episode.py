"""Meta-episodes for in-context learners (RL^2, VariBAD): k episodes on one pair as one episode.

Two forms with one observation layout (`meta_observation`): the `MetaEpisode` wrapper of a scalar
`MewaEnv`, and `MetaEpisodeVectorEnv`, the batched env playing thousands of meta-episodes at numpy
speed (`gym.make_vec("mewa/MEWA-Meta-v0", num_envs=...)`). Fed the same luck keys and actions they
give the same observations and rewards (tested).

Observation, float32[24]: the env's 18 floats; the previous action, one-hot (4); the previous reward;
a new-episode flag, 1.0 on the first observation of every inner episode after the first (never on
the last observation of a meta-episode).
"""

from __future__ import annotations

from typing import Any, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from mewa_bench.envs.batched import MewaVectorEnv
from mewa_bench.game.palette import NUM_COLORS, OBS_SIZE
from mewa_bench.game.task import Task

META_OBS_SIZE = OBS_SIZE + NUM_COLORS + 2
PREVIOUS_ACTION = slice(OBS_SIZE, OBS_SIZE + NUM_COLORS)
PREVIOUS_REWARD = OBS_SIZE + NUM_COLORS
NEW_EPISODE = OBS_SIZE + NUM_COLORS + 1


def meta_observation_space(tasks: Sequence[Task]) -> spaces.Box:
    """Bounds of the 24 floats (the lowest reward of the tasks bounds the previous reward)."""
    lowest = min(t.rewards[0] for t in tasks)
    low = np.concatenate([np.zeros(OBS_SIZE), np.zeros(NUM_COLORS), [lowest], [0.0]]).astype(np.float32)
    high = np.concatenate([np.full(OBS_SIZE, 255.0), np.ones(NUM_COLORS), [0.0], [1.0]]).astype(np.float32)
    return spaces.Box(low, high, dtype=np.float32)


def meta_observation(obs: np.ndarray, action: np.ndarray, reward: np.ndarray, new_episode: np.ndarray) -> np.ndarray:
    """float32 [..., 24] from env observations [..., 18]; `action` -1 means no previous action."""
    obs = np.asarray(obs, dtype=np.float32)
    out = np.zeros(obs.shape[:-1] + (META_OBS_SIZE,), dtype=np.float32)
    out[..., :OBS_SIZE] = obs
    action = np.asarray(action)
    if action.ndim == 0:
        if action >= 0:
            out[OBS_SIZE + int(action)] = 1.0
    else:
        rows = np.flatnonzero(action >= 0)
        out[rows, OBS_SIZE + action[rows]] = 1.0
    out[..., PREVIOUS_REWARD] = reward
    out[..., NEW_EPISODE] = new_episode
    return out


class MetaEpisode(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Play `episodes` consecutive episodes of the same (task, worker) pair as one long episode.

    Each `reset()` draws a new pair from the wrapped `MewaEnv` (or takes the one fixed by `options`);
    the inner episodes replay it with `keep_pair`. The meta-episode ends with the last inner episode
    (terminated or truncated as that one was). `info["episode_in_trial"]` counts inner episodes from
    0; `info["inner_done"]` marks their ends. Observations: see the module docstring.
    """

    def __init__(self, env: gym.Env, episodes: int = 10) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, episodes=episodes)
        gym.Wrapper.__init__(self, env)
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        self.episodes = episodes
        self.observation_space = meta_observation_space(env.unwrapped.tasks)
        self._episode = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start a meta-episode on a new pair (or on the pair fixed by `options`)."""
        obs, info = self.env.reset(seed=seed, options=options)
        self._episode = 0
        return meta_observation(obs, -1, 0.0, 0.0), {**info, "episode_in_trial": 0}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Step the inner episode; start the next inner episode on the same pair when it ends."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        info = {**info, "episode_in_trial": self._episode, "inner_done": terminated or truncated}
        if not (terminated or truncated):
            return meta_observation(obs, int(action), reward, 0.0), reward, False, False, info
        self._episode += 1
        if self._episode == self.episodes:
            return meta_observation(obs, int(action), reward, 0.0), reward, terminated, truncated, info
        obs, _ = self.env.reset(options={"keep_pair": True})
        return meta_observation(obs, int(action), reward, 1.0), reward, False, False, info


def make_meta_env(episodes: int = 10, **kwargs: Any) -> MetaEpisode:
    """`gym.make("mewa/MEWA-Meta-v0", ...)`: `MetaEpisode(MewaEnv(**kwargs), episodes)`."""
    from mewa_bench.envs.mewa_env import MewaEnv

    return MetaEpisode(MewaEnv(**kwargs), episodes)


class MetaEpisodeVectorEnv(MewaVectorEnv):
    """`num_envs` meta-episodes stepped together: `MetaEpisode`'s layout at the batched env's speed.

    Each sub-env plays `episodes` inner episodes on one (task, worker) pair (a new luck key each),
    then ends its meta-episode (terminated or truncated as the last inner episode was). The step
    that ends an inner episode other than the last returns the first observation of the next one,
    new-episode flag set. What follows the end of a meta-episode is the `autoreset_mode`'s, as in
    `MewaVectorEnv`: in NEXT_STEP (default) the next step ignores the action and returns the first
    observation of a new meta-episode on a new pair with reward 0; SAME_STEP and DISABLED as there.
    Seeds as in `MewaVectorEnv`: with a list, lane i plays what `MetaEpisode(MewaEnv())` plays after
    `reset(seed=s_i)`, in every mode; with an int, SAME_STEP and DISABLED play the same meta-episodes.

    `infos`: `progress`, `episode_in_trial` (the inner episode each step belonged to), `inner_done`
    and, on steps where inner episodes end, `episode_return` and `normalised_return` with their
    `_`-prefixed masks. Same construction arguments as `MewaVectorEnv`, plus `episodes`.
    """

    def __init__(self, num_envs: int = 1, episodes: int = 10, task: Task | dict | None = None,
                 worker: Sequence[float] | None = None, tasks: Sequence[Task | dict] | None = None,
                 include_centre: bool = False, render_mode: str | None = None,
                 workers: Sequence[Sequence[float]] | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP) -> None:
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        super().__init__(num_envs, task, worker, tasks, include_centre, render_mode, workers, autoreset_mode)
        self.episodes = episodes
        self.single_observation_space = meta_observation_space(self.tasks)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self._inner = np.zeros(num_envs, dtype=np.int64)
        self._last_obs = np.zeros((num_envs, META_OBS_SIZE), dtype=np.float32)  # for masked resets

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a meta-episode in every sub-env, or in those of `options["reset_mask"]` (as `MewaVectorEnv.reset`)."""
        if options and "reset_mask" in options:
            self._last_obs, info = super().reset(seed=seed, options=options)
            return self._last_obs.copy(), info
        obs, info = super().reset(seed=seed, options=options)
        self.single_observation_space = meta_observation_space(self.tasks)  # options may change the task
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._inner[:] = 0
        zeros = np.zeros(self.num_envs)
        self._last_obs = meta_observation(obs, np.full(self.num_envs, -1), zeros, zeros)
        return self._last_obs.copy(), {**info, "episode_in_trial": self._inner.copy()}

    def _begin(self, rows: np.ndarray, current: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start new meta-episodes in `rows`; every sub-env's observation and infos afterwards."""
        _, info = super()._begin(rows)
        self._inner[rows] = 0
        obs = (self._last_obs if current is None else current).copy()
        zeros = np.zeros(len(rows))
        obs[rows] = meta_observation(self._stack.obs[self._state[rows]], np.full(len(rows), -1), zeros, zeros)
        return obs, {**info, "episode_in_trial": self._inner.copy()}

    @property
    def episode_in_trial(self) -> np.ndarray:
        """Index of each sub-env's current inner episode."""
        return self._inner.copy()

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every sub-env; inner episodes that end are followed at once by the next on the same pair."""
        st = self._stack
        reward, resetting = self._move(actions)  # autoresets the meta-episodes that ended on the previous step
        self._inner[resetting] = 0
        inner_terminated, inner_truncated, infos = self._episode_ends(resetting)
        inner_done = inner_terminated | inner_truncated
        last = inner_done & (self._inner + 1 == self.episodes)
        infos.update(episode_in_trial=self._inner.copy(), inner_done=inner_done)
        following = np.flatnonzero(inner_done & ~last)  # the next inner episode starts on the same pair
        if following.size:
            self._inner[following] += 1
            self._start_episodes(following, new_pairs=False)
        previous = np.where(resetting, -1, np.asarray(actions))
        obs = meta_observation(st.obs[self._state], previous, reward, inner_done & ~last)
        obs, infos = self._autoreset(last, obs, infos)
        self._last_obs = obs
        return obs.copy(), reward, inner_terminated & last, inner_truncated & last, infos
