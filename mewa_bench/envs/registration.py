"""Registration of the MEWA env ids with Gymnasium (done on `import mewa_bench`)."""

from __future__ import annotations

import gymnasium as gym

ENV_IDS = ("mewa/MEWA-v0", "mewa/MEWA-Meta-v0")


def register_envs() -> None:
    """Register `mewa/MEWA-v0` and `mewa/MEWA-Meta-v0` (scalar and vector entry points) once."""
    if "mewa/MEWA-v0" in gym.registry:
        return
    gym.register(
        id="mewa/MEWA-v0",
        entry_point="mewa_bench.envs.mewa_env:MewaEnv",
        vector_entry_point="mewa_bench.envs.batched:MewaVectorEnv",
    )
    gym.register(  # ten episodes on one pair as one episode, for in-context learners (RL^2, VariBAD)
        id="mewa/MEWA-Meta-v0",
        entry_point="mewa_bench.envs.meta_episode:make_meta_env",
        vector_entry_point="mewa_bench.envs.meta_episode:MetaEpisodeVectorEnv",
    )
