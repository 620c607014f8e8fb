"""Stable-Baselines3 over the batched envs: a `VecEnv` whose lanes are one `MewaVectorEnv`.

```python
from stable_baselines3 import PPO
from mewa_bench.envs.sb3 import make_sb3_vec_env

env = make_sb3_vec_env("mewa/MEWA-v0", num_envs=16)        # VecMonitor(MewaSB3VecEnv(...))
PPO("MlpPolicy", env, seed=0).learn(20_000)
```

The batched env runs in `AutoresetMode.SAME_STEP`, which is SB3's convention: the step that ends an
episode returns the next episode's first observation, `done` is True, and `infos[i]` holds the last
observation as `terminal_observation` and `TimeLimit.truncated` (truncated and not terminated),
plus that step's MEWA infos (`progress`, `episode_return`, `normalised_return`; with
`mewa/MEWA-Meta-v0` also `episode_in_trial` and `inner_done`). On `mewa/MEWA-Meta-v0` `done` marks
only the end of a meta-episode, so a recurrent policy (sb3-contrib's RecurrentPPO) keeps its memory
across the inner episodes of one pair and resets it when a new pair begins.

Seeds: SB3's `env.seed(s)` (which `PPO(..., seed=s)` calls) gives lane i the seed s + i at the next
reset, as for its own `DummyVecEnv`: lane i then plays what `MewaEnv` plays after `reset(seed=s + i)`.
Needs the interop extra (stable-baselines3), imported when a function here is first called.
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from mewa_bench.envs.batched import MewaVectorEnv
from mewa_bench.extras import require

FEATURE = "the Stable-Baselines3 VecEnv (mewa_bench.envs.sb3)"


def _vec_env_module() -> Any:
    return require("stable_baselines3.common.vec_env", "interop", FEATURE)


def lane_info(infos: dict[str, Any], i: int) -> dict[str, Any]:
    """Lane i's entries of vector infos (those its `_` masks allow), as Python scalars."""
    info: dict[str, Any] = {}
    for key, value in infos.items():
        if key.startswith("_") or not isinstance(value, np.ndarray) or value.dtype == object:
            continue
        mask = infos.get("_" + key)
        if mask is None or mask[i]:
            info[key] = value[i].item()
    return info


def lane_infos(infos: dict[str, Any], done: np.ndarray, truncated: np.ndarray) -> list[dict[str, Any]]:
    """SB3's per-lane info dicts from a SAME_STEP step's vector infos (an ended lane: its last step's)."""
    out: list[dict[str, Any]] = []
    for i in range(len(done)):
        if done[i]:
            info = lane_info(infos["final_info"], i)
            info["terminal_observation"] = infos["final_obs"][i]
        else:
            info = lane_info(infos, i)
        info["TimeLimit.truncated"] = bool(truncated[i])
        out.append(info)
    return out


@functools.cache
def sb3_vec_env_class() -> type:
    """The `MewaSB3VecEnv` class (a subclass of SB3's `VecEnv`, so defined once SB3 is imported)."""
    VecEnv = _vec_env_module().VecEnv

    class MewaSB3VecEnv(VecEnv):
        """SB3's `VecEnv` API over a batched MEWA env in SAME_STEP mode (see the module docstring).

        `self.venv` is the batched env; `get_attr(name)` reads its attribute (a per-lane array gives
        each lane its entry); `env_method` calls a method of the batched env once, for all lanes."""

        def __init__(self, venv: MewaVectorEnv) -> None:
            if getattr(venv, "autoreset_mode", None) != AutoresetMode.SAME_STEP:
                raise ValueError("MewaSB3VecEnv needs a batched env in AutoresetMode.SAME_STEP, got "
                                 f"{getattr(venv, 'autoreset_mode', None)}")
            self.venv = venv
            super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
            self._actions = np.zeros(venv.num_envs, dtype=np.int64)

        def reset(self) -> np.ndarray:
            """Reset every lane, with the seeds and options set by `seed()` / `set_options()` (used once)."""
            seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
            options = [o for o in self._options if o]
            if options and (len(options) < self.num_envs or any(o != options[0] for o in options)):
                raise ValueError("the lanes share one batched env: set_options() takes one dict for all lanes")
            obs, infos = self.venv.reset(seed=seeds, options=options[0] if options else None)
            self.reset_infos = lane_infos(infos, np.zeros(self.num_envs, dtype=bool), np.zeros(self.num_envs, bool))
            self._reset_seeds()
            self._reset_options()
            return obs

        def step_async(self, actions: np.ndarray) -> None:
            self._actions = np.asarray(actions, dtype=np.int64).reshape(self.num_envs)

        def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
            obs, reward, terminated, truncated, infos = self.venv.step(self._actions)
            done = terminated | truncated
            return obs, reward.astype(np.float32), done, lane_infos(infos, done, truncated & ~terminated)

        def close(self) -> None:
            self.venv.close()

        def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
            value = getattr(self.venv, attr_name)
            lanes = list(self._get_indices(indices))
            if isinstance(value, np.ndarray) and value.ndim >= 1 and len(value) == self.num_envs:
                return [value[i] for i in lanes]
            return [value for _ in lanes]

        def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
            setattr(self.venv, attr_name, value)

        def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list:
            result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
            return [result for _ in self._get_indices(indices)]

        def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
            return [False for _ in self._get_indices(indices)]  # the lanes are no gym.Env: never wrapped

    MewaSB3VecEnv.__qualname__ = MewaSB3VecEnv.__name__
    return MewaSB3VecEnv


def make_sb3_vec_env(env_id: str = "mewa/MEWA-v0", num_envs: int = 8, monitor: bool = True, **env_kwargs: Any) -> Any:
    """An SB3 `VecEnv` over `gym.make_vec(env_id, num_envs, autoreset_mode=SAME_STEP, **env_kwargs)`,
    wrapped in SB3's `VecMonitor` (episode returns and lengths in the training logs) unless `monitor=False`."""
    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        autoreset_mode=AutoresetMode.SAME_STEP, **env_kwargs)
    env = sb3_vec_env_class()(venv)
    return _vec_env_module().VecMonitor(env) if monitor else env
