"""An agent that misbehaves as its agent arg `fault` says, once it is asked to act."""

import ast
import ctypes
import gc
import os
import sys
import time

import numpy as np

import mewa_bench
from mewa_bench.envs.mewa_env import MewaEnv


def spy_on_parent():
    """1 if the parent's marker on the mewa_bench module is visible, plus 2 if any MewaEnv is reachable."""
    marker = 1 if getattr(mewa_bench, "_parent_marker", None) is not None else 0
    env = 2 if any(isinstance(obj, MewaEnv) for obj in gc.get_objects()) else 0
    return marker + env


def misbehave(fault, value):
    """Do what `fault` names."""
    if fault == "raise":
        raise ValueError("boom: the agent's act failed")
    if fault == "return":
        return ast.literal_eval(value)
    if fault == "hang":
        time.sleep(3600)
    if fault == "memory":
        return int(np.zeros(8 << 30, dtype=np.uint8)[0])
    if fault == "exit":
        os._exit(3)
    if fault == "sys_exit":
        sys.exit(5)
    if fault == "segfault":
        ctypes.string_at(0)
    if fault == "spy":
        return spy_on_parent()
    return 0


class Agent:
    """Misbehaves in act() (or in observe() with fault=raise_in_observe); fault=raise_at_init fails to construct."""

    def __init__(self, observation_space, action_space, fault="none", value="0"):
        if fault == "raise_at_init":
            raise RuntimeError("cannot build this agent")
        self.fault, self.value = fault, value

    def act(self, observation):
        return misbehave(self.fault, self.value)

    def observe(self, transition):
        if self.fault == "raise_in_observe":
            raise KeyError("missing")
