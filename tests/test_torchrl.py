"""TorchRL drives the batched envs (GymWrapper over gym.make_vec) and the scalar env (GymEnv with num_envs)."""

from __future__ import annotations

import multiprocessing

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

import mewa_bench  # noqa: F401 - registers the env ids
from mewa_bench.envs.registration import ENV_IDS
from mewa_bench.game.palette import OBS_COMPLETED

torch.set_num_threads(1)


@pytest.fixture(autouse=True, scope="module")
def keep_the_start_method():
    """Importing torchrl sets multiprocessing's global start method to spawn: undo it for the other tests."""
    before = multiprocessing.get_start_method(allow_none=True)
    yield
    if multiprocessing.get_start_method(allow_none=True) != before:
        multiprocessing.set_start_method(before, force=True)


def check_terminal_observations(td, env_id: str) -> None:
    """At a terminated step `next.observation` is the last observation (every structure completed), and
    the rollout's next row starts the new episode from nothing completed."""
    terminated = td["next", "terminated"].squeeze(-1)
    assert terminated.any()
    last = td["next", "observation"][terminated][:, OBS_COMPLETED]
    assert (last == 1).all()
    lanes, steps = torch.nonzero(terminated[:, :-1], as_tuple=True)
    first = td["observation"][lanes, steps + 1][:, OBS_COMPLETED]
    assert (first == 0).all()


@pytest.mark.parametrize("mode", [AutoresetMode.SAME_STEP, AutoresetMode.DISABLED], ids=lambda m: m.name)
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gym_wrapper_over_the_batched_env(env_id: str, mode: AutoresetMode) -> None:
    from torchrl.envs import GymWrapper
    from torchrl.envs.utils import check_env_specs

    kwargs = {"episodes": 2} if "Meta" in env_id else {}
    env = GymWrapper(gym.make_vec(env_id, num_envs=4, autoreset_mode=mode, **kwargs))
    check_env_specs(env, seed=0)
    td = env.rollout(300, break_when_any_done=False)
    assert td.batch_size == (4, 300)
    check_terminal_observations(td, env_id)
    if mode == AutoresetMode.SAME_STEP:  # TorchRL reads infos in this mode: MEWA's are numeric, so they stack
        assert td["next", "progress"].shape[:2] == (4, 300)
        assert (td["next", "progress"][td["next", "terminated"].squeeze(-1)] == 4).all()


@pytest.mark.slow
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gym_env_with_num_envs(env_id: str) -> None:
    """TorchRL's own vectorisation: Gymnasium's AsyncVectorEnv over the scalar env, in subprocesses started
    by spawn (TorchRL's default), which import `mewa_bench` through Gymnasium's "module:id" form."""
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv(f"mewa_bench:{env_id}", num_envs=2, **({"episodes": 2} if "Meta" in env_id else {}))
    check_env_specs(env, seed=0)
    td = env.rollout(250, break_when_any_done=False)
    assert td.batch_size == (2, 250) and td["next", "done"].any()
    # TorchRL builds this AsyncVectorEnv in NEXT_STEP mode and handles its resets its own way (a terminated
    # step's next observation is filled in, the last observation follows), so only the run is checked here.
    env.close()
