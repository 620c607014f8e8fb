"""Test agent: on its first act, forks children that sleep until they are killed, until forking fails."""

import os
import time


class Agent:
    def __init__(self, observation_space, action_space):
        pass

    def act(self, observation):
        while True:
            if os.fork() == 0:
                time.sleep(3600)
                os._exit(0)
