"""A class-style agent with only act(): plays a fixed action, read from its checkpoint file if given."""

from pathlib import Path

import numpy as np


class Agent:
    """Always plays `action` (a numpy integer), or the number stored in the `checkpoint` file."""

    def __init__(self, observation_space, action_space, action="0", checkpoint=None):
        self.action = int(Path(checkpoint).read_text()) if checkpoint else int(action)

    def act(self, observation):
        return np.int64(self.action)
