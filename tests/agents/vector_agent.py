"""Test agent: a batched (vector) agent whose "network" is exact integer arithmetic, so its actions cannot
depend on how lanes are batched. It uses every call of the batched protocol: reset_task's seeds,
observe's transitions, end_episode, and (with sampled=true) one generator per lane.

Agent args: `seed`, `sampled` (true: noise from each lane's generator), `fault` (none, raise, short,
two_d, float, nan, range, list, hang, crash, memory: how act() misbehaves), `at_call` (the act() call that
misbehaves), `flag` (a file path: the fault only happens while that file exists, so a resumed run can
succeed). `vector_twin_agent.py` plays the same policy one lane per object.
"""

import os
import time

import numpy as np

WEIGHTS = np.random.default_rng(7).integers(-3, 4, size=(4, 18)).astype(np.int64)
MODULUS = 1_000_003


def scores(obs: np.ndarray, memory: np.ndarray, episodes: np.ndarray) -> np.ndarray:
    """Integer action scores [n, 4] in 0..10 of observations [n, 18] given each lane's memory and episode count
    (a hash of the whole history: the agent plays about as a random agent does)."""
    return (obs.astype(np.int64) @ WEIGHTS.T + memory[:, None] * np.arange(1, 5) + episodes[:, None]) % 11


def remembered(memory: np.ndarray, action: np.ndarray, reward: np.ndarray, terminated: np.ndarray) -> np.ndarray:
    """The memory after a step."""
    return (memory * 31 + action + np.round(reward * 8).astype(np.int64) + terminated) % MODULUS


class VectorAgent:
    def __init__(self, observation_space, action_space, num_lanes, seed="0", sampled="false", fault="none",
                 at_call="3", flag=""):
        self.seed, self.sampled = int(seed), sampled == "true"
        self.fault, self.at_call, self.flag = fault, int(at_call), flag
        self.memory = np.zeros(num_lanes, dtype=np.int64)
        self.episodes = np.zeros(num_lanes, dtype=np.int64)
        self.rngs = [np.random.default_rng([self.seed]) for _ in range(num_lanes)]
        self.calls = 0

    def reset_task(self, lanes, seeds):
        assert lanes.dtype == np.int64 and seeds.dtype == np.int64 and lanes.shape == seeds.shape
        self.memory[lanes] = seeds % MODULUS
        self.episodes[lanes] = 0
        for lane, seed in zip(lanes.tolist(), seeds.tolist()):
            self.rngs[lane] = np.random.default_rng([self.seed, seed])

    def act(self, lanes, observations):
        if isinstance(observations, dict):  # sapien mode: a batch of states and a batch of images
            assert observations["image"].shape[0] == len(lanes) and observations["image"].dtype == np.uint8
            observations = observations["state"]
        assert observations.dtype == np.float32 and observations.shape == (len(lanes), 18)
        self.calls += 1
        s = scores(observations, self.memory[lanes], self.episodes[lanes])
        if self.sampled:
            s = s * 8 + np.stack([self.rngs[lane].integers(0, 24, 4) for lane in lanes.tolist()])
        actions = np.argmax(s, axis=1)
        if self.fault != "none" and self.calls >= self.at_call and (not self.flag or os.path.exists(self.flag)):
            return self.misbehave(actions)
        return actions

    def misbehave(self, actions):
        if self.fault == "raise":
            raise ZeroDivisionError("the vector agent divided by zero")
        if self.fault == "short":
            return actions[:-1]
        if self.fault == "two_d":
            return actions[:, None]
        if self.fault == "float":
            return actions.astype(np.float64)
        if self.fault == "nan":
            out = actions.astype(np.float64)
            out[-1] = np.nan
            return out
        if self.fault == "range":
            out = actions.copy()
            out[-1] = 7
            return out
        if self.fault == "list":
            return actions.tolist()
        if self.fault == "hang":
            time.sleep(60)
        if self.fault == "crash":
            os._exit(3)
        if self.fault == "memory":  # 8 GiB, over the test's memory limit
            return np.zeros(8 << 30, dtype=np.uint8)[: len(actions)].astype(np.int64)
        return actions

    def observe(self, lanes, transitions):
        assert transitions.action.shape == (len(lanes),) and transitions.action.dtype == np.int64
        self.memory[lanes] = remembered(self.memory[lanes], transitions.action, transitions.reward,
                                        transitions.terminated.astype(np.int64))

    def end_episode(self, lanes):
        self.episodes[lanes] += 1
