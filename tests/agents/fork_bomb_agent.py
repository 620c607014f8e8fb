"""Test agent: on its first act, forks children that sleep until they are killed, until forking fails.

With `children`: forks that many, waits `hold` seconds, then plays on (the children live until the sandbox ends).
"""

import os
import time


class Agent:
    def __init__(self, observation_space, action_space, children="", hold="0"):
        self.children, self.hold, self.forked = int(children) if children else None, float(hold), False

    def act(self, observation):
        while not self.forked:
            if os.fork() == 0:
                time.sleep(3600)
                os._exit(0)
            if self.children is not None:
                self.children -= 1
                if self.children == 0:
                    self.forked = True
                    time.sleep(self.hold)
        return 0
