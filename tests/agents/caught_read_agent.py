"""Test agent: tries to read the file (or list the folder) at its agent arg `path` when it first acts, swallows
the error it gets and plays on, as an agent hiding its attempt would (`how`: read, list or link: a symlink
made in its scratch directory to `path`, then read).
"""

import os
from pathlib import Path


class Agent:
    def __init__(self, observation_space, action_space, path="", how="read"):
        self.path, self.how, self.tried = path, how, False

    def act(self, observation):
        if not self.tried:
            self.tried = True
            try:
                if self.how == "list":
                    os.listdir(self.path)
                elif self.how == "link":
                    os.symlink(self.path, "innocent.json")
                    Path("innocent.json").read_bytes()
                else:
                    Path(self.path).read_bytes()
            except OSError:
                pass  # nothing to see: play on as if nothing happened
        return 0
