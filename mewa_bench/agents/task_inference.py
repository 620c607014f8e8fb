"""Which public task an agent is in, inferred from what it observes (for agents that are not told).

An agent may know the tasks listed in the suite files (the public task distribution) but never which
one it faces. `TaskBelief` keeps the listed tasks that are consistent with every observed step: the
first observation fixes the colours, K and the worker's blocks; rewards, completions and returned
structures then reveal M and the sub-goal order. Used by the shipped reference agents.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from mewa_bench.design.suites import load_suite
from mewa_bench.game.rules import (initial_state, is_terminal, observation, outcomes, state_from_observation,
                                   step_reward)
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition, state_vector

REWARD_TOLERANCE = 1e-6


class Explanation(NamedTuple):
    """How a task's rules produce an observed step: the mistake type at stake (-1: none), and if one happened."""

    mistake_type: int
    mistaken: bool


def starts_like(task: Task, obs: np.ndarray) -> bool:
    """True if `obs` is the first observation of an episode of `task`."""
    return bool(np.array_equal(observation(task, initial_state(task)), obs))


def explain(task: Task, transition: Transition) -> Explanation | None:
    """How `task`'s rules produce `transition`, or None if they cannot (for any worker)."""
    obs = state_vector(transition.obs)
    next_obs = state_vector(transition.next_obs)
    state = state_from_observation(task, obs)
    if is_terminal(task, state) or not np.array_equal(observation(task, state), obs):
        return None
    result = outcomes(task, state, int(transition.action))
    branches = [(result.ok, False)] + ([(result.mistake, True)] if result.mistake is not None else [])
    for reached, mistaken in branches:
        if (np.array_equal(observation(task, reached), next_obs)
                and bool(transition.terminated) == is_terminal(task, reached)
                and abs(step_reward(task, reached) - float(transition.reward)) <= REWARD_TOLERANCE):
            return Explanation(result.mistake_type, mistaken)
    return None


def public_tasks(suites: str) -> list[Task]:
    """The tasks listed in the given suites (comma-separated names or paths), each task once."""
    tasks: dict[tuple, Task] = {}
    for name in suites.split(","):
        for task in load_suite(name.strip()).tasks:
            tasks.setdefault((task.key(), task.average_worker), task)
    return list(tasks.values())


class TaskBelief:
    """The known tasks still consistent with everything observed since `reset()`, in their given order."""

    def __init__(self, tasks: Sequence[Task]) -> None:
        self.tasks = tuple(tasks)
        self.candidates = list(self.tasks)

    def reset(self) -> None:
        """A new pair: every task is possible again."""
        self.candidates = list(self.tasks)

    def start_episode(self, obs: np.ndarray) -> None:
        """Keep the candidates whose episodes start with `obs`."""
        self.candidates = [task for task in self.candidates if starts_like(task, obs)]

    def update(self, transition: Transition) -> Explanation | None:
        """Drop the candidates that cannot produce `transition`; the explanation of the first one left."""
        explained = [(task, explain(task, transition)) for task in self.candidates]
        self.candidates = [task for task, why in explained if why is not None]
        return next((why for _, why in explained if why is not None), None)

    @property
    def task(self) -> Task | None:
        """The task acted for: the first candidate left (None if no known task explains what was seen)."""
        return self.candidates[0] if self.candidates else None
