"""Test agent: reads or writes the file at its agent arg `path` when it first acts (`mode`: read or write;
a write writes a line, or `size` bytes if given).

A relative path is relative to the agent's working directory (its scratch directory in the sandbox).
"""

from pathlib import Path


class Agent:
    def __init__(self, observation_space, action_space, path="", mode="read", size=""):
        self.path, self.mode, self.size, self.done = Path(path), mode, size, False

    def act(self, observation):
        if not self.done:
            self.done = True
            if self.mode == "read":
                return len(self.path.read_bytes()) % 4
            self.path.write_bytes(bytes(int(self.size)) if self.size else b"the agent was here\n")
        return 0
