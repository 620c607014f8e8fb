"""Test agent: burns CPU in act() without end (stopped by a CPU-time limit or a per-call time limit)."""


class Agent:
    def __init__(self, observation_space, action_space):
        pass

    def act(self, observation):
        total = 0
        while True:
            total += 1
