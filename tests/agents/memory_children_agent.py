"""Test agent: when it first acts, forks `children` processes that each fill `megabytes` MB of memory and wait;
each stays within the per-process memory limit, together they do not."""

import os
import time


class Agent:
    def __init__(self, observation_space, action_space, children="3", megabytes="600"):
        self.children, self.size, self.started = int(children), int(megabytes) << 20, False

    def act(self, observation):
        if not self.started:
            self.started = True
            for _ in range(self.children):
                if os.fork() == 0:
                    block = bytearray(self.size)
                    block[::4096] = b"\x01" * len(range(0, self.size, 4096))  # touch every page
                    time.sleep(60)
                    os._exit(0)
            time.sleep(60)
        return 0
