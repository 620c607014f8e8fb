"""Test agent: `vector_agent.py`'s policy played one lane per object (the one-lane protocol), its twin."""

import numpy as np

from vector_agent import MODULUS, remembered, scores


class Agent:
    def __init__(self, observation_space, action_space, seed="0", sampled="false"):
        self.seed, self.sampled = int(seed), sampled == "true"

    def reset_task(self, seed=None):
        self.memory, self.episodes = np.array([seed % MODULUS]), np.array([0])
        self.rng = np.random.default_rng([self.seed, seed])

    def act(self, observation):
        s = scores(observation[None], self.memory, self.episodes)
        if self.sampled:
            s = s * 8 + self.rng.integers(0, 24, 4)
        return int(np.argmax(s[0]))

    def observe(self, transition):
        self.memory = remembered(self.memory, np.array([transition.action]), np.array([transition.reward]),
                                 np.array([int(transition.terminated)]))

    def end_episode(self):
        self.episodes = self.episodes + 1
