"""Test agent: reads or writes the file at its agent arg `path` when it first acts (`mode`: read, write or unlinked;
a write writes a line, or `size` bytes if given; `copies`: that many files, path.0, path.1, ..., then it waits 30 s;
unlinked: as write with copies, but each file is removed from its directory while the agent keeps it open).

A relative path is relative to the agent's working directory (its scratch directory in the sandbox).
"""

import time
from pathlib import Path


class Agent:
    def __init__(self, observation_space, action_space, path="", mode="read", size="", copies=""):
        self.path, self.mode, self.size, self.copies, self.done = Path(path), mode, size, copies, False

    def act(self, observation):
        if not self.done:
            self.done = True
            if self.mode == "read":
                return len(self.path.read_bytes()) % 4
            data = bytes(int(self.size)) if self.size else b"the agent was here\n"
            if not self.copies:
                self.path.write_bytes(data)
                return 0
            self.kept = []
            for i in range(int(self.copies)):
                copy = self.path.with_name(f"{self.path.name}.{i}")
                if self.mode == "unlinked":
                    self.kept.append(copy.open("wb"))
                    copy.unlink()
                    self.kept[-1].write(data)
                    self.kept[-1].flush()
                else:
                    copy.write_bytes(data)
            time.sleep(30)
        return 0
