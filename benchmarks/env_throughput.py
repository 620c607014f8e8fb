"""Steps per second of the MEWA envs, as ratios to a baseline measured in the same run.

Baseline: an env in the style of the authors' original implementation (SPEC section 11: the state
is a nested structure deep-copied on every step, the rules re-run each step). It is built on the
same `rules.outcomes`, so it plays the identical game. The machines are shared and noisy: compare
the ratios, not the absolute numbers.

    .venv/bin/python benchmarks/env_throughput.py [--seconds 2]
"""

from __future__ import annotations

import argparse
import copy
import time

import gymnasium as gym
import numpy as np

import mewa_bench  # noqa: F401
from mewa_bench.envs import MetaEpisodeVectorEnv, MewaEnv, MewaVectorEnv
from mewa_bench.game import Task, observation, outcomes
from mewa_bench.game.rules import initial_state, is_terminal, step_reward

TASK = Task(colors=(0, 1, 2, 3), order=(3, 1, 2, 0), K=5, M=3, rewards=(-0.4, -0.3, -0.2, -0.1),
            worker_blocks=(2, 2, 4, 0)).with_distribution((0.6, 0.4, 0.25, 0.1))
WORKER = (0.5, 0.4, 0.3, 0.2)


class DeepcopyEnv:
    """Original-style env: dict state deep-copied every step, rules applied step by step."""

    def __init__(self, task: Task, worker: tuple[float, ...], seed: int) -> None:
        self.task, self.worker, self.rng = task, worker, np.random.default_rng(seed)

    def reset(self) -> np.ndarray:
        self.state = {"cells": list(initial_state(self.task)), "t": 0, "history": []}
        return observation(self.task, tuple(self.state["cells"]))

    def step(self, action: int):
        state = copy.deepcopy(self.state)
        out = outcomes(self.task, tuple(state["cells"]), action)
        mistake = out.mistake_type >= 0 and self.rng.random() < self.worker[out.mistake_type]
        cells = out.mistake if mistake else out.ok
        state["cells"], state["t"] = list(cells), state["t"] + 1
        self.state = state
        done = is_terminal(self.task, cells)
        return observation(self.task, cells), step_reward(self.task, cells), done, state["t"] >= self.task.T, {}


def time_scalar(env, seconds: float, reset) -> float:
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 4, size=1_000_000).tolist()
    if hasattr(env, "np_random"):
        env.reset(seed=0)
    reset(env)
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for a in actions[n % 900_000 : n % 900_000 + 10_000]:
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                reset(env)
        n += 10_000
    return n / (time.perf_counter() - start)


def time_batched(num_envs: int, seconds: float, env: MewaVectorEnv | None = None) -> float:
    env = env or MewaVectorEnv(num_envs=num_envs, task=TASK, worker=WORKER)
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 4, size=(64, num_envs))
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds or n < 4:
        env.step(actions[n % 64])
        n += 1
    return n * num_envs / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="time per measurement")
    args = parser.parse_args()
    rows = [("baseline: deep-copy-per-step env (original style)",
             time_scalar(DeepcopyEnv(TASK, WORKER, 0), args.seconds, lambda e: e.reset()))]
    rows.append(("MewaEnv unwrapped, fixed worker",
                 time_scalar(MewaEnv(task=TASK, worker=WORKER), args.seconds, lambda e: e.reset())))
    rows.append(("MewaEnv unwrapped, worker sampled per reset",
                 time_scalar(MewaEnv(task=TASK), args.seconds, lambda e: e.reset())))
    made = gym.make("mewa/MEWA-v0", task=TASK, worker=WORKER)
    rows.append(("gymnasium.make (checker + order wrappers)", time_scalar(made, args.seconds, lambda e: e.reset())))
    for n in (1, 64, 4096, 65536):
        rows.append((f"MewaVectorEnv, {n} pairs", time_batched(n, args.seconds)))
    base = rows[0][1]
    print(f"{'configuration':<52} {'steps/s':>14} {'x baseline':>11}")
    for name, rate in rows:
        print(f"{name:<52} {rate:>14,.0f} {rate / base:>10.1f}x")
    # Meta-training (target: within 1.5x of the fixed worker): workers sampled from the meta-train
    # distribution at every reset, and meta-episodes of 10 episodes per pair.
    n = 4096
    fixed = time_batched(n, args.seconds)
    meta_rows = [(f"MewaVectorEnv, {n} pairs, fixed worker (baseline)", fixed),
                 (f"MewaVectorEnv, {n} pairs, worker sampled per reset",
                  time_batched(n, args.seconds, MewaVectorEnv(num_envs=n, task=TASK))),
                 (f"MetaEpisodeVectorEnv, {n} pairs, 10 episodes per pair",
                  time_batched(n, args.seconds, MetaEpisodeVectorEnv(num_envs=n, task=TASK)))]
    print(f"\n{'meta-training configuration':<52} {'steps/s':>14} {'slowdown':>11}")
    for name, rate in meta_rows:
        print(f"{name:<52} {rate:>14,.0f} {fixed / rate:>10.2f}x")


if __name__ == "__main__":
    main()
