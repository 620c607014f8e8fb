"""Test agent: plays the RL^2 checkpoint given as `checkpoint=...` (mewa_bench.agents.rl2.RL2Agent)."""

from mewa_bench.agents.rl2 import RL2Agent


def make_agent(observation_space, action_space, checkpoint=None, seed="0"):
    return RL2Agent(checkpoint, seed=seed)
