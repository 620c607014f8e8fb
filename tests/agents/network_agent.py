"""Test agent: tries to reach the network when it first acts, as its agent arg `how` says.

python: socket.socket(AF_INET) + connect; caught: the same, but it swallows the error and plays on;
raw: socket(2) through ctypes, past Python's audit hooks (the error number comes back in the message);
dns: a name lookup.
"""

import ctypes
import socket


class Agent:
    def __init__(self, observation_space, action_space, how="python", host="1.1.1.1"):
        self.how, self.host = how, host

    def act(self, observation):
        if self.how == "python":
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                s.connect((self.host, 80))
        elif self.how == "caught":
            try:
                socket.create_connection((self.host, 80), timeout=1)
            except OSError:
                pass
        elif self.how == "raw":
            libc = ctypes.CDLL(None, use_errno=True)
            fd = libc.socket(socket.AF_INET, socket.SOCK_STREAM, 0)
            raise RuntimeError(f"raw socket() returned {fd}, errno {ctypes.get_errno()}")
        elif self.how == "dns":
            socket.getaddrinfo("example.com", 80)
        return 0
