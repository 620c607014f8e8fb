"""Test agent: plays the VariBAD checkpoint given as `checkpoint=...` (mewa_bench.agents.varibad.VariBADAgent)."""

from mewa_bench.agents.varibad import VariBADAgent


def make_agent(observation_space, action_space, checkpoint=None, seed="0"):
    return VariBADAgent(checkpoint, seed=seed)
