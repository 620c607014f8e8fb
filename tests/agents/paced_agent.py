"""Test agent: random play, reseeded per unit (so any run order gives the same units), sleeping per
act the seconds written in $HOME/pace if that file exists: in the sandbox (where HOME is the
scratch directory) a run lasts long enough to be interrupted. The pace is no agent arg, so it
stays out of the results file."""

import os
import time
from pathlib import Path

import numpy as np


class Agent:
    def __init__(self, observation_space, action_space):
        pace = Path(os.environ.get("HOME", "/nonexistent"), "pace")
        self.delay = float(pace.read_text()) if pace.exists() else 0.0
        self.rng = np.random.default_rng(0)

    def reset_task(self, seed=None):
        self.rng = np.random.default_rng(seed)

    def act(self, observation):
        if self.delay:
            time.sleep(self.delay)
        return int(self.rng.integers(0, 4))
