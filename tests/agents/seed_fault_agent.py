"""Test agent: random play that raises in reset_task when its unit seed is one of agent arg `bad` (comma-separated):
a failure on the units of one suite only."""

import numpy as np


class Agent:
    def __init__(self, observation_space, action_space, bad=""):
        self.bad = {int(s) for s in bad.split(",") if s}
        self.rng = np.random.default_rng(0)

    def reset_task(self, seed=None):
        if seed in self.bad:
            raise ValueError("this unit's seed is one the agent was told to fail on")
        self.rng = np.random.default_rng(seed)

    def act(self, observation):
        return int(self.rng.integers(0, 4))
