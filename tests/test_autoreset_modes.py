"""The batched envs in Gymnasium's three autoreset modes, per-lane seeds, and against SyncVectorEnv."""

from __future__ import annotations

import hashlib
from typing import Any

import gymnasium as gym
import numpy as np

import mewa_bench  # noqa: F401 - registers the env ids

# sha256 of 3000 NEXT_STEP steps (observations, rewards, flags and infos) of 16 lanes, computed from the
# code before the autoreset modes existed: the default mode must keep these bytes.
NEXT_STEP_DIGESTS = {
    ("mewa/MEWA-v0", ()): "a95b44781470ad77bd0db0dbebdc414dd99f8a63525017049b060f098a9a6404",
    ("mewa/MEWA-Meta-v0", (("episodes", 3),)): "4f75da280020ccbdf9aa9d5225237bea2e27503e7d45db99c3c084b40380613b",
}


def feed(h: Any, value: Any) -> None:
    """Hash a step's output: dicts by sorted key, everything else as a numpy array (dtype and bytes)."""
    if isinstance(value, dict):
        for key in sorted(value):
            h.update(key.encode())
            feed(h, value[key])
    else:
        a = np.asarray(value)
        h.update(a.dtype.str.encode())
        h.update(a.tobytes())


def run_digest(env_id: str, steps: int = 3000, **kwargs: Any) -> str:
    """sha256 over a seeded random-action run of 16 lanes."""
    env = gym.make_vec(env_id, num_envs=16, **kwargs)
    h = hashlib.sha256()
    obs, info = env.reset(seed=7)
    feed(h, obs)
    feed(h, info)
    rng = np.random.default_rng(11)
    for _ in range(steps):
        for part in env.step(rng.integers(0, 4, size=16)):
            feed(h, part)
    return h.hexdigest()


def test_next_step_keeps_its_bytes() -> None:
    for (env_id, kwargs), expected in NEXT_STEP_DIGESTS.items():
        assert run_digest(env_id, **dict(kwargs)) == expected, env_id
