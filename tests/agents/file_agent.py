"""Test agent: reads or writes the file at its agent arg `path` when it first acts (`mode`: read, write or unlinked;
a write writes a line, or `size` bytes if given; `copies`: that many files, path.0, path.1, ..., then it waits 30 s;
unlinked: as write with copies, but each file is removed from its directory while the agent keeps it open;
mapped: the same, but the agent keeps a memory mapping of each file and closes it).

A relative path is relative to the agent's working directory (its scratch directory in the sandbox).
"""

import ctypes
import mmap
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
                elif self.mode == "mapped":  # through libc: Python's mmap would keep a copy of the descriptor
                    with copy.open("w+b") as f:
                        f.write(data)
                        f.flush()
                        self.kept.append(_libc_mmap(len(data), f.fileno()))
                    copy.unlink()
                else:
                    copy.write_bytes(data)
            time.sleep(30)
        return 0


def _libc_mmap(size: int, fd: int) -> int:
    """A shared read-only mapping of `fd` made by libc, which keeps no descriptor of its own."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
    return libc.mmap(None, size, mmap.PROT_READ, mmap.MAP_SHARED, fd, 0)
