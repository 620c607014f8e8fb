"""The README's batched GRU agent written against the one-lane API (one object, one forward pass per lane
and step): the baseline of `benchmarks/evaluate.py --neural`."""

import numpy as np
import torch


class Agent:
    def __init__(self, observation_space, action_space, seed="0", hidden="64"):
        self.seed = int(seed)
        rng = np.random.default_rng(self.seed)
        self.gru = torch.nn.GRUCell(18 + 5, int(hidden))
        self.head = torch.nn.Linear(int(hidden), int(action_space.n))
        for p in [*self.gru.parameters(), *self.head.parameters()]:
            p.data = torch.as_tensor(rng.normal(0.0, 0.1, p.shape), dtype=torch.float32)
        self.h = torch.zeros(1, int(hidden))
        self.previous = np.zeros((1, 5), dtype=np.float32)
        self.rng = np.random.default_rng([self.seed])

    def reset_task(self, seed=None):
        self.h.zero_()
        self.previous[:] = 0.0
        self.rng = np.random.default_rng([self.seed, seed])

    @torch.no_grad()
    def act(self, observation):
        x = torch.as_tensor(np.concatenate([observation[None] / 8.0, self.previous], axis=1))
        self.h = self.gru(x, self.h)
        cdf = torch.softmax(self.head(self.h), dim=1).double().cumsum(dim=1).numpy()[0]
        return int((cdf[:-1] < self.rng.random() * cdf[-1]).sum())

    def observe(self, transition):
        self.previous[:] = 0.0
        self.previous[0, transition.action] = 1.0
        self.previous[0, 4] = transition.reward / 10.0
