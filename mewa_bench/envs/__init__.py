"""Gymnasium environments: the scalar env, the batched vector env and the meta-episode wrapper."""

from mewa_bench.envs.batched import MewaVectorEnv
from mewa_bench.envs.meta_episode import MetaEpisode, MetaEpisodeVectorEnv
from mewa_bench.envs.mewa_env import MewaEnv

__all__ = ["MetaEpisode", "MetaEpisodeVectorEnv", "MewaEnv", "MewaVectorEnv"]
