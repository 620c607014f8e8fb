"""Plays random actions for a while, then misbehaves: for testing that errors say where and keep results.

Agent args: `fault` (raise, invalid, hang, memory, none), `after_units` (healthy reset_task calls
before the fault), `at_step` (step of the first episode of the faulty unit), `flag` (a file path:
the fault only happens while that file exists, so a resumed run can succeed).
"""

import os
import time

import numpy as np


class Agent:
    def __init__(self, observation_space, action_space, fault="raise", after_units="2", at_step="3", flag=""):
        self.fault, self.after, self.at_step, self.flag = fault, int(after_units), int(at_step), flag
        self.units, self.steps = 0, 0
        self.rng = np.random.default_rng(0)

    def reset_task(self):
        self.units += 1
        self.steps = 0
        self.rng = np.random.default_rng(0)  # state reset per pair: results independent of unit order

    def act(self, observation):
        self.steps += 1
        armed = self.units > self.after and self.steps == self.at_step + 1
        if armed and (not self.flag or os.path.exists(self.flag)):
            if self.fault == "raise":
                raise ZeroDivisionError("the agent divided by zero")
            if self.fault == "invalid":
                return 7
            if self.fault == "hang":
                time.sleep(3600)
            if self.fault == "memory":
                return int(np.ones(8 << 30, dtype=np.uint8)[0])
        return int(self.rng.integers(0, 4))
