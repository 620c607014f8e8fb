"""Test agent: plays `steps` steps, then raises an exception whose message carries what it saw (an attempt to
carry a hidden suite's episodes out through the reason a failed submission shows)."""

import numpy as np


class Agent:
    def __init__(self, observation_space, action_space, steps="3"):
        self.left, self.seen = int(steps), []

    def act(self, observation):
        self.seen.append(np.asarray(observation).ravel()[:8].tolist())
        self.left -= 1
        if self.left < 0:
            raise RuntimeError(f"LEAK {self.seen}")
        return 0
